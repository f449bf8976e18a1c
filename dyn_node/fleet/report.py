"""DIR/fleet.html: one self-contained page answering for the whole fleet.

The fleet verdict, the worst bags (linked to their own report.html), per-joint utilisation
distributions across the fleet, violations over recording time (is it getting worse) and the
input-quality problems. Figures are drawn once per fleet with matplotlib (Agg) and embedded as
base64 PNGs, so the page needs no other file; the HTML helpers (escaping, tables, images) are
report.py's.
matplotlib is fine once per fleet run (report.py keeps Pillow: a 0.64 s import per dyn-audit, LIBRARIES.md).
"""
from __future__ import annotations

import io
import math
import time
from pathlib import Path
from typing import Any

from dyn_node.audit.exit_codes import MEANINGS
from dyn_node.audit.report import _e, _img, _num, _table  # one set of HTML helpers for both pages

WORST_BAGS = 25
CATEGORY_COLOURS = {"ok": "#2e7d32", "violations": "#c62828", "partial": "#ef6c00",
                    "unusable": "#6d4c41", "timeout": "#6a1b9a", "crashed": "#000000"}
QUALITY_KEYS = ("invalid_messages", "out_of_order_messages", "zero_stamp_messages", "gaps",
                "stale_periods", "unreadable_ranges", "chunks_damaged")


def _f(x: Any) -> str:
    """A row's number; NaN (the tables' "none") as the evidence's null is shown."""
    return _num(None if isinstance(x, float) and math.isnan(x) else x, "{:.3g}")


