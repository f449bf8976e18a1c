"""The answers of dyn_node's question services, as messages: request in, response filled.

A request becomes a :class:`~dyn_node.core.check.questions.Question` (arrays), the core answers
it (in the question worker process, or in-process for the audit and tests: the same function),
and the answer fills the response. The numbers come from the same core functions ``dyn-check`` and the audit use
(:func:`dyn_node.core.check.on_demand.check`, :func:`~dyn_node.core.check.on_demand.inverse_dynamics`, the
retimer); this module only converts between ``dyn_node_interfaces`` messages and arrays. No
threads, no node: :mod:`dyn_node.ros.services` calls these on its lanes' threads.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
from dyn_node_interfaces.srv import CheckTrajectory, ComputeInverseDynamics, RetimeTrajectory
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from dyn_node.core.check import feasibility, on_demand, questions
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import RobotModel
from dyn_node.core.robot.settings import Settings
from dyn_node.ros.convert import _rows, status_to_msg, trajectory_arrays, trajectory_message

#: reasons of a response that is not accepted, beyond the TrajectoryError codes (non_finite,
#: unknown_joints, empty_points, ...)
BUSY, NO_MODEL, INTERNAL_ERROR, SHUTTING_DOWN, TOO_LARGE, EXPIRED = (
    "busy", "no_model", "internal_error", "shutting_down", "too_large", "expired")
RETIMER_UNAVAILABLE = questions.RETIMER_UNAVAILABLE
#: the question worker process ended while answering (it is restarted)
WORKER_FAILED = "worker_failed"


def reject(response: Any, reason: str, message: str) -> Any:
    """``response`` not accepted, with the reason code and (where it has one) the message."""
    response.accepted = False
    response.reason = reason
    if hasattr(response, "message"):
        response.message = message
    return response


def _start_fields(response: Any, joint_names: Sequence[str],
                  start: feasibility.StartState | None) -> None:
    if start is None:
        response.start_state = JointState()
        response.start_state_age = math.nan
        return
    response.start_state = JointState(name=list(joint_names),
                                      position=np.asarray(start.positions, dtype=float).tolist(),
                                      velocity=np.asarray(start.velocities, dtype=float).tolist())
    response.start_state_age = float(start.age_s)


def with_effort(traj: JointTrajectory, effort_model_order: np.ndarray,
                model_joints: Sequence[str]) -> JointTrajectory:
    """A copy of ``traj`` whose points carry the N×nv model-order efforts in its joint order."""
    order = [list(model_joints).index(n) for n in traj.joint_names]
    eff = np.ascontiguousarray(np.asarray(effort_model_order, dtype=float)[:, order])
    points = [JointTrajectoryPoint(positions=p.positions, velocities=p.velocities,
                                   accelerations=p.accelerations, effort=row.tolist(),
                                   time_from_start=p.time_from_start)
              for p, row in zip(traj.points, eff)]
    return JointTrajectory(header=traj.header, joint_names=list(traj.joint_names), points=points)


def point_efforts(traj: JointTrajectory) -> list[Sequence[float]]:
    """Each point's effort list: validated as joint_trajectory_controller does, never used."""
    return [p.effort for p in traj.points]


def question_of(kind: str, request: Any,
                start: feasibility.StartState | None = None) -> questions.Question:
    """A request as the arrays the core answers (:mod:`dyn_node.core.check.questions`)."""
    traj = request.states if kind == questions.INVERSE_DYNAMICS else request.trajectory
    names, times, P, V, A = trajectory_arrays(traj)
    return questions.Question(kind, names, times, P, V, A, _rows([p.effort for p in traj.points]),
                              start, bool(getattr(request, "from_current_state", False)))


def fill(model: RobotModel, request: Any, response: Any, question: questions.Question,
         result: Any) -> Any:
    """``response`` filled with the core's ``result`` for ``request`` (``question``'s kind)."""
    if question.kind == questions.CHECK:
        return _fill_check(model, request, response, question.start, result)
    if question.kind == questions.INVERSE_DYNAMICS:
        return _fill_inverse_dynamics(model, request, response, result)
    return _fill_retime(model, request, response, question.start, result)


