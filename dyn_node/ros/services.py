"""dyn_node's questions as ROS 2 services: ``~/check_trajectory``, ``~/compute_inverse_dynamics``
and ``~/retime_trajectory`` (types from ``dyn_node_interfaces``).

Requests are answered in order by one worker thread of their own, so a long check never holds
the executor, the joint_states thread or a trajectory to execute. The service callbacks are
coroutines in a reentrant callback group: each queues its request and awaits the worker's
answer (a guard condition wakes the executor when it is ready), so several calls are in flight
at once and none blocks another callback. A request that cannot be queued is answered at once:
``accepted: false`` with ``reason`` ``busy`` (``check_queue_depth`` waiting) or ``no_model``.
Every request gets a response, malformed ones included (with the reason). Service introspection
publishes each request and response with contents on ``<service>/_service_event``, which the
recorder records and the audit re-checks.
"""
from __future__ import annotations

import collections
import threading
from dataclasses import dataclass
from typing import Any, Callable

from dyn_node_interfaces.srv import CheckTrajectory, ComputeInverseDynamics, RetimeTrajectory
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.service_introspection import ServiceIntrospectionState
from rclpy.task import Future

from dyn_node.core.check import feasibility
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.ros import service_answers as answers

CHECK, INVERSE_DYNAMICS, RETIME = "check", "inverse_dynamics", "retime"
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


class QuestionServices:
    """The three services of ``node`` and their worker. ``core()`` returns the node's current
    core (model, settings) or None; ``start_state(core)`` the robot's state a trajectory received
    now starts from (or None); ``dynamics(core)`` a Dynamics for the calling thread;
    ``failed(what)`` logs and counts an exception."""

    def __init__(self, node: Node, *, core: Callable[[], Any],
                 start_state: Callable[[Any], feasibility.StartState | None],
                 dynamics: Callable[[Any], Dynamics], failed: Callable[[str], None]):
        self._core, self._start_state = core, start_state
        self._dynamics, self._failed = dynamics, failed
        self._group = ReentrantCallbackGroup()
        self._wake = node.create_guard_condition(lambda: None, callback_group=self._group)
        self._jobs: collections.deque[_Job] = collections.deque()
        self._cond = threading.Condition()
        self._closed = False
        callbacks = {CHECK: self._on_check, INVERSE_DYNAMICS: self._on_inverse_dynamics,
                     RETIME: self._on_retime}
        self.services = {}
        for kind, (name, srv_type) in SERVICES.items():
            srv = node.create_service(srv_type, name, callbacks[kind], callback_group=self._group)
            srv.configure_introspection(node.get_clock(), EVENT_QOS,
                                        ServiceIntrospectionState.CONTENTS)
            self.services[kind] = srv
        self._thread = threading.Thread(target=self._loop, name="dyn_node_services", daemon=True)
        self._thread.start()

    def event_topics(self) -> list[str]:
        """The fully qualified ``<service>/_service_event`` topics of the three services."""
        return [srv.service_name + EVENT_SUFFIX for srv in self.services.values()]

    # --- callbacks (executor thread): queue, then await the worker's answer ----------------
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
            start = None
            if getattr(request, "from_current_state", False):
                start = self._start_state(core)  # at receipt, as for joint_trajectory
            with self._cond:
                if self._closed:
                    answers.reject(response, answers.SHUTTING_DOWN, "dyn_node is shutting down")
                    return None
                waiting = len(self._jobs)
                if waiting >= core.settings.check_queue_depth:
                    answers.reject(response, answers.BUSY,
                                   f"busy: {waiting} requests already waiting (check_queue_depth)")
                    return None
                future = Future()
                self._jobs.append(_Job(kind, request, response, future, core, start))
                self._cond.notify()
            return future
        except Exception as exc:  # never leave a caller without an answer
            self._failed(f"{kind} service")
            answers.reject(response, answers.INTERNAL_ERROR, f"{type(exc).__name__}: {exc}")
            return None

    # --- worker thread ----------------------------------------------------------------------
    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._jobs and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                job = self._jobs.popleft()
            try:
                self._answer(job)
            except Exception as exc:
                self._failed(f"{job.kind} service")
                answers.reject(job.response, answers.INTERNAL_ERROR, f"{type(exc).__name__}: {exc}")
            self._finish(job)

    def _answer(self, job: _Job) -> None:
        dyn = self._dynamics(job.core)
        settings = job.core.settings
        if job.kind == CHECK:
            answers.answer_check(dyn, settings, job.request, job.response, job.start)
        elif job.kind == INVERSE_DYNAMICS:
            answers.answer_inverse_dynamics(dyn, job.request, job.response)
        else:
            answers.answer_retime(dyn, settings, job.request, job.response, job.start)

    def _finish(self, job: _Job) -> None:
        job.future.set_result(job.response)
        try:
            self._wake.trigger()  # the executor resumes the awaiting callback, which responds
        except Exception:  # the node is gone: nobody waits any more
            pass

    def close(self) -> None:
        """Stop the worker; requests still queued are answered ``shutting_down``."""
        with self._cond:
            self._closed = True
            pending = list(self._jobs)
            self._jobs.clear()
            self._cond.notify_all()
        for job in pending:
            answers.reject(job.response, answers.SHUTTING_DOWN, "dyn_node is shutting down")
            self._finish(job)
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=0.5)  # a request in progress is abandoned (daemon thread)


__all__ = ["QuestionServices", "SERVICES", "EVENT_SUFFIX", "CHECK", "INVERSE_DYNAMICS", "RETIME"]
