"""The FollowJointTrajectory gate: dyn_node between a planner (MoveIt) and the controller.

With ``gate.controller_action`` set, dyn_node serves ``~/follow_joint_trajectory``
(control_msgs/action/FollowJointTrajectory). Each goal is checked from the robot's current state
like an executed trajectory and decided by :mod:`dyn_node.gate.decision` (``gate.mode``).

- Forwarded (or retimed): the downstream goal response is the client's (a goal the controller
  rejects is rejected); feedback is relayed; the terminal status (SUCCEEDED / ABORTED / CANCELED)
  and the result pass through unchanged; a cancel from the client cancels downstream. Pre-emption
  is the controller's: a new goal forwarded to it ends the running one, and that end is relayed.
- Rejected: accepted, then ended at once ABORTED with ``INVALID_GOAL`` and the verdict line as
  ``error_string`` (a goal response cannot carry text; MoveIt logs the string).
- Downstream absent or silent for ``gate.timeout`` s, or gone mid-goal: ABORTED, ``INVALID_GOAL``,
  with an ``error_string`` saying so. On a clean shutdown what was forwarded is cancelled.

Each decision is published (and recorded) on ``~/gate_decisions`` as a JSON std_msgs/String,
and each forwarded goal's end likewise (``event: result``); ``dyn_node: gate`` in /diagnostics
counts them. Only the decision is on a goal's path: its record (the goal and the forwarded
trajectory as JSON, ~2 ms for 100 points) is made once the client has its goal response, and
before the goal's end record. The action server, the client and their callbacks live on a helper
node spun by an executor of its own, so a goal never waits for dyn_node's executor, nor delays it.
"""
from __future__ import annotations

import json
import threading
import time
import traceback
import uuid
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from action_msgs.msg import GoalStatus
from control_msgs.action import FollowJointTrajectory
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectoryPoint

from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.core.robot.settings import ParamSpec
from dyn_node.core.robot.status import ERROR, NAME_PREFIX, OK, WARN, Status
from dyn_node.core.check.trajectory import Trajectory
from dyn_node.errors import PLANNING_ERROR, STATE_ERROR, TrajectoryError
from dyn_node.gate.decision import (FORWARDED, REJECTED, RETIMED, Decision, GateOptions, decide_goal, goal_dict,
                                    rejected, start_dict)
from dyn_node.ros.fjt_client import ClientThread
from dyn_node.ros.params import KINDS, parameter_descriptor
from dyn_node.ros.sim.action import end_canceled

STATUS_NAME = NAME_PREFIX + "gate"
Result = FollowJointTrajectory.Result

GATE_PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("gate.controller_action", "string", "",
              "downstream FollowJointTrajectory action (e.g. /arm_controller/follow_joint_trajectory); "
              "empty: no gate"),
    ParamSpec("gate.mode", "string", "reject", "reject | retime | check: what the gate does with an "
              "infeasible goal"),
    ParamSpec("gate.retime_all", "bool", False, "retime mode: retime feasible goals too"),
    ParamSpec("gate.timeout", "double", 5.0, "how long (s) the gate waits for the downstream server "
              "and its goal response; also how long it may vanish mid-goal", 0.01, 3600.0),
)
DECISIONS_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
_POLL_S = 0.05  # how often a forwarded goal's execute callback looks at cancel and the server


@dataclass
class _Goal:
    """One goal through the gate, from its goal callback to its end."""

    goal_id: str
    decision: Decision
    down_goal: Any = None
    down: Any = None  # downstream ClientGoalHandle once accepted
    abort_text: str = ""  # ends ABORTED/INVALID_GOAL with this (rejected, downstream trouble)
    handle: Any = None
    feedback: list = field(default_factory=list)  # received before the client's goal was accepted
    heard: float = field(default_factory=time.monotonic)  # last feedback (monotonic s)
    record: Callable[[], None] | None = None  # publishes the decision's record, once


def declare_gate_parameters(node: Node) -> dict[str, Any]:
    out = {}
    for p in GATE_PARAMETERS:
        d: ParameterDescriptor = parameter_descriptor(p.name, KINDS[p.kind], p.description, low=p.low,
                                                      high=p.high, read_only=True)
        out[p.name] = node.declare_parameter(p.name, p.default, d).value
    return out


def to_joint_trajectory(template: Any, tr: Trajectory, names: list[str]) -> Any:
    """``template`` (the goal's JointTrajectory, header kept) with ``tr``'s points (model order)."""
    msg = type(template)()
    msg.header = template.header
    msg.joint_names = list(names)
    for i, t in enumerate(tr.times):
        p = JointTrajectoryPoint(positions=tr.positions[i].tolist())
        if tr.velocities is not None:
            p.velocities = tr.velocities[i].tolist()
        if tr.accelerations is not None:
            p.accelerations = tr.accelerations[i].tolist()
        sec = int(np.floor(t))
        p.time_from_start.sec, p.time_from_start.nanosec = sec, min(int(round((t - sec) * 1e9)), 999_999_999)
        msg.points.append(p)
    return msg


