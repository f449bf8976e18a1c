"""The simulator's physics status: solver state, penetration and the energy budget, per period.

Energy budget (mjENBL_ENERGY must be on): E = kinetic + potential (gravity) energy of the state
each step starts from. The work done over a step by a generalized force f held over it is
h·f·(v_k + v_k+1)/2 (exactly the change of kinetic energy a constant f causes with a constant
mass matrix): every force under Euler, which takes them at the start state; the joint torques and
the push under RK4. RK4's stages see damping and constraint forces change within the step: their
work is the trapezoid of the power, h·(f_k·v_k + f_k+1·v_k+1)/2, f of each step's start state
(:meth:`PhysicsMonitor.start_forces`).
Sources: ``actuators`` (qfrc_applied + qfrc_actuator: dyn_sim's joint torques), ``push`` (the
external wrench, xfrc_applied), ``damping`` (qfrc_passive) and ``constraints`` (qfrc_constraint:
contacts and limits). The energy error is ΔE − Σ work, summed over the period; its ratio to the
largest of |ΔE|, Σ|work| and the peak kinetic energy is ``energy_error_rel``. A step is
diverging when MuJoCo flags a bad qpos/qvel/qacc (it then resets the state) or the energy is not
finite: an ERROR with the failure label ``evaluation error``. So is a fault of the simulator's
divergence guard (:class:`dyn_node.sim.control.Fault`: the joint, quantity and step; the state
held at the last good one): it stays ERROR, with the fault's line, until the simulator is reset.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import mujoco
import numpy as np

from dyn_node.errors import EVALUATION_ERROR

OK, WARN, ERROR = 0, 1, 2
WARNINGS = {int(w): n.removeprefix("mjWARN_").lower() for n, w in mujoco.mjtWarning.__members__.items()
            if n != "mjNWARNING"}
DIVERGING = {"badqpos", "badqvel", "badqacc"}
#: energy_error_rel above which the period is WARN (1 %, the free-motion check's bound)
ENERGY_WARN = 1e-2
PENETRATION_WARN_M = 5e-3
SOURCES = ("actuators", "push", "damping", "constraints")


@dataclass
class PhysicsPeriod:
    """What happened since the last report (times in simulation s, energies in J)."""

    steps: int = 0
    max_iterations: int = 0
    last_residual: float = 0.0
    max_penetration_m: float = 0.0
    warnings: dict[str, int] = field(default_factory=dict)
    work_sum: np.ndarray = field(default_factory=lambda: np.zeros(len(SOURCES)))
    work: dict[str, float] = field(default_factory=lambda: dict.fromkeys(SOURCES, 0.0))
    energy_start: float = math.nan
    energy_end: float = math.nan
    peak_kinetic: float = 0.0
    energy_error: float = 0.0
    non_finite: bool = False
    #: the simulator's divergence fault (its one line), "" when none
    fault: str = ""

    @property
    def energy_error_rel(self) -> float:
        scale = max(abs(self.energy_end - self.energy_start), sum(abs(w) for w in self.work.values()),
                    self.peak_kinetic, 1e-9)
        return abs(self.energy_error) / scale if math.isfinite(self.energy_error) else math.inf

    @property
    def diverging(self) -> bool:
        return self.non_finite or bool(self.fault) or bool(DIVERGING & set(self.warnings))


@dataclass(frozen=True)
class PhysicsStatus:
    level: int
    message: str
    values: dict[str, str]
    failure_label: str | None


class PhysicsMonitor:
    """Per-step accounting around ``mj_step`` (call :meth:`before` and :meth:`after` it)."""

    def __init__(self, mj: mujoco.MjModel):
        self.mj = mj
        self._rk4 = mj.opt.integrator == int(mujoco.mjtIntegrator.mjINT_RK4)
        self._forces = np.zeros((len(SOURCES), mj.nv))  # RK4: the start state's, per source
        self._energy_start = np.full(2, math.nan)  # RK4: E_k (after the stages data.energy is about E_k+1's)
        self._v, self._v_start = np.zeros(mj.nv), np.zeros(mj.nv)
        self._warn = np.zeros(len(WARNINGS), dtype=int)
        self._pending: tuple[float, np.ndarray] | None = None  # E_k and step k's work
        self.period = PhysicsPeriod()
        #: the simulator's divergence fault, until :meth:`clear_fault`
        self.fault = None

    def diverged(self, fault: object) -> None:
        """The step just taken diverged and was undone: ERROR from now until a reset."""
        self.fault = fault
        self._pending = None

    def clear_fault(self) -> None:
        self.fault = None
        self._pending = None

    def before(self, d: mujoco.MjData) -> None:
        self._v[:] = d.qvel
        self._v_start[:] = d.qvel

    def start_forces(self, d: mujoco.MjData) -> None:
        """RK4 only: ``d`` after mj_forward at the step's start state (before the stages)."""
        _source_forces(d, self._forces)
        self._energy_start[:] = d.energy

    def after(self, d: mujoco.MjData) -> None:
        """Account the step just taken (Euler: ``d``'s forward quantities are those of its
        start; RK4: :meth:`start_forces` had them). Kept lean (it runs every step): MuJoCo's
        warning counters are read at report time."""
        p = self.period
        half = 0.5 * self.mj.opt.timestep
        vm = self._v
        vm += d.qvel
        vm *= half  # h·(v_k + v_k+1)/2
        if self._rk4:
            energy = self._energy_start
            work = self._forces @ vm  # held: joint torques, push
            # state-dependent (damping, constraints): the trapezoid's first half now, the
            # previous step's second half from this start state's power
            work[2:] = self._forces[2:] @ (half * self._v_start)
            if self._pending is not None:
                self._pending[1][2:] += work[2:]
        else:
            energy = d.energy
            work = _source_forces(d, self._forces) @ vm
        E = float(energy.sum())
        if self._pending is not None:
            E_prev, w_prev = self._pending
            p.energy_error += (E - E_prev) - sum(w_prev)
            p.work_sum += w_prev
            if p.steps == 0:  # a new period: its budget runs from the last step's energy
                p.energy_start = E_prev
        else:
            p.energy_start = E
        p.energy_end = E
        p.peak_kinetic = max(p.peak_kinetic, float(energy[1]))
        self._pending = (E, work.copy())
        p.steps += 1
        n = int(d.solver_niter[0])
        if n:
            p.max_iterations = max(p.max_iterations, n)
            p.last_residual = float(d.solver[n - 1].gradient)
        if d.ncon:  # contacts are robot–scene only (the scene's collision filter)
            p.max_penetration_m = max(p.max_penetration_m, -float(d.contact.dist[:d.ncon].min()))

    def _warnings(self, d: mujoco.MjData) -> dict[str, int]:
        counts = np.array([d.warning[i].number for i in WARNINGS])
        new = {name: int(counts[j] - self._warn[j]) for j, name in enumerate(WARNINGS.values())
               if counts[j] > self._warn[j]}
        self._warn = counts
        return new

    def report(self, d: mujoco.MjData) -> PhysicsStatus:
        """The status of the period so far (``d``: the simulation's data), and a new period."""
        p, self.period = self.period, PhysicsPeriod()
        p.warnings = self._warnings(d)
        p.non_finite = p.steps > 0 and not math.isfinite(p.energy_end)
        p.fault = self.fault.text if self.fault is not None else ""
        p.work = dict(zip(SOURCES, (float(w) for w in p.work_sum)))
        if p.diverging:
            self._pending = None  # MuJoCo reset the state: the next budget starts afresh
        return physics_status(p, iterations_limit=self.mj.opt.iterations)


