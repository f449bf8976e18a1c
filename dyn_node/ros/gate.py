"""The FollowJointTrajectory gate: dyn_node between a planner (MoveIt) and the controller.

With ``gate.controller_action`` set, dyn_node serves ``~/follow_joint_trajectory``
(control_msgs/action/FollowJointTrajectory). Each goal is checked from the robot's current state
like an executed trajectory and decided by :mod:`dyn_node.gate.decision` (``gate.mode``).

- Forwarded (or retimed): the downstream goal response is the client's (a goal the controller
  rejects is rejected); feedback is relayed; the terminal status and the result pass through
  unchanged; a cancel from the client cancels downstream. Pre-emption is the controller's.
- Refused (the check's rejection, a stale state in reject/retime, the gate busy or closing, the
  controller absent or late): accepted, then ended at once ABORTED ``INVALID_GOAL`` with the
  reason as ``error_string`` (a goal response cannot carry text; MoveIt logs the string).
- The invariant: no goal the controller accepted for a client's goal is left running once the
  client's goal ended. A late acceptance is cancelled on arrival; silence for ``gate.timeout``,
  a client cancel and shutdown cancel downstream and wait (bounded) for the controller's end;
  what the controller never confirms is recorded ``downstream_cancel_unconfirmed``.

Each goal's decision and its end are published (and recorded) on ``~/gate_decisions``
(:mod:`dyn_node.gate.outcomes`); ``dyn_node: gate`` in /diagnostics counts them. The action
server and the downstream client live on a helper node spun by one thread of their own; every
goal is a coroutine on it (goal callback, execution, following: rclpy futures, no thread per goal,
no polling). A goal is decided in its goal callback when the gate is idle and its check bounded
(:meth:`Gate._inline`); otherwise its check runs on one worker thread behind a bounded queue
(``gate.max_pending``).
"""
from __future__ import annotations

import json
import queue
import threading
import time
import traceback
import uuid
from dataclasses import dataclass, field
from typing import Any, Callable

from action_msgs.msg import GoalStatus
from builtin_interfaces.msg import Time
from control_msgs.action import FollowJointTrajectory
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.action import ActionClient, ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from dyn_node.core.check.execution import Timing
from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.core.robot.settings import ParamSpec
from dyn_node.core.robot.status import ERROR, NAME_PREFIX, OK, WARN, Status
from dyn_node.errors import STATE_ERROR, TrajectoryError
from dyn_node.gate import outcomes as out
from dyn_node.gate.decision import (FORWARDED, NOT_FORWARDED, REJECTED, RETIMED, Decision, GateOptions, RetimePlan,
                                    decide_goal, goal_dict, rejected, start_dict, timing_dict)
from dyn_node.ros.actions import Waits, end_canceled
from dyn_node.ros.convert import goal_trajectory_message, stamp_to_s, trajectory_arrays
from dyn_node.ros.params import KINDS, parameter_descriptor

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
              "and its goal response, for a sign of life during a goal, and for a cancel's "
              "confirmation", 0.01, 3600.0),
    ParamSpec("gate.max_state_age", "double", 0.1, "reject and retime: the oldest joint_states (s, by "
              "receipt) a goal is checked from; older, none, or without a goal joint: refused "
              "(stale_state, state error)", 0.001, 60.0),
    ParamSpec("gate.start_tolerance", "double", 0.01, "how far (rad) a goal's first point may lie from "
              "the measured state (MoveIt's allowed_start_tolerance)", 0.0, 10.0),
    ParamSpec("gate.max_pending", "integer", 50, "goals waiting for their check at most; one more is "
              "refused at once (gate_busy)", 1, 100000),
)
DECISIONS_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
# a flood of goal requests waits in the server's queue for the executor, not dropped at depth 10
_REQUESTS_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)


