"""A Python client for dyn_node's question services, usable from any rclpy node.

``DynClient(node, namespace="/dyn_node")`` calls ``~/check_trajectory``, ``~/compute_inverse_dynamics``
and ``~/retime_trajectory`` (types from ``dyn_node_interfaces``); several calls can be in flight.
Blocking calls need ``node`` spun meanwhile: they spin an unspun node themselves, wait when
another thread spins it, and raise :class:`BlockingCallError` in a single-threaded executor's
callback (use the ``*_async`` variants there). docs/node.md "Python client" has the whole API.
"""
from __future__ import annotations

import math
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from dyn_node_interfaces.srv import CheckTrajectory, ComputeInverseDynamics, RetimeTrajectory
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import Executor, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from dyn_node.core.robot.limits import LIMIT_KINDS
from dyn_node.core.robot.status import ERROR, NAME_PREFIX
from dyn_node.ros.convert import s_to_duration

STATUS_NAME = NAME_PREFIX + "trajectory feasibility"  # feasibility.STATUS_NAME, without its imports


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
    """dyn_node's verdict on one trajectory: a ``~/check_trajectory`` response
    (:meth:`from_response`) or a ``~/feasibility`` DiagnosticArray (:meth:`from_msg`).

    ``feasible``: the trajectory can run as timed. ``level``: 0 OK, 1 WARN (feasible, close to a
    limit), 2 ERROR (infeasible or rejected). ``rejected``: it could not be checked at all
    (``reason`` is the code: ``non_finite``, ``bad_times``, ``unknown_joints``, ``busy`` ...; the
    message says what). ``time_scale``: the smallest stretch of the duration that makes it
    feasible (≤ 1 when feasible; inf: no slowdown helps; NaN when rejected). ``worst_*``: the
    joint, limit kind and peak ratio closest to (or furthest over) its limit; ``binding_*``: what
    sets ``time_scale``. ``effort``: the torque of each point (points × joints, the request's
    joint order; empty when rejected).
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
    effort: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)), repr=False)
    statuses: tuple = field(default=(), repr=False)  # the DiagnosticStatus messages as answered

    def status_values(self, place: str) -> dict[str, str] | None:
        """The key/values of the ``…/<place>`` status (a joint, a frame, ...), None without one."""
        st = next((s for s in self.statuses if s.name == f"{STATUS_NAME}/{place}"), None)
        return None if st is None else {kv.key: kv.value for kv in st.values}

    @classmethod
    def from_response(cls, resp: CheckTrajectory.Response) -> "Verdict":
        """A ``~/check_trajectory`` response (a request not accepted: ``rejected``, ``reason``)."""
        if any(s.name == STATUS_NAME for s in resp.statuses):
            v = cls.from_msg(DiagnosticArray(status=list(resp.statuses)))
        else:  # answered at once (busy, no_model): no statuses
            v = cls(feasible=False, level=ERROR, message=resp.message, time_scale=math.nan,
                    worst_joint="", worst_constraint="", worst_ratio=math.nan,
                    first_violation_time_s=math.nan, ratios={}, violations=(), request="check")
        effort = np.array([list(p.effort) for p in resp.effort.points], dtype=float)
        return replace(v, rejected=not resp.accepted, reason=resp.reason or v.reason,
                       statuses=tuple(resp.statuses),
                       feasible=bool(resp.accepted and resp.feasible),
                       binding_joint=resp.binding_joint, binding_constraint=resp.binding_constraint,
                       effort=effort.reshape(len(resp.effort.points), len(resp.effort.joint_names)))

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
        pt.time_from_start = s_to_duration(float(t))  # the one rounding rule
    return msg


def states_message(joint_names: Sequence[str], positions: Any, velocities: Any = None,
                   accelerations: Any = None) -> JointTrajectory:
    """A ``~/compute_inverse_dynamics`` request's states from N×k arrays in ``joint_names`` order (velocities and
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


