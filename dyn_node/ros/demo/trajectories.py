"""The demo's robot, poses and trajectories (the model table, the comfortable and aggressive
moves, the task-limits transfer) and the statistics of what was observed. No ROS."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import RobotModel
from dyn_node.core.check.trajectory import Trajectory, interpolate, validate_trajectory


READY = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
#: Named Panda poses (rad): the 'ready' pose of franka_ros, the arm stretched forward
#: horizontally (largest gravity lever), and folded back onto itself.
PANDA_POSES: dict[str, tuple[float, ...]] = {
    "ready": READY,
    "stretched": (0.0, 1.57, 0.0, -0.0698, 0.0, 1.57, 0.785),
    "folded": (0.0, -1.7, 0.0, -3.0, 0.0, 2.5, 0.785),
}
#: RNEA column of the table: every joint moving at this fraction of its velocity limit while
#: accelerating at TABLE_ACCEL (rad/s²) in the same direction.
TABLE_SPEED_FRACTION = 0.5
TABLE_ACCEL = 5.0
SAFETY_FACTOR = 1.05
TRACKING_TOLERANCE = 0.05
LEAD_S = 1.0      # trajectories start this long after they are sent: the verdict comes first
SETTLE_S = 0.4    # observation continues this long after a trajectory's last point
FINGERS = "panda_finger_joint1,panda_finger_joint2"


# --------------------------------------------------------------------------------------------
# Model table
# --------------------------------------------------------------------------------------------
def named_poses(model: RobotModel) -> dict[str, np.ndarray]:
    """Panda's named poses, or zero / mid-range / a seeded random pose for other robots."""
    if model.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8)):
        return {k: np.array(v) for k, v in PANDA_POSES.items()}
    lo, hi = model.limits.position_lower, model.limits.position_upper
    lo_f = np.where(np.isfinite(lo), lo, -math.pi)
    hi_f = np.where(np.isfinite(hi), hi, math.pi)
    zero = np.clip(np.zeros(model.nv), lo_f, hi_f)
    return {"zero": zero, "mid-range": 0.5 * (lo_f + hi_f),
            "random(seed 0)": np.random.default_rng(0).uniform(lo_f, hi_f)}


