"""A Python client for dyn_node's on-demand requests, usable from any rclpy node.

``DynClient(node, namespace="/dyn_node")`` publishes on ``~/check_trajectory`` and
``~/inverse_dynamics_request`` and matches each answer by a request id in ``frame_id`` (the node
echoes the whole header), so several requests can be in flight. Blocking calls need ``node`` spun
meanwhile: they spin an unspun node themselves, wait when another thread spins it, and raise
:class:`BlockingCallError` in a single-threaded executor's callback (use the ``*_async`` variants
there). README "Python client" has the whole API.
"""
from __future__ import annotations

import copy
import itertools
import math
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import Executor, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from dyn_node.core.limits import LIMIT_KINDS
from dyn_node.core.status import ERROR, NAME_PREFIX
from dyn_node.ros.qos import LATCHED_HISTORY

STATUS_NAME = NAME_PREFIX + "trajectory feasibility"  # feasibility.STATUS_NAME, without its imports
_POLL_S = 0.01


class DynClientError(RuntimeError):
    """Base class of the client's errors."""


class NotRunningError(DynClientError):
    """No dyn_node answers at the client's namespace (nothing matched within the timeout)."""


class RequestTimeout(DynClientError, TimeoutError):
    """dyn_node is there but did not answer within the timeout."""


class BlockingCallError(DynClientError):
    """A blocking call from the only thread that could deliver its answer (a callback of a
    single-threaded executor spinning the client's node)."""


class RequestRejected(DynClientError):
    """dyn_node rejected an inverse-dynamics request; ``verdict`` says why."""

    def __init__(self, verdict: "Verdict"):
        super().__init__(verdict.message)
        self.verdict = verdict


@dataclass(frozen=True)
class Violation:
    """A limit exceeded by one joint: ``ratio`` = peak |value| / limit (> 1) at ``time_s`` s from
    the trajectory's start (for ``position``, the distance from mid-range over half the range)."""

    joint: str
    kind: str
    ratio: float
    time_s: float


@dataclass(frozen=True)
class Verdict:
    """dyn_node's verdict on one trajectory, parsed from its ``~/feasibility`` DiagnosticArray.

    ``feasible``: the trajectory can run as timed. ``level``: 0 OK, 1 WARN (feasible, close to a
    limit), 2 ERROR (infeasible or rejected). ``rejected``: it could not be checked at all
    (``reason`` is the code: ``non_finite``, ``bad_times``, ``unknown_joints``, ``busy`` ...; the
    message says what). ``time_scale``: the smallest stretch of the duration that makes it
    feasible (≤ 1 when feasible; inf: no slowdown helps; NaN when rejected). ``worst_*``: the
    joint, limit kind and peak ratio closest to (or furthest over) its limit. ``binding_*``: the
    joint (or place) and kind whose slowdown sets ``time_scale`` (may differ from ``worst_*``).
    ``first_violation_time_s``: s from the trajectory's start (NaN: none). ``ratios[joint][kind]``:
    peak ratio per limit kind (None: that joint has no such limit). ``request``: ``check`` or
    ``execute`` (or ``inverse_dynamics`` for a rejected torque request). ``stamp_ns`` /
    ``frame_id``: the header the node echoed. ``values``: the summary status's key/values as
    published, for anything not parsed here.
    """

    feasible: bool
    level: int
    message: str
    time_scale: float
    worst_joint: str
    worst_constraint: str
    worst_ratio: float
    first_violation_time_s: float
    ratios: Mapping[str, Mapping[str, float | None]]
    violations: tuple[Violation, ...]
    request: str = ""
    rejected: bool = False
    reason: str = ""
    failure_label: str = ""
    payload_margin_kg: float = math.nan
    n_points: int = 0
    duration_s: float = math.nan
    stamp_ns: int = 0
    frame_id: str = ""
    values: Mapping[str, str] = field(default_factory=dict)
    binding_joint: str = ""
    binding_constraint: str = ""

    @classmethod
    def from_msg(cls, msg: DiagnosticArray) -> "Verdict":
        """Parse a ``~/feasibility`` array; raises ValueError when it holds no verdict."""
        summary = next((s for s in msg.status if s.name == STATUS_NAME), None)
        if summary is None:
            raise ValueError(f"no '{STATUS_NAME}' status in the array")
        vals = {kv.key: kv.value for kv in summary.values}
        prefix = STATUS_NAME + "/"
        ratios: dict[str, dict[str, float | None]] = {}
        times: dict[str, dict[str, float]] = {}
        for st in msg.status:
            if not st.name.startswith(prefix):
                continue
            joint = st.name[len(prefix):]
            kv = {x.key: x.value for x in st.values}
            ratios[joint] = {k: _ratio(kv.get(f"{k}_ratio")) for k in LIMIT_KINDS if f"{k}_ratio" in kv}
            times[joint] = {k: _float(kv.get(f"{k}_time_s")) for k in LIMIT_KINDS}
        violations = tuple(Violation(j, k, r, times[j][k]) for j, kinds in ratios.items()
                           for k, r in kinds.items() if r is not None and r > 1.0)
        level = summary.level[0] if isinstance(summary.level, (bytes, bytearray)) else int(summary.level)
        st = msg.header.stamp
        return cls(
            feasible=vals.get("feasible") == "true", level=level, message=summary.message,
            time_scale=_float(vals.get("time_scale")), worst_joint=vals.get("worst_joint", ""),
            worst_constraint=vals.get("worst_constraint", ""), worst_ratio=_float(vals.get("worst_ratio")),
            first_violation_time_s=_float(vals.get("first_violation_time_s")), ratios=ratios,
            violations=violations, request=vals.get("request", ""),
            rejected=level == ERROR and summary.message.startswith("rejected: "),
            reason=vals.get("reason", ""), failure_label=vals.get("failure_label", ""),
            payload_margin_kg=_float(vals.get("payload_margin_kg")),
            n_points=int(_float(vals.get("n_points"), 0.0)), duration_s=_float(vals.get("duration_s")),
            stamp_ns=int(st.sec) * 1_000_000_000 + int(st.nanosec), frame_id=msg.header.frame_id,
            values=vals, binding_joint=vals.get("binding_joint", ""),
            binding_constraint=vals.get("binding_constraint", ""))


