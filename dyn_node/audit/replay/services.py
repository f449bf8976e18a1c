"""The audit of dyn_node's question services: each recorded request/response pair of
``~/check_trajectory``, ``~/compute_inverse_dynamics`` and ``~/retime_trajectory`` (their
``<service>/_service_event`` topics, introspection with contents) answered again by the same
core, and the answer compared with the recorded response.

A question is not an execution: an infeasible answer is listed, never a violation of the run.
Responses the node gave without looking at the request (``busy``, ``no_model``, shutting down,
``expired``, ``too_large``, ``worker_failed``: the worker process died) depend on its load or its live settings, not on the request's content, and are counted, not replayed. Each answered pair also
goes once into the audit's :class:`~dyn_node.audit.accounting.RequestTally` (its kind, and "no"
when not accepted or, for a check or retime, not feasible), beside the request topics' questions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from dyn_node.audit.accounting import CHECK, INVERSE_DYNAMICS, RETIME, RequestTally
from dyn_node.audit.replay.common import Pending, Recheck, worst_status_difference
from dyn_node.bag.reader import BagMessage, MessageDecoder
from dyn_node.core.robot.status import format_value
from dyn_node.errors import TrajectoryError

if TYPE_CHECKING:
    from dyn_node.core.check.feasibility import StartState

ROLE_SERVICE_EVENT = "service_event"
EVENT_SUFFIX = "/_service_event"
#: event type → the question it asks
QUESTIONS = {"dyn_node_interfaces/srv/CheckTrajectory_Event": CHECK,
             "dyn_node_interfaces/srv/ComputeInverseDynamics_Event": INVERSE_DYNAMICS,
             "dyn_node_interfaces/srv/RetimeTrajectory_Event": RETIME}
# service_msgs/ServiceEventInfo event types the server side publishes
REQUEST_RECEIVED, RESPONSE_SENT = 1, 2
#: answers given without looking at the request: not reproducible from the bag
NOT_REPLAYED = ("busy", "no_model", "shutting_down", "internal_error", "expired", "too_large",
                "worker_failed")


def service_role(topic: str, schema: str) -> str | None:
    """The role of a recorded service event topic of ours, else None."""
    return ROLE_SERVICE_EVENT if topic.endswith(EVENT_SUFFIX) and schema in QUESTIONS else None


@dataclass
class _Diff:
    """Differences between a recorded answer and the recomputed one."""

    numeric: float = 0.0
    where: dict | None = None
    values: int = 0
    fields: list[str] = field(default_factory=list)

    def number(self, name: str, got: float, want: float) -> None:
        if got == want or (math.isnan(got) and math.isnan(want)):
            return
        d = abs(got - want) if math.isfinite(got) and math.isfinite(want) else math.inf
        if not d <= self.numeric:
            self.numeric, self.where = d, {"field": name, "recorded": got, "recomputed": want}

    def array(self, name: str, got: np.ndarray, want: np.ndarray) -> None:
        if got.shape != want.shape:
            self.numeric, self.where = math.inf, {"field": name, "recorded": str(got.shape),
                                                  "recomputed": str(want.shape)}
            return
        if got.size and not np.array_equal(got, want, equal_nan=True):
            i = np.unravel_index(int(np.nanargmax(np.abs(got - want))), got.shape)
            self.number(f"{name}[{','.join(map(str, i))}]", float(got[i]), float(want[i]))

    def value(self, name: str, got: Any, want: Any) -> None:
        if got != want:
            self.values += 1
            self.fields.append(name)


def _arrays(traj: Any) -> tuple[list[str], list[float], list, list, list, list]:
    """Names, times, positions, velocities, accelerations and efforts (only validated)."""
    pts = traj.points
    times = [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts]
    return (list(traj.joint_names), times, [list(p.positions) for p in pts],
            [list(p.velocities) for p in pts], [list(p.accelerations) for p in pts],
            [list(p.effort) for p in pts])


def _effort(traj: Any) -> np.ndarray:
    return np.array([list(p.effort) for p in traj.points], dtype=float).reshape(
        len(traj.points), -1 if traj.points else 0)


def _start(resp: Any) -> StartState | None:
    """The state the node said it started from (empty: none)."""
    from dyn_node.core.check import feasibility

    st = resp.start_state
    if not st.name:
        return None
    return feasibility.StartState(np.asarray(st.position, dtype=float),
                                  np.asarray(st.velocity, dtype=float), float(resp.start_state_age))


def _statuses(statuses: Sequence[Any]) -> dict[str, dict[str, str]]:
    return {s.name: {k: format_value(v) for k, v in s.values.items()} for s in statuses}


class ServiceReplay:
    """Pairs each request with its response (by client and sequence number) and re-answers it
    with the configuration in force; the comparison goes to the re-check of ``sink`` (a
    :class:`~dyn_node.audit.replay.recheck.Rechecker`, or None) under the event topic's name; each
    answered pair is added once to ``tally`` (the audit's, shared with the request topics)."""

    def __init__(self, sink: Any = None, *, tally: RequestTally | None = None):
        self.sink = sink
        self.tally = tally if tally is not None else RequestTally()
        self._requests: dict[tuple[str, bytes, int], Any] = {}
        self._own: dict[str, tuple[Recheck, Pending]] = {}
        #: question → {requests, answered, accepted, feasible, infeasible, not accepted reasons}
        self.summary: dict[str, dict[str, Any]] = {}

    @property
    def questions(self) -> int:
        return sum(s["requests"] for s in self.summary.values())

    def feed(self, m: BagMessage, decoder: MessageDecoder, dynamics: Any, settings: Any) -> None:
        kind = QUESTIONS[m.channel.schema_name]
        check, pending = self._checks(m.topic)
        stats = self.summary.setdefault(kind, {"requests": 0, "answered": 0, "accepted": 0,
                                               "feasible": 0, "infeasible": 0, "not_accepted": {}})
        try:
            ev = decoder.decode(m.channel, m.data)
            info = ev.info
            # char[16]: signed or unsigned by decoder, the same 16 bytes either way
            key = (m.topic, bytes(int(x) & 0xFF for x in info.client_gid), int(info.sequence_number))
        except Exception:  # noqa: BLE001 - an undecodable event is a discrepancy, not a crash
            check.unmatched += 1
            return
        if info.event_type == REQUEST_RECEIVED and ev.request:
            stats["requests"] += 1
            self._requests[key] = ev.request[0]
            pending.put(key, True)  # unanswered until its response comes
        elif info.event_type == RESPONSE_SENT and ev.response:
            request = self._requests.pop(key, None)
            if request is None or pending.take(key) is None:
                check.unmatched += 1  # a response whose request was not recorded
                return
            self._compare(kind, request, ev.response[0], dynamics, settings, check, stats,
                          {"t_ns": m.log_time_ns, "sequence_number": key[2]})

    def _checks(self, topic: str) -> tuple[Recheck, Pending]:
        sink = self.sink
        if sink is None:
            return self._own.setdefault(topic, (Recheck(), Pending()))
        if topic not in sink.checks:
            sink.checks[topic], sink.pending[topic], sink.topics[topic] = Recheck(), Pending(), topic
        return sink.checks[topic], sink.pending[topic]

    def _compare(self, kind: str, request: Any, resp: Any, dynamics: Any, settings: Any,
                 check: Recheck, stats: dict, where: dict) -> None:
        stats["answered"] += 1
        # the node's answer as recorded; a busy/no_model refusal is a "no" like an invalid request
        self.tally.add(kind, answered_yes=bool(resp.accepted) and (kind == INVERSE_DYNAMICS
                                                                   or bool(resp.feasible)))
        if resp.accepted:
            stats["accepted"] += 1
            if kind != INVERSE_DYNAMICS:
                stats["feasible" if resp.feasible else "infeasible"] += 1
        else:
            stats["not_accepted"][resp.reason] = stats["not_accepted"].get(resp.reason, 0) + 1
            if resp.reason in NOT_REPLAYED:
                return
        d = _Diff()
        if kind == CHECK:
            _check(d, request, resp, dynamics, settings)
        elif kind == INVERSE_DYNAMICS:
            _inverse_dynamics(d, request, resp, dynamics)
        elif not _retime(d, request, resp, dynamics, settings):
            stats.setdefault("not_replayed", {}).setdefault("retimer_unavailable", 0)
            stats["not_replayed"]["retimer_unavailable"] += 1
            return
        check.mismatched_values += d.values
        check.diff(d.numeric, {**where, **(d.where or {}),
                               **({"differing_fields": d.fields[:10]} if d.fields else {})})

    def finish(self) -> dict[str, Any]:
        """The questions answered, per service (for the record)."""
        return {k: dict(v) for k, v in self.summary.items()}


def _rejected(d: _Diff, resp: Any, exc: TrajectoryError) -> None:
    d.value("accepted", bool(resp.accepted), False)
    d.value("reason", resp.reason, exc.code or "invalid")
    if hasattr(resp, "message"):
        d.value("message", resp.message, str(exc))


def _check(d: _Diff, request: Any, resp: Any, dynamics: Any, settings: Any) -> None:
    from dyn_node.core.check import on_demand  # the check's stack only for a bag with questions

    names, times, P, V, A, E = _arrays(request.trajectory)
    out = on_demand.check(dynamics, settings, names, times, P, V, A, start=_start(resp),
                          start_unknown=on_demand.question_start_unknown(request.from_current_state),
                          efforts=E)
    mine = on_demand.with_request(out.statuses, on_demand.REQUEST_CHECK)
    worst, where, mismatched = worst_status_difference(resp.statuses, _statuses(mine))
    d.values += mismatched
    if worst:
        d.numeric, d.where = worst, where
    if out.error is not None:
        _rejected(d, resp, out.error)
        return
    r = out.result
    d.value("accepted", bool(resp.accepted), True)
    for name, got, want in (("feasible", bool(resp.feasible), bool(r.feasible)),
                            ("message", resp.message, r.message),
                            ("worst_joint", resp.worst_joint, r.worst_joint),
                            ("worst_constraint", resp.worst_constraint, r.worst_constraint),
                            ("binding_joint", resp.binding_joint, r.time_scale_joint),
                            ("binding_constraint", resp.binding_constraint, r.time_scale_constraint),
                            ("start_segment", resp.start_segment, r.start_segment)):
        d.value(name, got, want)
    for name, got, want in (("time_scale", resp.time_scale, r.time_scale),
                            ("worst_ratio", resp.worst_ratio, r.worst_ratio),
                            ("first_violation_time", resp.first_violation_time, r.first_violation_time_s)):
        d.number(name, float(got), float(want))
    order = [list(dynamics.model.joint_names).index(n) for n in resp.effort.joint_names]
    d.array("effort", _effort(resp.effort), np.asarray(r.waypoint_effort)[:, order])


def _inverse_dynamics(d: _Diff, request: Any, resp: Any, dynamics: Any) -> None:
    from dyn_node.core.check import on_demand  # the check's stack only for a bag with questions

    model_joints = list(dynamics.model.joint_names)
    st = request.states
    pts = st.points
    try:
        Q, V, A = on_demand.states(model_joints, list(st.joint_names), [p.positions for p in pts],
                                   [p.velocities for p in pts], [p.accelerations for p in pts])
        tau = on_demand.inverse_dynamics(dynamics, Q, V, A)
    except TrajectoryError as exc:
        _rejected(d, resp, exc)
        return
    d.value("accepted", bool(resp.accepted), True)
    order = [model_joints.index(n) for n in resp.effort.joint_names] if resp.accepted else []
    d.array("effort", _effort(resp.effort), tau[:, order] if order else np.zeros((0, 0)))


def _retime(d: _Diff, request: Any, resp: Any, dynamics: Any, settings: Any) -> bool:
    """False when the retimer is not available here (nothing compared)."""
    from dyn_node.core.check import on_demand  # the check's stack only for a bag with questions

    names, times, P, V, A, E = _arrays(request.trajectory)
    try:
        traj = on_demand.validated(dynamics.model.joint_names, names, times, P, V, A, efforts=E)
    except TrajectoryError as exc:
        _rejected(d, resp, exc)
        return True
    try:
        from dyn_node.retime import retime
    except ImportError:
        return False
    try:
        r = retime(dynamics, traj, start=_start(resp), feasibility=on_demand.options_for(settings),
                   limit_margin=settings.retime_limit_margin)
    except TrajectoryError as exc:
        _rejected(d, resp, exc)
        return True
    d.value("accepted", bool(resp.accepted), True)
    d.value("feasible", bool(resp.feasible), bool(r.feasible))
    d.value("message", resp.message, r.message)
    d.value("blocked", resp.blocked, r.blocked)
    for name in ("duration_in", "duration_out", "duration_uniform", "lower_bound"):
        d.number(name, float(getattr(resp, name)), float(getattr(r, name)))
    if r.trajectory is not None:
        got = np.array([list(p.positions) for p in resp.trajectory.points], dtype=float)
        d.array("trajectory.positions", got, np.asarray(r.trajectory.positions, dtype=float))
    return True
