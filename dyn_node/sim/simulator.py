"""A simulated robot: MuJoCo at a fixed step with a computed-torque joint controller.

The independent "other side" of the demo: it integrates the same URDF with MuJoCo (never
Pinocchio) and executes trajectories as ros2_control's joint_trajectory_controller does, with
real saturation at the effort limits. Control law, trajectory rules and the external push:
docs/SIMULATOR.md. Nothing here reads a clock, so a run is deterministic and steppable from
tests. No rclpy: :mod:`dyn_node.ros.sim_node` is the ROS adapter.
"""
from __future__ import annotations

import copy
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Sequence

import mujoco
import numpy as np

from dyn_node.errors import InputError, ModelError, TrajectoryError
from dyn_node.core.robot.model import RobotModel
from dyn_node.sim.mujoco_model import MujocoRobot, mujoco_from_model, mujoco_urdf
from dyn_node.sim.scene import INTEGRATORS, Scene, SolverSettings
from dyn_node.sim.physics_status import PhysicsMonitor
from dyn_node.sim.contact_truth import ContactTruth, contact_truth, scene_geom_ids
from dyn_node.core.check.trajectory import Trajectory, validate_trajectory
from dyn_node.sim.control import DivergenceGuard, Fault, choose_integrator, gain_warning
from dyn_node.sim.reference import ActiveTrajectory, reference_from_goal

DEFAULT_TIMESTEP = 0.001
#: Closed-loop natural frequency (rad/s) and damping ratio for the automatic gains.
DEFAULT_NATURAL_FREQUENCY = 40.0
DEFAULT_DAMPING_RATIO = 1.0


@dataclass(frozen=True)
class SimConfig:
    """Simulator settings, model joint order.

    ``kp``/``kd`` both empty: computed torque, every mode of the loop at bandwidth
    ``natural_frequency`` ω with ``damping_ratio`` ζ (:mod:`dyn_node.sim.control`). Given
    (N·m/rad, N·m·s/rad; one alone takes the other as ``M_ii(q0)·ω²`` or ``2ζ·M_ii(q0)·ω``):
    a joint PD plus the reference's inverse dynamics. ``initial_positions`` empty: the middle of
    each joint's range (0 when unlimited), clipped into the limits. ``feedforward`` off drops
    the reference acceleration and h(q, q̇) (computed torque) or the inverse dynamics (PD).
    """

    timestep: float = DEFAULT_TIMESTEP
    kp: tuple[float, ...] = ()
    kd: tuple[float, ...] = ()
    natural_frequency: float = DEFAULT_NATURAL_FREQUENCY
    damping_ratio: float = DEFAULT_DAMPING_RATIO
    feedforward: bool = True
    initial_positions: tuple[float, ...] = ()
    saturate: bool = True
    #: static objects the robot collides with (None: contacts off, the plant of every test so far)
    scene: Scene | None = None
    solver: SolverSettings = SolverSettings()
    #: MuJoCo's mjENBL_ENERGY (data.energy = potential, kinetic); no effect on the dynamics
    energy: bool = False
    #: solver.integrator is a default, not the user's choice: implicitfast replaces an explicit
    #: integrator the URDF's damping is too stiff for (dyn_node.sim.control.choose_integrator)
    integrator_auto: bool = True


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


# --------------------------------------------------------------------------------------------
# External wrenches: URDF link → MuJoCo body, and the wrench MuJoCo takes
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LinkMount:
    """Where URDF link ``link`` sits in a MuJoCo model: on body ``body`` (id ``body_id``), its
    origin at ``translation`` (m) and its axes ``rotation`` (columns: link axes) in the body's
    frame. The identity when the link is a body of its own."""

    link: str
    body: str
    body_id: int
    rotation: np.ndarray
    translation: np.ndarray


