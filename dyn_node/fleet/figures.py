"""fleet.html's figures as matplotlib Figure objects (so their axes can be tested), with axes
that fit the data: a linear value axis unless the values span more than a decade (then log,
with ticks at 1-2-5 of every decade in range), and a time axis that spans the recordings
(padded a little), labelled in the units that fit its span, never the years around it.
"""
from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone
from typing import Any, Sequence

CATEGORY_COLOURS = {"ok": "#2e7d32", "violations": "#c62828", "partial": "#ef6c00",
                    "unusable": "#6d4c41", "timeout": "#6a1b9a", "crashed": "#000000"}
LOG_ABOVE = 10.0  # a value axis goes logarithmic when max/min of the positive values exceeds this


def value_axis(ax: Any, values: Sequence[float], *, reference: float, label: str) -> None:
    """Scale, limits and ticks of a value axis holding ``values`` and the ``reference`` line
    (the limit): linear from 0 when they fit in a decade, else log over their decades."""
    from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter

    pos = [v for v in values if math.isfinite(v) and v > 0] + [reference]
    lo, hi = min(pos), max(pos)
    ax.set_ylabel(label)
    if hi / lo <= LOG_ABOVE:
        ax.set_ylim(0, hi * 1.1)
        ax.yaxis.set_major_locator(MaxNLocator(nbins=6))
        return
    ax.set_yscale("log")
    bottom, top = math.floor(math.log10(lo / 1.2)), math.ceil(math.log10(hi * 1.2))  # off the frame
    ax.set_ylim(10 ** bottom, 10 ** top)
    # 1-2-5 in each decade while that stays readable, else the decades alone
    subs = (1.0, 2.0, 5.0) if top - bottom <= 3 else (1.0,)
    ax.yaxis.set_major_locator(LogLocator(base=10, subs=subs, numticks=30))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _p: f"{v:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def time_axis(ax: Any, starts: Sequence[datetime]) -> tuple[datetime, datetime]:
    """Limits of a time axis over ``starts`` (padded by 5 % of their span, at least 30 s) with
    date ticks that fit that span; returns the limits."""
    import matplotlib.dates as mdates

    t0, t1 = min(starts), max(starts)
    pad = max((t1 - t0) * 0.05, timedelta(seconds=30))
    lo, hi = t0 - pad, t1 + pad
    ax.set_xlim(lo, hi)
    loc = mdates.AutoDateLocator(minticks=3, maxticks=8, tz=timezone.utc)
    ax.xaxis.set_major_locator(loc)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(loc, tz=timezone.utc))
    return lo, hi


def utilisation_figure(joints: list[dict]) -> Any:
    """Per robot, the distribution across bags of each joint's peak live effort utilisation and
    its peak executed-trajectory effort ratio (box plots, % of the limit; 100 % is the limit).
    None when no bag was audited."""
    import matplotlib.pyplot as plt

    robots = sorted({j["robot"] for j in joints})
    if not robots:
        return None
    fig, axes = plt.subplots(len(robots), 1, figsize=(9, 2.8 * len(robots)), squeeze=False)
    for ax, robot in zip(axes[:, 0], robots):
        rows = [j for j in joints if j["robot"] == robot]
        names = sorted({j["joint"] for j in rows}, key=lambda n: next(
            j["joint_index"] for j in rows if j["joint"] == n))
        shown: list[float] = []
        for offset, key, colour in ((-0.18, "live_effort_peak", "#1565c0"),
                                    (0.18, "traj_effort_peak", "#ef6c00")):
            data = [[100 * j[key] for j in rows if j["joint"] == n and math.isfinite(j[key])]
                    for n in names]
            pos = [i + offset for i, d in enumerate(data) if d]
            if pos:
                bp = ax.boxplot([d for d in data if d], positions=pos, widths=0.3, patch_artist=True,
                                manage_ticks=False, medianprops={"color": "black"},
                                flierprops={"marker": "o", "markersize": 4, "markerfacecolor": colour,
                                            "markeredgecolor": colour})
                for b in bp["boxes"]:
                    b.set_facecolor(colour)
                    b.set_alpha(0.5)
                shown += [v for d in data for v in d]
        ax.axhline(100, color="#c62828", lw=1, ls="--")
        ax.set_xticks(range(len(names)), names, rotation=20, fontsize=7)
        ax.set_xlim(-0.6, len(names) - 0.4)
        value_axis(ax, shown, reference=100.0, label="% of effort limit")
        ax.grid(axis="y", which="major", color="#dddddd", lw=0.6)
        ax.set_title(f"{robot}: peak effort utilisation per joint across bags "
                     "(blue: live, orange: executed trajectories; dashed: the limit)", fontsize=9)
    fig.tight_layout()
    return fig


def timeline_figure(rows: list[dict]) -> Any:
    """Violations (live episodes + bad executed trajectories) and the worst ratio of each bag
    against its recording start time (UTC). None when no bag has a recording time."""
    import matplotlib.pyplot as plt

    pts = [r for r in rows if r["recording_start_ns"] is not None]
    if not pts:
        return None
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 4.8), sharex=True)
    for cat, colour in CATEGORY_COLOURS.items():
        sel = [r for r in pts if r["exit_category"] == cat]
        if not sel:
            continue
        t = [_utc(r) for r in sel]
        a1.scatter(t, [r["live_episodes_total"] + r["trajectories_bad"] for r in sel], s=14,
                   color=colour, label=cat)
        a2.scatter(t, [r["worst_ratio"] for r in sel], s=14, color=colour)
    counts = [r["live_episodes_total"] + r["trajectories_bad"] for r in pts]
    a1.set_ylim(-0.5, max(counts) * 1.15 + 1)
    a1.yaxis.get_major_locator().set_params(integer=True)
    a1.set_ylabel("violations")
    a1.legend(fontsize=7, ncol=6, loc="upper left")
    a1.set_title("violations per bag over recording time (live episodes + bad executed "
                 "trajectories)", fontsize=9)
    a2.axhline(1.0, color="#c62828", lw=1, ls="--")
    value_axis(a2, [r["worst_ratio"] for r in pts], reference=1.0, label="worst value / limit")
    time_axis(a2, [_utc(r) for r in pts])
    a2.set_xlabel("recording start (UTC)")
    for ax in (a1, a2):
        ax.grid(color="#eeeeee", lw=0.6)
    fig.tight_layout()
    return fig


def _utc(row: dict) -> datetime:
    return datetime.fromtimestamp(row["recording_start_ns"] * 1e-9, tz=timezone.utc)
