"""dyn_sim's joint controller and its guards: computed torque on MuJoCo's own model, the gain
rule against the timestep, and the divergence check of a step (no rclpy).

Automatic gains (no ``kp``/``kd`` given): computed torque,
``τ = M(q)(q̈_ref + ω²·e + 2ζω·ė) + h(q, q̇)`` with M and h (bias − passive) of the plant's own
MuJoCo model (``mj_inverse`` at the measured state), so every mode of the closed loop — coupled
ones included — obeys ``ë + 2ζω·ė + ω²·e = 0``. User ``kp``/``kd`` (N·m/rad, N·m·s/rad) keep
their meaning: ``τ = τ_ff(ref) + Kp·e + Kd·ė`` with τ_ff MuJoCo's inverse dynamics of the
reference. Either way the torque is held over a step (zero-order hold) and clipped at the effort
limits. Gain rule and divergence status: docs/SIMULATOR.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

#: ω·dt of the automatic gains at most: the sampled loop's poles stay within 20 % of the
#: continuous ones' decay (ζ = 1); the sampled loop itself is unstable from ω·dt ≈ 1.
MAX_OMEGA_DT = 0.2
#: λ_max(M⁻¹D)·dt of the URDF's joint damping above which an explicit integrator (RK4 is
#: stable to 2.79, semi-implicit Euler to 2) is replaced by implicitfast, which integrates
#: damping implicitly: e.g. xArm7's joint7, 2 N·m·s/rad on 1.4e-4 kg·m², gives 14 at 1 ms.
MAX_DAMPING_DT = 1.0
#: A step's kinetic energy may not grow by more than this factor plus :data:`ENERGY_JUMP_J`.
ENERGY_JUMP_FACTOR = 4.0
ENERGY_JUMP_J = 1.0


def sampled_loop_radius(M: np.ndarray, kp: np.ndarray, kd: np.ndarray, dt: float, *,
                        rk4: bool = True) -> float:
    """Spectral radius of the closed loop of a PD torque ``Kp·e + Kd·ė`` held over each step of
    ``dt`` s on a plant of inertia ``M`` (the error dynamics around the reference, frozen at one
    pose). RK4 integrates the held torque exactly (``e += dt·ė + dt²/2·ë``); semi-implicit Euler
    (MuJoCo's ``euler``/``implicit*``) takes ``e += dt·ė_new``. Below 1: the step integrates the
    gains; ≥ 1: the loop grows every step, whatever the physics."""
    Minv = np.linalg.inv(M)
    P, D = Minv @ np.diag(kp), Minv @ np.diag(kd)
    n = len(kp)
    eye = np.eye(n)
    vel = np.hstack([-dt * P, eye - dt * D])
    pos = (np.hstack([eye - 0.5 * dt * dt * P, dt * eye - 0.5 * dt * dt * D]) if rk4
           else np.hstack([eye, np.zeros((n, n))]) + dt * vel)  # e + dt·ė_new
    return float(np.abs(np.linalg.eigvals(np.vstack([pos, vel]))).max())


def damping_rate_dt(M: np.ndarray, damping: np.ndarray, dt: float) -> float:
    """λ_max(M⁻¹D)·dt: the fastest decay the joint damping D (diagonal) imposes, per step."""
    L = np.linalg.cholesky(M)
    Li = np.linalg.inv(L)
    return float(np.linalg.eigvalsh(Li @ np.diag(damping) @ Li.T).max()) * dt


def choose_integrator(asked: str, M: np.ndarray, damping: np.ndarray, dt: float, *,
                      auto: bool = True) -> tuple[str, str]:
    """(integrator used, "" or the one line about it). ``auto`` (the integrator was not chosen by
    the user): an explicit one the damping is too stiff for becomes implicitfast; else it is kept
    and the line says it will diverge."""
    rate = damping_rate_dt(M, damping, dt)
    if asked in ("rk4", "euler") and rate > MAX_DAMPING_DT:
        why = (f"integrator {asked} cannot integrate the URDF's joint damping at timestep {dt:g} s "
               f"(λ_max(M⁻¹D)·dt = {rate:.3g} > {MAX_DAMPING_DT:g})")
        if auto:
            return "implicitfast", f"{why}: using implicitfast, which integrates damping implicitly"
        return asked, f"{why}: kept as asked; expect the physics to diverge (implicitfast would not)"
    return asked, ""


def gain_warning(M: np.ndarray, kp: np.ndarray, kd: np.ndarray, dt: float, *, rk4: bool,
                 automatic: bool, omega: float) -> str:
    """One line when the step cannot integrate the gains (or the automatic bandwidth is past
    :data:`MAX_OMEGA_DT`), else ""."""
    if automatic:
        if omega * dt > MAX_OMEGA_DT:
            return (f"natural_frequency {omega:g} rad/s × timestep {dt:g} s = {omega * dt:.3g} > "
                    f"{MAX_OMEGA_DT:g}: the sampled loop will not have that bandwidth"
                    f"{' and is unstable' if omega * dt >= 0.8 else ''}; lower one of them")
        return ""
    rho = sampled_loop_radius(M, kp, kd, dt, rk4=rk4)
    if rho >= 1.0:
        return (f"kp/kd cannot be integrated at timestep {dt:g} s: the held PD torque's sampled loop "
                f"grows ×{rho:.3g} per step at the start pose (stiffest mode of M⁻¹K); lower the "
                "gains or the timestep, or leave kp/kd unset for computed torque")
    return ""


@dataclass(frozen=True)
class Fault:
    """Why the simulation stopped integrating: at ``step`` (the one that diverged), ``quantity``
    of ``joint`` was ``value``. ``text`` is the one line said everywhere."""

    step: int
    time: float
    joint: str
    quantity: str
    value: float
    detail: str = ""

    @property
    def text(self) -> str:
        value = "NaN, Inf or huge" if math.isnan(self.value) else f"{self.value:.6g}"
        return (f"physics diverged at step {self.step} (t = {self.time:.3f} s): {self.quantity} of "
                f"joint {self.joint} = {value}{' (' + self.detail + ')' if self.detail else ''}; "
                "holding the last good state until reset")


WARNING_NAMES = {int(w): n.removeprefix("mjWARN_").lower() for n, w in mujoco.mjtWarning.__members__.items()}


class DivergenceGuard:
    """Checks every step (see :meth:`check`) and keeps the last good state to return to. Kept
    lean (it runs every step): three sums for NaN/Inf, MuJoCo's clock for its own reset (it
    resets the data, time included, on a bad qpos/qvel/qacc), one M·q̇ for the energy."""

    BAD = {int(mujoco.mjtWarning.mjWARN_BADQPOS): "position", int(mujoco.mjtWarning.mjWARN_BADQVEL): "velocity",
           int(mujoco.mjtWarning.mjWARN_BADQACC): "acceleration"}

    def __init__(self, mj: mujoco.MjModel, d: mujoco.MjData, qi: np.ndarray, di: np.ndarray,
                 names: tuple[str, ...]):
        self.mj, self.qi, self.di, self.names = mj, qi, di, names
        self._qpos, self._qvel = d.qpos.copy(), d.qvel.copy()
        self._Mv = np.zeros(mj.nv)
        self.remember(d)

    def _counts(self, d: mujoco.MjData) -> np.ndarray:
        return np.array([d.warning[w].number for w in self.BAD])

    def _kinetic(self, d: mujoco.MjData) -> float:
        mujoco.mj_mulM(self.mj, d, self._Mv, d.qvel)  # M of the last computed state: a measure
        return 0.5 * float(d.qvel @ self._Mv)

    def remember(self, d: mujoco.MjData) -> None:
        """``d`` is a good state (after a reset)."""
        self._qpos[:], self._qvel[:] = d.qpos, d.qvel
        self._warn = self._counts(d)
        self._ke = self._kinetic(d)
        self._time = d.time

    def check(self, d: mujoco.MjData, step: int, time: float) -> Fault | None:
        """After a step: a Fault (and ``d`` back at the last good state) or None (``d`` is good)."""
        fault = self._find(d, step, time)
        if fault is None:
            self._qpos[:], self._qvel[:] = d.qpos, d.qvel
            self._time = d.time
            return None
        t = self._time
        d.qpos[:], d.qvel[:] = self._qpos, self._qvel
        d.qacc[:] = 0.0
        d.qfrc_applied[:] = 0.0
        mujoco.mj_forward(self.mj, d)
        self.remember(d)
        self._time = d.time = t
        return fault

    def _find(self, d: mujoco.MjData, step: int, time: float) -> Fault | None:
        if not math.isfinite(float(d.qpos.sum() + d.qvel.sum() + d.qacc.sum())):
            for quantity, arr, ids in (("position", d.qpos, self.qi), ("velocity", d.qvel, self.di),
                                       ("acceleration", d.qacc, self.di)):
                x = arr[ids]
                bad = ~np.isfinite(x)
                if bad.any():
                    i = int(np.argmax(bad))
                    return Fault(step, time, self.names[i], quantity, float(x[i]), "not finite")
        dt = self.mj.opt.timestep
        # after MuJoCo's reset its clock restarts at 0 (one step: dt), which only the first
        # step's own clock cannot tell apart: there, the counters are read
        if d.time < self._time + 0.5 * dt or (self._time < dt and np.any(self._counts(d) > self._warn)):
            return self._mujoco_reset(d, step, time)
        ke = self._kinetic(d)
        if ke > ENERGY_JUMP_FACTOR * self._ke + ENERGY_JUMP_J:
            v = d.qvel[self.di]
            i = int(np.argmax(np.abs(v)))
            return Fault(step, time, self.names[i], "velocity", float(v[i]),
                         f"kinetic energy jumped from {self._ke:.3g} J to {ke:.3g} J in one step")
        self._ke = ke
        return None

    def _mujoco_reset(self, d: mujoco.MjData, step: int, time: float) -> Fault:
        """MuJoCo found a NaN, Inf or huge value and reset the data itself: which, and where."""
        counts = self._counts(d)
        new = counts > self._warn
        k = int(np.argmax(new)) if new.any() else 2
        w = list(self.BAD)[k]
        idx = int(d.warning[w].lastinfo)
        dofs = self.di.tolist()
        dof = dofs.index(idx) if idx in dofs else int(np.argmax(np.abs(self._qvel[self.di])))
        return Fault(step, time, self.names[dof], self.BAD[w], math.nan,
                     f"MuJoCo's {WARNING_NAMES[w]} warning: it reset the state")