@dataclass
class _Goal:
    """One goal through the gate, from its goal callback to its end."""

    goal_id: str
    goal: Any
    receipt_s: float = 0.0  # the node's clock when the goal arrived (the execution model's receipt)
    t0: float = field(default_factory=time.monotonic)
    decision: Decision | None = None
    down_goal: Any = None
    down: Any = None  # downstream ClientGoalHandle once accepted
    end: tuple[str, str] | None = None  # (outcome event, error_string): refused before execution
    handle: Any = None
    feedback: list = field(default_factory=list)  # received before the client's goal was accepted
    heard: float = field(default_factory=time.monotonic)  # last sign of life downstream (monotonic s)
    poke: Any = None  # a future the gate completes to wake the goal's coroutine
    cancel_requested: bool = False  # set by the cancel callback, before rclpy marks the handle
    record: Callable[..., None] | None = None  # publishes the decision's record, once
    names: list = field(default_factory=list)  # the model's joint names (the forwarded trajectory's)


#: the most points a goal decided in its goal callback may have (the check takes ~25 µs a point
#: on the Panda: the executor is held for at most ~15 ms); longer goals go to the check thread
INLINE_MAX_POINTS = 500
#: and the longest (s): the check samples every sample_period (1 ms by default), so a two-point
#: goal lasting minutes is a long check too
INLINE_MAX_DURATION_S = 10.0

#: executor turns close() runs after the spin thread stopped (pending result responses)
_DRAIN_TURNS = 20


def declare_gate_parameters(node: Node) -> dict[str, Any]:
    out_ = {}
    for p in GATE_PARAMETERS:
        d: ParameterDescriptor = parameter_descriptor(p.name, KINDS[p.kind], p.description, low=p.low,
                                                      high=p.high, read_only=True)
        out_[p.name] = node.declare_parameter(p.name, p.default, d).value
    return out_


