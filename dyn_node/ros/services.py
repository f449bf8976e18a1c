"""dyn_node's questions as ROS 2 services: ``~/check_trajectory``, ``~/compute_inverse_dynamics``
and ``~/retime_trajectory`` (types from ``dyn_node_interfaces``).

Each service has a queue and a thread of its own (a *lane*): the lane turns the request into
arrays (:func:`~dyn_node.ros.service_answers.question_of`), has the question worker process
compute the answer (:class:`~dyn_node.core.live.question_process.QuestionProcess`, one thread per
service there) and fills the response. The computation runs in another process because a thread
of this one shares the interpreter lock with the joint_states thread (the module docstring of
``question_process`` has the reasons and figures). So a long check never holds the executor,
the joint_states thread or a trajectory to execute, and a 1 ms inverse-dynamics call never
waits behind a retime. A worker that dies answers the calls it held ``worker_failed`` and is
restarted. The service callbacks are coroutines in a reentrant callback group: each queues its request and awaits its lane's answer (a guard condition wakes the
executor when it is ready), so several calls are in flight at once and none blocks another
callback. A request that cannot be queued is answered at once: ``accepted: false`` with
``reason`` ``busy`` (``check_queue_depth`` of its kind waiting), ``too_large`` (more points than
``services.max_points``) or ``no_model``. A call that waited longer than ``services.max_queue_age``
is answered ``expired`` without being computed: an rclpy service server cannot see its client
give up (no cancel, no per-request liveness), so the time its caller has most likely waited
stands for it. Every request gets a response, malformed ones included (with the reason). Service
introspection publishes each request and response with contents on ``<service>/_service_event``,
which the recorder records and the audit re-checks.
"""
from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from dyn_node_interfaces.srv import CheckTrajectory, ComputeInverseDynamics, RetimeTrajectory
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.service_introspection import ServiceIntrospectionState
from rclpy.task import Future

from dyn_node.core.check import feasibility
from dyn_node.core.check.questions import CHECK, INVERSE_DYNAMICS, RETIME
from dyn_node.core.live.question_process import QuestionProcess, WorkerFailed
from dyn_node.ros import service_answers as answers

#: question → (service name, type)
SERVICES: dict[str, tuple[str, Any]] = {
    CHECK: ("~/check_trajectory", CheckTrajectory),
    INVERSE_DYNAMICS: ("~/compute_inverse_dynamics", ComputeInverseDynamics),
    RETIME: ("~/retime_trajectory", RetimeTrajectory),
}
EVENT_SUFFIX = "/_service_event"
# reliable and deep: the recorder must get every event of a burst
EVENT_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                       history=HistoryPolicy.KEEP_LAST)


@dataclass
class _Job:
    kind: str
    request: Any
    response: Any
    future: Future
    core: Any
    start: feasibility.StartState | None
    queued_at: float = field(default_factory=time.monotonic)


def _points(kind: str, request: Any) -> list:
    return request.states.points if kind == INVERSE_DYNAMICS else request.trajectory.points


def request_points(kind: str, request: Any) -> int:
    """How many points (states) a request holds: what ``services.max_points`` bounds."""
    return len(_points(kind, request))


#: points freed per step by release_points
RELEASE_CHUNK = 1000


def release_points(kind: str, request: Any) -> None:
    """Free a request's points a slice at a time once it is no longer needed (its service event
    was published when it was taken). Freed when the executor drops the request, they went in
    one piece, holding the interpreter lock: ~25 ms for 50,000 points, back to back with the
    response's, which paused joint_states as long."""
    points = _points(kind, request)
    while points:
        del points[-RELEASE_CHUNK:]


