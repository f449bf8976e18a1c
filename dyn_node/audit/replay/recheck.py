"""dyn-audit's stage 3, the re-check: the node's recorded outputs (gravity_torque,
inverse_dynamics, feasibility, trajectory_effort, and the contact outputs through
:class:`~dyn_node.audit.replay.contact.ContactRecheck`) against what the replay recomputed for
the same input, matched by header stamp."""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from dyn_node.audit.replay.common import MAX_PENDING, Pending, Recheck, worst_status_difference
from dyn_node.audit.replay.contact import CONTACT_ROLES, ContactRecheck
from dyn_node.audit.replay.roles import ROLE_FEAS, ROLE_GRAVITY, ROLE_ID, ROLE_TRAJ_EFFORT
from dyn_node.audit.replay.stats import Histogram
from dyn_node.bag.cdr import decode_joint_state
from dyn_node.bag.reader import BagMessage, MessageDecoder
from dyn_node.errors import TrajectoryError


OUTPUT_ROLES = (ROLE_GRAVITY, ROLE_ID, ROLE_FEAS, ROLE_TRAJ_EFFORT)


@dataclass
class RecheckResult:
    """Per output role: the comparison, the recomputed values never answered, the topic; and
    the latency of the recorded gravity_torque (from the input's stamp, from its receipt)."""

    checks: dict[str, Recheck]
    unanswered: dict[str, int]
    topics: dict[str, str]
    latency_stamp: Histogram
    latency_receipt: Histogram


