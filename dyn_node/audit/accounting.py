"""Executed trajectories and questions, counted apart.

A trajectory sent on ``joint_trajectory`` or as a FollowJointTrajectory goal through the gate is
*executed*: its "infeasible" is a violation of the run (a goal the gate rejected was sent to be
executed: it counts as executed and rejected; a retimed goal as what was forwarded, feasible). A check, retime or inverse-dynamics request is a *question*: its
"no" is an answer, listed but never a violation. Every trajectory entry of an evidence record
carries ``request`` (``execute`` or the question's kind); the counts of both live here so the
audit, its report, dyn-fleet and the demo say the same thing.

Questions come from two sources, each counted once: the request topics of older bags
(``~/check_trajectory``, ``~/inverse_dynamics_request``: one per message, answered as the audit
re-answers it) and the question services (``<service>/_service_event``: one per recorded
request/response pair, answered as the node's recorded response says; the client's own events
and a response without its request are not counted). A response not accepted counts as a
question answered "rejected" whatever its reason (invalid request, or ``busy``/``no_model``,
given without looking at the request), as a request topic's rejected request did.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterable

EXECUTE, GATE_GOAL = "execute", "gate_goal"
#: request kinds sent to be executed (the rest are questions)
EXECUTED_KINDS: frozenset[str] = frozenset({EXECUTE, GATE_GOAL})
CHECK, RETIME, INVERSE_DYNAMICS = "check", "retime", "inverse_dynamics"
QUESTION_KINDS: tuple[str, ...] = (CHECK, RETIME, INVERSE_DYNAMICS)

#: bag role → request kind of the request topics (service events carry their kind in their type)
REQUEST_OF_ROLE: dict[str, str] = {
    "joint_trajectory": EXECUTE,
    "check_trajectory": CHECK,
    "inverse_dynamics_request": INVERSE_DYNAMICS,
}


def request_of_role(role: str) -> str:
    """The request kind of a bag role; an unknown role is a question of that name, never an
    execution (only what was sent to be executed counts against the run)."""
    return REQUEST_OF_ROLE.get(role, role)


def request_of(entry: dict) -> str:
    """An evidence trajectory entry's request; entries written before the key existed were
    executed (only joint_trajectory was checked then)."""
    r = entry.get("request")
    return r if isinstance(r, str) and r else EXECUTE


def is_executed(entry: dict) -> bool:
    return request_of(entry) in EXECUTED_KINDS


@dataclass
class RequestTally:
    """Requests by kind: how many, and how many were answered "no" (infeasible or rejected)."""

    total: dict[str, int] = field(default_factory=dict)
    no: dict[str, int] = field(default_factory=dict)

    def add(self, request: str, *, answered_yes: bool) -> None:
        self.total[request] = self.total.get(request, 0) + 1
        if not answered_yes:
            self.no[request] = self.no.get(request, 0) + 1

    @classmethod
    def of_entries(cls, entries: Iterable[dict]) -> "RequestTally":
        t = cls()
        for e in entries:
            t.add(request_of(e), answered_yes=bool(e.get("feasible")))
        return t

    @property
    def executed(self) -> int:
        return sum(n for k, n in self.total.items() if k in EXECUTED_KINDS)

    @property
    def executed_bad(self) -> int:
        return sum(n for k, n in self.no.items() if k in EXECUTED_KINDS)

    @property
    def questions(self) -> int:
        return sum(n for k, n in self.total.items() if k not in EXECUTED_KINDS)

    @property
    def questions_no(self) -> int:
        return sum(n for k, n in self.no.items() if k not in EXECUTED_KINDS)

    def to_dict(self) -> dict[str, Any]:
        """The evidence's ``outputs.trajectory_counts``."""
        return {"executed": self.executed, "executed_infeasible_or_rejected": self.executed_bad,
                "questions": self.questions, "questions_infeasible_or_rejected": self.questions_no,
                "by_request": {k: {"total": n, "infeasible_or_rejected": self.no.get(k, 0)}
                               for k, n in sorted(self.total.items())}}

    def executed_text(self) -> str:
        """``1 executed trajectory`` / ``4 executed trajectories (3 gate goals)``."""
        goals = self.total.get(GATE_GOAL, 0)
        return (f"{self.executed} executed trajector{'y' if self.executed == 1 else 'ies'}"
                + (f" ({goals} gate goal{'' if goals == 1 else 's'})" if goals else ""))

    def sentence(self) -> str:
        """``1 of 4 executed trajectories infeasible or rejected; 2 of 5 questions answered
        infeasible or rejected (check)``: each count over its own total."""
        parts = [f"{self.executed_bad} of {self.executed_text()} infeasible or rejected"]
        return "; ".join(parts + ([self.questions_sentence()] if self.questions else []))

    def questions_sentence(self) -> str:
        """``2 of 5 questions answered infeasible or rejected (check 5)``."""
        kinds = ", ".join(f"{k} {n}" for k, n in sorted(self.total.items()) if k not in EXECUTED_KINDS)
        return (f"{self.questions_no} of {self.questions} question{'' if self.questions == 1 else 's'}"
                f" answered infeasible or rejected ({kinds})")


def counts_of(outputs: dict) -> dict[str, int]:
    """(executed, executed_bad, questions, questions_no) of a record's outputs: its
    ``trajectory_counts`` (exact, even past the listed entries), else counted from the entries."""
    c = outputs.get("trajectory_counts")
    if isinstance(c, dict):
        return {"executed": int(c["executed"]), "executed_bad": int(c["executed_infeasible_or_rejected"]),
                "questions": int(c["questions"]), "questions_no": int(c["questions_infeasible_or_rejected"])}
    t = RequestTally.of_entries(outputs.get("trajectories") or [])
    return {"executed": t.executed, "executed_bad": t.executed_bad, "questions": t.questions,
            "questions_no": t.questions_no}