def _rpy_matrix(rpy: Sequence[float]) -> np.ndarray:
    """URDF's fixed-axis roll-pitch-yaw: R = Rz(yaw)·Ry(pitch)·Rx(roll)."""
    cr, sr = math.cos(rpy[0]), math.sin(rpy[0])
    cp, sp = math.cos(rpy[1]), math.sin(rpy[1])
    cy, sy = math.cos(rpy[2]), math.sin(rpy[2])
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _joint_origin(joint: ET.Element) -> tuple[np.ndarray, np.ndarray]:
    origin = joint.find("origin")
    xyz = [float(x) for x in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()]
    rpy = [float(x) for x in (origin.get("rpy", "0 0 0") if origin is not None else "0 0 0").split()]
    return _rpy_matrix(rpy), np.array(xyz)


def link_mount(mj: mujoco.MjModel, urdf: ET.Element, link: str) -> LinkMount:
    """The body of ``mj`` that carries URDF link ``link`` and the link's pose in it. ``urdf``
    is the URDF MuJoCo compiled (locked joints already fixed, :func:`mujoco_urdf`); MuJoCo names
    each body after its link. Raises InputError (``unknown_frame``) for a link the URDF lacks."""
    links = {el.get("name") for el in urdf.findall("link")}
    if link not in links:
        raise InputError(f"'{link}' is not a link of the robot (links: {', '.join(sorted(links))})",
                         code="unknown_frame")
    parent_joint = {j.find("child").get("link"): j for j in urdf.findall("joint")
                    if j.find("child") is not None}
    R, p = np.eye(3), np.zeros(3)  # the link's pose in the frame of `name`
    name = link
    while (body_id := mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_BODY, name)) < 0:
        joint = parent_joint.get(name)
        if joint is None or joint.get("type") != "fixed":
            # a root link or the child of a moving joint is always a body of its own
            raise ModelError(f"link '{name}' has no MuJoCo body", code="no_body")
        Rj, pj = _joint_origin(joint)
        R, p = Rj @ R, Rj @ p + pj
        name = joint.find("parent").get("link")
    return LinkMount(link=link, body=name, body_id=int(body_id), rotation=R, translation=p)


