"""fleet.html: its figures' axes fit the data (tested on the matplotlib figure objects), its
headline says what was lost, and executed trajectories and questions are counted apart."""
from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone

import pytest

pytest.importorskip("matplotlib")
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.dates as mdates  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402

from dyn_node.fleet import figures  # noqa: E402
from dyn_node.fleet.report import render_fleet_html  # noqa: E402

T0 = 1_764_770_000_000_000_000  # 2025-12-03, ns


def _row(k: int, start_s: float, *, cat="ok", worst=0.5, partial=False, bad=0, questions=0, no=0) -> dict:
    return {"path": f"/bags/b{k}", "report": f"bags/b{k}/report.html", "robot": "panda",
            "exit_category": cat, "exit_code": {"ok": 0, "violations": 1, "partial": 3}.get(cat, 2),
            "verdict": "error" if cat == "unusable" else ("violations" if cat == "violations" else "feasible"),
            "recording_start_ns": None if cat == "unusable" else T0 + int(start_s * 1e9),
            "worst_ratio": worst, "worst_joint": "panda_joint2", "worst_constraint": "effort",
            "worst_source": "live", "worst_time_scale": math.nan, "live_episodes_total": 0,
            "trajectories": 4, "trajectories_bad": bad, "questions": questions, "questions_infeasible": no,
            "partial": partial, "resumed": False, "messages": 1000, "error": "", "error_code": "",
            **{k: 0 for k in ("invalid_messages", "out_of_order_messages", "zero_stamp_messages", "gaps",
                              "stale_periods", "unreadable_ranges", "chunks_damaged")}}


def _joints(peaks: dict[str, list[float]]) -> list[dict]:
    return [{"robot": "panda", "joint": j, "joint_index": i, "live_effort_peak": p,
             "traj_effort_peak": math.nan} for i, (j, ps) in enumerate(peaks.items()) for p in ps]


def _visible(ticks, lo: float, hi: float) -> list[float]:
    return [t for t in ticks if lo - 1e-9 * abs(hi - lo) <= t <= hi + 1e-9 * abs(hi - lo)]


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


# copies of one bag (one start time: the 2025-2029 axis), four bags in a minute, a week
@pytest.mark.parametrize("starts_s", [[0, 0, 0, 0], [0, 15, 30, 58], [0, 3600, 86400 * 3, 86400 * 7]])
def test_time_axis_spans_the_recordings_not_years(starts_s):
    rows = [_row(k, s, worst=0.4 + 0.5 * k) for k, s in enumerate(starts_s)]
    fig = figures.timeline_figure(rows)
    ax = fig.axes[1]
    fig.canvas.draw()
    lo, hi = (mdates.num2date(x) for x in ax.get_xlim())
    first = datetime.fromtimestamp(T0 * 1e-9, tz=timezone.utc)
    t0, t1 = first + timedelta(seconds=min(starts_s)), first + timedelta(seconds=max(starts_s))
    pad = max((t1 - t0) * 0.05, timedelta(seconds=30))
    assert lo <= t0 and hi >= t1                      # every bag inside
    assert abs((hi - lo) - (t1 - t0 + 2 * pad)) < timedelta(milliseconds=1)  # and no more
    ticks = _visible(ax.get_xticks(), *ax.get_xlim())
    assert 3 <= len(ticks) <= 10
    labels = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
    assert labels and not any(str(y) in "".join(labels) for y in (2024, 2026, 2027, 2028, 2029))


@pytest.mark.parametrize("peaks, log", [
    ({"j1": [0.02, 0.05], "j2": [0.3, 0.6], "j3": [1.4, 25.0]}, True),   # 2 % .. 2500 %
    ({"j1": [0.40, 0.55], "j2": [0.62, 0.8], "j3": [0.9, 1.05]}, False),  # 40 % .. 105 %
])
def test_utilisation_axis_has_ticks_over_the_data(peaks, log):
    fig = figures.utilisation_figure(_joints(peaks))
    ax = fig.axes[0]
    fig.canvas.draw()
    lo, hi = ax.get_ylim()
    data = [100 * p for ps in peaks.values() for p in ps]
    assert lo <= min(data) and hi >= max(data) and lo <= 100 <= hi
    ticks = _visible(ax.get_yticks(), lo, hi)
    assert ax.get_yscale() == ("log" if log else "linear")
    # enough labelled ticks to read a value off: below, between and above the data
    assert len(ticks) >= 4, ticks
    assert min(ticks) <= min(data) and max(ticks) >= 100
    labels = [t.get_text() for t in ax.get_yticklabels() if t.get_text()]
    assert len(labels) >= 4
    if log:  # within a decade of the data, never the empty decades symlog put at 0 and 10²
        assert hi / max(data) <= 12 and min(data) / lo <= 12


def test_headline_says_partial_bags_and_counts_executed_and_questions_apart():
    rows = [_row(0, 0, cat="violations", worst=2.0, bad=1, questions=5, no=2),
            _row(1, 10, cat="violations", worst=1.5, partial=True, questions=0),
            _row(2, 20), _row(3, 30)]
    page = render_fleet_html(rows, _joints({"j1": [0.5]}), exit_code=1)
    assert "<h1>dyn-fleet: VIOLATIONS (1 partial: data lost)</h1>" in page
    assert "Executed trajectories: 1 of 16 infeasible or rejected" in page
    assert "questions (not executed): 2 of 5 answered infeasible or rejected" in page
    assert "<td>2 of 5</td>" in page  # the worst bag's questions answered no, in its own column