def model_table(model: RobotModel) -> str:
    """Readable table: per pose and joint, g(q) and RNEA(q, q̇, q̈) (N·m) and % of the limit."""
    dyn = Dynamics(model)
    lim = model.limits.effort
    v = TABLE_SPEED_FRACTION * np.where(np.isfinite(model.limits.velocity), model.limits.velocity, 1.0)
    a = np.full(model.nv, TABLE_ACCEL)
    lines = [f"{model.name}: {model.nv} DoF, {model.total_mass:.2f} kg, source {model.source}",
             f"gravity g(q) and RNEA τ(q, q̇, q̈) with every joint at {TABLE_SPEED_FRACTION:.0%} of "
             f"its velocity limit, accelerating at {TABLE_ACCEL:g} rad/s²; % = |torque| / effort limit",
             ""]
    poses = named_poses(model)
    head = f"{'joint':<14}{'limit N·m':>10}"
    for name in poses:
        head += f" | {name + ' g':>15}{'%':>5}{'τ':>9}{'%':>5}"
    lines += [head, "-" * len(head)]
    rows = {name: (dyn.gravity(q), dyn.rnea(q, v, a)) for name, q in poses.items()}
    for j, jn in enumerate(model.joint_names):
        row = f"{jn:<14}{lim[j]:>10.1f}"
        for name in poses:
            g, tau = rows[name]
            row += (f" | {g[j]:>15.2f}{abs(g[j]) / lim[j] * 100:>4.0f}%"
                    f"{tau[j]:>9.2f}{abs(tau[j]) / lim[j] * 100:>4.0f}%")
        lines.append(row)
    worst = max(((abs(rows[p][i][j]) / lim[j], p, jn, i) for p in poses for i in (0, 1)
                 for j, jn in enumerate(model.joint_names)))
    lines += ["", f"highest utilisation: {worst[2]} at {worst[0] * 100:.0f}% in the "
                  f"'{worst[1]}' pose {'while moving' if worst[3] else 'holding still'}"]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Demo trajectories (model order = Panda's 7 arm joints)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DemoTrajectory:
    """Waypoints at rest (v = a = 0 at each point, so JTC interpolates quintic min-jerk segments)."""

    name: str
    times: tuple[float, ...]
    positions: tuple[tuple[float, ...], ...]
    description: str

    @property
    def duration(self) -> float:
        return self.times[-1]

    def scaled(self, k: float, name: str, description: str) -> "DemoTrajectory":
        """Same path, k times longer (v = a = 0 at the waypoints stay 0)."""
        return replace(self, name=name, times=tuple(t * k for t in self.times), description=description)

    def validated(self, joint_names: Sequence[str]) -> Trajectory:
        z = [[0.0] * len(joint_names)] * len(self.times)
        return validate_trajectory(joint_names, joint_names, self.times, self.positions, z, z)


def demo_trajectories(short: bool = False) -> tuple[DemoTrajectory, DemoTrajectory]:
    """(comfortable, aggressive) for Panda, both starting and ending at READY.

    The aggressive one shakes joint2 (±0.1 rad) and joint4 (∓0.07 rad) with 0.13 s segments: its
    inertial torque is about twice joint2's 87 N·m limit while velocities stay near their limits,
    so effort is what saturates in the simulator.
    """
    r = np.array(READY)
    target = r + np.array([0.6, 0.35, 0.0, 0.5, 0.0, -0.35, 0.0])
    seg = 0.8 if short else 1.5
    comfortable = DemoTrajectory("comfortable", (0.0, seg, 2 * seg),
                                 tuple(tuple(p) for p in (r, target, r)),
                                 f"ready → reach → ready, {2 * seg:g} s")
    d = np.zeros(7)
    d[1], d[3] = 0.1, -0.07
    shakes = [r, r + d, r - d, r + d] + ([] if short else [r - d, r + d]) + [r]
    T = 0.13
    aggressive = DemoTrajectory("aggressive", tuple(i * T for i in range(len(shakes))),
                                tuple(tuple(p) for p in shakes),
                                f"joint2/joint4 shake, {T:g} s segments")
    return comfortable, aggressive


#: The task-limits scene's limits file: the URDF's joint limits plus a 250 mm/s TCP speed limit.
DEMO_TASK_LIMITS = Path(__file__).resolve().parents[3] / "config" / "demo_task_limits.yaml"
TASK_PLACE = "panda_hand"


def task_transfer() -> DemoTrajectory:
    """ready → a 1 rad swing of joint1 (with joint2/4/6) → ready in 1 s segments: inside every
    joint limit (joint1 at 86% of its speed, efforts lower) but the TCP moves at 0.64 m/s."""
    r = np.array(READY)
    target = r + np.array([1.0, 0.2, 0.0, 0.3, 0.0, -0.1, 0.0])
    return DemoTrajectory("fast transfer", (0.0, 1.0, 2.0), tuple(tuple(p) for p in (r, target, r)),
                          "ready → joint1 +1 rad → ready, 2 s")


# --------------------------------------------------------------------------------------------
# Statistics on what was observed
# --------------------------------------------------------------------------------------------
def tracking_error(traj: Trajectory, start_s: float, stamps_s: np.ndarray, q: np.ndarray) -> float:
    """Largest |q − reference| (rad) over samples inside [start, end], the JTC quintic reference."""
    t = stamps_s - start_s
    inside = (t >= traj.times[0]) & (t <= traj.times[-1])
    if not np.any(inside):
        return math.nan
    ref, _, _, _ = interpolate(traj, "quintic").evaluate(t[inside])
    return float(np.abs(q[inside] - ref).max())


def effort_residual(measured: dict[int, np.ndarray], model_effort: dict[int, np.ndarray],
                    t0_ns: int, t1_ns: int) -> tuple[float, float, int]:
    """(RMS over joints and samples, max |residual|, samples) of measured − model effort (N·m),
    pairing joint_states and ~/inverse_dynamics by header stamp inside [t0, t1]."""
    keys = sorted(k for k in measured.keys() & model_effort.keys() if t0_ns <= k <= t1_ns)
    if not keys:
        return math.nan, math.nan, 0
    r = np.array([measured[k] - model_effort[k] for k in keys])
    return float(np.sqrt(np.mean(r * r))), float(np.abs(r).max()), len(keys)