def _png(fig, alt: str) -> str:
    """The matplotlib figure as an embedded PNG (closed: the page is the only place it lives)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=96, bbox_inches="tight")
    plt.close(fig)
    return _img(buf.getvalue(), alt)


def utilisation_figure(joints: list[dict]) -> str:
    """Per robot, the distribution across bags of each joint's peak live effort utilisation and
    its peak trajectory effort ratio (box plots; 100 % is the limit)."""
    import matplotlib.pyplot as plt

    robots = sorted({j["robot"] for j in joints})
    if not robots:
        return "<p>No bag was audited: no utilisation to show.</p>"
    fig, axes = plt.subplots(len(robots), 1, figsize=(9, 2.6 * len(robots)), squeeze=False)
    for ax, robot in zip(axes[:, 0], robots):
        rows = [j for j in joints if j["robot"] == robot]
        names = sorted({j["joint"] for j in rows}, key=lambda n: next(
            j["joint_index"] for j in rows if j["joint"] == n))
        for offset, key, colour in ((-0.18, "live_effort_peak", "#1565c0"),
                                    (0.18, "traj_effort_peak", "#ef6c00")):
            data = [[100 * j[key] for j in rows if j["joint"] == n and not math.isnan(j[key])]
                    for n in names]
            pos = [i + offset for i, d in enumerate(data) if d]
            if pos:
                bp = ax.boxplot([d for d in data if d], positions=pos, widths=0.3, patch_artist=True,
                                manage_ticks=False)
                for b in bp["boxes"]:
                    b.set_facecolor(colour)
                    b.set_alpha(0.5)
        ax.axhline(100, color="#c62828", lw=1, ls="--")
        ax.set_xticks(range(len(names)), names, rotation=20, fontsize=7)
        ax.set_ylabel("% of effort limit")
        ax.set_title(f"{robot}: peak effort utilisation per joint across bags "
                     "(blue: live, orange: trajectories)", fontsize=9)
        ax.set_yscale("symlog", linthresh=100)
        ax.set_ylim(bottom=0)  # utilisations are magnitudes
    fig.tight_layout()
    return _png(fig, "peak effort utilisation per joint across bags")


def timeline_figure(rows: list[dict]) -> str:
    """Violations (live episodes + bad trajectories) and the worst ratio of each bag against
    its recording start time."""
    import matplotlib.pyplot as plt
    from datetime import datetime, timezone

    pts = [r for r in rows if r["recording_start_ns"] is not None]
    if not pts:
        return "<p>No bag with a recording time.</p>"
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 4.6), sharex=True)
    for cat, colour in CATEGORY_COLOURS.items():
        sel = [r for r in pts if r["exit_category"] == cat]
        if not sel:
            continue
        t = [datetime.fromtimestamp(r["recording_start_ns"] * 1e-9, tz=timezone.utc) for r in sel]
        a1.scatter(t, [r["live_episodes_total"] + r["trajectories_bad"] for r in sel], s=14,
                   color=colour, label=cat)
        a2.scatter(t, [r["worst_ratio"] for r in sel], s=14, color=colour)
    a1.set_ylabel("violations")
    a1.legend(fontsize=7, ncol=6, loc="upper left")
    a1.set_title("violations per bag over recording time (live episodes + bad trajectories)", fontsize=9)
    a2.axhline(1.0, color="#c62828", lw=1, ls="--")
    a2.set_ylabel("worst value / limit")
    a2.set_yscale("log")
    a2.set_xlabel("recording start (UTC)")
    fig.autofmt_xdate()
    fig.tight_layout()
    return _png(fig, "violations and worst ratio per bag over recording time")


def _link(r: dict) -> str:
    name = _e(Path(r["path"]).name)
    return f'<a href="{_e(r["report"])}">{name}</a>' if r.get("report") else name


def render_fleet_html(rows: list[dict], joints: list[dict], *, exit_code: int) -> str:
    n = len(rows)
    cats = {c: sum(r["exit_category"] == c for r in rows) for c in CATEGORY_COLOURS}
    verdict = {0: "FEASIBLE", 1: "VIOLATIONS", 2: "UNUSABLE", 3: "PARTIAL"}[exit_code]
    audited = [r for r in rows if r["verdict"] != "error"]
    worst = sorted((r for r in audited if not math.isnan(r["worst_ratio"])),
                   key=lambda r: -r["worst_ratio"])[:WORST_BAGS]
    failed = [r for r in rows if r["verdict"] == "error"]
    quality = [r for r in audited if any(r[k] for k in QUALITY_KEYS)]
    summary = ", ".join(f'<span style="color:{CATEGORY_COLOURS[c]}">{v} {c}</span>'
                        for c, v in cats.items() if v)
    parts = [
        f"<h1>dyn-fleet: {verdict}</h1>",
        f"<p><b>{n} bags</b>: {summary}. Exit code {exit_code} ({_e(MEANINGS[exit_code])}). "
        f"{sum(bool(r['resumed']) for r in rows)} unchanged since their evidence (not re-audited). "
        f"Messages: {sum(r['messages'] for r in rows):,}. Written {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}.</p>",
        "<h2>Worst bags</h2>",
        _table(["bag", "robot", "result", "worst joint", "constraint", "value / limit", "source",
                "time scale", "live episodes", "bad trajectories"],
               [[_link(r), _e(r["robot"]), _e(r["exit_category"]), _e(r["worst_joint"]),
                 _e(r["worst_constraint"]), _f(r["worst_ratio"]), _e(r["worst_source"]),
                 _f(r["worst_time_scale"]), str(r["live_episodes_total"]), str(r["trajectories_bad"])]
                for r in worst]) if worst else "<p>No bag has a limit ratio.</p>",
        "<h2>Per-joint utilisation across the fleet</h2>", utilisation_figure(joints),
        "<h2>Violations over recording time</h2>", timeline_figure(rows),
        "<h2>Bags not audited</h2>",
        _table(["bag", "category", "error code", "error"],
               [[_e(r["path"]), _e(r["exit_category"]), _e(r["error_code"]), _e(r["error"])]
                for r in failed]) if failed else "<p>Every bag was audited.</p>",
        "<h2>Input-quality problems</h2>",
        _table(["bag", *QUALITY_KEYS], [[_link(r), *(str(r[k]) for k in QUALITY_KEYS)]
                                        for r in quality])
        if quality else "<p>No invalid, out-of-order, missing or damaged input in the audited bags.</p>",
    ]
    style = ("body{font-family:sans-serif;margin:1.5em;max-width:72em}table{border-collapse:collapse;"
             "font-size:0.85em}td,th{border:1px solid #ccc;padding:2px 6px;text-align:left}"
             "th{background:#f0f0f0}img{max-width:100%}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>dyn-fleet</title>"
            f"<style>{style}</style></head><body>{''.join(parts)}</body></html>")


def write_fleet_report(rows: list[dict], joints: list[dict], out_dir: Path, *, exit_code: int) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    path = Path(out_dir) / "fleet.html"
    tmp = path.with_suffix(".html.tmp")
    tmp.write_text(render_fleet_html(rows, joints, exit_code=exit_code), encoding="utf-8")
    tmp.replace(path)
    return path