def _source_forces(d: mujoco.MjData, out: np.ndarray) -> np.ndarray:
    """``out`` = the generalized forces in ``d`` per source (rows in SOURCES' order)."""
    np.add(d.qfrc_applied, d.qfrc_actuator, out=out[0])
    # xfrc_applied's share of qfrc_smooth = passive − bias + applied + actuator + xfrc
    out[1] = d.qfrc_smooth + d.qfrc_bias - d.qfrc_passive - out[0]
    out[2], out[3] = d.qfrc_passive, d.qfrc_constraint
    return out


def physics_status(p: PhysicsPeriod, *, iterations_limit: int) -> PhysicsStatus:
    """The ``dyn_sim: physics`` status of a period (level, message, keys, label)."""
    values = {"steps": str(p.steps), "solver_iterations_max": str(p.max_iterations),
              "solver_iterations_limit": str(iterations_limit),
              "solver_residual": f"{p.last_residual:.3g}",
              "max_penetration_m": f"{p.max_penetration_m:.6g}",
              "energy_j": f"{p.energy_end:.9g}", "energy_change_j": f"{p.energy_end - p.energy_start:.9g}",
              **{f"work_{k}_j": f"{w:.9g}" for k, w in p.work.items()},  # 9 digits: recomputable
              "energy_error_j": f"{p.energy_error:.9g}", "energy_error_rel": f"{p.energy_error_rel:.3g}",
              "warnings": ", ".join(f"{k} ×{n}" for k, n in sorted(p.warnings.items())) or "none"}
    if p.fault:
        return PhysicsStatus(ERROR, p.fault, {**values, "fault": p.fault}, EVALUATION_ERROR)
    if p.diverging:
        what = ", ".join(sorted(DIVERGING & set(p.warnings))) or "non-finite energy"
        return PhysicsStatus(ERROR, f"simulation diverging ({what}): MuJoCo reset the state; lower "
                             "the timestep or stiffen nothing further", values, EVALUATION_ERROR)
    problems = []
    if p.warnings:
        problems.append(f"MuJoCo warnings: {values['warnings']}")
    if p.max_penetration_m > PENETRATION_WARN_M:
        problems.append(f"penetration {p.max_penetration_m * 1e3:.3g} mm > {PENETRATION_WARN_M * 1e3:g} mm")
    if p.energy_error_rel > ENERGY_WARN:
        problems.append(f"energy budget off by {p.energy_error_rel:.2g} (> {ENERGY_WARN:g})")
    if p.max_iterations >= iterations_limit:
        problems.append(f"solver used all {iterations_limit} iterations")
    if problems:
        return PhysicsStatus(WARN, "; ".join(problems), values, EVALUATION_ERROR)
    return PhysicsStatus(OK, f"ok: energy {p.energy_end:.4g} J, budget error {p.energy_error_rel:.2g}",
                         values, None)
