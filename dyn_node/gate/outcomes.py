"""How a goal through the gate ends, and the ``event`` record each end writes on ``~/gate_decisions``.

Every goal gets one decision record (``event: decision``) and one end record (``event`` below).
The invariant the gate keeps: no goal the controller accepted for a client's goal is left running
after the client's goal ended; where the gate ends a goal the controller still runs, it cancels it
and waits (bounded) for the controller's end (``cancel``: ``confirmed`` or
``downstream_cancel_unconfirmed``). docs/gate.md lists each end with the client's status.
"""
from __future__ import annotations

from typing import Any

#: the controller's end passed through unchanged (SUCCEEDED, ABORTED, CANCELED: the client's
#: cancel or the controller's pre-emption)
RESULT = "result"
#: the check refused the goal (reject mode, malformed, stale state, retiming failed)
REFUSED = "refused"
#: the goal's check could not be queued: gate.max_pending goals waiting already
GATE_BUSY = "gate_busy"
#: the gate was shutting down when the goal arrived
REFUSED_CLOSING = "refused_closing"
#: no downstream action server within gate.timeout
DOWNSTREAM_UNAVAILABLE = "downstream_unavailable"
#: the controller's goal response did not come within gate.timeout; if it comes later and
#: accepts, that goal is cancelled on arrival (``late_goal_cancelled`` record)
DOWNSTREAM_LATE = "downstream_late"
LATE_GOAL_CANCELLED = "late_goal_cancelled"
#: not an end: when and from which state the controller runs a forwarded goal, as the node's
#: controller tracker follows it (``timing``, ``start``); the audit's replay follows the same
TRACKED = "tracked"
#: the controller refused the goal at its goal response (passed to the client as a rejection)
DOWNSTREAM_REJECTED = "downstream_rejected"
#: no feedback and no result for gate.timeout (controller hung or gone): cancelled downstream
DOWNSTREAM_SILENT = "downstream_silent"
#: the gate shut down while the goal ran: cancelled downstream
CANCELLED_ON_SHUTDOWN = "cancelled_on_shutdown"
#: the gate cancelled downstream (client cancel, silence, shutdown) and the controller did not end
#: its goal within gate.timeout
CANCEL_UNCONFIRMED = "downstream_cancel_unconfirmed"
CONFIRMED = "confirmed"

#: ends after which nothing of the goal ran on the controller (never forwarded, or never accepted)
NOT_FORWARDED_ENDS = (GATE_BUSY, REFUSED_CLOSING, DOWNSTREAM_UNAVAILABLE, DOWNSTREAM_LATE, DOWNSTREAM_REJECTED)
#: ends of a forwarded goal the gate gave up on: the audit does not count it as executed
NOT_EXECUTED_ENDS = NOT_FORWARDED_ENDS + (DOWNSTREAM_SILENT, CANCEL_UNCONFIRMED)


def end_record(goal_id: str, event: str, status: int | None, result: Any = None, *,
               cancel: str | None = None, cause: str | None = None, elapsed_s: float | None = None) -> dict:
    """The end record of one goal: the client's terminal status (None: rejected at the goal
    response), the result's code and string, whether a downstream cancel was confirmed and, for
    ``downstream_cancel_unconfirmed``, the ``cause`` of the cancel (client cancel, silence, …)."""
    return {"version": 1, "event": event, "goal_id": goal_id, "status": status,
            "error_code": None if result is None else int(result.error_code),
            "error_string": "" if result is None else result.error_string,
            "cancel": cancel, "cause": cause, "elapsed_s": elapsed_s}


def tracked_record(goal_id: str, timing: dict, start: dict | None) -> dict:
    """The ``tracked`` record: the execution model's timing (``stamp_s``, ``receipt_s``) and the
    robot's state (None: none fresh) the tracker followed the forwarded goal from."""
    return {"version": 1, "event": TRACKED, "goal_id": goal_id, "timing": timing, "start": start}


def busy_text(pending: int) -> str:
    return (f"dyn_node gate: busy, {pending} goals waiting for their check (gate.max_pending); "
            "goal refused, send it again")


def closing_text() -> str:
    return "dyn_node gate: shutting down; goal refused"


def unavailable_text(action: str, timeout: float) -> str:
    return f"dyn_node gate: downstream action server {action} not available within {timeout:g} s (gate.timeout)"


def late_text(action: str, timeout: float) -> str:
    return (f"dyn_node gate: downstream action server {action} did not answer the goal request within "
            f"{timeout:g} s (gate.timeout); a late acceptance is cancelled")


def silent_text(action: str, timeout: float, confirmed: bool) -> str:
    tail = ("the controller confirmed the cancel" if confirmed else
            f"cancel sent, not confirmed within {timeout:g} s")
    return (f"dyn_node gate: downstream action server {action} went away during the goal (no feedback "
            f"and no result for {timeout:g} s); {tail}")


def unconfirmed_text(action: str, timeout: float, cause: str) -> str:
    return (f"dyn_node gate: cancel ({cause}) sent to {action}, not confirmed within {timeout:g} s "
            "(gate.timeout): the controller may still be moving")


def shutdown_text() -> str:
    return "dyn_node gate: shutting down; the goal was cancelled on the controller"
