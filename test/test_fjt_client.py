"""dyn_node.ros.fjt_client.steady: when a gate's per-sample output shows it keeps up with
joint_states (a client that just started a gate sends goals from then on)."""
from __future__ import annotations

import numpy as np

from dyn_node.ros.fjt_client import STEADY_GAP_S, STEADY_S, steady


def _stream(seconds: float, period: float = 0.01, gap_at: float | None = None, gap: float = 0.0) -> list[float]:
    t = list(np.arange(0.0, seconds, period))
    if gap_at is not None:
        t = [x for x in t if x < gap_at] + [x + gap for x in t if x >= gap_at]
    return t


def test_a_stream_covering_the_window_without_gaps_is_steady():
    r = _stream(1.5)
    assert steady(r, r[-1] + 0.005)
    # the defaults: one second, gaps under the gate's 0.1 s state age
    assert STEADY_S == 1.0 and 0.0 < STEADY_GAP_S < 0.1


def test_nothing_or_too_short_a_stream_is_not_steady():
    assert not steady([], 10.0)
    r = _stream(0.5)
    assert not steady(r, r[-1] + 0.005)          # half the window covered
    assert steady(r, r[-1] + 0.005, window=0.4)  # ... which is enough for a shorter window


def test_a_gap_inside_the_window_or_at_its_end_is_not_steady():
    r = _stream(1.5, gap_at=1.0, gap=0.2)        # 210 ms without an output, 0.5 s ago
    now = r[-1] + 0.005
    assert not steady(r, now)
    assert steady(r, now, window=0.4)            # a window after the gap
    r2 = _stream(3.0, gap_at=0.5, gap=0.2)       # the same gap, over a second before now
    assert steady(r2, r2[-1] + 0.005)
    assert not steady(r2, r2[-1] + STEADY_GAP_S * 1.5)  # the stream stopped


def test_the_gap_bound():
    r = _stream(1.5, period=STEADY_GAP_S * 0.99)  # outputs just under max_gap apart
    assert steady(r, r[-1])
    r = _stream(1.5, period=STEADY_GAP_S * 1.01)
    assert not steady(r, r[-1])