@dataclass(frozen=True)
class Retimed:
    """dyn_node's answer to ``~/retime_trajectory``. ``accepted`` false: not retimed (``reason``:
    ``non_finite``, ``busy``, ``retimer_unavailable`` ...; ``message`` says what). ``feasible``: a
    retimed ``trajectory`` (model joint order) was found; durations in s: the request's, the
    retimed one's, the request uniformly stretched, and a lower bound along this path.
    ``verdict``: the check of the output (None without one)."""

    accepted: bool
    reason: str
    feasible: bool
    trajectory: JointTrajectory
    duration_in: float
    duration_out: float
    duration_uniform: float
    lower_bound: float
    message: str
    blocked: str
    verdict: Verdict | None

    @classmethod
    def from_response(cls, resp: RetimeTrajectory.Response) -> "Retimed":
        verdict = None
        if any(s.name == STATUS_NAME for s in resp.statuses):
            verdict = Verdict.from_msg(DiagnosticArray(status=list(resp.statuses)))
        return cls(bool(resp.accepted), resp.reason, bool(resp.accepted and resp.feasible),
                   resp.trajectory, resp.duration_in, resp.duration_out, resp.duration_uniform,
                   resp.lower_bound, resp.message, resp.blocked, verdict)


def _efforts(resp: ComputeInverseDynamics.Response, names: list[str]) -> np.ndarray:
    if not resp.accepted:
        raise RequestRejected(Verdict(
            feasible=False, level=ERROR, message=resp.message, time_scale=math.nan, worst_joint="",
            worst_constraint="", worst_ratio=math.nan, first_violation_time_s=math.nan, ratios={},
            violations=(), request="inverse_dynamics", rejected=True, reason=resp.reason))
    msg = resp.effort
    order = [list(msg.joint_names).index(n) for n in names]
    out = np.array([[p.effort[i] for i in order] for p in msg.points], dtype=float)
    return out.reshape(len(msg.points), len(names))