class Gate:
    """The gate of one DynNode. ``state()`` → (core, StartState | None): the node's model and
    settings and the robot's state now (:meth:`dyn_node.ros.node.DynNode.execution_state`);
    ``publish(pub, msg)`` publishes and records."""

    def __init__(self, node: Node, params: dict[str, Any], state: Callable[[], tuple[Any, Any]],
                 publish: Callable[[Any, Any], None]):
        self.options = GateOptions(mode=params["gate.mode"], retime_all=params["gate.retime_all"])
        self.downstream = params["gate.controller_action"]
        self.timeout = float(params["gate.timeout"])
        self._state, self._publish = state, publish
        self._lock = threading.Lock()
        self._check_lock = threading.Lock()  # one check at a time, on one Dynamics
        self._dyn: Dynamics | None = None
        self._goals: dict[int, _Goal] = {}  # id(goal request) → goal, until its execution starts
        self._running_goals: dict[int, _Goal] = {}
        self.counts = {FORWARDED: 0, REJECTED: 0, RETIMED: 0, "downstream_failures": 0}
        self.last_line = ""
        self.last_decision = ""
        self._closing = False
        self.pub = node.create_publisher(String, "~/gate_decisions", DECISIONS_QOS)
        self.server_name = node.resolve_topic_name("~/follow_joint_trajectory")
        self.io = Node("_dyn_node_gate", context=node.context, namespace=node.get_namespace(),
                       use_global_arguments=False, enable_rosout=False, start_parameter_services=False)
        # the downstream client on a thread of its own (see ClientThread: requests and responses
        # on one thread); the server in a group of its own (an action waitable run by two threads
        # at once loses requests); execute callbacks run as tasks, outside any group
        self.down = ClientThread(node.context, self.downstream, "_dyn_node_gate_client",
                                 namespace=node.get_namespace(), use_global_arguments=False)
        self.client = self.down.client
        self.server = ActionServer(self.io, FollowJointTrajectory, self.server_name,
                                   execute_callback=self._execute, goal_callback=self._on_goal,
                                   handle_accepted_callback=self._on_accepted,
                                   cancel_callback=lambda _h: CancelResponse.ACCEPT,
                                   callback_group=MutuallyExclusiveCallbackGroup())
        self.logger = node.get_logger()
        self.executor = MultiThreadedExecutor(num_threads=4, context=node.context)
        self.executor.add_node(self.io)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="dyn_node gate", daemon=True)
        self._thread.start()
        self.logger.info(f"gate: {self.server_name} → {self.downstream} ({self.options.mode})")

    def _spin(self) -> None:
        # spin_once with a stop flag (see dyn_node.ros.sim.action.JtcFace._spin)
        while not self._stop.is_set() and self.executor.context.ok():
            self.executor.spin_once(timeout_sec=0.1)

    # --- the decision (goal callback) -----------------------------------------------------------
    def _check(self, goal: Any) -> tuple[Decision, list[str], dict]:
        """The decision, the model's joint names, and what the record needs of the decision's
        inputs (the goal's arrays and the start state, made JSON-ready by :meth:`_record`)."""
        core, start = self._state()
        pts = goal.trajectory.points
        arrays = (list(goal.trajectory.joint_names),
                  [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts],
                  [p.positions for p in pts], [p.velocities for p in pts], [p.accelerations for p in pts])
        inputs = {"arrays": arrays, "start": start}
        if core is None:
            return rejected(TrajectoryError("no robot model yet", code="no_model")), [], inputs
        model, settings = core.model, core.settings
        with self._check_lock:
            if self._dyn is None or self._dyn.model is not model:
                self._dyn = Dynamics(model, DynamicsOptions(include_friction=settings.include_friction))
            return (decide_goal(self._dyn, settings, self.options, *arrays, start=start),
                    list(model.joint_names), inputs)

    def _on_goal(self, goal: Any) -> GoalResponse:
        try:
            return self._answer(goal)
        except Exception:  # the client gets an answer whatever happens here
            self.logger.error(f"gate: goal callback failed, goal rejected:\n{traceback.format_exc()}")
            return GoalResponse.REJECT

    def _answer(self, goal: Any) -> GoalResponse:
        gid = uuid.uuid4().hex  # the gate's own id: rclpy shows the goal callback no goal id
        try:
            decision, names, inputs = self._check(goal)
        except Exception as exc:  # a failing check must still answer the client
            decision, names, inputs = rejected(TrajectoryError(f"check failed: {exc!r}", code="evaluation_failed")), [], {}
        g = _Goal(goal_id=gid, decision=decision)
        with self._lock:
            self.counts[decision.decision] += 1
            self.last_line, self.last_decision = decision.line, decision.decision
        g.record = lambda: self._record(g, names, goal, inputs)
        if not decision.forwards:
            g.abort_text = decision.error_string
            return self._keep(goal, g, GoalResponse.ACCEPT)
        down_goal = goal
        if decision.decision == RETIMED:
            down_goal = FollowJointTrajectory.Goal()
            for f in down_goal.get_fields_and_field_types():
                setattr(down_goal, f, getattr(goal, f))
            down_goal.trajectory = to_joint_trajectory(goal.trajectory, decision.trajectory, names)
        g.down_goal = down_goal
        try:
            return self._keep(goal, g, self._forward(g))
        except Exception:  # answered REJECT by _on_goal: no execution will record the decision
            self._publish_decision(g)
            raise

    def _keep(self, goal: Any, g: _Goal, response: GoalResponse) -> GoalResponse:
        if response == GoalResponse.ACCEPT:
            with self._lock:
                self._goals[id(goal)] = g
        return response

    def _forward(self, g: _Goal) -> GoalResponse:
        """Send downstream and wait for its goal response (at most gate.timeout s each)."""
        if not self.client.wait_for_server(timeout_sec=self.timeout):
            return self._downstream_failed(g, f"downstream action server {self.downstream} not available "
                                              f"within {self.timeout:g} s (gate.timeout)")
        fut = self.down.call(lambda: self.client.send_goal_async(g.down_goal,
                                                                 feedback_callback=lambda m: self._relay(g, m)),
                             self.timeout)
        done = threading.Event()
        if fut is not None:
            fut.add_done_callback(lambda _f: done.set())
        if fut is None or not done.wait(self.timeout):
            return self._downstream_failed(g, f"downstream action server {self.downstream} did not answer "
                                              f"the goal request within {self.timeout:g} s (gate.timeout)")
        g.down = fut.result()
        if not g.down.accepted:  # no execution follows: the decision is recorded here
            self._publish_decision(g)
            self._record_result(g, "downstream_rejected", None, None)
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _downstream_failed(self, g: _Goal, text: str) -> GoalResponse:
        with self._lock:
            self.counts["downstream_failures"] += 1
        g.abort_text = f"dyn_node gate: {text}"
        self.logger.error(g.abort_text)
        return GoalResponse.ACCEPT

    # --- execution ------------------------------------------------------------------------------
    def _on_accepted(self, handle: Any) -> None:
        with self._lock:
            g = self._goals[id(handle.request)]
            g.handle, early = handle, g.feedback
            g.feedback = []
        for fb in early:
            handle.publish_feedback(fb)
        handle.execute()

    def _relay(self, g: _Goal, msg: Any) -> None:
        g.heard = time.monotonic()
        with self._lock:
            if g.handle is None:
                g.feedback.append(msg.feedback)
                return
        if g.handle.is_active:
            g.handle.publish_feedback(msg.feedback)

    def _execute(self, handle: Any) -> Any:
        with self._lock:
            g = self._goals.pop(id(handle.request))
            if not g.abort_text:
                self._running_goals[id(g)] = g  # a clean shutdown cancels it from now on
        try:
            self._publish_decision(g)
            if g.abort_text:
                handle.abort()
                return Result(error_code=Result.INVALID_GOAL, error_string=g.abort_text)
            return self._follow(handle, g)
        finally:
            with self._lock:
                self._running_goals.pop(id(g), None)

    def _follow(self, handle: Any, g: _Goal) -> Any:
        """Wait for the downstream result, passing a cancel on. The controller is taken for gone
        when it sends no feedback (joint_trajectory_controller sends it at 20 Hz) for
        gate.timeout s: a killed process stays in the DDS graph until its lease ends (20 s)."""
        fut = self.down.call(g.down.get_result_async, self.timeout)
        done = threading.Event()
        if fut is not None:
            fut.add_done_callback(lambda _f: done.set())
        cancel_sent = False
        g.heard = time.monotonic()
        while not done.wait(_POLL_S):
            if handle.is_cancel_requested and not cancel_sent:
                self.down.call(g.down.cancel_goal_async, self.timeout)
                cancel_sent = True
            if time.monotonic() - g.heard > self.timeout:
                text = (f"dyn_node gate: downstream action server {self.downstream} went away during "
                        f"the goal (no feedback and no result for {self.timeout:g} s)")
                with self._lock:
                    self.counts["downstream_failures"] += 1
                self.logger.error(text)
                self._record_result(g, "downstream_lost", GoalStatus.STATUS_ABORTED, None)
                handle.abort()
                return Result(error_code=Result.INVALID_GOAL, error_string=text)
        res = fut.result()
        self._record_result(g, "result", res.status, res.result)
        if res.status == GoalStatus.STATUS_SUCCEEDED:
            handle.succeed()
        elif res.status == GoalStatus.STATUS_CANCELED:
            end_canceled(handle)  # cancelled by the client, or pre-empted by the controller
        else:
            handle.abort()
        return res.result

    # --- records and status ---------------------------------------------------------------------
    def _publish_decision(self, g: _Goal) -> None:
        """The decision's record and log line, off the goal's path: from its execution (the
        client has its goal response, the controller its goal), or before a REJECT answer; always
        before the goal's ``event: result`` record. A failing record never fails the goal."""
        with self._lock:  # once: execution and close() may both get here
            record, g.record = g.record, None
        if record is None:
            return
        try:
            record()
        except Exception:
            self.logger.error(f"gate {g.goal_id[:8]}: decision record failed:\n{traceback.format_exc()}")

    def _record(self, g: _Goal, names: list[str], goal: Any, inputs: dict) -> None:
        d = g.decision
        rec = d.to_dict(goal_id=g.goal_id, mode=self.options.mode, joint_names=names)
        if inputs:
            rec.update(goal=goal_dict(*inputs["arrays"]), start=start_dict(inputs["start"]),
                       retime_all=self.options.retime_all)
        rec.update(event="decision", downstream=self.downstream, tolerances={
            "path": [[t.name, t.position, t.velocity, t.acceleration] for t in goal.path_tolerance],
            "goal": [[t.name, t.position, t.velocity, t.acceleration] for t in goal.goal_tolerance],
            "goal_time_s": goal.goal_time_tolerance.sec + goal.goal_time_tolerance.nanosec * 1e-9})
        line = f"gate {g.goal_id[:8]}: {d.line}"
        if d.decision == REJECTED:  # one severity per call site: rclpy's logger insists
            self.logger.warning(line)
        else:
            self.logger.info(line)
        self._publish(self.pub, String(data=json.dumps(rec, allow_nan=False)))

    def _record_result(self, g: _Goal, event: str, status: int | None, result: Any) -> None:
        rec = {"version": 1, "event": event, "goal_id": g.goal_id, "status": status,
               "error_code": None if result is None else int(result.error_code),
               "error_string": "" if result is None else result.error_string}
        self._publish(self.pub, String(data=json.dumps(rec, allow_nan=False)))

    def status(self) -> Status:
        with self._lock:
            counts, line, last = dict(self.counts), self.last_line, self.last_decision
        values = {"mode": self.options.mode, "controller_action": self.downstream,
                  "forwarded": counts[FORWARDED], "rejected": counts[REJECTED], "retimed": counts[RETIMED],
                  "downstream_failures": counts["downstream_failures"], "last_decision": line}
        if not self.client.server_is_ready():
            values["failure_label"] = STATE_ERROR
            return Status(STATUS_NAME, ERROR, f"downstream action server {self.downstream} not available",
                          values=values)
        if last == REJECTED:
            values["failure_label"] = PLANNING_ERROR
            return Status(STATUS_NAME, WARN, f"last goal {line}", values=values)
        return Status(STATUS_NAME, OK, line or "no goal yet", values=values)

    def close(self) -> None:
        """Cancel what was forwarded and is still running (waiting up to gate.timeout s for the
        controller to confirm), then stop. A crash cancels nothing: the client's own timeout applies."""
        self._closing = True
        with self._lock:
            goals = list(self._running_goals.values())
            unexecuted = list(self._goals.values())
        for g in unexecuted:  # answered, never executed: their decisions still go in the bag
            self._publish_decision(g)
        waits = []
        deadline = time.monotonic() + self.timeout
        for g in goals:
            done = threading.Event()
            fut = self.down.call(g.down.cancel_goal_async, max(0.1, deadline - time.monotonic()))
            if fut is not None:
                fut.add_done_callback(lambda _f, e=done: e.set())
                waits.append(done)
        confirmed = sum(done.wait(max(0.0, deadline - time.monotonic())) for done in waits)
        if goals:
            self.logger.info(f"gate: shutting down, {len(goals)} forwarded goal(s) cancelled "
                             f"({confirmed} confirmed by {self.downstream})")
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.server.destroy()
        self.down.close()
        self.executor.shutdown(timeout_sec=2.0)
        self.io.destroy_node()


def attach_gate(node: Any, params: dict[str, Any]) -> Gate | None:
    """Start the gate of ``node`` (a DynNode, recording set up) when ``gate.controller_action`` is
    set in ``params`` (:func:`declare_gate_parameters`); None otherwise."""
    if not params["gate.controller_action"]:
        return None
    gate = Gate(node, params, node.execution_state, node._publish)
    node.recording.add_publisher(gate.pub)
    node.status_providers.append(gate.status)
    return gate
