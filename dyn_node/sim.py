"""A simulated robot: MuJoCo at a fixed step with a joint-space PD + feedforward controller.

The simulator is the independent "other side" of the demo: it integrates the same URDF with
MuJoCo (not Pinocchio) and executes trajectories the way ros2_control's
joint_trajectory_controller (JTC) does:

- the trajectory is checked with :func:`dyn_node.trajectory.validate_trajectory` (JTC's rules);
- it starts at its header stamp, or on receipt when the stamp is zero;
- when the first point's absolute time lies after the receipt time, the first segment runs from
  the state at receipt (position, velocity) to the first point, as JTC does;
- segments are interpolated quintic (positions, velocities, accelerations), cubic (positions and
  velocities) or linear (positions only), the JTC rules;
- after the last point the last position is held.

Control law, per 1 ms step, in model joint order::

    τ = clip(τ_ff(q_ref, q̇_ref, q̈_ref) + Kp (q_ref − q) + Kd (q̇_ref − q̇), ±effort_limit)

with the feedforward τ_ff from MuJoCo's own inverse dynamics (``mj_inverse``) of the reference,
so the controller never uses Pinocchio. Saturation at the URDF effort limits is real: an
infeasible trajectory visibly fails to track. The measured effort reported is the applied
(saturated) torque.

Time is simulation time in seconds (starts at 0); nothing here reads a clock, so a run is
deterministic and steppable from tests. No rclpy: :mod:`dyn_node.sim_node` is the ROS adapter.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import mujoco
import numpy as np

from .errors import ModelError, TrajectoryError
from .model import RobotModel
from .mujoco_model import MujocoRobot, mujoco_from_model
from .trajectory import PiecewisePolynomial, Trajectory, interpolate, validate_trajectory

DEFAULT_TIMESTEP = 0.001
#: Closed-loop natural frequency (rad/s) and damping ratio for the automatic gains.
DEFAULT_NATURAL_FREQUENCY = 40.0
DEFAULT_DAMPING_RATIO = 1.0


@dataclass(frozen=True)
class SimConfig:
    """Simulator settings. Gains in N·m/rad and N·m·s/rad, model joint order.

    ``kp``/``kd`` empty: automatic, ``M_ii(q0)·ω²`` and ``2ζ·M_ii(q0)·ω`` from the joint-space
    inertia at the initial pose (so each joint gets the same closed-loop bandwidth ω).
    ``initial_positions`` empty: the middle of each joint's range (0 when unlimited), clipped
    into the limits. ``feedforward`` off leaves a pure PD controller.
    """

    timestep: float = DEFAULT_TIMESTEP
    kp: tuple[float, ...] = ()
    kd: tuple[float, ...] = ()
    natural_frequency: float = DEFAULT_NATURAL_FREQUENCY
    damping_ratio: float = DEFAULT_DAMPING_RATIO
    feedforward: bool = True
    initial_positions: tuple[float, ...] = ()
    saturate: bool = True


@dataclass(frozen=True)
class SimState:
    """One simulator sample at time ``t`` (s), arrays in model order.

    ``q`` (rad|m), ``v`` (rad/s|m/s), ``effort`` = the torque applied this step (N·m, after
    saturation), ``q_ref``/``v_ref`` the controller's reference, ``saturated`` per joint.
    """

    t: float
    q: np.ndarray
    v: np.ndarray
    effort: np.ndarray
    q_ref: np.ndarray
    v_ref: np.ndarray
    saturated: np.ndarray


@dataclass(frozen=True)
class ActiveTrajectory:
    """A trajectory being executed; times are simulation seconds.

    ``start_time`` is the trajectory's t = 0 (its stamp or the receipt time), ``received_time``
    when the simulator took it. ``first_segment`` (or None) spans [received_time, first point].
    """

    trajectory: Trajectory
    mode: str
    start_time: float
    received_time: float
    polynomial: PiecewisePolynomial
    first_segment: PiecewisePolynomial | None

    @property
    def end_time(self) -> float:
        return self.start_time + float(self.trajectory.times[-1])

    @property
    def first_point_time(self) -> float:
        return self.start_time + float(self.trajectory.times[0])

    def reference(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q_ref, q̇_ref, q̈_ref) at simulation times t (M,), each M×nv; the last point held."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        q, v, a, _ = self.polynomial.evaluate(t - self.start_time)
        if self.first_segment is not None:
            early = t < self.first_point_time
            if np.any(early):
                q0, v0, a0, _ = self.first_segment.evaluate(t[early] - self.received_time)
                q[early], v[early], a[early] = q0, v0, a0
        late = t >= self.end_time
        if np.any(late):
            # Hold the last point at rest, as the controller does once the trajectory has played.
            q[late] = self.trajectory.positions[-1]
            v[late] = 0.0
            a[late] = 0.0
        return q, v, a


def jtc_mode(traj: Trajectory) -> str:
    """The interpolation ros2_control's joint_trajectory_controller applies to ``traj``."""
    if traj.velocities is not None and traj.accelerations is not None:
        return "quintic"
    if traj.velocities is not None:
        return "cubic"
    return "linear"


