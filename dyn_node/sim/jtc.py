"""joint_trajectory_controller's goal rules (ros2_controllers, Jazzy), pure: what dyn_sim's
FollowJointTrajectory server decides, without rclpy.

- Goal validation: :func:`dyn_node.core.check.trajectory.validate_trajectory` (the controller's
  joint, length and time rules) and the execution model's refusals
  (:func:`dyn_node.core.check.execution.refusals`: a non-zero last velocity, a stamped end in the
  past), which the check judges by too.
- Tolerances: the controller's defaults (``constraints.*`` parameters) overridden per joint by the
  goal's (a positive value replaces the default, -1 erases it, 0 keeps it; any other negative
  value, or a joint the controller does not have, makes the controller use its defaults).
- Monitoring, once per controller update: before the last point's time the path tolerance
  (PATH_TOLERANCE_VIOLATED); after it the goal tolerance, SUCCESSFUL once inside it, and
  GOAL_TOLERANCE_VIOLATED when still outside ``goal_time_tolerance`` after the end (a zero
  goal_time_tolerance waits for ever, as the controller does).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np


#: FollowJointTrajectory.Result error codes (control_msgs 5.x)
SUCCESSFUL, INVALID_GOAL, INVALID_JOINTS, OLD_HEADER_TIMESTAMP = 0, -1, -2, -3
PATH_TOLERANCE_VIOLATED, GOAL_TOLERANCE_VIOLATED = -4, -5

#: the controller's result strings (joint_trajectory_controller.cpp, Jazzy)
SUCCESS_TEXT = "Goal successfully reached!"
PATH_TEXT = "Aborted due to path tolerance violation"
PREEMPTED_TEXT = "Current goal cancelled due to new incoming action."
_ERASE = -1.0
_FLOAT_EPS = float(np.finfo(np.float32).eps)


@dataclass(frozen=True)
class JointTolerances:
    """Per-joint (model order) position, velocity and acceleration tolerances; 0 = not checked."""

    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray

    @staticmethod
    def uniform(n: int, position: float = 0.0, velocity: float = 0.0,
                acceleration: float = 0.0) -> "JointTolerances":
        return JointTolerances(np.full(n, float(position)), np.full(n, float(velocity)),
                               np.full(n, float(acceleration)))


@dataclass(frozen=True)
class SegmentTolerances:
    """``path`` applies while the trajectory plays, ``goal`` after its last point, which must be
    met within ``goal_time`` s of the end (0: no limit)."""

    path: JointTolerances
    goal: JointTolerances
    goal_time: float


def default_tolerances(n: int, *, trajectory: float | Sequence[float] = 0.0,
                       goal: float | Sequence[float] = 0.0, stopped_velocity: float = 0.01,
                       goal_time: float = 0.0) -> SegmentTolerances:
    """The controller's defaults from its ``constraints`` parameters (tolerances.hpp,
    get_segment_tolerances(params)): per joint the path position tolerance ``trajectory`` and the
    goal position tolerance ``goal`` (one value or one per joint), every joint's goal velocity
    tolerance ``stopped_velocity``; nothing on path velocity or acceleration."""
    zero = np.zeros(n)
    path = JointTolerances(np.broadcast_to(np.asarray(trajectory, float), (n,)).copy(), zero, zero.copy())
    end = JointTolerances(np.broadcast_to(np.asarray(goal, float), (n,)).copy(),
                          np.full(n, float(stopped_velocity)), zero.copy())
    return SegmentTolerances(path, end, float(goal_time))


def _resolve(default: float, value: float) -> float:
    if value > 0.0:
        return float(value)
    if abs(value - _ERASE) < _FLOAT_EPS:
        return 0.0
    if value < 0.0:
        raise ValueError(f"illegal tolerance {value}")
    return float(default)


def _override(base: JointTolerances, joints: Sequence[str],
              entries: Sequence[tuple[str, float, float, float]]) -> JointTolerances:
    p, v, a = base.position.copy(), base.velocity.copy(), base.acceleration.copy()
    for name, tp, tv, ta in entries:
        if name not in joints:
            raise ValueError(f"unknown joint {name!r}")
        i = list(joints).index(name)
        p[i], v[i], a[i] = _resolve(p[i], tp), _resolve(v[i], tv), _resolve(a[i], ta)
    return JointTolerances(p, v, a)


def goal_tolerances(defaults: SegmentTolerances, joints: Sequence[str],
                    path: Sequence[tuple[str, float, float, float]],
                    goal: Sequence[tuple[str, float, float, float]],
                    goal_time: float) -> tuple[SegmentTolerances, str]:
    """The tolerances a goal runs with, and "" or why the defaults were used instead (the
    controller logs it and keeps the goal)."""
    try:
        return SegmentTolerances(_override(defaults.path, joints, path),
                                 _override(defaults.goal, joints, goal),
                                 _resolve(defaults.goal_time, goal_time)), ""
    except ValueError as exc:
        return defaults, f"{exc}: using the default tolerances"


def _within(err_p: np.ndarray, err_v: np.ndarray, tol: JointTolerances) -> np.ndarray:
    ok = np.ones(len(err_p), dtype=bool)
    for e, t in ((err_p, tol.position), (err_v, tol.velocity)):
        ok &= (t <= 0.0) | (np.abs(e) <= t)
    return ok  # acceleration error: the simulator has no acceleration state (the controller's 0)


@dataclass(frozen=True)
class Outcome:
    """A goal's end: ``code`` (a Result error code) and the controller's ``text``."""

    code: int
    text: str


def monitor(t: float, end_time: float, err_p: np.ndarray, err_v: np.ndarray,
            tol: SegmentTolerances, joints: Sequence[str]) -> Outcome | None:
    """One controller update of an active goal: its end, or None while it continues.

    ``err_*`` = reference − measured (model order) at simulation time ``t``; ``end_time`` is the
    last point's time. The controller checks the path tolerance up to the end and the goal
    tolerance after it.
    """
    if t < end_time:
        ok = _within(err_p, err_v, tol.path)
        if not ok.all():
            return Outcome(PATH_TOLERANCE_VIOLATED, PATH_TEXT)
        return None
    if _within(err_p, err_v, tol.goal).all():
        return Outcome(SUCCESSFUL, SUCCESS_TEXT)
    late = t - end_time
    if tol.goal_time != 0.0 and late > tol.goal_time:
        bad = [j for j, ok in zip(joints, _within(err_p, err_v, tol.goal)) if not ok]
        return Outcome(GOAL_TOLERANCE_VIOLATED,
                       f"Aborted due to goal_time_tolerance exceeding by {late:.6f} seconds "
                       f"(outside the goal tolerance: {', '.join(bad)})")
    return None


def duration_s(sec: int, nanosec: int) -> float:
    value = sec + nanosec * 1e-9
    return value if math.isfinite(value) else math.nan
