"""The audit of the FollowJointTrajectory gate: every decision recorded on ``~/gate_decisions``
decided again by the same core (:func:`dyn_node.gate.decision.decide_goal`, from the goal and the
start state the record carries, with the configuration in force) and compared: decision, reason,
verdict line, numbers and the trajectory forwarded, identical. A goal was sent to be executed: it
counts as an executed trajectory (request kind ``gate_goal``, :mod:`dyn_node.audit.accounting`),
infeasible or rejected when the gate rejected it or forwarded it infeasible (``check`` mode); a
retimed goal counts as the feasible trajectory it forwarded. A goal the controller never got or
the gate gave up on (``not_forwarded`` decisions; ends such as ``downstream_silent`` or
``downstream_cancel_unconfirmed``, :data:`dyn_node.gate.outcomes.NOT_EXECUTED_ENDS`) is not an
executed feasible trajectory: it counts as "no". A ``not_forwarded`` decision is replayed against
the check's decision it keeps (``checked_decision``). The decisions themselves are listed apart in
the evidence (``outputs.gate``). Retimed decisions are not replayed where ``dyn_node.retime`` is
missing.
"""
from __future__ import annotations

import importlib.util
import json
import math
from typing import Any, Callable

import numpy as np

from dyn_node.audit.accounting import GATE_GOAL, RequestTally
from dyn_node.audit.replay.common import Recheck
from dyn_node.bag.reader import BagMessage, MessageDecoder
from dyn_node.gate.outcomes import TRACKED

ROLE_GATE = "gate_decisions"
MAX_LISTED = 200  # decisions listed one by one in the evidence


def gate_role(topic: str, schema: str) -> str | None:
    return ROLE_GATE if topic.endswith("/gate_decisions") and schema == "std_msgs/msg/String" else None


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


