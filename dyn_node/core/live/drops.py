"""Counting the joint_states samples lost between the publishers and the node (no rclpy).

Two sources, never added for the same loss: publication sequence numbers (exact, used while at
most one publisher is matched) and the middleware's message-lost event (otherwise; a lower bound
on Fast DDS). The rules for switching between them: docs/INTERNALS.md, "Counting dropped messages".
"""
from __future__ import annotations

SEQUENCE_NUMBERS = "sequence_numbers"
LOST_EVENTS = "middleware_lost_events"


class DropCounter:
    """Running count of lost samples; feed it every taken sample's sequence number, the
    matched-publisher count and the lost event's running total, in any order."""

    def __init__(self) -> None:
        self._before = 0            # counted in earlier periods
        self._gaps = 0              # sequence gaps in this period
        self._last_seq: int | None = None
        self._lost_total = 0        # the lost event's running total
        self._lost_base = 0         # ... when this period began
        self._single = True         # at most one publisher matched (assumed until told)
        self._settled = True        # ... and no sample of a departed publisher can be queued
        self._departed_ns = 0       # system time the count last dropped back to one
        self._numbered = False      # the rmw gives sequence numbers

    @property
    def method(self) -> str:
        """How the current period counts: SEQUENCE_NUMBERS or LOST_EVENTS."""
        return SEQUENCE_NUMBERS if self._single and self._settled and self._numbered \
            else LOST_EVENTS

    @property
    def total(self) -> int:
        """Samples lost since the node started, by both methods' periods together."""
        if self.method == SEQUENCE_NUMBERS:
            return self._before + self._gaps
        return self._before + max(0, self._lost_total - self._lost_base)

    def _new_period(self) -> None:
        self._before = self.total
        self._gaps = 0
        self._last_seq = None
        self._lost_base = self._lost_total

    def publishers(self, matched: int, now_ns: int) -> bool:
        """The number of matched publishers is ``matched``, as learned at system time
        ``now_ns``; True if the method changed."""
        single = matched <= 1
        if single == self._single:
            return False
        self._new_period()
        self._single = single
        # from one publisher to several, the method changes at once; back to one, at the first
        # sample received after now
        self._settled = not single
        self._departed_ns = now_ns
        return True

    def lost(self, running_total: int) -> None:
        """The middleware's message-lost event: its running total for the subscription."""
        self._lost_total = max(self._lost_total, int(running_total))

    def sequence(self, seq: int | None, received_ns: int | None = None) -> bool:
        """A taken sample's publication sequence number (None or 0: the rmw gave none) and the
        system time the middleware received it (None or 0: not given, taken as recent); True if
        the total or the method changed (a gap, or a new baseline)."""
        if not seq:
            return False
        if not self._numbered or (self._single and not self._settled
                                  and (not received_ns or received_ns > self._departed_ns)):
            self._new_period()
            self._numbered = self._settled = True
            self._last_seq = seq
            return True
        last, self._last_seq = self._last_seq, seq
        # a lower number is a restarted publisher (or another one): a new baseline, no gap
        if last is not None and seq > last + 1 and self.method == SEQUENCE_NUMBERS:
            self._gaps += seq - last - 1
            return True
        return False