def _float(text: str | None, default: float = math.nan) -> float:
    if text is None or text == "":
        return default
    try:
        return float(text)
    except ValueError:
        return default


def _ratio(text: str | None) -> float | None:
    return None if text in (None, "unlimited") else _float(text)


def trajectory_message(joint_names: Sequence[str], times: Sequence[float], positions: Any,
                       velocities: Any = None, accelerations: Any = None) -> JointTrajectory:
    """A JointTrajectory from times (s from the start) and N×k arrays in ``joint_names`` order."""
    msg = states_message(joint_names, positions, velocities, accelerations)
    for pt, t in zip(msg.points, times):
        ns = int(round(float(t) * 1e9))
        pt.time_from_start.sec, pt.time_from_start.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
    return msg


def states_message(joint_names: Sequence[str], positions: Any, velocities: Any = None,
                   accelerations: Any = None) -> JointTrajectory:
    """A ``~/inverse_dynamics_request`` from N×k arrays in ``joint_names`` order (velocities and
    accelerations may be None: zero)."""
    P = np.atleast_2d(np.asarray(positions, dtype=float))
    msg = JointTrajectory(joint_names=list(joint_names))
    for i, row in enumerate(P):
        pt = JointTrajectoryPoint(positions=row.tolist())
        if velocities is not None:
            pt.velocities = np.atleast_2d(np.asarray(velocities, dtype=float))[i].tolist()
        if accelerations is not None:
            pt.accelerations = np.atleast_2d(np.asarray(accelerations, dtype=float))[i].tolist()
        msg.points.append(pt)
    return msg


