"""The question services' computation on arrays: one :class:`Question` in, the core's answer out.

The node's ``~/check_trajectory``, ``~/compute_inverse_dynamics`` and ``~/retime_trajectory``
convert a request to a Question (in the ROS adapter), and :func:`answer` computes it with the
same core functions ``dyn-check`` and the audit use. Questions and answers are plain picklable
objects (arrays, dataclasses), so the answer can be computed in the question worker process
(:mod:`dyn_node.core.live.question_process`) with exactly the numbers of an in-process call.
Pure (no rclpy).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from dyn_node.core.check import feasibility, on_demand
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.settings import Settings
from dyn_node.core.robot.status import Status
from dyn_node.errors import TrajectoryError

CHECK, INVERSE_DYNAMICS, RETIME = "check", "inverse_dynamics", "retime"
KINDS = (CHECK, INVERSE_DYNAMICS, RETIME)
RETIMER_UNAVAILABLE = "retimer_unavailable"


@dataclass(frozen=True)
class Question:
    """One request as arrays, in the request's joint order: ``positions`` … ``efforts`` are N×k
    arrays, or lists of per-point rows when the points disagree in length (validation names the
    odd one). ``start``: the robot's state at receipt (``from_current_state``), else None."""

    kind: str
    names: Sequence[str]
    times: Sequence[float]
    positions: Any
    velocities: Any
    accelerations: Any
    efforts: Any
    start: feasibility.StartState | None = None
    from_current_state: bool = False

    @property
    def n_points(self) -> int:
        return len(self.positions)


@dataclass(frozen=True)
class Refusal:
    """A question not answered: ``reason`` (a TrajectoryError code, ``retimer_unavailable``,
    ...) and the one-line message."""

    reason: str
    message: str


@dataclass(frozen=True)
class CheckAnswer:
    """What a check's response carries, taken from the core's
    :class:`~dyn_node.core.check.on_demand.CheckOutcome` (its result's fields as they are): the
    outcome itself holds the samples (~10 MB for 20,000 points), which would cost the node more
    to unpickle than the response needs."""

    statuses: list[Status]
    error: TrajectoryError | None = None
    feasible: bool = False
    time_scale: float = math.nan
    worst_joint: str = ""
    worst_constraint: str = ""
    worst_ratio: float = math.nan
    first_violation_time_s: float = math.nan
    time_scale_joint: str = ""
    time_scale_constraint: str = ""
    message: str = ""
    start_segment: Any = ""
    waypoint_effort: np.ndarray | None = None

    @classmethod
    def of(cls, outcome: on_demand.CheckOutcome) -> CheckAnswer:
        r = outcome.result
        if r is None:
            return cls(outcome.statuses, outcome.error)
        return cls(outcome.statuses, None, r.feasible, r.time_scale, r.worst_joint,
                   r.worst_constraint, r.worst_ratio, r.first_violation_time_s, r.time_scale_joint,
                   r.time_scale_constraint, r.message, r.start_segment, r.waypoint_effort)


@dataclass(frozen=True)
class RetimeAnswer:
    """What a retime's response carries, from the retimer's result (``statuses``: its exact
    re-check's, None when it has none)."""

    feasible: bool
    trajectory: Any
    duration_in: float
    duration_out: float
    duration_uniform: float
    lower_bound: float
    message: str
    blocked: Any
    statuses: list[Status] | None

    @classmethod
    def of(cls, result: Any, hardware_id: str) -> RetimeAnswer:
        return cls(result.feasible, result.trajectory, result.duration_in, result.duration_out,
                   result.duration_uniform, result.lower_bound, result.message, result.blocked,
                   None if result.check is None else result.check.statuses(hardware_id))


def answer(dynamics: Dynamics, settings: Settings, question: Question) -> Any:
    """The core's answer to ``question``: a :class:`CheckAnswer` (check), the N×nv torques in
    model order (inverse dynamics), a :class:`RetimeAnswer` (retime), or a :class:`Refusal`
    saying why not."""
    q = question
    if q.kind == CHECK:
        return CheckAnswer.of(on_demand.check(
            dynamics, settings, q.names, q.times, q.positions, q.velocities, q.accelerations,
            start=q.start, start_unknown=on_demand.question_start_unknown(q.from_current_state),
            efforts=q.efforts))
    try:
        if q.kind == INVERSE_DYNAMICS:
            Q, V, A = on_demand.states(dynamics.model.joint_names, q.names, q.positions,
                                       q.velocities, q.accelerations)
            return on_demand.inverse_dynamics(dynamics, Q, V, A)
        if q.kind == RETIME:
            return _retime(dynamics, settings, q)
    except TrajectoryError as exc:
        return Refusal(exc.code or "invalid", str(exc))
    raise ValueError(f"unknown question kind {q.kind!r}")


def _retime(dynamics: Dynamics, settings: Settings, q: Question) -> Any:
    # validated first: a malformed request says what is wrong, retimer or not
    traj = on_demand.validated(dynamics.model.joint_names, q.names, q.times, q.positions,
                               q.velocities, q.accelerations, efforts=q.efforts)
    try:  # imported here: answered (not accepted) when the retimer is not there
        from dyn_node.retime import retime
    except ImportError as exc:
        return Refusal(RETIMER_UNAVAILABLE, f"the retimer is not available: {exc}")
    result = retime(dynamics, traj, start=q.start, feasibility=on_demand.options_for(settings),
                    limit_margin=settings.retime_limit_margin)
    return RetimeAnswer.of(result, dynamics.model.name)


def warm_up(dynamics: Dynamics, settings: Settings) -> None:
    """Answer a two-point check once, so the compiled kernels are loaded before the first request."""
    n = dynamics.model.nv
    answer(dynamics, settings, Question(CHECK, list(dynamics.model.joint_names), [0.0, 1.0],
                                        np.zeros((2, n)), None, None, None))


__all__ = ["Question", "Refusal", "CheckAnswer", "RetimeAnswer", "answer", "warm_up", "CHECK", "INVERSE_DYNAMICS", "RETIME", "KINDS"]