class DynClient:
    """Check trajectories, ask for torques and retimings from a running dyn_node (see the module
    doc).

    ``namespace`` is the dyn_node's fully qualified name (``/dyn_node`` by default; e.g.
    ``/robot1/dyn_node`` for a namespaced one). Construct once per node and keep it: creating the
    service clients and discovering dyn_node's services takes discovery time.
    """

    def __init__(self, node: Node, namespace: str = "/dyn_node"):
        self._node = node
        ns = "/" + namespace.strip("/")
        self.namespace = ns
        self._lock = threading.Lock()
        self._pending: set[Future] = set()
        group = MutuallyExclusiveCallbackGroup()  # responses are taken beside the caller's callbacks
        self._clients = {
            "check": node.create_client(CheckTrajectory, f"{ns}/check_trajectory", callback_group=group),
            "efforts": node.create_client(ComputeInverseDynamics, f"{ns}/compute_inverse_dynamics",
                                          callback_group=group),
            "retime": node.create_client(RetimeTrajectory, f"{ns}/retime_trajectory", callback_group=group),
        }

    # --- public API --------------------------------------------------------------------------
    def check(self, traj: JointTrajectory, timeout: float = 10.0, *,
              from_current_state: bool = False) -> Verdict:
        """dyn_node's verdict on ``traj`` (from the robot's current state with
        ``from_current_state``), checked like ``joint_trajectory`` but never executed. Raises
        :class:`NotRunningError`, :class:`RequestTimeout` or :class:`BlockingCallError` (see the
        module doc); a trajectory dyn_node does not accept (NaN, times not increasing, unknown
        joints, queue full) is a Verdict with ``rejected`` set and the ``reason``."""
        return self._wait(lambda: self.check_async(traj, timeout=timeout,
                                                   from_current_state=from_current_state), timeout)

    def efforts(self, traj_or_states: JointTrajectory, timeout: float = 10.0) -> np.ndarray:
        """τ(q, q̇, q̈) for each point of ``traj_or_states`` (missing velocities or accelerations
        mean zero): an array (points, joints) in the request's joint order, N·m (N for prismatic
        joints). Raises like :meth:`check`, and :class:`RequestRejected` for a malformed request."""
        return self._wait(lambda: self.efforts_async(traj_or_states, timeout=timeout), timeout)

    def retime(self, traj: JointTrajectory, timeout: float = 30.0, *,
               from_current_state: bool = False) -> Retimed:
        """The fastest trajectory along ``traj``'s path within every limit. Raises like
        :meth:`check`; a request not retimed is a :class:`Retimed` with ``accepted`` false."""
        return self._wait(lambda: self.retime_async(traj, timeout=timeout,
                                                    from_current_state=from_current_state), timeout)

    def check_async(self, traj: JointTrajectory, *, timeout: float = 10.0,
                    from_current_state: bool = False) -> Future:
        """Call ``~/check_trajectory`` now; the Future completes with its :class:`Verdict` (or a
        :class:`NotRunningError` when the service is not there within ``timeout``)."""
        req = CheckTrajectory.Request(trajectory=_checked(traj), from_current_state=from_current_state)
        return self._call("check", req, Verdict.from_response, timeout)

    def efforts_async(self, traj_or_states: JointTrajectory, *, timeout: float = 10.0) -> Future:
        """Call ``~/compute_inverse_dynamics`` now; the Future completes with the torque array."""
        names = list(_checked(traj_or_states).joint_names)
        req = ComputeInverseDynamics.Request(states=traj_or_states)
        return self._call("efforts", req, lambda resp: _efforts(resp, names), timeout)

    def retime_async(self, traj: JointTrajectory, *, timeout: float = 30.0,
                     from_current_state: bool = False) -> Future:
        """Call ``~/retime_trajectory`` now; the Future completes with its :class:`Retimed`."""
        req = RetimeTrajectory.Request(trajectory=_checked(traj), from_current_state=from_current_state)
        return self._call("retime", req, Retimed.from_response, timeout)

    def ready(self) -> bool:
        """True when dyn_node's three services are discovered."""
        return all(c.service_is_ready() for c in self._clients.values())

    def destroy(self) -> None:
        """Destroy the client's service clients; pending futures fail."""
        for cli in self._clients.values():
            self._node.destroy_client(cli)
        with self._lock:
            pending = list(self._pending)
            self._pending.clear()
        for f in pending:
            if not f.done():
                f.set_exception(DynClientError("client destroyed before the answer came"))

    # --- calling -----------------------------------------------------------------------------
    def _call(self, which: str, req: Any, convert: Callable[[Any], Any], timeout: float) -> Future:
        fut = Future()
        with self._lock:
            self._pending.add(fut)
        cli = self._clients[which]
        if cli.service_is_ready():
            self._send(cli, req, convert, fut)
        else:
            # Not discovered yet (just created, or dyn_node not up): call once it is, from a thread
            # of our own so a callback calling the async variant is never held up. A request sent
            # before discovery may be lost.
            threading.Thread(target=self._send_when_ready, args=(cli, req, convert, fut, timeout),
                             name="dyn_client send", daemon=True).start()
        return fut

    def _send(self, cli: Any, req: Any, convert: Callable[[Any], Any], fut: Future) -> None:
        def done(call: Future) -> None:
            with self._lock:
                self._pending.discard(fut)
            if fut.done() or fut.cancelled():
                return
            try:
                fut.set_result(convert(call.result()))
            except Exception as exc:  # RequestRejected, or a call that failed
                fut.set_exception(exc)
        cli.call_async(req).add_done_callback(done)

    def _send_when_ready(self, cli: Any, req: Any, convert: Callable[[Any], Any], fut: Future,
                         timeout: float) -> None:
        if cli.wait_for_service(timeout_sec=timeout) and self._node.context.ok():
            if not (fut.done() or fut.cancelled()):
                self._send(cli, req, convert, fut)
            return
        with self._lock:
            self._pending.discard(fut)
        if not fut.done() and not fut.cancelled():
            fut.set_exception(self._not_running(timeout))

    def _not_running(self, timeout: float) -> NotRunningError:
        return NotRunningError(f"dyn_node is not running at {self.namespace}: its services "
                               f"(check_trajectory, ...) were not there within {timeout:g} s")

    # --- blocking ------------------------------------------------------------------------------
    def _wait(self, start: Any, timeout: float) -> Any:
        executor = self._node.executor
        if executor is not None and _inside_single_threaded(executor):
            raise BlockingCallError(
                "a blocking DynClient call from a callback of the single-threaded executor that "
                "spins this node would wait for itself: use the *_async variants there, or a "
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
            with self._lock:
                self._pending.discard(fut)
            fut.cancel()
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


def _checked(traj: Any) -> JointTrajectory:
    if not isinstance(traj, JointTrajectory):
        raise TypeError(f"a trajectory_msgs/JointTrajectory is needed, not {type(traj).__name__}")
    return traj


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