class DynClient:
    """Check trajectories and ask for torques from a running dyn_node (see the module doc).

    ``namespace`` is the dyn_node's fully qualified name (``/dyn_node`` by default; e.g.
    ``/robot1/dyn_node`` for a namespaced one). Construct once per node and keep it: creating the
    publishers and subscriptions and matching them with dyn_node takes discovery time.
    """

    def __init__(self, node: Node, namespace: str = "/dyn_node"):
        self._node = node
        ns = "/" + namespace.strip("/")
        self.namespace = ns
        self._lock = threading.Lock()
        self._checks: dict[str, Future] = {}
        self._efforts: dict[str, tuple[Future, list[str]]] = {}
        self._ids = itertools.count(1)
        self._tag = f"dyn_client/{uuid.uuid4().hex[:12]}/"
        group = MutuallyExclusiveCallbackGroup()  # answers are taken beside the caller's callbacks
        self._pub_check = node.create_publisher(JointTrajectory, f"{ns}/check_trajectory", 10)
        self._pub_states = node.create_publisher(JointTrajectory, f"{ns}/inverse_dynamics_request", 10)
        self._sub_verdict = node.create_subscription(DiagnosticArray, f"{ns}/feasibility", self._on_verdict,
                                                     LATCHED_HISTORY, callback_group=group)
        self._sub_effort = node.create_subscription(JointTrajectory, f"{ns}/trajectory_effort",
                                                    self._on_effort, 100, callback_group=group)

    # --- public API --------------------------------------------------------------------------
    def check(self, traj: JointTrajectory, timeout: float = 10.0) -> Verdict:
        """dyn_node's verdict on ``traj``, checked exactly like ``joint_trajectory`` but never
        executed. Raises :class:`NotRunningError`, :class:`RequestTimeout` or
        :class:`BlockingCallError` (see the module doc); a trajectory dyn_node rejects (NaN,
        times not increasing, unknown joints, queue full) is a Verdict with ``rejected`` set."""
        return self._wait(lambda: self.check_async(traj, timeout=timeout), timeout)

    def efforts(self, traj_or_states: JointTrajectory, timeout: float = 10.0) -> np.ndarray:
        """τ(q, q̇, q̈) for each point of ``traj_or_states`` (missing velocities or accelerations
        mean zero): an array (points, joints) in the request's joint order, N·m (N for prismatic
        joints). Raises like :meth:`check`, and :class:`RequestRejected` for a malformed request."""
        return self._wait(lambda: self.efforts_async(traj_or_states, timeout=timeout), timeout)

    def check_async(self, traj: JointTrajectory, *, timeout: float = 10.0) -> Future:
        """Send a check request now; the Future completes with its :class:`Verdict` (or a
        :class:`NotRunningError` when dyn_node has not matched within ``timeout``)."""
        fut = Future()
        self._send(traj, self._pub_check, self._checks, fut, None, timeout)
        return fut

    def efforts_async(self, traj_or_states: JointTrajectory, *, timeout: float = 10.0) -> Future:
        """Send an inverse-dynamics request now; the Future completes with the torque array."""
        fut = Future()
        self._send(traj_or_states, self._pub_states, self._efforts, fut, list(traj_or_states.joint_names),
                   timeout)
        return fut

    def ready(self) -> bool:
        """True when dyn_node's request and answer topics are matched with this client's."""
        return (self._pub_check.get_subscription_count() > 0
                and self._pub_states.get_subscription_count() > 0
                and self._sub_verdict.get_publisher_count() > 0
                and self._sub_effort.get_publisher_count() > 0)

    def destroy(self) -> None:
        """Destroy the client's publishers and subscriptions; pending futures fail."""
        for ent in (self._pub_check, self._pub_states):
            self._node.destroy_publisher(ent)
        for ent in (self._sub_verdict, self._sub_effort):
            self._node.destroy_subscription(ent)
        with self._lock:
            pending = [f for f in self._checks.values()] + [f for f, _ in self._efforts.values()]
            self._checks.clear()
            self._efforts.clear()
        for f in pending:
            if not f.done():
                f.set_exception(DynClientError("client destroyed before the answer came"))

    # --- sending -----------------------------------------------------------------------------
    def _send(self, traj: JointTrajectory, pub: Any, table: dict, fut: Future, extra: Any,
              timeout: float) -> None:
        if not isinstance(traj, JointTrajectory):
            raise TypeError(f"a trajectory_msgs/JointTrajectory is needed, not {type(traj).__name__}")
        rid = f"{self._tag}{next(self._ids)}"
        msg = copy.copy(traj)          # the header is replaced, the points are shared (read only)
        msg.header = copy.deepcopy(traj.header)
        msg.header.frame_id = rid
        with self._lock:
            table[rid] = fut if extra is None else (fut, extra)
        if self.ready():
            pub.publish(msg)
            return
        # Not matched yet (just created, or dyn_node not up): publish once matched, from a
        # thread of our own so a callback calling the async variant is never held up.
        threading.Thread(target=self._publish_when_ready, args=(pub, msg, rid, table, fut, timeout),
                         name="dyn_client send", daemon=True).start()

    def _publish_when_ready(self, pub: Any, msg: JointTrajectory, rid: str, table: dict, fut: Future,
                            timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not self.ready():
            if fut.done() or fut.cancelled():
                return
            if time.monotonic() >= deadline or not self._node.context.ok():
                with self._lock:
                    table.pop(rid, None)
                if not fut.done() and not fut.cancelled():
                    fut.set_exception(self._not_running(timeout))
                return
            time.sleep(_POLL_S)  # the ROS graph has no wait primitive for matches
        pub.publish(msg)

    def _not_running(self, timeout: float) -> NotRunningError:
        return NotRunningError(f"dyn_node is not running at {self.namespace}: nothing matched "
                               f"{self.namespace}/check_trajectory and its answer topics within "
                               f"{timeout:g} s")

    # --- answers -------------------------------------------------------------------------------
    def _on_verdict(self, msg: DiagnosticArray) -> None:
        rid = msg.header.frame_id
        if not rid.startswith(self._tag):
            return
        with self._lock:
            fut = self._checks.pop(rid, None)
            ent = self._efforts.pop(rid, None) if fut is None else None
        try:
            verdict = Verdict.from_msg(msg)
        except ValueError as exc:
            verdict, err = None, DynClientError(f"unreadable verdict for request {rid}: {exc}")
        if fut is not None and not fut.done():
            if verdict is None:
                fut.set_exception(err)
            else:
                fut.set_result(verdict)
        elif ent is not None and not ent[0].done():
            ent[0].set_exception(RequestRejected(verdict) if verdict is not None else err)

    def _on_effort(self, msg: JointTrajectory) -> None:
        rid = msg.header.frame_id
        if not rid.startswith(self._tag):
            return
        with self._lock:
            ent = self._efforts.pop(rid, None)
        if ent is None or ent[0].done():
            return  # a check's torques: the verdict is the answer to a check
        fut, names = ent
        order = [list(msg.joint_names).index(n) for n in names]
        out = np.array([[p.effort[i] for i in order] for p in msg.points], dtype=float)
        fut.set_result(out.reshape(len(msg.points), len(names)))

    # --- blocking ------------------------------------------------------------------------------
    def _wait(self, start: Any, timeout: float) -> Any:
        executor = self._node.executor
        if executor is not None and _inside_single_threaded(executor):
            raise BlockingCallError(
                "a blocking DynClient call from a callback of the single-threaded executor that "
                "spins this node would wait for itself: use check_async/efforts_async there, or a "
                "MultiThreadedExecutor")
        fut = start()
        deadline = time.monotonic() + timeout
        if executor is None:
            self._spin_privately(fut, timeout)
        else:
            done = threading.Event()
            fut.add_done_callback(lambda _f: done.set())
            done.wait(max(0.0, deadline - time.monotonic()))
        if not fut.done() and not fut.cancelled():
            self._forget(fut)
            if not self.ready():
                raise self._not_running(timeout)
            raise RequestTimeout(f"no answer from dyn_node at {self.namespace} within {timeout:g} s")
        if fut.exception() is not None:
            raise fut.exception()
        return fut.result()

    def _spin_privately(self, fut: Future, timeout: float) -> None:
        ex = SingleThreadedExecutor(context=self._node.context)
        ex.add_node(self._node)
        try:
            ex.spin_until_future_complete(fut, timeout_sec=timeout)
        finally:
            ex.remove_node(self._node)
            ex.shutdown(timeout_sec=1.0)

    def _forget(self, fut: Future) -> None:
        with self._lock:
            for table in (self._checks, self._efforts):
                for rid, ent in list(table.items()):
                    if ent is fut or (isinstance(ent, tuple) and ent[0] is fut):
                        del table[rid]
        fut.cancel()


def _inside_single_threaded(executor: Executor) -> bool:
    """True when this thread is inside ``executor``'s spin and nothing else can run callbacks.

    rclpy has no API for "the thread spinning this executor"; the stack says it: a
    SingleThreadedExecutor runs callbacks inside its own ``spin*`` frames, on this thread."""
    if isinstance(executor, MultiThreadedExecutor):
        return False
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_locals.get("self") is executor:
            return True
        frame = frame.f_back
    return False
