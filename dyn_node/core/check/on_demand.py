"""On-demand answers without ROS: the verdict on one trajectory, and torques for given states.

The node's question services (``~/check_trajectory``, ``~/compute_inverse_dynamics``,
``~/retime_trajectory``) and the ``dyn-check`` command answer through these functions (the node's execute path, ``joint_trajectory``, applies the same
rules inline because it hands the validated trajectory to the controller tracker in between).
Arrays cross in the message's joint order on the way in and come back in model order; pure
(no rclpy).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from dyn_node.core.check import feasibility, task_motion
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.errors import TrajectoryError
from dyn_node.core.robot.settings import Settings
from dyn_node.core.robot.status import Status
from dyn_node.core.check.trajectory import Trajectory, check_joint_names, validate_trajectory

#: ``request`` key of every verdict: what was asked.
REQUEST_EXECUTE, REQUEST_CHECK, REQUEST_INVERSE_DYNAMICS = "execute", "check", "inverse_dynamics"
REQUEST_RETIME = "retime"
#: why a question's start segment is not checked when it did not ask for the robot's state
START_NOT_REQUESTED = "from_current_state not set"


def question_start_unknown(from_current_state: bool) -> str:
    """Why a question's start segment goes unchecked when it has no state (node and audit)."""
    return feasibility.NO_CURRENT_STATE if from_current_state else START_NOT_REQUESTED


@dataclass(frozen=True)
class CheckOutcome:
    """One trajectory's verdict: ``statuses`` as the node publishes them on ``~/feasibility``;
    ``result`` when it could be checked, else ``error`` (the reason it was rejected)."""

    statuses: list[Status]
    result: feasibility.FeasibilityResult | None = None
    error: TrajectoryError | None = None
    trajectory: Trajectory | None = None

    @property
    def feasible(self) -> bool:
        return self.result is not None and bool(self.result.feasible)


def options_for(settings: Settings) -> feasibility.FeasibilityOptions:
    """The feasibility options the node derives from its settings."""
    return feasibility.FeasibilityOptions(
        sample_period=settings.sample_period, effort_warn_ratio=settings.effort_warn_ratio,
        execution=feasibility.ExecutionOptions(
            allow_nonzero_velocity_at_trajectory_end=settings.allow_nonzero_velocity_at_trajectory_end))


def check(dynamics: Dynamics, settings: Settings, names: Sequence[str], times: Sequence[float],
          positions: Any, velocities: Any = None, accelerations: Any = None, *,
          start: feasibility.StartState | None = None,
          start_unknown: str = "no current state given", efforts: Any = None,
          timing: feasibility.Timing | None = None,
          execution: feasibility.ExecutionOptions | None = None) -> CheckOutcome:
    """Validate and check one trajectory by the node's rules (ros2_control's validation; a single
    point is valid but cannot be checked) and return what the node would publish. ``start`` /
    ``start_unknown``, ``timing`` (header stamp and receipt; None: zero stamp) and
    ``execution``: as for :func:`feasibility.check_trajectory` (the execution model);
    ``efforts``: the points' effort lists, only validated (each empty or one per joint, as the
    controller requires)."""
    model = dynamics.model
    hid = model.name
    duration = float(times[-1]) if len(times) and all(map(math.isfinite, times)) else 0.0
    try:
        traj = validated(model.joint_names, names, times, positions, velocities, accelerations,
                         efforts=efforts)
        result = feasibility.check_trajectory(dynamics, traj, options_for(settings), start=start,
                                              start_unknown=start_unknown, timing=timing,
                                              execution=execution)
    except TrajectoryError as exc:
        return CheckOutcome(feasibility.rejected_statuses(exc, hid, len(times), duration), error=exc)
    return CheckOutcome(result.statuses(hid), result=result, trajectory=traj)


def validated(model_joints: Sequence[str], names: Sequence[str], times: Sequence[float],
              positions: Any, velocities: Any = None, accelerations: Any = None, *,
              efforts: Any = None) -> Trajectory:
    """A trajectory to check or retime, validated by the node's rules (``efforts``: as for
    joint_trajectory, each point's empty or one per joint); raises TrajectoryError."""
    args = (model_joints, names, times, positions, velocities, accelerations)
    # first as a command (one point is valid), then as something to check (two or more),
    # so a malformed single point is rejected for what is wrong with it, as the node does
    traj = validate_trajectory(*args, min_points=1, efforts=efforts)
    if traj.n_points < 2:
        validate_trajectory(*args, min_points=2)
    return traj


def with_request(statuses: Sequence[Status], request: str) -> list[Status]:
    """``statuses`` with the key ``request`` added to the summary (first) status."""
    if not statuses:
        return []
    first = statuses[0]
    values = {**first.values, "request": request}
    return [Status(first.name, first.level, first.message, first.hardware_id, values), *statuses[1:]]


def states(model_joints: Sequence[str], names: Sequence[str], positions: Any,
           velocities: Any = None, accelerations: Any = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Q, V, A), N×nv in model order, from per-point rows in ``names`` order. A point's empty
    velocities or accelerations mean zero (so positions alone ask for gravity); anything else
    malformed raises :class:`TrajectoryError` naming the point and field."""
    names = check_joint_names(model_joints, names, what="request")
    n_pts = len(positions)
    if n_pts == 0:
        raise TrajectoryError("request has no points", code="empty_points")
    order = np.array([names.index(n) for n in model_joints])
    out = []
    for field, rows, required in (("positions", positions, True), ("velocities", velocities, False),
                                  ("accelerations", accelerations, False)):
        m = np.zeros((n_pts, len(names)))
        for i in range(n_pts):
            r = rows[i] if rows is not None and len(rows) > i else ()
            if len(r) == 0 and not required:
                continue
            if len(r) != len(names):
                raise TrajectoryError(f"point {i}: {len(r)} {field} for {len(names)} joints",
                                      code="length_mismatch")
            m[i] = np.asarray(r, dtype=float)
        if not np.all(np.isfinite(m)):
            i, j = np.argwhere(~np.isfinite(m))[0]
            raise TrajectoryError(f"point {i}: {field} of {names[j]} is {m[i, j]}", code="non_finite")
        out.append(np.ascontiguousarray(m[:, order]))
    return out[0], out[1], out[2]


def inverse_dynamics(dynamics: Dynamics, Q: np.ndarray, V: np.ndarray, A: np.ndarray) -> np.ndarray:
    """τ for N states (N×nv, model order), computed exactly as the feasibility check computes its
    sample torques (friction and payload included; with a task section, by the frame pass,
    plus J_frameᵀ·W of a task wrench, else :meth:`Dynamics.terms_batch`), so a state that is
    also a check sample gets the same bits."""
    try:
        tau = task_motion.inverse_dynamics(dynamics, Q, V, A)
        if tau is None:
            tau = np.ascontiguousarray(dynamics.terms_batch(Q, V, A).full)
    except (ArithmeticError, ValueError, RuntimeError) as exc:
        raise TrajectoryError(f"torques could not be evaluated: {type(exc).__name__}: {exc}",
                              code="evaluation_failed") from exc
    if not np.all(np.isfinite(tau)):
        i = int(np.argwhere(~np.isfinite(tau))[0][0])
        raise TrajectoryError(f"point {i}: the torque is not finite (state too large)", code="non_finite")
    return tau