class Rechecker:
    """Stage 3: the node's recorded outputs against what the replay recomputed for the same
    input (matched by header stamp). Recomputed values are kept only for the output roles whose
    topics the bag may hold (``known_topics``; None: unknown, all kept)."""

    def __init__(self, known_topics: Any = None, decoder: MessageDecoder | None = None):
        self.want = {r: known_topics is None
                     or any(t.rstrip("/").rsplit("/", 1)[-1] == r for t in known_topics)
                     for r in OUTPUT_ROLES}
        self.decoder = decoder or MessageDecoder()
        self.pending = {r: Pending() for r in OUTPUT_ROLES}
        self.checks = {r: Recheck() for r in OUTPUT_ROLES}
        self.topics: dict[str, str] = {}
        self.lat_stamp, self.lat_receipt = Histogram(), Histogram()
        self.input_log: OrderedDict[int, int] = OrderedDict()  # stamp → input log time (for latency)
        self.known_topics = known_topics
        self.contact = ContactRecheck(self)  # its roles join want/pending/checks above

    # what the replay recomputed ------------------------------------------------------------
    @property
    def wants_states(self) -> bool:
        return self.want[ROLE_GRAVITY] or self.want[ROLE_ID]

    def expect_state(self, key: int, t_ns: int, gravity: np.ndarray, tau: np.ndarray) -> None:
        if self.want[ROLE_GRAVITY]:
            self.pending[ROLE_GRAVITY].put(key, gravity)
            self.input_log[key] = t_ns
            if len(self.input_log) > MAX_PENDING:
                self.input_log.popitem(last=False)
        if self.want[ROLE_ID]:
            self.pending[ROLE_ID].put(key, tau)

    def expect_verdict(self, key: tuple[int, str], value: Any) -> None:
        """A FeasibilityResult, or the rejected entry, for a ~/feasibility answer."""
        if self.want[ROLE_FEAS]:
            self.pending[ROLE_FEAS].put(key, value)

    def expect_efforts(self, key: tuple[int, str], tau: np.ndarray) -> None:
        if self.want[ROLE_TRAJ_EFFORT]:
            self.pending[ROLE_TRAJ_EFFORT].put(key, tau)

    # what the node recorded ----------------------------------------------------------------
    def output(self, role: str, m: BagMessage, model: Any) -> None:
        """Compare one recorded output with its recomputed value (``model``: the one replayed)."""
        if role in CONTACT_ROLES:
            self.contact.output(role, m, model)
            return
        if role not in OUTPUT_ROLES:
            return
        self.topics[role] = m.topic
        if role == ROLE_TRAJ_EFFORT:
            self._traj_effort(m, model)
        elif role == ROLE_FEAS:
            self._feasibility(m, model)
        else:
            self._torques(role, m, model)

    def result(self) -> RecheckResult:
        return RecheckResult(self.checks, {r: p.left() for r, p in self.pending.items()},
                             self.topics, self.lat_stamp, self.lat_receipt)

    def _torques(self, role: str, m: BagMessage, model: Any) -> None:
        chk = self.checks[role]
        try:
            out = decode_joint_state(m.data)
        except ValueError:
            chk.unmatched += 1
            return
        want = self.pending[role].take(out.stamp_ns)
        if want is None:
            chk.unmatched += 1
            return
        names = model.joint_names
        got = out.effort
        if out.names != names and set(out.names) == set(names):
            got = got[[out.names.index(n) for n in names]]
        d = float(np.max(np.abs(got - want))) if got.shape == want.shape else math.inf
        t_ns = m.log_time_ns
        chk.diff(d, {"stamp_ns": out.stamp_ns, "t_ns": t_ns})
        if role == ROLE_GRAVITY:
            src = self.input_log.get(out.stamp_ns)
            self.lat_stamp.add((t_ns - out.stamp_ns) * 1e-9)
            if src is not None:
                self.lat_receipt.add((t_ns - src) * 1e-9)

    def _recorded_and_recomputed(self, m: BagMessage, role: str) -> tuple[Any, int, Any] | None:
        """(recorded output, its header stamp in ns, the value recomputed for that stamp), or None
        (counted as unmatched) when the output cannot be decoded or has no recomputed input."""
        try:
            msg = self.decoder.decode(m.channel, m.data)
        except Exception:  # noqa: BLE001 - a damaged output is a finding, not a crash
            self.checks[role].unmatched += 1
            return None
        key = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        want = self.pending[role].take((key, msg.header.frame_id))
        if want is None:
            self.checks[role].unmatched += 1
            return None
        return msg, key, want

    def _feasibility(self, m: BagMessage, model: Any) -> None:
        found = self._recorded_and_recomputed(m, ROLE_FEAS)
        if found is None:
            return
        arr, key, res = found
        if any(st.message.startswith(("rejected: busy", "rejected: no robot model yet")) for st in arr.status):
            return  # a request the node could not take (queue full, no model yet): nothing to compare
        worst, where, mismatched = worst_status_difference(arr.status, _statuses(res, model.name))
        chk = self.checks[ROLE_FEAS]
        chk.mismatched_values += mismatched
        chk.diff(worst, {"stamp_ns": key, "t_ns": m.log_time_ns, **(where or {})})

    def _traj_effort(self, m: BagMessage, model: Any) -> None:
        found = self._recorded_and_recomputed(m, ROLE_TRAJ_EFFORT)
        if found is None:
            return
        msg, key, want = found
        try:
            order = [list(msg.joint_names).index(n) for n in model.joint_names]
            got = np.array([[p.effort[i] for i in order] for p in msg.points], dtype=float)
            d = float(np.max(np.abs(got - want))) if got.shape == want.shape else math.inf
        except (ValueError, IndexError):
            d = math.inf
        self.checks[ROLE_TRAJ_EFFORT].diff(d, {"stamp_ns": key, "t_ns": m.log_time_ns})


def _statuses(res: Any, model_name: str) -> dict[str, dict[str, str]]:
    """The ~/feasibility statuses the node publishes for a result (or a rejected entry), by name,
    with their values formatted as the node formats them."""
    from dyn_node.core.robot.status import format_value

    if isinstance(res, dict):  # rejected: the node published rejected_statuses
        from dyn_node.core.check.feasibility import rejected_statuses

        err = TrajectoryError(res["message"].removeprefix("rejected: "), code=res["error_code"] or "error")
        statuses = rejected_statuses(err, model_name, res.get("n_points", 0), res.get("duration_s", 0.0))
    else:
        statuses = res.statuses(model_name)
    return {s.name: {k: format_value(v) for k, v in s.values.items()} for s in statuses}