class _Lane:
    """One service's queue and its thread (converts, asks the worker process, fills the response)."""

    def __init__(self, kind: str, work: Callable[[_Job], None]):
        self.kind, self._work = kind, work
        self.jobs: collections.deque[_Job] = collections.deque()
        self.cond = threading.Condition()
        self.closed = False
        self.thread = threading.Thread(target=self._loop, name=f"dyn_node_{kind}", daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while True:
            with self.cond:
                while not self.jobs and not self.closed:
                    self.cond.wait()
                if self.closed:
                    return
                job = self.jobs.popleft()
            self._work(job)

    def close(self) -> list[_Job]:
        """Stop the worker; returns the jobs still queued (to be answered by the caller)."""
        with self.cond:
            self.closed = True
            pending = list(self.jobs)
            self.jobs.clear()
            self.cond.notify_all()
        return pending


class QuestionServices:
    """The three services of ``node``, their lanes and the question worker process.
    ``core()`` returns the node's current core (model, settings) or None;
    ``start_state(core)`` the robot's state a trajectory received now starts from (or None);
    ``failed(what)`` logs and counts an exception."""

    def __init__(self, node: Node, *, core: Callable[[], Any],
                 start_state: Callable[[Any], feasibility.StartState | None],
                 failed: Callable[[str], None]):
        self._core, self._start_state, self._failed = core, start_state, failed
        self.process = QuestionProcess(log=node.get_logger().warn)
        first = core()
        if first is not None:  # the worker loads the kernels with it while the node starts
            self.process.preload(first.model)
        self._group = ReentrantCallbackGroup()
        self._wake = node.create_guard_condition(lambda: None, callback_group=self._group)
        self._lanes = {kind: _Lane(kind, self._work) for kind in SERVICES}
        callbacks = {CHECK: self._on_check, INVERSE_DYNAMICS: self._on_inverse_dynamics,
                     RETIME: self._on_retime}
        self.services = {}
        for kind, (name, srv_type) in SERVICES.items():
            srv = node.create_service(srv_type, name, callbacks[kind], callback_group=self._group)
            srv.configure_introspection(node.get_clock(), EVENT_QOS,
                                        ServiceIntrospectionState.CONTENTS)
            self.services[kind] = srv

    def event_topics(self) -> list[str]:
        """The fully qualified ``<service>/_service_event`` topics of the three services."""
        return [srv.service_name + EVENT_SUFFIX for srv in self.services.values()]

    # --- callbacks (executor thread): queue, then await the lane's answer -------------------
    async def _on_check(self, request: Any, response: Any) -> Any:
        return await self._ask(CHECK, request, response)

    async def _on_inverse_dynamics(self, request: Any, response: Any) -> Any:
        return await self._ask(INVERSE_DYNAMICS, request, response)

    async def _on_retime(self, request: Any, response: Any) -> Any:
        return await self._ask(RETIME, request, response)

    async def _ask(self, kind: str, request: Any, response: Any) -> Any:
        future = self._submit(kind, request, response)
        if future is None:
            return response  # answered at once
        return await future

    def _submit(self, kind: str, request: Any, response: Any) -> Future | None:
        try:
            core = self._core()
            if core is None:
                answers.reject(response, answers.NO_MODEL, "no robot model yet")
                return None
            n, most = request_points(kind, request), core.settings.services_max_points
            if n > most:
                answers.reject(response, answers.TOO_LARGE,
                               f"too large: {n} points, more than services.max_points ({most})")
                release_points(kind, request)
                return None
            start = None
            if getattr(request, "from_current_state", False):
                start = self._start_state(core)  # at receipt, as for joint_trajectory
            lane = self._lanes[kind]
            with lane.cond:
                if lane.closed:
                    answers.reject(response, answers.SHUTTING_DOWN, "dyn_node is shutting down")
                    return None
                waiting = len(lane.jobs)
                if waiting >= core.settings.check_queue_depth:
                    answers.reject(response, answers.BUSY, f"busy: {waiting} {kind} requests "
                                   "already waiting (check_queue_depth)")
                    return None
                future = Future()
                lane.jobs.append(_Job(kind, request, response, future, core, start))
                lane.cond.notify()
            return future
        except Exception as exc:  # never leave a caller without an answer
            self._failed(f"{kind} service")
            answers.reject(response, answers.INTERNAL_ERROR, f"{type(exc).__name__}: {exc}")
            return None

    # --- lane threads -----------------------------------------------------------------------
    def _work(self, job: _Job) -> None:
        try:
            waited, most = time.monotonic() - job.queued_at, job.core.settings.services_max_queue_age
            if waited > most:
                answers.reject(job.response, answers.EXPIRED, f"expired: waited {waited:.3g} s in "
                               f"the queue, more than services.max_queue_age ({most:g} s)")
            else:
                self._answer(job)
        except Exception as exc:
            self._failed(f"{job.kind} service")
            answers.reject(job.response, answers.INTERNAL_ERROR, f"{type(exc).__name__}: {exc}")
        self._finish(job)

    def _answer(self, job: _Job) -> None:
        """Arrays from the request here, the answer from the worker process, the response here."""
        model = job.core.model
        question = answers.question_of(job.kind, job.request, job.start)
        try:
            result = self.process.ask(job.core.settings, model, question)
        except WorkerFailed as exc:
            closing = self._lanes[job.kind].closed  # the node ends, and the worker with it
            answers.reject(job.response, answers.SHUTTING_DOWN if closing else answers.WORKER_FAILED,
                           str(exc))
            return
        answers.fill(model, job.request, job.response, question, result)
        release_points(job.kind, job.request)

    def _finish(self, job: _Job) -> None:
        job.future.set_result(job.response)
        try:
            self._wake.trigger()  # the executor resumes the awaiting callback, which responds
        except Exception:  # the node is gone: nobody waits any more
            pass

    def close(self) -> None:
        """Stop the lanes; requests still queued are answered ``shutting_down``."""
        for lane in self._lanes.values():
            for job in lane.close():
                answers.reject(job.response, answers.SHUTTING_DOWN, "dyn_node is shutting down")
                self._finish(job)
        # first: a lane waiting on the worker is released at once (its question answered
        # shutting_down), so the joins below do not wait out their timeout
        self.process.close()
        deadline = time.monotonic() + 0.5
        for lane in self._lanes.values():  # a request in progress is abandoned (daemon threads)
            if lane.thread.is_alive() and lane.thread is not threading.current_thread():
                lane.thread.join(timeout=max(0.0, deadline - time.monotonic()))


__all__ = ["QuestionServices", "request_points", "SERVICES", "EVENT_SUFFIX", "CHECK", "INVERSE_DYNAMICS", "RETIME"]