class Gate:
    """The gate of one DynNode. ``state()`` → (core, StartState | None): the node's model and
    settings and the robot's state now (:meth:`dyn_node.ros.node.DynNode.execution_state`);
    ``publish(pub, msg)`` publishes and records; ``executed(decision, goal, names)``: called for
    each goal the controller accepted (the node publishes its verdict and tracks it)."""

    def __init__(self, node: Node, params: dict[str, Any], state: Callable[[], tuple[Any, Any]],
                 publish: Callable[[Any, Any], None], executed: Callable[..., None] | None = None):
        self.options = GateOptions(mode=params["gate.mode"], retime_all=params["gate.retime_all"],
                                   max_state_age=float(params["gate.max_state_age"]),
                                   start_tolerance=float(params["gate.start_tolerance"]))
        self.downstream = params["gate.controller_action"]
        self.timeout = float(params["gate.timeout"])
        self._state, self._publish, self._executed = state, publish, executed
        self._lock = threading.Lock()
        self._dyn: Dynamics | None = None  # the checks' (one at a time: inline only while none is queued)
        self._retime_s = 0.2  # the retimer's expected run time (s), learnt from its runs
        self._jobs: queue.Queue = queue.Queue(maxsize=int(params["gate.max_pending"]))
        self._pending = 0  # goals queued for or in the check thread
        self._inline_free_at = 0.0  # monotonic s from which a goal may be decided in its callback
        self._goals: dict[int, _Goal] = {}  # id(goal request) → goal, until its execution starts
        self._running: dict[int, _Goal] = {}  # accepted downstream, until the client's goal ends
        self._handles: dict[int, _Goal] = {}  # id(server goal handle) → goal, while it executes
        self._active = 0  # goals between their goal callback and their end
        self._idle = threading.Condition(self._lock)
        self.counts = {FORWARDED: 0, REJECTED: 0, RETIMED: 0, NOT_FORWARDED: 0, "downstream_failures": 0,
                       "forwarded_unchecked": 0, out.CANCEL_UNCONFIRMED: 0, out.GATE_BUSY: 0, out.REFUSED_CLOSING: 0}
        self.last_line = ""
        self.last_decision: Decision | None = None
        self._closing = False
        self.logger = node.get_logger()
        self._clock = node.get_clock()  # the clock goal stamps and joint_states receipts are on
        self.pub = node.create_publisher(String, "~/gate_decisions", DECISIONS_QOS)
        self.server_name = node.resolve_topic_name("~/follow_joint_trajectory")
        self.io = Node("_dyn_node_gate", context=node.context, namespace=node.get_namespace(),
                       use_global_arguments=False, enable_rosout=False, start_parameter_services=False)
        # server and client on one thread: rclpy registers a request's future after sending it,
        # so a second thread taking the response in between would lose it (see fjt_client)
        # and one reentrant group: a mutually exclusive one stays held while a goal's coroutine
        # waits, and nothing else (the client's response, a timer) could run
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(self.io)
        group = ReentrantCallbackGroup()
        self.waits = Waits(self.io, self.executor, group)
        self.client = ActionClient(self.io, FollowJointTrajectory, self.downstream, callback_group=group)
        self.server = ActionServer(self.io, FollowJointTrajectory, self.server_name,
                                   execute_callback=self._execute, goal_callback=self._on_goal,
                                   handle_accepted_callback=self._on_accepted, cancel_callback=self._on_cancel,
                                   goal_service_qos_profile=_REQUESTS_QOS, result_service_qos_profile=_REQUESTS_QOS,
                                   cancel_service_qos_profile=_REQUESTS_QOS, callback_group=group)
        self._stop = threading.Event()
        self._worker = threading.Thread(target=self._check_loop, name="dyn_node gate check", daemon=True)
        self._worker.start()
        self._thread = threading.Thread(target=self._spin, name="dyn_node gate", daemon=True)
        self._thread.start()
        self.logger.info(f"gate: {self.server_name} → {self.downstream} ({self.options.mode})")

    def _spin(self) -> None:
        while not self._stop.is_set() and self.executor.context.ok():
            self.executor.spin_once(timeout_sec=0.1)

    # --- the check (worker thread) --------------------------------------------------------------
    def _check_loop(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            g, fut = job
            answer = self._decide(g)
            with self._lock:
                self._pending -= 1
            fut.set_result(answer)

    def _decide(self, g: _Goal) -> tuple[Decision, list[str], dict]:
        try:
            return self._check(g)
        except Exception as exc:  # a failing check still answers the client
            self.logger.error(f"gate: check failed:\n{traceback.format_exc()}")
            return rejected(TrajectoryError(f"check failed: {exc!r}", code="evaluation_failed")), [], {}

    def _inline(self, g: _Goal) -> bool:
        """Whether to decide in the goal callback: a crossing to the check thread and back costs
        the goal its scheduling (GIL, executor wake-up), up to ~5 ms each way on a busy machine.
        Only a bounded check (reject or check mode, at most INLINE_MAX_POINTS points lasting at
        most INLINE_MAX_DURATION_S) with no
        check queued or running, and while inline checks took at most half of the executor's
        time: under a flood goals go through the bounded queue (gate_busy when it is full)."""
        points = g.goal.trajectory.points
        if self.options.mode == "retime" or len(points) > INLINE_MAX_POINTS:
            return False
        if points and stamp_to_s(points[-1].time_from_start) > INLINE_MAX_DURATION_S:
            return False
        with self._lock:
            return self._pending == 0 and time.monotonic() >= self._inline_free_at

    def _check(self, g: _Goal) -> tuple[Decision, list[str], dict]:
        """The decision, the model's joint names, and what the record needs of the decision's
        inputs (the goal's arrays, its stamp and receipt, and the start state, made JSON-ready by
        :meth:`_record`)."""
        core, start = self._state()
        arrays = trajectory_arrays(g.goal.trajectory)
        timing = Timing(stamp_s=stamp_to_s(g.goal.trajectory.header.stamp), receipt_s=g.receipt_s)
        inputs: dict[str, Any] = {"arrays": arrays, "start": start, "timing": timing}
        if core is None:
            return rejected(TrajectoryError("no robot model yet", code="no_model")), [], inputs
        model, settings = core.model, core.settings
        if self._dyn is None or self._dyn.model is not model:
            self._dyn = Dynamics(model, DynamicsOptions(include_friction=settings.include_friction))
        plan = None
        if self.options.mode == "retime":
            plan = RetimePlan(self._retime_s, lambda: self._state()[1], self.options.max_state_age)
            inputs["plan"] = plan
        d = decide_goal(self._dyn, settings, self.options, *arrays, start=start, plan=plan, timing=timing)
        if plan is not None and d.decision == RETIMED:  # the next plan leads by what this one took
            self._retime_s = 0.7 * self._retime_s + 0.3 * d.check_time_s
        return d, list(model.joint_names), inputs

    # --- the goal callback: decide, forward, answer ---------------------------------------------
    async def _on_goal(self, goal: Any) -> GoalResponse:
        # the gate's id: rclpy shows no goal id here
        g = _Goal(goal_id=uuid.uuid4().hex, goal=goal, receipt_s=self._clock.now().nanoseconds * 1e-9)
        with self._lock:
            self._active += 1
        try:
            return await self._answer(g)
        except Exception as exc:  # the client gets an answer whatever happens here
            self.logger.error(f"gate: goal callback failed, goal refused:\n{traceback.format_exc()}")
            self._refuse(g, out.REFUSED, f"dyn_node gate: internal error: {exc!r}")
            return self._keep(g)

    async def _answer(self, g: _Goal) -> GoalResponse:
        if self._closing:
            return self._refuse_unchecked(g, out.REFUSED_CLOSING, out.closing_text())
        if self._inline(g):
            t = time.monotonic()
            decision, names, inputs = self._decide(g)
            self._inline_free_at = 2 * time.monotonic() - t  # as long again before the next one
        else:
            fut = self.waits.future()
            with self._lock:
                try:
                    self._jobs.put_nowait((g, fut))
                except queue.Full:
                    waiting = self._jobs.qsize()
                else:
                    waiting = None
                    self._pending += 1
            if waiting is not None:
                return self._refuse_unchecked(g, out.GATE_BUSY, out.busy_text(waiting))
            await fut
            decision, names, inputs = fut.result()
        g.decision = decision
        g.record = lambda *a: self._record(g, names, inputs, *a)
        if not decision.forwards:
            self._count(decision.decision, decision.line, decision)
            self._refuse(g, out.REFUSED, decision.error_string)
            return self._keep(g)
        g.down_goal = g.goal
        if decision.decision == RETIMED:
            g.down_goal = FollowJointTrajectory.Goal()
            for f in g.down_goal.get_fields_and_field_types():
                setattr(g.down_goal, f, getattr(g.goal, f))
            g.down_goal.trajectory = goal_trajectory_message(g.goal.trajectory, decision.trajectory, names)
            # the answer starts at the robot's state now: the controller starts it on receipt
            g.down_goal.trajectory.header.stamp = Time()
        return await self._forward(g, names)

    def _refuse_unchecked(self, g: _Goal, event: str, text: str) -> GoalResponse:
        """Refused before any check (busy, closing): recorded as not forwarded, not replayed."""
        g.decision = rejected(TrajectoryError(text, code=event))
        g.record = lambda *a: self._record(g, [], {}, NOT_FORWARDED, event)
        self._count(NOT_FORWARDED, f"not forwarded: {text}", g.decision, extra=event)
        self._refuse(g, event, text)
        return self._keep(g)

    def _refuse(self, g: _Goal, event: str, text: str) -> None:
        g.end = (event, text)

    def _keep(self, g: _Goal) -> GoalResponse:
        with self._lock:
            self._goals[id(g.goal)] = g
        return GoalResponse.ACCEPT

    async def _forward(self, g: _Goal, names: list[str]) -> GoalResponse:
        """Send downstream and wait for its goal response: at most gate.timeout s from the
        decision for the server and the response together."""
        deadline = time.monotonic() + self.timeout
        while not self.client.server_is_ready():  # only while the server is absent
            if self._closing or time.monotonic() >= deadline:
                return self._not_forwarded(g, out.DOWNSTREAM_UNAVAILABLE,
                                           out.unavailable_text(self.downstream, self.timeout))
            await self.waits.sleep(min(0.02, deadline - time.monotonic()))
        if self._closing:
            return self._not_forwarded(g, out.REFUSED_CLOSING, out.closing_text())
        fut = self.client.send_goal_async(g.down_goal, feedback_callback=lambda m: self._relay(g, m))
        if not await self.waits.any((fut,), deadline - time.monotonic()):
            self.executor.create_task(self._cancel_late(g, fut))
            return self._not_forwarded(g, out.DOWNSTREAM_LATE, out.late_text(self.downstream, self.timeout))
        g.down = fut.result()
        if not g.down.accepted:  # no execution follows: the goal's records are made here
            self._count(NOT_FORWARDED, f"not forwarded: the controller rejected it; {g.decision.line}", g.decision)
            self._publish_decision(g, NOT_FORWARDED, out.DOWNSTREAM_REJECTED)
            self._publish_end(g, out.end_record(g.goal_id, out.DOWNSTREAM_REJECTED, None))
            self._done(g)
            return GoalResponse.REJECT
        with self._lock:
            self._running[id(g)] = g  # shutdown cancels it from now on
        self._count(g.decision.decision, g.decision.line, g.decision)
        g.names = names
        return self._keep(g)

    def _not_forwarded(self, g: _Goal, event: str, text: str) -> GoalResponse:
        with self._lock:
            self.counts["downstream_failures"] += event in (out.DOWNSTREAM_UNAVAILABLE, out.DOWNSTREAM_LATE)
        self.logger.error(text)
        self._count(NOT_FORWARDED, f"not forwarded: {text}", g.decision)
        self._refuse(g, event, text)
        return self._keep(g)

    async def _cancel_late(self, g: _Goal, fut: Any) -> None:
        """A goal response after gate.timeout: an acceptance is cancelled on arrival (the client's
        goal ended long ago) and the cancel's confirmation recorded."""
        await self.waits.any((fut,), None)
        gh = fut.result()
        if gh is None or not gh.accepted:
            return
        confirmed = await self._cancel_downstream(gh)
        self.logger.warning(f"gate {g.goal_id[:8]}: late acceptance by {self.downstream} cancelled "
                            f"({'confirmed' if confirmed else 'not confirmed'})")
        self._publish_end(g, out.end_record(g.goal_id, out.LATE_GOAL_CANCELLED, None,
                                            cancel=out.CONFIRMED if confirmed else out.CANCEL_UNCONFIRMED))

    async def _cancel_downstream(self, gh: Any) -> bool:
        """Cancel ``gh`` and wait (gate.timeout) for its end: whether the controller ended it."""
        res = gh.get_result_async()
        gh.cancel_goal_async()
        return await self.waits.any((res,), self.timeout)

    # --- execution ------------------------------------------------------------------------------
    def _on_accepted(self, handle: Any) -> None:
        with self._lock:
            g = self._goals.pop(id(handle.request))
            g.handle, early = handle, g.feedback
            g.feedback = []
        self._handles[id(handle)] = g
        for fb in early:
            handle.publish_feedback(fb)
        handle.execute()

    def _on_cancel(self, handle: Any) -> CancelResponse:
        g = self._handles.get(id(handle))
        if g is not None:
            g.cancel_requested = True
            self._wake(g)
        return CancelResponse.ACCEPT

    def _relay(self, g: _Goal, msg: Any) -> None:
        g.heard = time.monotonic()
        if g.handle is None:
            g.feedback.append(msg.feedback)
        elif g.handle.is_active:
            g.handle.publish_feedback(msg.feedback)

    def _wake(self, g: _Goal) -> None:
        poke = g.poke
        if poke is not None and not poke.done():
            poke.set_result(True)

    async def _execute(self, handle: Any) -> Any:
        g = self._handles[id(handle)]
        try:
            self._publish_decision(g)
            if g.end is not None:
                event, text = g.end
                res = Result(error_code=Result.INVALID_GOAL, error_string=text)
                handle.abort()
                self._publish_end(g, out.end_record(g.goal_id, event, GoalStatus.STATUS_ABORTED, res))
                return res
            if self._executed is not None:  # off the goal response's path
                try:
                    self._executed(g.decision, g.down_goal, g.names, lambda timing, start: self._publish(
                        self.pub, String(data=json.dumps(out.tracked_record(
                            g.goal_id, timing_dict(timing), start_dict(start)), allow_nan=False))))
                except Exception:
                    self.logger.error(f"gate {g.goal_id[:8]}: verdict or tracking failed:\n{traceback.format_exc()}")
            return await self._follow(handle, g)
        finally:
            self._handles.pop(id(handle), None)
            self._done(g)

    async def _follow(self, handle: Any, g: _Goal) -> Any:
        """Wait for the downstream result; cancel downstream on a client cancel, on shutdown, or
        after gate.timeout s without feedback (joint_trajectory_controller sends it at 20 Hz; a
        killed process stays in the DDS graph until its lease ends), then wait gate.timeout s for
        the controller's end."""
        res_fut = g.down.get_result_async()
        cause, cancel_at = None, None
        g.heard = time.monotonic()
        while not res_fut.done():
            if cause is None:
                cause = ("client_cancel" if g.cancel_requested or handle.is_cancel_requested else
                         out.CANCELLED_ON_SHUTDOWN if self._closing else None)
            if cause is not None and cancel_at is None:
                g.down.cancel_goal_async()
                cancel_at = time.monotonic()
            deadline = (cancel_at if cancel_at is not None else g.heard) + self.timeout
            if time.monotonic() >= deadline:
                if cancel_at is not None:
                    break  # the controller never confirmed
                cause = out.DOWNSTREAM_SILENT
                continue
            g.poke = self.waits.future()
            await self.waits.any((res_fut, g.poke), deadline - time.monotonic())
        return self._end(handle, g, res_fut, cause)

    def _end(self, handle: Any, g: _Goal, res_fut: Any, cause: str | None) -> Any:
        """End the client's goal after following it (see :mod:`dyn_node.gate.outcomes`)."""
        elapsed = time.monotonic() - g.t0
        if not res_fut.done():
            with self._lock:
                self.counts[out.CANCEL_UNCONFIRMED] += 1
                self.counts["downstream_failures"] += cause == out.DOWNSTREAM_SILENT
            text = (out.silent_text(self.downstream, self.timeout, False) if cause == out.DOWNSTREAM_SILENT
                    else out.unconfirmed_text(self.downstream, self.timeout, cause))
            self.logger.error(f"gate {g.goal_id[:8]}: {text}")
            res = Result(error_code=Result.INVALID_GOAL, error_string=text)
            handle.abort()
            self._publish_end(g, out.end_record(g.goal_id, out.CANCEL_UNCONFIRMED, GoalStatus.STATUS_ABORTED, res,
                                                cancel=out.CANCEL_UNCONFIRMED, cause=cause, elapsed_s=elapsed))
            return res
        got = res_fut.result()
        if cause == out.DOWNSTREAM_SILENT:  # the controller ended it once cancelled: still aborted
            with self._lock:
                self.counts["downstream_failures"] += 1
            text = out.silent_text(self.downstream, self.timeout, True)
            self.logger.error(f"gate {g.goal_id[:8]}: {text}")
            res = Result(error_code=Result.INVALID_GOAL, error_string=text)
            handle.abort()
            self._publish_end(g, out.end_record(g.goal_id, cause, GoalStatus.STATUS_ABORTED, res,
                                                cancel=out.CONFIRMED, elapsed_s=elapsed))
            return res
        event = out.CANCELLED_ON_SHUTDOWN if cause == out.CANCELLED_ON_SHUTDOWN else out.RESULT
        if got.status == GoalStatus.STATUS_SUCCEEDED:
            handle.succeed()
        elif got.status == GoalStatus.STATUS_CANCELED:
            end_canceled(handle)  # cancelled by the client or the gate, or pre-empted by the controller
        else:
            handle.abort()
        self._publish_end(g, out.end_record(g.goal_id, event, got.status, got.result,
                                            cancel=out.CONFIRMED if cause else None, elapsed_s=elapsed))
        return got.result

    def _done(self, g: _Goal) -> None:
        with self._lock:
            self._running.pop(id(g), None)
            self._active -= 1
            self._idle.notify_all()

    # --- records and status ---------------------------------------------------------------------
    def _count(self, key: str, line: str, decision: Decision, extra: str | None = None) -> None:
        with self._lock:
            self.counts[key] += 1
            if extra:
                self.counts[extra] += 1
            unchecked = key == FORWARDED and self.options.mode == "check" and decision.reason != ""
            self.counts["forwarded_unchecked"] += unchecked
            self.last_line, self.last_decision = line, decision

    def _publish_decision(self, g: _Goal, decision: str | None = None, reason: str | None = None) -> None:
        """The decision's record and log line, off the goal's path and before its end record. A
        goal the check let through but the controller never got says ``not_forwarded``."""
        with self._lock:  # once
            record, g.record = g.record, None
        if record is None:
            return
        if decision is None and g.end is not None and g.decision is not None and g.decision.forwards:
            decision, reason = NOT_FORWARDED, g.end[0]
        try:
            record(decision, reason) if decision else record()
        except Exception:  # a failing record never fails the goal
            self.logger.error(f"gate {g.goal_id[:8]}: decision record failed:\n{traceback.format_exc()}")

    def _record(self, g: _Goal, names: list[str], inputs: dict, decision: str | None = None,
                reason: str | None = None) -> None:
        d = g.decision
        goal = g.goal
        rec = d.to_dict(goal_id=g.goal_id, mode=self.options.mode, joint_names=names)
        if inputs:
            rec.update(goal=goal_dict(*inputs["arrays"]), start=start_dict(inputs["start"]),
                       timing=timing_dict(inputs["timing"]), retime_all=self.options.retime_all,
                       max_state_age=self.options.max_state_age, start_tolerance=self.options.start_tolerance)
            plan = inputs.get("plan")
            if plan is not None:
                rec.update(retime_lead_s=plan.lead_s, planned_from=start_dict(plan.planned_from),
                           rechecked_from=start_dict(plan.rechecked_from))
        if decision is not None:  # checked, then not forwarded: the check's decision kept apart
            rec.update(checked_decision=rec["decision"] if inputs else None, checked_reason=rec["reason"],
                       checked_forwarded=rec["forwarded"], decision=decision, reason=reason or rec["reason"],
                       forwarded=None)
        rec.update(event="decision", downstream=self.downstream, failure_label=d.failure_label, tolerances={
            "path": [[t.name, t.position, t.velocity, t.acceleration] for t in goal.path_tolerance],
            "goal": [[t.name, t.position, t.velocity, t.acceleration] for t in goal.goal_tolerance],
            "goal_time_s": goal.goal_time_tolerance.sec + goal.goal_time_tolerance.nanosec * 1e-9})
        line = f"gate {g.goal_id[:8]}: " + (d.line if decision is None else f"not forwarded ({reason}); checked: {d.line}")
        if rec["decision"] in (FORWARDED, RETIMED) and d.reason == "":
            self.logger.info(line)
        else:  # one severity per call site: rclpy's logger insists
            self.logger.warning(line)
        self._publish(self.pub, String(data=json.dumps(rec, allow_nan=False)))

    def _publish_end(self, g: _Goal, rec: dict) -> None:
        self._publish_decision(g)  # always first
        try:
            self._publish(self.pub, String(data=json.dumps(rec, allow_nan=False)))
        except Exception:
            self.logger.error(f"gate {g.goal_id[:8]}: end record failed:\n{traceback.format_exc()}")

    def status(self) -> Status:
        with self._lock:
            counts, line, last = dict(self.counts), self.last_line, self.last_decision
        values = {"mode": self.options.mode, "controller_action": self.downstream,
                  "forwarded": counts[FORWARDED], "rejected": counts[REJECTED], "retimed": counts[RETIMED],
                  "not_forwarded": counts[NOT_FORWARDED], "forwarded_unchecked": counts["forwarded_unchecked"],
                  "gate_busy": counts[out.GATE_BUSY],
                  "downstream_cancel_unconfirmed": counts[out.CANCEL_UNCONFIRMED],
                  "downstream_failures": counts["downstream_failures"], "last_decision": line}
        if not self.client.server_is_ready():
            values["failure_label"] = STATE_ERROR
            return Status(STATUS_NAME, ERROR, f"downstream action server {self.downstream} not available",
                          values=values)
        if last is not None and (line.startswith((REJECTED, NOT_FORWARDED.replace("_", " ")))
                                 or (line.startswith(FORWARDED) and last.reason != "")):
            values["failure_label"] = last.failure_label
            return Status(STATUS_NAME, WARN, f"last goal {line}", values=values)
        return Status(STATUS_NAME, OK, line or "no goal yet", values=values)

    def close(self) -> None:
        """Refuse new goals, cancel what was forwarded and still runs (each waiting gate.timeout s
        for the controller's end), then stop. A crash cancels nothing: the client's timeout applies."""
        self._closing = True
        with self._lock:
            running = list(self._running.values())
        for g in running:
            self._wake(g)
        deadline = time.monotonic() + 2 * self.timeout + 1.0
        with self._lock:
            self._idle.wait_for(lambda: self._active <= 0, timeout=max(0.0, deadline - time.monotonic()))
            left = self._active
        if running or left:
            self.logger.info(f"gate: shutting down, {len(running)} forwarded goal(s) cancelled"
                             + (f", {left} goal(s) not ended in time" if left else ""))
        try:
            self._jobs.put_nowait(None)
        except queue.Full:
            pass  # a daemon thread: it ends with the process
        self._stop.set()
        self._thread.join(timeout=5.0)
        if not self._thread.is_alive():
            # results just set are sent by tasks the executor runs on its next turns: run them
            # here, so no client waits for a result its goal already has
            for _ in range(_DRAIN_TURNS):
                self.executor.spin_once(timeout_sec=0.01)
        self.server.destroy()
        self.client.destroy()
        self.executor.shutdown(timeout_sec=2.0)
        self.io.destroy_node()


def attach_gate(node: Any, params: dict[str, Any]) -> Gate | None:
    """Start the gate of ``node`` (a DynNode, recording set up) when ``gate.controller_action`` is
    set in ``params`` (:func:`declare_gate_parameters`); None otherwise."""
    if not params["gate.controller_action"]:
        return None
    gate = Gate(node, params, node.execution_state, node._publish, executed=lambda *a: _executed(node, *a))
    node.recording.add_publisher(gate.pub)
    node.status_providers.append(gate.status)
    return gate


def _executed(node: Any, decision: Decision, goal: Any, names: list[str],
              record: Callable[[Timing, Any], None]) -> None:
    """A goal the controller accepted: its verdict on ~/feasibility (request ``execute``) and the
    controller tracker following it, as for a trajectory on the joint_trajectory topic (from
    now and the robot's state now: ``record`` writes both first, for the audit's replay)."""
    from dyn_node.core.check.on_demand import REQUEST_EXECUTE
    from dyn_node.ros.convert import verdict_array

    core = node._core
    if core is None or decision.trajectory is None or list(core.model.joint_names) != names:
        return
    from dyn_node.core.check.on_demand import options_for

    header = goal.trajectory.header
    _core, state = node.execution_state()
    timing = Timing(stamp_to_s(header.stamp), node.get_clock().now().nanoseconds * 1e-9)
    record(timing, state)
    core.tracker.follow(decision.trajectory, timing=timing, start=state, lock=node._io_lock,
                        options=options_for(core.settings).execution)
    if decision.result is not None:
        node._publish_verdict(node._pub_feasibility, verdict_array(decision.result.statuses(core.model.name),
                                                                   header.stamp, header.frame_id, REQUEST_EXECUTE))