def body_wrench(mount: LinkMount, body_rotation: np.ndarray, body_position: np.ndarray,
                com: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """MuJoCo's ``xfrc_applied`` row (world axes, at the body's centre of mass ``com``) for
    ``wrench`` = [f; m] at the link's origin in the link's axes, the body at
    (``body_rotation``, ``body_position``) in the world: F = R_wl·f, τ = R_wl·m + (p_o − com) × F."""
    R_wl = body_rotation @ mount.rotation
    p_o = body_position + body_rotation @ mount.translation
    F = R_wl @ wrench[:3]
    return np.concatenate([F, R_wl @ wrench[3:] + np.cross(p_o - com, F)])


@dataclass(frozen=True)
class AppliedWrench:
    """A push being applied: ``wrench`` [f (N); m (N·m)] at ``mount.link``'s origin in its
    axes, on the steps from ``start_step`` up to (not including) ``end_step``."""

    mount: LinkMount
    wrench: np.ndarray
    start_step: int
    end_step: int

    @property
    def force_n(self) -> float:
        return float(np.linalg.norm(self.wrench[:3]))

    @property
    def moment_nm(self) -> float:
        return float(np.linalg.norm(self.wrench[3:]))


# --------------------------------------------------------------------------------------------
# The simulator
# --------------------------------------------------------------------------------------------
def default_initial_positions(model: RobotModel) -> np.ndarray:
    """Middle of each joint's position range (0 where unlimited)."""
    lo, hi = model.limits.position_lower, model.limits.position_upper
    both = np.isfinite(lo) & np.isfinite(hi)
    # only bounded joints are averaged: ±inf + ∓inf (continuous joints) would warn and give NaN
    mid = np.zeros(len(lo))
    mid[both] = 0.5 * (lo[both] + hi[both])
    return np.clip(mid, lo, hi)


class Simulator:
    """MuJoCo simulation of ``model`` under computed torque (or a user's PD + feedforward).

    Deterministic: the same calls give the same states. Not thread-safe (the ROS adapter steps it
    from one thread and hands trajectories over through :meth:`execute`).
    """

    def __init__(self, model: RobotModel, config: SimConfig = SimConfig()):
        if not (config.timestep > 0 and math.isfinite(config.timestep)):
            raise ModelError(f"timestep must be a positive number of seconds, got {config.timestep}",
                             code="bad_timestep")
        self.model = model
        self.config = config
        # Joint-limit constraints stay off, contacts too without a scene: the plant is the
        # rigid-body dynamics plus URDF damping and armature that Pinocchio models too.
        self.robot: MujocoRobot = mujoco_from_model(model, damping=True, armature=True,
                                                    frictionloss=False, contacts=False,
                                                    timestep=config.timestep, scene=config.scene,
                                                    solver=config.solver)
        self.mj = self.robot.model
        self.mj.opt.timestep = config.timestep
        if config.energy:
            self.mj.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
        self.data = mujoco.MjData(self.mj)
        # the feedforward is the rigid-body model a controller knows: never the scene's contacts
        self._ff_model = copy.deepcopy(self.mj)
        self._ff_model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        self._ff_data = mujoco.MjData(self._ff_model)
        self._scene_geoms = scene_geom_ids(self.mj, config.scene.names) if config.scene else frozenset()
        self._qi = self.robot.qpos_ids
        self._di = self.robot.dof_ids
        nv = model.nv
        self.effort_limit = np.asarray(model.limits.effort, dtype=float).copy()
        q0 = (np.asarray(config.initial_positions, dtype=float) if len(config.initial_positions)
              else default_initial_positions(model))
        if q0.shape != (nv,) or not np.all(np.isfinite(q0)):
            raise ModelError(f"initial_positions needs {nv} finite values, got {list(q0)}",
                             code="bad_initial_positions")
        # the integrator applies with or without a scene (dyn_sim's default RK4 unless asked),
        # unless the URDF's damping is too stiff for an explicit one at this step
        M0 = self._inertia(q0)
        self._damping = self.mj.dof_damping[self._di].copy()
        #: the MuJoCo integrator in use, and "" or why it is not the one asked for
        self.integrator, self.integrator_note = choose_integrator(
            config.solver.integrator, M0, self._damping, config.timestep, auto=config.integrator_auto)
        self.mj.opt.integrator = int(INTEGRATORS[self.integrator])
        self._rk4 = self.integrator == "rk4"
        # implicit integrators solve (M + dt·D)·q̈ = f: the computed torque wants that matrix
        self._implicit_d = (config.timestep * self._damping if self.integrator.startswith("implicit")
                            else np.zeros(nv))
        #: computed torque (automatic gains) or a user's joint PD
        self.computed_torque = not (len(config.kp) or len(config.kd))
        self.kp, self.kd = self._gains(q0)
        #: "" or the one line saying the step cannot integrate the gains (dyn_sim logs it)
        self.gain_warning = gain_warning(M0, self.kp, self.kd, config.timestep,
                                         rk4=self._rk4, automatic=self.computed_torque,
                                         omega=config.natural_frequency)
        self._scratch = np.zeros(self.mj.nv)
        #: why the physics stopped (None: running); cleared by :meth:`reset`
        self.fault: Fault | None = None
        self.controller_enabled = True
        self._open_loop = np.zeros(nv)
        self._steps = 0
        self._effort = np.zeros(nv)
        self._saturated = np.zeros(nv, dtype=bool)
        self.active: ActiveTrajectory | None = None
        self._ref_cache: tuple[int, np.ndarray, np.ndarray] | None = None
        # the URDF MuJoCo compiled, to place links merged into an ancestor body
        self._mujoco_urdf = ET.fromstring(mujoco_urdf(model)[0])
        self._mounts: dict[str, LinkMount] = {}
        #: the push being applied (None: none)
        self.wrench: AppliedWrench | None = None
        #: per-step physics accounting (energy budget, solver, penetration), when enabled
        self.physics: PhysicsMonitor | None = PhysicsMonitor(self.mj) if config.energy else None
        self._guard = DivergenceGuard(self.mj, self.data, self._qi, self._di, model.joint_names)
        self.reset(q0)

    # --- setup ---------------------------------------------------------------------------------
    def _inertia(self, q0: np.ndarray) -> np.ndarray:
        """MuJoCo's joint-space inertia (armature included) at q0, model order."""
        d = mujoco.MjData(self.mj)
        d.qpos[self._qi] = q0
        mujoco.mj_forward(self.mj, d)
        M = np.zeros((self.mj.nv, self.mj.nv))
        mujoco.mj_fullM(self.mj, d, M)
        return M[np.ix_(self._di, self._di)]

    def _gains(self, q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per joint: ω², 2ζω (1/s², 1/s) for computed torque; else the user's N·m/rad gains."""
        nv = self.model.nv
        c = self.config
        w = c.natural_frequency
        if self.computed_torque:
            kp, kd = np.full(nv, w * w), np.full(nv, 2.0 * c.damping_ratio * w)
        elif len(c.kp) and len(c.kd):
            kp, kd = np.asarray(c.kp, float), np.asarray(c.kd, float)
        else:
            mii = np.maximum(np.diag(self._inertia(q0)), 1e-6)
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
        self.clear_wrench()
        mujoco.mj_forward(self.mj, self.data)
        self.active = None
        self._hold = q.copy()
        self._ref_cache = None
        self.fault = None
        self._guard.remember(self.data)
        if self.physics is not None:
            self.physics.clear_fault()

    # --- state -----------------------------------------------------------------------------------
    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.model.joint_names

    @property
    def time(self) -> float:
        """Simulation time (s): steps × timestep, exact and free of float drift."""
        return self._steps * self.config.timestep

    @property
    def steps(self) -> int:
        """Steps taken so far (a push's ``start_step``/``end_step`` count in these)."""
        return self._steps

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
        self.active = reference_from_goal(traj, start, now, self.q, self.v)
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
        mujoco.mj_inverse(self._ff_model, d)
        return d.qfrc_inverse[self._di].copy()

    def _computed_torque(self, q: np.ndarray, v: np.ndarray, q_ref: np.ndarray, v_ref: np.ndarray,
                         a_ref: np.ndarray) -> np.ndarray:
        """M(q)(q̈_ref + Kp·e + Kd·ė) + h(q, q̇): MuJoCo's inverse dynamics at the measured state
        of the wanted acceleration (h = bias − passive). Without feedforward: M(q)(Kp·e + Kd·ė)."""
        a_des = self.kp * (q_ref - q) + self.kd * (v_ref - v)
        if self.config.feedforward:
            a_des += a_ref
            return self.feedforward(q, v, a_des) + self._implicit_d * a_des
        d = self._ff_data
        d.qpos[self._qi] = q
        mujoco.mj_kinematics(self._ff_model, d)
        mujoco.mj_comPos(self._ff_model, d)
        mujoco.mj_makeM(self._ff_model, d)
        self._scratch[:] = 0.0
        self._scratch[self._di] = a_des
        out = np.zeros(self.mj.nv)
        mujoco.mj_mulM(self._ff_model, d, out, self._scratch)
        return out[self._di] + self._implicit_d * a_des

    def contact_truth(self) -> ContactTruth:
        """Robot–scene contacts of the last step (empty without a scene)."""
        return contact_truth(self.mj, self.data, self._scene_geoms)

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
        if self.computed_torque:
            tau = self._computed_torque(q, v, q_ref, v_ref, a_ref)
        else:
            tau = self.kp * (q_ref - q) + self.kd * (v_ref - v)
            if self.config.feedforward:
                tau += self.feedforward(q_ref, v_ref, a_ref)
        if not self.config.saturate:
            return tau, np.zeros(self.model.nv, dtype=bool)
        sat = np.abs(tau) >= self.effort_limit
        return np.clip(tau, -self.effort_limit, self.effort_limit), sat

    # --- external push --------------------------------------------------------------------------
    def link_mount(self, link: str) -> LinkMount:
        """Where URDF link ``link`` sits in the MuJoCo model (cached); InputError if unknown."""
        mount = self._mounts.get(link)
        if mount is None:
            mount = self._mounts[link] = link_mount(self.mj, self._mujoco_urdf, link)
        return mount

    def apply_wrench(self, link: str, force: Sequence[float], moment: Sequence[float], *,
                     hold_s: float) -> AppliedWrench | None:
        """Push the robot from the next step on with [force (N); moment (N·m)] at ``link``'s
        origin in its axes, for ``hold_s`` s (rounded to whole steps, at least one), replacing
        any push before. A zero wrench ends the push (whatever ``link``) and returns None.
        Raises InputError (``unknown_frame``, ``non_finite``, ``bad_hold``), state unchanged."""
        w = np.concatenate([np.asarray(force, dtype=float).reshape(3), np.asarray(moment, dtype=float).reshape(3)])
        if not np.all(np.isfinite(w)):
            raise InputError(f"wrench is not finite ({w.tolist()})", code="non_finite")
        if not (hold_s > 0 and math.isfinite(hold_s)):
            raise InputError(f"hold must be a positive number of seconds, got {hold_s}", code="bad_hold")
        if not np.any(w):
            self.clear_wrench()
            return None
        mount = self.link_mount(link)
        self.clear_wrench()
        steps = max(1, int(round(hold_s / self.config.timestep)))
        self.wrench = AppliedWrench(mount=mount, wrench=w, start_step=self._steps,
                                    end_step=self._steps + steps)
        return self.wrench

    def clear_wrench(self) -> None:
        """End the push (if any): nothing is applied from the next step on."""
        if self.wrench is not None:
            self.data.xfrc_applied[self.wrench.mount.body_id] = 0.0
        self.wrench = None

    def _push(self) -> None:
        w, d = self.wrench, self.data
        b = w.mount.body_id
        d.xfrc_applied[b] = body_wrench(w.mount, d.xmat[b].reshape(3, 3), d.xpos[b], d.xipos[b], w.wrench)

    def _rk4_step(self) -> None:
        """mj_step's RK4 branch, written out: the push needs the start state's kinematics and the
        physics monitor its forces, which RK4's later stages overwrite in ``data``."""
        m, d = self.mj, self.data
        if self.wrench is not None:
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            self._push()
        mujoco.mj_checkPos(m, d)
        mujoco.mj_checkVel(m, d)
        mujoco.mj_forward(m, d)
        mujoco.mj_checkAcc(m, d)
        if self.physics is not None:
            self.physics.start_forces(d)
        mujoco.mj_RungeKutta(m, d, 4)

    def step(self, n: int = 1) -> SimState:
        """Advance n steps of ``timestep`` s and return the state after the last one."""
        if n <= 0:
            return self.state()
        dt = self.config.timestep
        # One vectorised reference evaluation for the batch, plus the time after it for state().
        ts = (self._steps + np.arange(n + 1)) * dt
        Q, V, A = self.reference(ts)
        for k in range(n):
            if self.fault is not None:
                # diverged: the last good state is held, nothing integrated, until reset
                self._steps += 1
                self._effort, self._saturated = np.zeros(self.model.nv), np.zeros(self.model.nv, dtype=bool)
                continue
            tau, sat = self.control(Q[k], V[k], A[k])
            self.data.qfrc_applied[self._di] = tau
            if self.wrench is not None and self._steps >= self.wrench.end_step:
                self.clear_wrench()
            if self.physics is not None:
                self.physics.before(self.data)
            if self._rk4:
                self._rk4_step()
            elif self.wrench is None:
                mujoco.mj_step(self.mj, self.data)
            else:
                # step1 computes this state's kinematics, which the push's rotation and lever
                # arm need; step2 integrates with it (the Euler integrator's mj_step, split)
                mujoco.mj_step1(self.mj, self.data)
                self._push()
                mujoco.mj_step2(self.mj, self.data)
            self._steps += 1
            self.fault = self._guard.check(self.data, self._steps, self.time)
            if self.fault is not None:
                self.active = None
                self._hold = self.q
                if self.physics is not None:
                    self.physics.diverged(self.fault)
            elif self.physics is not None:
                self.physics.after(self.data)
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