def answer(kind: str, dynamics: Dynamics, settings: Settings, request: Any, response: Any,
           start: feasibility.StartState | None = None) -> Any:
    """``response`` to ``request``, computed in this process (the worker computes the same)."""
    question = question_of(kind, request, start)
    return fill(dynamics.model, request, response, question,
                questions.answer(dynamics, settings, question))


def answer_check(dynamics: Dynamics, settings: Settings, request: CheckTrajectory.Request,
                 response: CheckTrajectory.Response,
                 start: feasibility.StartState | None) -> CheckTrajectory.Response:
    """The verdict on ``request.trajectory`` (from ``start`` when given), as ``dyn-check``'s."""
    return answer(questions.CHECK, dynamics, settings, request, response, start)


def answer_inverse_dynamics(dynamics: Dynamics, request: ComputeInverseDynamics.Request,
                            response: ComputeInverseDynamics.Response) -> ComputeInverseDynamics.Response:
    """τ(q, q̇, q̈) of each state, exactly as the check computes its sample torques."""
    return answer(questions.INVERSE_DYNAMICS, dynamics, Settings(), request, response)


def answer_retime(dynamics: Dynamics, settings: Settings, request: RetimeTrajectory.Request,
                  response: RetimeTrajectory.Response,
                  start: feasibility.StartState | None) -> RetimeTrajectory.Response:
    """The fastest trajectory along the request's path within every limit (the retimer's)."""
    return answer(questions.RETIME, dynamics, settings, request, response, start)


def _fill_check(model: RobotModel, request: Any, response: Any,
                start: feasibility.StartState | None, r: questions.CheckAnswer) -> Any:
    response.statuses = [status_to_msg(s) for s in
                         on_demand.with_request(r.statuses, on_demand.REQUEST_CHECK)]
    _start_fields(response, model.joint_names, start)
    if r.error is not None:
        return reject(response, r.error.code or "invalid", str(r.error))
    response.accepted = True
    response.reason = ""
    response.feasible = bool(r.feasible)
    response.time_scale = float(r.time_scale)
    response.worst_joint, response.worst_constraint = r.worst_joint, r.worst_constraint
    response.worst_ratio = float(r.worst_ratio)
    response.first_violation_time = float(r.first_violation_time_s)
    response.binding_joint, response.binding_constraint = r.time_scale_joint, r.time_scale_constraint
    response.message = r.message
    response.start_segment = r.start_segment
    response.effort = with_effort(request.trajectory, r.waypoint_effort, model.joint_names)
    return response


def _fill_inverse_dynamics(model: RobotModel, request: Any, response: Any, tau: Any) -> Any:
    if isinstance(tau, questions.Refusal):
        return reject(response, tau.reason, tau.message)
    response.accepted = True
    response.reason = ""
    response.effort = with_effort(request.states, tau, model.joint_names)
    return response


def _fill_retime(model: RobotModel, request: Any, response: Any,
                 start: feasibility.StartState | None, result: Any) -> Any:
    _start_fields(response, model.joint_names, start)
    if isinstance(result, questions.Refusal):
        return reject(response, result.reason, result.message)
    response.accepted = True
    response.reason = ""
    response.feasible = bool(result.feasible)
    if result.trajectory is not None:
        response.trajectory = trajectory_message(result.trajectory, model.joint_names,
                                                 request.trajectory.header)
    response.duration_in = float(result.duration_in)
    response.duration_out = float(result.duration_out)
    response.duration_uniform = float(result.duration_uniform)
    response.lower_bound = float(result.lower_bound)
    response.message = result.message
    response.blocked = result.blocked
    if result.statuses is not None:
        response.statuses = [status_to_msg(s) for s in on_demand.with_request(
            result.statuses, on_demand.REQUEST_RETIME)]
    return response
