"""DropCounter: which source counts a loss, and that no loss is counted twice or across a change
of publishers."""
from __future__ import annotations

from dyn_node.core.live.drops import LOST_EVENTS, SEQUENCE_NUMBERS, DropCounter


def feed(c: DropCounter, seqs, received_ns: int | None = None) -> None:
    for s in seqs:
        c.sequence(s, received_ns)


def test_one_publisher_counts_sequence_gaps_exactly_and_ignores_the_lost_event():
    c = DropCounter()
    assert c.method == LOST_EVENTS           # nothing numbered seen yet
    assert c.sequence(5) is True             # the first numbered sample switches the method
    assert c.method == SEQUENCE_NUMBERS and c.total == 0   # nothing before it can be seen
    feed(c, [6, 7, 10, 11, 15])
    assert c.total == 2 + 3
    c.lost(5)                                # the same losses, as the middleware reports them
    assert c.total == 5
    assert c.sequence(16) is False and c.sequence(18) is True and c.total == 6


def test_a_restarted_publisher_is_a_new_baseline_not_a_gap():
    c = DropCounter()
    feed(c, [1, 2, 3, 900, 901])
    assert c.total == 896
    feed(c, [1, 2, 4])                       # the publisher restarted: numbering from 1 again
    assert c.total == 897


def test_several_publishers_count_lost_events_from_when_they_appeared():
    c = DropCounter()
    feed(c, [1, 2, 4], 100)
    c.lost(1)
    assert c.total == 1
    assert c.publishers(2, 200) is True and c.method == LOST_EVENTS
    feed(c, [5, 1, 6, 2, 9, 3], 300)         # two numberings interleaved: no gap is taken
    assert c.total == 1
    c.lost(4)                                # three more lost while both are matched
    assert c.total == 4
    assert c.publishers(3, 400) is False     # still several: the same period
    assert c.publishers(1, 500) is True
    # samples the departed publisher sent may still be queued: the lost events count until a
    # sample received after the departure was known
    assert c.method == LOST_EVENTS and c.total == 4
    feed(c, [10, 4, 11], 450)                # received before 500: leftovers among them
    c.lost(5)
    assert c.total == 5
    assert c.sequence(12, 501) is True and c.method == SEQUENCE_NUMBERS
    assert c.total == 5                      # what the earlier periods counted stays counted
    feed(c, [13], 502)                       # no gap from a leftover's number: 12 is the baseline
    assert c.total == 5
    feed(c, [15], 503)
    assert c.total == 6
    c.lost(9)                                # lost events while sequence counting: ignored
    assert c.total == 6


def test_without_sequence_numbers_the_lost_event_is_all_there_is():
    c = DropCounter()
    for s in (None, 0, None):
        assert c.sequence(s) is False
    c.lost(3)
    c.lost(2)                                # a running total never goes back
    assert c.method == LOST_EVENTS and c.total == 3
    c.publishers(0, 10)                      # no publisher matched counts as one
    assert c.method == LOST_EVENTS and c.total == 3
    c.sequence(40)                           # numbering starts late: the lost count is kept
    assert c.method == SEQUENCE_NUMBERS and c.total == 3
    feed(c, [41, 43])
    assert c.total == 4


def test_no_reception_time_settles_at_the_next_sample():
    c = DropCounter()
    feed(c, [1, 2])
    c.publishers(2, 100)
    c.publishers(1, 200)
    assert c.method == LOST_EVENTS
    assert c.sequence(7, None) is True and c.method == SEQUENCE_NUMBERS
    feed(c, [9])
    assert c.total == 1


def test_the_total_never_decreases_across_changes():
    c = DropCounter()
    totals = []
    steps = [lambda: c.sequence(1, 1), lambda: c.sequence(5, 2), lambda: c.lost(2),
             lambda: c.publishers(2, 3), lambda: c.lost(7), lambda: c.sequence(2, 4),
             lambda: c.publishers(1, 5), lambda: c.lost(8), lambda: c.sequence(3, 4),
             lambda: c.sequence(9, 6), lambda: c.sequence(12, 7),
             lambda: c.publishers(2, 8), lambda: c.lost(9), lambda: c.publishers(1, 9)]
    for step in steps:
        step()
        totals.append(c.total)
    assert totals == sorted(totals) and totals[-1] == 3 + 5 + 1 + 2 + 1