# --------------------------------------------------------------------------------------------
# The simulator
# --------------------------------------------------------------------------------------------
def default_initial_positions(model: RobotModel) -> np.ndarray:
    """Middle of each joint's position range (0 where unlimited)."""
    lo, hi = model.limits.position_lower, model.limits.position_upper
    mid = np.where(np.isfinite(lo) & np.isfinite(hi), 0.5 * (lo + hi), 0.0)
    return np.clip(mid, lo, hi)


class Simulator:
    """MuJoCo simulation of ``model`` under a PD + feedforward joint controller.

    Deterministic: the same calls give the same states. Not thread-safe (the ROS adapter steps it
    from one thread and hands trajectories over through :meth:`execute`).
    """

    def __init__(self, model: RobotModel, config: SimConfig = SimConfig()):
        if not (config.timestep > 0 and math.isfinite(config.timestep)):
            raise ModelError(f"timestep must be a positive number of seconds, got {config.timestep}",
                             code="bad_timestep")
        self.model = model
        self.config = config
        # Joint-limit and contact constraints stay off: the plant is the rigid-body dynamics
        # plus URDF damping and armature that Pinocchio models too, so residuals mean something.
        self.robot: MujocoRobot = mujoco_from_model(model, damping=True, armature=True,
                                                    frictionloss=False, contacts=False,
                                                    timestep=config.timestep)
        self.mj = self.robot.model
        self.mj.opt.timestep = config.timestep
        self.data = mujoco.MjData(self.mj)
        self._ff_data = mujoco.MjData(self.mj)
        self._qi = self.robot.qpos_ids
        self._di = self.robot.dof_ids
        nv = model.nv
        self.effort_limit = np.asarray(model.limits.effort, dtype=float).copy()
        q0 = (np.asarray(config.initial_positions, dtype=float) if len(config.initial_positions)
              else default_initial_positions(model))
        if q0.shape != (nv,) or not np.all(np.isfinite(q0)):
            raise ModelError(f"initial_positions needs {nv} finite values, got {list(q0)}",
                             code="bad_initial_positions")
        self.kp, self.kd = self._gains(q0)
        self.controller_enabled = True
        self._open_loop = np.zeros(nv)
        self._steps = 0
        self._effort = np.zeros(nv)
        self._saturated = np.zeros(nv, dtype=bool)
        self.active: ActiveTrajectory | None = None
        self._ref_cache: tuple[int, np.ndarray, np.ndarray] | None = None
        self.reset(q0)

    # --- setup ---------------------------------------------------------------------------------
    def _gains(self, q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        nv = self.model.nv
        c = self.config
        if len(c.kp) and len(c.kd):
            kp, kd = np.asarray(c.kp, float), np.asarray(c.kd, float)
        else:
            d = mujoco.MjData(self.mj)
            d.qpos[self._qi] = q0
            mujoco.mj_forward(self.mj, d)
            M = np.zeros((self.mj.nv, self.mj.nv))
            mujoco.mj_fullM(self.mj, d, M)
            mii = np.maximum(np.diag(M)[self._di], 1e-6)
            w = c.natural_frequency
            kp = np.asarray(c.kp, float) if len(c.kp) else mii * w * w
            kd = np.asarray(c.kd, float) if len(c.kd) else 2.0 * c.damping_ratio * mii * w
        for label, k in (("kp", kp), ("kd", kd)):
            if k.shape != (nv,) or not np.all(np.isfinite(k)) or np.any(k < 0):
                raise ModelError(f"{label} needs {nv} finite values ≥ 0, got {list(k)}",
                                 code="bad_gains")
        return kp, kd

    def reset(self, q: Sequence[float], v: Sequence[float] | None = None) -> None:
        """Put the robot at rest (or at velocity v) at q, holding q; time is kept."""
        q = np.asarray(q, dtype=float)
        self.data.qpos[:] = 0.0
        self.data.qvel[:] = 0.0
        self.data.qpos[self._qi] = q
        if v is not None:
            self.data.qvel[self._di] = np.asarray(v, dtype=float)
        self.data.qfrc_applied[:] = 0.0
        mujoco.mj_forward(self.mj, self.data)
        self.active = None
        self._hold = q.copy()
        self._ref_cache = None

    # --- state -----------------------------------------------------------------------------------
    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.model.joint_names

    @property
    def time(self) -> float:
        """Simulation time (s): steps × timestep, exact and free of float drift."""
        return self._steps * self.config.timestep

    @property
    def q(self) -> np.ndarray:
        return self.data.qpos[self._qi].copy()

    @property
    def v(self) -> np.ndarray:
        return self.data.qvel[self._di].copy()

    def reference(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Controller reference (q, q̇, q̈) at simulation times t, each M×nv."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if self.active is None:
            z = np.zeros((len(t), self.model.nv))
            return np.tile(self._hold, (len(t), 1)), z, z.copy()
        return self.active.reference(t)

    def state(self) -> SimState:
        if self._ref_cache is not None and self._ref_cache[0] == self._steps:
            q_ref, v_ref = self._ref_cache[1], self._ref_cache[2]
        else:
            q_r, v_r, _ = self.reference(self.time)
            q_ref, v_ref = q_r[0], v_r[0]
        return SimState(t=self.time, q=self.q, v=self.v, effort=self._effort.copy(),
                        q_ref=q_ref.copy(), v_ref=v_ref.copy(), saturated=self._saturated.copy())

    # --- trajectories ----------------------------------------------------------------------------
    def execute(self, names: Sequence[str], times: Sequence[float],
                positions: Sequence[Sequence[float]],
                velocities: Sequence[Sequence[float]] | None = None,
                accelerations: Sequence[Sequence[float]] | None = None,
                start_time: float | None = None) -> ActiveTrajectory:
        """Validate and start a trajectory (JTC rules); raises TrajectoryError, state unchanged.

        ``start_time`` (simulation s) is the header stamp; None or 0 means on receipt (now).
        """
        # Locked joints (Panda's fingers) may be named; their values are dropped, as dyn_node does.
        traj = validate_trajectory(self.model.joint_names, names, times, positions, velocities,
                                   accelerations, min_points=1,
                                   ignored_joints=tuple(self.model.locked_joints))
        return self.execute_trajectory(traj, start_time)

    def execute_trajectory(self, traj: Trajectory, start_time: float | None = None) -> ActiveTrajectory:
        """Replace the active trajectory with ``traj`` (already in model order)."""
        if start_time is not None and not math.isfinite(start_time):
            raise TrajectoryError(f"start time is not finite ({start_time})", code="non_finite")
        now = self.time
        start = now if not start_time else float(start_time)
        mode = jtc_mode(traj)
        poly = interpolate(traj, mode)
        first = None
        first_abs = start + float(traj.times[0])
        if first_abs > now + 1e-12:
            # JTC: from the state at receipt to the first point, same interpolation rule.
            q_now, v_now = self.q, self.v
            pos = np.vstack([q_now, traj.positions[0]])
            vel = acc = None
            if traj.velocities is not None:
                vel = np.vstack([v_now, traj.velocities[0]])
            if traj.accelerations is not None:
                # The measured state carries no acceleration; start the segment from rest in a.
                acc = np.vstack([np.zeros_like(q_now), traj.accelerations[0]])
            seg = Trajectory(times=np.array([0.0, first_abs - now]), positions=pos,
                             velocities=vel, accelerations=acc)
            first = interpolate(seg, mode)
        self.active = ActiveTrajectory(traj, mode, start, now, poly, first)
        self._hold = traj.positions[-1].copy()
        self._ref_cache = None
        return self.active

    def hold(self, q: Sequence[float] | None = None) -> None:
        """Stop any trajectory and hold q (default: the current position)."""
        self.active = None
        self._hold = self.q if q is None else np.asarray(q, dtype=float).copy()
        self._ref_cache = None

    @property
    def executing(self) -> bool:
        """A trajectory is active and not yet past its last point."""
        return self.active is not None and self.time < self.active.end_time

    # --- control and stepping -------------------------------------------------------------------
    def feedforward(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """MuJoCo inverse dynamics of (q, q̇, q̈) in model order (N·m): M a + bias − passive."""
        d = self._ff_data
        d.qpos[self._qi] = q
        d.qvel[self._di] = v
        d.qacc[:] = 0.0
        d.qacc[self._di] = a
        mujoco.mj_inverse(self.mj, d)
        return d.qfrc_inverse[self._di].copy()

    def set_open_loop_torque(self, tau: Sequence[float]) -> None:
        """Disable the controller and apply ``tau`` (N·m, not saturated) from the next step."""
        self.controller_enabled = False
        self._open_loop = np.asarray(tau, dtype=float).copy()

    def forward_acceleration(self, q: Sequence[float], v: Sequence[float],
                             tau: Sequence[float]) -> np.ndarray:
        """MuJoCo's q̈ (model order) for torque tau at (q, q̇); the simulation state is untouched."""
        d = mujoco.MjData(self.mj)
        d.qpos[self._qi] = q
        d.qvel[self._di] = v
        d.qfrc_applied[self._di] = tau
        mujoco.mj_forward(self.mj, d)
        return d.qacc[self._di].copy()

    def control(self, q_ref: np.ndarray, v_ref: np.ndarray, a_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(applied torque, saturated mask) for the current state and the given reference."""
        if not self.controller_enabled:
            return self._open_loop.copy(), np.zeros(self.model.nv, dtype=bool)
        q = self.data.qpos[self._qi]
        v = self.data.qvel[self._di]
        tau = self.kp * (q_ref - q) + self.kd * (v_ref - v)
        if self.config.feedforward:
            tau += self.feedforward(q_ref, v_ref, a_ref)
        if not self.config.saturate:
            return tau, np.zeros(self.model.nv, dtype=bool)
        sat = np.abs(tau) >= self.effort_limit
        return np.clip(tau, -self.effort_limit, self.effort_limit), sat

    def step(self, n: int = 1) -> SimState:
        """Advance n steps of ``timestep`` s and return the state after the last one."""
        if n <= 0:
            return self.state()
        dt = self.config.timestep
        # One vectorised reference evaluation for the batch, plus the time after it for state().
        ts = (self._steps + np.arange(n + 1)) * dt
        Q, V, A = self.reference(ts)
        for k in range(n):
            tau, sat = self.control(Q[k], V[k], A[k])
            self.data.qfrc_applied[self._di] = tau
            mujoco.mj_step(self.mj, self.data)
            self._steps += 1
            self._effort, self._saturated = tau, sat
        self._ref_cache = (self._steps, Q[n], V[n])
        return self.state()

    def run(self, duration: float, every: int = 1) -> list[SimState]:
        """Step for ``duration`` s, returning the state every ``every`` steps (for tests/demo)."""
        n = int(round(duration / self.config.timestep))
        out = []
        done = 0
        while done < n:
            k = min(every, n - done)
            out.append(self.step(k))
            done += k
        return out