class GateReplay:
    """Re-decides each recorded decision; the comparison goes to the re-check of ``sink`` (a
    Rechecker, or None) under the decisions topic."""

    def __init__(self, sink: Any = None, *, tally: RequestTally | None = None,
                 tracker: Callable[[], Any] | None = None):
        self.sink = sink
        # the replay's controller tracker now (a new configuration makes a new one): it follows
        # forwarded goals as the node's does
        self._tracker = tracker
        self._forwarded: dict[str, Any] = {}  # goal id → the trajectory forwarded, until tracked or ended
        self.tally = tally if tally is not None else RequestTally()
        self.bad = 0  # goals executed infeasible or rejected, or not executed
        self._own: dict[str, Recheck] = {}
        self._yes: set[str] = set()  # goals counted executed feasible, until an end says otherwise
        self.summary: dict[str, Any] = {"requests": 0, "answered": 0, "forwarded": 0, "rejected": 0,
                                        "retimed": 0, "not_forwarded": 0, "not_executed": 0, "not_replayed": 0,
                                        "results": {}, "decisions": []}

    def _check(self, topic: str) -> Recheck:
        if self.sink is None:
            return self._own.setdefault(topic, Recheck())
        if topic not in self.sink.checks:
            from dyn_node.audit.replay.common import Pending

            self.sink.checks[topic], self.sink.pending[topic], self.sink.topics[topic] = Recheck(), Pending(), topic
        return self.sink.checks[topic]

    def feed(self, m: BagMessage, decoder: MessageDecoder, dynamics: Any, settings: Any) -> None:
        check = self._check(m.topic)
        try:
            rec = json.loads(decoder.decode(m.channel, m.data).data)
        except Exception:  # noqa: BLE001 - an unreadable record is a discrepancy, not a crash
            check.unmatched += 1
            return
        if rec.get("event") == TRACKED:
            self._track(rec, settings)
            return
        if rec.get("event") != "decision":
            self._forwarded.pop(rec.get("goal_id"), None)
            self._end(rec)
            return
        if rec.get("forwarded") and self._tracker is not None:
            self._forwarded[rec["goal_id"]] = rec["forwarded"]
        s = self.summary
        s["requests"] += 1
        ok = executed_feasible(rec)
        self.tally.add(GATE_GOAL, answered_yes=ok)
        self.bad += not ok
        s["not_executed"] += rec.get("decision") == "not_forwarded"
        if ok:
            self._yes.add(rec["goal_id"])
        s[rec["decision"]] = s.get(rec["decision"], 0) + 1
        if len(s["decisions"]) < MAX_LISTED:
            s["decisions"].append({"t_ns": m.log_time_ns, "goal_id": rec["goal_id"], "decision": rec["decision"],
                                   "reason": rec["reason"], "verdict": rec["verdict"]})
        if "goal" not in rec or rec["decision"] == "not_forwarded" and not rec.get("checked_decision") \
                or (rec["decision"] == "retimed" or rec.get("mode") == "retime") \
                and importlib.util.find_spec("dyn_node.retime") is None:
            s["not_replayed"] += 1
            return
        s["answered"] += 1
        self._compare(rec, dynamics, settings, check, {"t_ns": m.log_time_ns, "goal_id": rec["goal_id"]})

    def _track(self, rec: dict, settings: Any) -> None:
        """The controller tracker follows the forwarded goal from the timing and state the node's
        did (the ``tracked`` record, written just before it did)."""
        from dyn_node.core.check.on_demand import options_for
        from dyn_node.core.check.trajectory import Trajectory
        from dyn_node.gate.decision import start_from_dict, timing_from_dict

        fwd = self._forwarded.pop(rec.get("goal_id"), None)
        tracker = self._tracker() if self._tracker is not None else None
        if fwd is None or tracker is None or list(fwd["joint_names"]) != list(tracker.model.joint_names):
            return
        arr = lambda k: None if fwd[k] is None else np.asarray(fwd[k], dtype=float)  # noqa: E731
        traj = Trajectory(times=arr("times"), positions=arr("positions"), velocities=arr("velocities"),
                          accelerations=arr("accelerations"))
        tracker.follow(traj, timing=timing_from_dict(rec["timing"]), start=start_from_dict(rec["start"]),
                       options=options_for(settings).execution)

    def _end(self, rec: dict) -> None:
        """An end record: counted by event; a goal counted executed feasible whose end says the
        controller never ran it (or the gate gave up on it) counts as "no" from now on."""
        from dyn_node.gate.outcomes import NOT_EXECUTED_ENDS

        key = rec.get("event", "?")
        self.summary["results"][key] = self.summary["results"].get(key, 0) + 1
        if key in NOT_EXECUTED_ENDS and rec.get("goal_id") in self._yes:
            self._yes.discard(rec["goal_id"])
            self.bad += 1
            self.tally.no[GATE_GOAL] = self.tally.no.get(GATE_GOAL, 0) + 1
            self.summary["not_executed"] += 1

    def _compare(self, rec: dict, dynamics: Any, settings: Any, check: Recheck, where: dict) -> None:
        # here, not at the top: a bag without gate goals never loads the check's kernels for it
        from dyn_node.gate.decision import (GateOptions, RetimePlan, decide_goal, goal_arrays, start_from_dict,
                                            timing_from_dict)

        options = GateOptions(mode=rec["mode"], retime_all=bool(rec.get("retime_all")),
                              max_state_age=float(rec.get("max_state_age", math.inf)),
                              start_tolerance=float(rec.get("start_tolerance", 0.01)))
        plan = None
        if "retime_lead_s" in rec:  # retime mode followed the robot: replayed from the states it used
            again = start_from_dict(rec.get("rechecked_from"))
            plan = RetimePlan(float(rec["retime_lead_s"]), lambda: again, options.max_state_age)
        # the goal's stamp and receipt as the gate recorded them (none in older records: zero stamp)
        d = decide_goal(dynamics, settings, options, *goal_arrays(rec["goal"]), start=start_from_dict(rec["start"]),
                        plan=plan, timing=timing_from_dict(rec.get("timing")))
        mine = d.to_dict(goal_id=rec["goal_id"], mode=rec["mode"], joint_names=list(dynamics.model.joint_names))
        if rec["decision"] == "not_forwarded":  # the check's decision is what is replayed
            rec = {**rec, "decision": rec["checked_decision"], "reason": rec.get("checked_reason"),
                   "forwarded": rec.get("checked_forwarded")}
        differing = [k for k in ("decision", "reason", "feasible", "verdict", "error_string", "worst_joint",
                                 "worst_constraint", "retime_message") if not _same(rec.get(k), mine.get(k))]
        worst, at = 0.0, None
        for k in ("time_scale", "worst_ratio", "duration_in", "duration_out", "duration_uniform"):
            a, b = rec.get(k), mine.get(k)
            if _same(a, b):
                continue
            diff = abs(a - b) if isinstance(a, float) and isinstance(b, float) else math.inf
            if not diff <= worst:
                worst, at = diff, {"field": k, "recorded": a, "recomputed": b}
        got, want = rec.get("forwarded"), mine.get("forwarded")
        if (got is None) != (want is None):
            differing.append("forwarded")
        elif got is not None:
            for k in ("positions", "velocities", "accelerations", "times"):
                a = np.asarray(got[k] if got[k] is not None else [], dtype=float)
                b = np.asarray(want[k] if want[k] is not None else [], dtype=float)
                if a.shape != b.shape:
                    differing.append(f"forwarded.{k}")
                elif a.size and not np.array_equal(a, b):
                    diff = float(np.max(np.abs(a - b)))
                    if not diff <= worst:
                        worst, at = diff, {"field": f"forwarded.{k}"}
        check.mismatched_values += len(differing)
        check.diff(worst, {**where, **(at or {}), **({"differing_fields": differing} if differing else {})})

    def finish(self) -> dict[str, Any]:
        """The evidence's ``outputs.gate``: counts and each decision ({} when none was recorded)."""
        s = self.summary
        return dict(s) if s["requests"] or s["results"] else {}


def executed_feasible(rec: dict) -> bool:
    """Whether a decision's goal counts as an executed trajectory that was feasible: a retimed
    goal forwarded what the check passed; a forwarded one is as its verdict; a rejected one no."""
    decision = rec.get("decision")
    return decision == "retimed" or (decision == "forwarded" and rec.get("feasible") is True)
