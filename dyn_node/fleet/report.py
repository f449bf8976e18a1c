"""DIR/fleet.html: one self-contained page answering for the whole fleet.

The fleet verdict, the worst bags (linked to their own report.html), per-joint utilisation
distributions across the fleet, violations over recording time (is it getting worse) and the
input-quality problems. Figures are drawn once per fleet with matplotlib (Agg) and embedded as
base64 PNGs, so the page needs no other file; the HTML helpers (escaping, tables, images) are
audit.report_html's, the figures fleet.figures'.
matplotlib is fine once per fleet run (report.py keeps Pillow: a 0.64 s import per dyn-audit, LIBRARIES.md).
"""
from __future__ import annotations

import io
import math
import time
from pathlib import Path
from typing import Any

from dyn_node.audit.exit_codes import MEANINGS
from dyn_node.audit.report_html import _e, _img, _num, _table  # one set of HTML helpers for all pages
from dyn_node.fleet.figures import CATEGORY_COLOURS, timeline_figure, utilisation_figure
from dyn_node.fleet.rows import partial_note

WORST_BAGS = 25
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


def _figure(fig, alt: str, empty: str) -> str:
    return _png(fig, alt) if fig is not None else f"<p>{_e(empty)}</p>"


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
        f"<h1>dyn-fleet: {verdict}{_e(partial_note(rows))}</h1>",
        f"<p><b>{n} bags</b>: {summary}. Executed trajectories: "
        f"{sum(r['trajectories_bad'] for r in rows)} of {sum(r['trajectories'] for r in rows)} "
        f"infeasible or rejected; questions (not executed): {sum(r['questions_infeasible'] for r in rows)} "
        f"of {sum(r['questions'] for r in rows)} answered infeasible or rejected. Exit code {exit_code} ({_e(MEANINGS[exit_code])}). "
        f"{sum(bool(r['resumed']) for r in rows)} unchanged since their evidence (not re-audited). "
        f"Messages: {sum(r['messages'] for r in rows):,}. Written {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}.</p>",
        "<h2>Worst bags</h2>",
        _table(["bag", "robot", "result", "worst joint", "constraint", "value / limit", "source",
                "time scale", "live episodes", "bad executed trajectories", "questions answered no"],
               [[_link(r), _e(r["robot"]), _e(r["exit_category"]), _e(r["worst_joint"]),
                 _e(r["worst_constraint"]), _f(r["worst_ratio"]), _e(r["worst_source"]),
                 _f(r["worst_time_scale"]), str(r["live_episodes_total"]), str(r["trajectories_bad"]),
                 f'{r["questions_infeasible"]} of {r["questions"]}']
                for r in worst]) if worst else "<p>No bag has a limit ratio.</p>",
        "<h2>Per-joint utilisation across the fleet</h2>",
        _figure(utilisation_figure(joints), "peak effort utilisation per joint across bags",
                "No bag was audited: no utilisation to show."),
        "<h2>Violations over recording time</h2>",
        _figure(timeline_figure(rows), "violations and worst ratio per bag over recording time",
                "No bag with a recording time."),
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
