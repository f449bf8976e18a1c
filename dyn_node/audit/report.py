"""report.html for an audit: one self-contained page (no network fetches) plus the plots as PNGs.

Verdict at the top; per-joint model torque and measured effort (both signed) against the ±limit
over time; utilisation heat map (joint × time); violations table; each trajectory (executed or a
question) with its time scale and margins; with task limits (#18) each place and kind against its
limit (``task_limits.png``); input-quality findings; re-check and latency. Plots are drawn with
Pillow (:mod:`report_plots`: the canvas and the effort plot) and embedded as base64 ``data:`` URIs;
the HTML pieces are :mod:`report_html`'s. matplotlib is not imported, since importing and laying
out a matplotlib figure took longer than auditing a minute of 1 kHz joint states.
"""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from dyn_node.audit.report_html import _e, _img, _num, _table, trajectories_section
from dyn_node.audit.report_plots import (_AXIS, _BLUE, _DARK_BLUE, _GREEN, _ORANGE, _RDYLGN_R,
                                         _RED, _S, _TEXT, _WHITE, _Axes, _blend, _Canvas, _centres,
                                         _fmt_tick, _font, _legend, _nice_ticks, _rgb, effort_plot)

PNG_FILES = ("effort.png", "utilisation.png", "trajectories.png")

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0;color:#1d2433;background:#f5f6f8}
main{max-width:1180px;margin:0 auto;padding:18px 24px 48px}
h1{font-size:22px;margin:6px 0 12px}
h2{font-size:17px;margin:26px 0 8px;border-bottom:1px solid #d5d9e0;padding-bottom:4px}
.verdict{border-radius:8px;padding:14px 18px;color:#fff;font-size:18px;font-weight:600}
.verdict small{display:block;font-weight:400;font-size:14px;margin-top:4px;opacity:.95}
.ok{background:#1e7d3a}.bad{background:#b3261e}.unusable{background:#5f6368}
.partial{background:#8a5a00;color:#fff;border-radius:6px;padding:8px 12px;margin-top:8px}
table{border-collapse:collapse;width:100%;font-size:13px;background:#fff;margin:6px 0}
th,td{border:1px solid #dde1e7;padding:4px 7px;text-align:left;vertical-align:top}
th{background:#eef1f5} td.num{text-align:right;font-variant-numeric:tabular-nums}
.facts td:first-child{width:210px;color:#555} img{max-width:100%;background:#fff;border:1px solid #dde1e7}
.muted{color:#666} ul{margin:4px 0 4px 18px;padding:0} code{font-size:12px}
.pill{display:inline-block;border-radius:10px;padding:0 8px;font-size:12px;color:#fff}
.pill.ok{background:#1e7d3a}.pill.bad{background:#b3261e}.pill.warn{background:#b26a00}
"""


def contact_plot(series, joint_names: Sequence[str], start_ns: int, contact_level: Sequence[float],
                 episodes: list[dict], units: Sequence[str] | None = None) -> bytes:
    """Per joint the external-torque estimate τ̂_ext (min..max per time bin) with the ±contact
    threshold, then the wrench estimate's force ‖F̂‖ (max per bin); contact episodes shaded
    (orange: contact, red: collision). ``series``: SeriesBins over nv + 1 columns."""
    nv = len(joint_names)
    W, row, top, left, right = 1100, 110, 62, 110, 16
    H = top + (nv + 1) * row + 40
    cv = _Canvas(W, H)
    cv.text(W / 2, 16, "External torque and contact force over input stamp time (shaded: contact episodes)", 11, "ma")
    _legend(cv, left, 44, [("τ̂_ext (min–max per bin)", _blend(_BLUE, 0.55), "area"),
                           ("±contact threshold", _RED, "line"), ("contact", _blend(_ORANGE, 0.25), "area"),
                           ("collision", _blend(_RED, 0.22), "area")])
    t = _centres(series, start_ns)
    n = series.n
    have = series.count[:n] > 0
    w_s = series.width * 1e-9
    xlim = (float(t[0] - w_s / 2), float(t[-1] + w_s / 2)) if n else (0.0, 1.0)
    xticks = _nice_ticks(*xlim, n=10)
    for j in range(nv + 1):
        lo = np.where(have, series.tau_min[:n, j], np.nan)
        hi = np.where(have, series.tau_max[:n, j], np.nan)
        level = float(contact_level[j]) if j < nv else math.nan
        vals = np.concatenate([lo[np.isfinite(lo)], hi[np.isfinite(hi)],
                               [level, -level] if math.isfinite(level) else []])
        big = float(np.max(np.abs(vals))) if vals.size else 1.0
        ylim = (-1.15 * big, 1.15 * big) if j < nv else (0.0, 1.15 * big)
        y_top = top + j * row
        ax = _Axes(cv, (left, y_top, W - right, y_top + row - 14), xlim, ylim)
        for e in episodes:
            end = e["end_s"] if e["end_s"] is not None else xlim[1]
            ax.vspan(e["start_s"], max(end, e["start_s"] + w_s),
                     _blend(_RED, 0.22) if e["level"] == "collision" else _blend(_ORANGE, 0.25))
        ax.grid(xticks, _nice_ticks(*ylim, n=4), xlabels=j == nv)
        if j < nv:
            ax.bars(t - w_s / 2, t + w_s / 2, lo, hi, _blend(_BLUE, 0.55))
            ax.line(t, (lo + hi) / 2, _DARK_BLUE, 0.7)
            if math.isfinite(level):
                ax.hline(level, _RED, 1.0, dash=True)
                ax.hline(-level, _RED, 1.0, dash=True)
        else:
            ax.steps(t, w_s, hi, _DARK_BLUE, 1.2)
        ax.frame()
        label = str(joint_names[j]) if j < nv else "‖F̂‖ at the frame"
        unit = (units[j] if units else "N·m") if j < nv else "N"
        cv.text(8, y_top + (row - 14) / 2 - 7, label, 8, "lm")
        cv.text(8, y_top + (row - 14) / 2 + 7, unit, 8, "lm")
    cv.text(left + (W - right - left) / 2, H - 14, "time since bag start (s)", 9, "ms")
    return cv.png()


def _colormap(u: np.ndarray, vmax: float) -> np.ndarray:
    """RGB (uint8) of utilisation values on the reversed RdYlGn scale 0..vmax; NaN: light grey."""
    stops = np.array([_rgb(c) for c in _RDYLGN_R], dtype=float)
    pos = np.linspace(0.0, 1.0, len(stops))
    x = np.clip(np.nan_to_num(u / vmax, nan=0.0), 0.0, 1.0)
    rgb = np.stack([np.interp(x, pos, stops[:, k]) for k in range(3)], axis=-1)
    rgb[np.isnan(u)] = (238, 240, 243)
    return np.round(rgb).astype(np.uint8)


def utilisation_plot(series, joint_names: Sequence[str], start_ns: int) -> bytes:
    """Heat map of the largest utilisation (|τ| / limit) per joint and time bin."""
    from PIL import Image

    n = series.n
    nv = len(joint_names)
    u = np.where(series.count[:n, None] > 0, series.util[:n], np.nan).T  # nv × n
    W, left, right, top, rowh = 1100, 120, 110, 34, 30
    H = top + nv * rowh + 48
    cv = _Canvas(W, H)
    cv.text((left + W - right) / 2, 10, "Effort utilisation, joint × time (max per bin)", 11, "ma")
    t = _centres(series, start_ns)
    w_s = series.width * 1e-9
    x0 = float(t[0] - w_s / 2) if n else 0.0
    x1 = float(t[-1] + w_s / 2) if n else 1.0
    vmax = max(1.2, float(np.nanmax(u)) if np.isfinite(u).any() else 1.2)
    ax = _Axes(cv, (left, top, W - right, top + nv * rowh), (x0, x1), (nv - 0.5, -0.5))
    if n:
        heat = Image.fromarray(_colormap(u, vmax), "RGB").resize(
            (int(ax.r - ax.l), int(ax.b - ax.t)), Image.Resampling.NEAREST)
        cv.img.paste(heat, (int(ax.l), int(ax.t)))
    ax.grid(_nice_ticks(x0, x1, n=10), [], ygrid=False, xgrid=False)
    for j, name in enumerate(joint_names):
        y = float(ax.py(j)) / _S
        cv.d.line([(ax.l - 3 * _S, y * _S), (ax.l, y * _S)], fill=_AXIS, width=_S)
        cv.text(left - 6, y, str(name), 8, "rm")
    ax.frame()
    cv.text(left + (W - right - left) / 2, H - 10, "time since bag start (s)", 9, "ms")
    # colour bar
    cl, cr = W - right + 14, W - right + 30
    bar = _Axes(cv, (cl, top, cr, top + nv * rowh), (0.0, 1.0), (0.0, vmax))
    ramp = _colormap(np.linspace(vmax, 0.0, int(bar.b - bar.t))[:, None].repeat(2, axis=1), vmax)
    cv.img.paste(Image.fromarray(ramp, "RGB").resize((int(bar.r - bar.l), int(bar.b - bar.t))),
                 (int(bar.l), int(bar.t)))
    bar.hline(1.0, (0, 0, 0), 1.2)
    ticks = _nice_ticks(0.0, vmax, n=5)
    for v in ticks:
        y = float(bar.py(v))
        cv.d.line([(bar.r, y), (bar.r + 3 * _S, y)], fill=_AXIS, width=_S)
        cv.text(cr + 5, y / _S, _fmt_tick(v, ticks), 7.5, "lm")
    bar.frame()
    lbl = "utilisation (1 = at the limit)"
    f = _font(8)
    tw = int(f.getlength(lbl)) + 4 * _S
    from PIL import ImageDraw

    tag = Image.new("RGB", (tw, int(14 * _S)), _WHITE)
    ImageDraw.Draw(tag).text((2 * _S, 7 * _S), lbl, fill=_TEXT, font=f, anchor="lm")
    tag = tag.rotate(90, expand=True)
    cv.img.paste(tag, (int((cr + 38) * _S), int(bar.t + (bar.b - bar.t - tag.size[1]) / 2)))
    return cv.png()


def trajectories_plot(trajs: list[dict]) -> bytes:
    """Time scale k per trajectory (k ≤ 1 feasible) and the payload margin (kg)."""
    W, H, top, bottom = 1100, 320, 34, 44
    cv = _Canvas(W, H)
    idx = [t["index"] for t in trajs]
    lo_i, hi_i = (min(idx) - 0.6, max(idx) + 0.6) if idx else (-0.6, 0.6)
    xticks = [float(v) for v in _nice_ticks(lo_i, hi_i, n=8) if float(v).is_integer()]
    colors = [_GREEN if t["feasible"] else _RED for t in trajs]
    ks = [_finite(t.get("time_scale")) for t in trajs]
    kplot = [k if k is not None else 0.0 for k in ks]
    pm = [_finite(t.get("payload_margin_kg")) for t in trajs]
    pplot = [p if p is not None else 0.0 for p in pm]
    panels = (("Time scale (≤ 1: feasible)", "time scale k", kplot, colors, 1.0, True),
              ("Payload margin", "kg", pplot, [_GREEN if p >= 0 else _RED for p in pplot], 0.0, False))
    half = W / 2
    for p_i, (title, ylabel, vals, cols, ref, dashed) in enumerate(panels):
        x_off = p_i * half
        lo = min([0.0, ref, *vals])
        hi = max([0.0, ref, *vals])
        pad = 0.08 * (hi - lo) or 0.5
        # room below zero for the −∞ marks of payload margins
        minus_inf = p_i == 1 and any(t.get("payload_margin_kg") == "-inf" for t in trajs)
        ylim = (lo - (pad if lo < 0 else 0.0) - (2.5 * pad if minus_inf else 0.0), hi + pad)
        ax = _Axes(cv, (x_off + 78, top, x_off + half - 18, H - bottom), (lo_i, hi_i), ylim)
        cv.text(x_off + (78 + half - 18) / 2, 10, title, 10, "ma")
        ax.grid(xticks, _nice_ticks(*ylim, n=5), xgrid=False)
        xs = np.asarray(idx, dtype=float)
        ax.bars(xs - 0.4, xs + 0.4, np.zeros(len(vals)), np.asarray(vals, dtype=float), cols)
        ax.hline(ref, (0, 0, 0), 1.0, dash=dashed)
        for i, t in zip(idx, trajs):
            x = float(ax.px(i)) / _S
            y0 = float(ax.py(0.0)) / _S
            if p_i == 0 and t.get("time_scale") == "inf":
                cv.text(x, y0 - 2, "∞", 12, "ms", _RED)
            elif p_i == 0 and not t["accepted"]:
                cv.text(x, y0 - 2, "rejected", 7, "ms", _RED)
            elif p_i == 1 and t.get("payload_margin_kg") == "-inf":
                cv.text(x, y0 + 2, "−∞", 12, "ma", _RED)
        ax.frame()
        cv.text(x_off + 8, (top + H - bottom) / 2, ylabel, 8, "lm")
        cv.text(x_off + (78 + half - 18) / 2, H - 10, "trajectory #", 9, "ms")
    return cv.png()


def _finite(x: Any) -> float | None:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) else None


#: How the task kinds' plot rows are titled (value against limit; unit from the entry).
_TASK_ROW_TITLE = {
    "frame_speed": "linear speed", "frame_angular_speed": "angular speed",
    "frame_acceleration": "linear acceleration",
    "transferred_energy": "transferred energy ½·m_u·v² (advisory)",
    "kinetic_energy": "kinetic energy ½ q̇ᵀMq̇", "base_force": "base force |f|",
    "base_moment": "base moment |m|", "tipping": "tipping gauge (1 = edge)",
    "grasp_slip": "grasp tangential force vs μ·F·faces"}


def task_rows(trajs: list[dict]) -> list[tuple[str, str]]:
    """The (place, kind) pairs the trajectories' ``per_frame`` tables hold, first seen first."""
    rows: dict[tuple[str, str], None] = {}
    for t in trajs:
        for place, kinds in (t.get("per_frame") or {}).items():
            for kind in kinds:
                rows[(place, kind)] = None
    return list(rows)


def _task_points(trajs: list[dict], place: str, kind: str, curves: bool) -> list[tuple[dict, np.ndarray, np.ndarray]]:
    """Per trajectory: (entry, x, value). ``curves``: the per-sample curve over the trajectory's
    own time (``per_frame_curves``); else its peak at its time in the bag."""
    out = []
    for t in trajs:
        e = (t.get("per_frame") or {}).get(place, {}).get(kind)
        if e is None:
            continue
        c = (t.get("per_frame_curves") or {}).get(place, {}).get(kind) if curves else None
        if c is not None:
            out.append((t, np.asarray(c["t_s"], dtype=float), np.asarray(
                [np.nan if v is None or isinstance(v, str) else v for v in c["value"]], dtype=float)))
        elif not curves:
            v = _finite(e.get("value"))
            out.append((t, np.array([float(t["time_s"] or 0.0)]), np.array([np.nan if v is None else v])))
    return out


def task_plot(trajs: list[dict]) -> bytes:
    """One row per task place and kind: the value against its limit (red). With per-sample
    curves (``per_frame_curves``), each trajectory's value over its own time; otherwise each
    trajectory's peak at its time in the bag (green feasible, red not)."""
    rows = task_rows(trajs)
    curves = any(t.get("per_frame_curves") for t in trajs)
    W, row, top, left, right = 1100, 130, 40, 150, 16
    H = top + len(rows) * row + 40
    cv = _Canvas(W, H)
    cv.text(W / 2, 14, ("Task limits: value over each trajectory's time" if curves else
                        "Task limits: each trajectory's peak over the bag's time") + " (red: limit)", 11, "ma")
    data = [_task_points(trajs, p, k, curves) for p, k in rows]
    xs = [x for d in data for _, x, _ in d if x.size]
    xlim = (float(min(x.min() for x in xs)), float(max(x.max() for x in xs))) if xs else (0.0, 1.0)
    pad_x = 0.03 * (xlim[1] - xlim[0]) or 0.5
    xlim = (xlim[0] - pad_x, xlim[1] + pad_x)
    xticks = _nice_ticks(*xlim, n=10)
    for r, ((place, kind), pts) in enumerate(zip(rows, data)):
        limits = {v for t, _, _ in pts if (v := _finite(t["per_frame"][place][kind].get("limit"))) is not None}
        vals = np.concatenate([v[np.isfinite(v)] for _, _, v in pts] + [np.array(sorted(limits))])
        hi = float(vals.max()) if vals.size else 1.0
        ylim = (0.0, 1.15 * hi if hi > 0 else 1.0)
        y_top = top + r * row
        ax = _Axes(cv, (left, y_top, W - right, y_top + row - 16), xlim, ylim)
        ax.grid(xticks, _nice_ticks(*ylim, n=4), xlabels=r == len(rows) - 1)
        for t, x, v in pts:
            color = _GREEN if t["feasible"] else _RED
            if curves:  # orange, not red, beside the red limit line
                ax.line(x, v, _GREEN if t["feasible"] else _ORANGE, 1.2)
            else:
                w = pad_x * 0.5
                ax.bars(x - w / 2, x + w / 2, np.zeros(1), v, color)
        for lim in sorted(limits):
            ax.hline(lim, _RED, 1.3, dash=True)
        ax.frame()
        unit = next((t["per_frame"][place][kind].get("unit", "") for t, _, _ in pts), "")
        cv.text(8, y_top + (row - 16) / 2 - 16, place, 8, "lm")
        cv.text(8, y_top + (row - 16) / 2, kind, 8, "lm")
        cv.text(8, y_top + (row - 16) / 2 + 16, unit or "1", 8, "lm")
        cv.text(left + 6, y_top + 8, _TASK_ROW_TITLE.get(kind, kind), 7.5, "lm")
    cv.text(left + (W - right - left) / 2, H - 14, "time from the trajectory's start (s)" if curves
            else "time since bag start (s)", 9, "ms")
    return cv.png()


def _head(record: dict) -> list[str]:
    """Page head, verdict banner, findings and the facts table."""
    v, inp, cfg = record["verdict"], record["inputs"], record["configuration"]
    cls = {"feasible": "ok", "violations": "bad"}.get(v["result"], "unusable")
    title = {"feasible": "FEASIBLE — no violations", "violations": "VIOLATIONS FOUND"}.get(
        v["result"], "UNUSABLE INPUT")
    p: list[str] = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width,initial-scale=1'>",
        f"<title>{_e(record['tool']['name'])}: {_e(Path(inp['bag']).name)}</title><style>{_CSS}</style></head><body><main>",
        f"<h1>{_e(record['tool']['name'])} report — <code>{_e(inp['bag'])}</code></h1>",
        f"<div class='verdict {cls}' id='verdict'>{_e(title)}<small>{_e(v['summary'])}</small></div>",
    ]
    if v.get("partial"):
        p.append("<div class='partial'>Partial audit: parts of the bag could not be read — see "
                 "<a href='#input-quality' style='color:#fff'>input quality</a>.</div>")
    if v.get("findings"):
        p.append("<ul>" + "".join(f"<li>{_e(f)}</li>" for f in v["findings"]) + "</ul>")
    m = cfg["model"]
    span = inp["time_span"]
    facts = [("Model", f"{_e(m['name'])} ({m.get('dof', len(m['joint_names']))} DoF), source {_e(m['source'])}"),
             ("URDF sha256", f"<code>{_e(m['urdf_sha256'])}</code>"),
             ("Time span", f"{span['duration_s']:.3f} s"),
             ("Messages", ", ".join(f"{_e(t)}: {n}" for t, n in inp["message_counts"].items())),
             ("Failure labels", _e(", ".join(record["failure_labels"]) or "none")),
             ("Overrides", _e(", ".join(f"{k}={v2}" for k, v2 in cfg["overrides"].items()) or "none")),
             ("Tool", f"{_e(record['tool']['name'])} {_e(record['tool']['version'])}; "
                      f"{_e(record['timestamps']['finished_utc'])}; audit took "
                      f"{record['timestamps']['duration_s']:.2f} s; seed: {_e(record['seed']['note'])}")]
    p.append("<table class='facts'>" + "".join(f"<tr><td>{k}</td><td>{val}</td></tr>" for k, val in facts)
             + "</table>")
    return p


def _effort_section(out: dict, images: dict[str, bytes]) -> list[str]:
    """Per-joint peak effort table, the effort plot and the utilisation heat map."""
    p = ["<h2 id='effort'>Effort vs limit</h2>"]
    pj = out["effort"]["per_joint"]
    p.append(_table(["joint", "peak utilisation", "from", "at t (s)", "model effort then",
                     "measured effort then", "limit", "unit"],
                    [[_e(r["joint"]), _num(None if r["peak_utilisation"] is None else
                                           r["peak_utilisation"] * 100, "{:.1f}%"),
                      _e(r.get("peak_source") or "—"),
                      _num(r["peak_time_s"], "{:.3f}"), _num(r["peak_effort"]),
                      _num(r.get("peak_measured_effort")),
                      _num(r["effort_limit"]), _e(r["unit"])] for r in pj], (1, 3, 4, 5, 6)))
    if "effort.png" in images:
        p.append(_img(images["effort.png"], "per-joint effort vs limit over time"))
    if "utilisation.png" in images:
        p.append("<h2 id='utilisation'>Utilisation heat map</h2>")
        p.append(_img(images["utilisation.png"], "utilisation heat map, joint by time"))
    if "effort.png" not in images:
        p.append("<p class='muted'>No accepted joint_states: no effort plots.</p>")
    return p


def _violations_section(out: dict) -> list[str]:
    """Live limit-violation episodes, or a line saying there were none."""
    p = ["<h2 id='violations'>Violations</h2>"]
    viol = out["violations"]
    if viol:
        p.append(_table(["joint", "kind", "from (s)", "to (s)", "peak at (s)", "peak value", "limit",
                         "peak / limit", "messages"],
                        [[_e(x["joint"]), _e(x["kind"]), _num(x["start_s"], "{:.3f}"),
                          _num(x["end_s"], "{:.3f}"), _num(x["peak_time_s"], "{:.3f}"),
                          _num(x["peak_value"]), _num(x["limit"]),
                          _num(None if x.get("peak_ratio") is None or isinstance(x["peak_ratio"], str)
                               else x["peak_ratio"] * 100, "{:.1f}%"), str(x["messages"])]
                         for x in viol], (2, 3, 4, 5, 6, 7, 8)))
        if out.get("violation_episodes_total", 0) > len(viol):
            p.append(f"<p class='muted'>{out['violation_episodes_total'] - len(viol)} more not listed.</p>")
    else:
        p.append("<p>No live limit violations (effort, position, velocity, deceleration).</p>")
    return p


def _task_section(out: dict, images: dict[str, bytes]) -> list[str]:
    """Per trajectory and task place (frame_limits link, robot_limits, base_limits, grasp): the
    peak of each configured kind against its limit, and their plot."""
    trajs = [t for t in out["trajectories"] if t.get("per_frame")]
    if not trajs:
        return []
    p = ["<h2 id='task-limits'>Task limits (force, energy, contact)</h2>",
         "<p class='muted'>Transferred energy ½·m_u·v² is an upper bound of ISO/TS 15066's "
         "(which uses the reduced mass of robot and body region): advisory, not a certification.</p>"]
    rows = []
    for t in trajs:
        for place, kinds in t["per_frame"].items():
            for kind, e in kinds.items():
                rows.append([str(t["index"]), _e(place), _e(kind), _num(e.get("value")),
                             _num(e.get("limit")), _e(e.get("unit", "")),
                             _num(None if _finite(e.get("ratio")) is None else e["ratio"] * 100, "{:.1f}%")
                             if e.get("ratio") != "inf" else "∞", _num(e.get("time_s"), "{:.3f}")])
    p.append(_table(["#", "place", "kind", "peak", "limit", "unit", "peak / limit", "at t (s)"],
                    rows, (3, 4, 6, 7)))
    if "task_limits.png" in images:
        p.append(_img(images["task_limits.png"], "task kinds against their limits"))
    return p


def _input_quality_section(iq: dict) -> list[str]:
    """Counts of input problems and a table of each unreadable range, stale period, gap, etc."""
    p = ["<h2 id='input-quality'>Input quality</h2>"]
    rows = []
    for u in iq["unreadable_ranges"]:
        rows.append(["unreadable", _num(u["start_s"], "{:.3f}"),
                     "end of recording" if u["end_s"] is None else _num(u["end_s"], "{:.3f}"), _e(u["reason"])])
    for g in iq["stale_periods"]:
        rows.append(["stale", _num(g["start_s"], "{:.3f}"), _num(g["end_s"], "{:.3f}"),
                     f"no joint_states for {g['duration_s']:.3f} s (> stale_timeout)"])
    for g in iq["gaps"]:
        rows.append(["gap", _num(g["start_s"], "{:.3f}"), _num(g["end_s"], "{:.3f}"),
                     f"{g['duration_s'] * 1000:.1f} ms without joint_states"])
    for x in iq["invalid_messages"]["examples"]:
        rows.append(["invalid", _num(x["time_s"], "{:.3f}"), "", _e(f"{x.get('code', '')}: {x['reason']}")])
    for x in iq["out_of_order"]["examples"]:
        rows.append(["out of order", _num(x["time_s"], "{:.3f}"), "", f"stamp {x.get('stamp_ns')} ns older "
                     "than the previous one"])
    summary = (f"{iq['invalid_messages']['count']} invalid, {iq['out_of_order']['count']} out of order, "
               f"{iq.get('gaps_total', len(iq['gaps']))} gaps, "
               f"{iq.get('stale_periods_total', len(iq['stale_periods']))} stale periods, "
               f"{len(iq['unreadable_ranges'])} unreadable ranges; chunks CRC-checked: "
               f"{iq.get('chunks_crc_checked', 0)}, damaged: {iq.get('chunks_damaged', 0)}")
    p.append(f"<p>{_e(summary)}</p>")
    if rows:
        p.append(_table(["finding", "from (s)", "to (s)", "detail"], rows, (1, 2)))
    return p


def _contact_section(out: dict, images: dict[str, bytes]) -> list[str]:
    """Contact episodes from the momentum observer (replayed), their plot and the resets."""
    c = out.get("contact")
    if not c:
        return []
    p = ["<h2 id='contact'>Contact and collision (replayed)</h2>",
         f"<p>Observer gain {_e(', '.join(f'{k:g}' for k in sorted(set(c['observer_gain_per_s']))))} 1/s "
         f"(1/K = {c['time_constant_s'] * 1e3:.1f} ms); wrench at {_e(c['frame'])}; "
         f"{c['estimated']} of {c['samples']} joint states estimated; {c['resets_total']} observer reset(s).</p>"]
    if "contact.png" in images:
        p.append(_img(images["contact.png"], "external torque and contact force"))
    eps = c["episodes"]
    if eps:
        p.append(_table(["level", "from (s)", "to (s)", "duration (s)", "peak force (N)", "joints"],
                        [[_e(e["level"]), _num(e["start_s"], "{:.3f}"), _num(e["end_s"], "{:.3f}"),
                          _num(e["duration_s"], "{:.3f}"), _num(e["peak_force_n"], "{:.3g}"),
                          _e(", ".join(f"{j['joint']} {j['peak_torque']:.3g} {j['unit']}" for j in e["joints"]))]
                         for e in eps], (1, 2, 3, 4)))
    else:
        p.append("<p>No contact episodes.</p>")
    if c["resets"]:
        p.append("<p class='muted'>Observer resets: " + _e("; ".join(
            f"{r['time_s']:.3f} s {r['code']}" for r in c["resets"][:20])) + "</p>")
    return p


def _recheck_section(out: dict) -> list[str]:
    """Re-check of the node's recorded outputs, then the latency table when there is one."""
    p = ["<h2 id='recheck'>Re-check of the node's outputs</h2>"]
    if out["recheck"]:
        p.append(_table(["topic", "matched", "unmatched", "not answered by the node",
                         "largest |difference|", "identical"],
                        [[_e(t), str(d["matched"]), str(d.get("unmatched", 0)),
                          str(d.get("unanswered", 0)),
                          _e(d["not_comparable"]) if "not_comparable" in d
                          else _num(d["max_abs_difference"], "{:.3g}"), _num(d.get("identical"))]
                         for t, d in out["recheck"].items()], (1, 2, 3, 4)))
    else:
        p.append("<p class='muted'>The bag holds no outputs of the node to re-check.</p>")
    if out["latency"]:
        p.append(_table(["latency", "count", "p50 (ms)", "p95 (ms)", "p99 (ms)", "max (ms)"],
                        [[_e(k), str(d["count"]), *(_num(None if d.get(q) is None else d[q] * 1e3, "{:.3f}")
                                                    for q in ("p50", "p95", "p99", "max"))]
                         for k, d in out["latency"].items()], (1, 2, 3, 4, 5)))
    return p


def _gate_section(out: dict) -> list[str]:
    """The FollowJointTrajectory gate's decisions, each decided again by the audit (re-check)."""
    g = out.get("gate") or out.get("questions", {}).get("gate")  # records before gate goals were executed
    if not g:
        return []
    p = ["<h2 id='gate'>Gate decisions</h2>",
         f"<p>{g['requests']} goals: {g.get('forwarded', 0)} forwarded, {g.get('rejected', 0)} rejected, "
         f"{g.get('retimed', 0)} retimed; {g['answered']} decided again (re-check: the decisions "
         f"topic), {g['not_replayed']} not replayed.</p>"]
    p.append(_table(["goal", "decision", "reason", "verdict"],
                    [[_e(d["goal_id"][:8]), _e(d["decision"]), _e(d["reason"]), _e(d["verdict"])]
                     for d in g["decisions"]]))
    return p


def _controller_section(out: dict) -> list[str]:
    """Replayed time in each controller state, and the closing note and tags."""
    cs = out["controller_states"]
    return ["<h2 id='controller'>Controller states (replayed)</h2>",
            "<p>" + (_e(", ".join(f"{k}: {t:.3f} s" for k, t in cs.get("replayed_time_in_state_s", {}).items()))
                     or "none") + "</p>",
            "<p class='muted'>Every number is defined in evidence.json → metric_definitions. Times are "
            "seconds since the bag's first message (log time).</p>",
            "</main></body></html>"]


def render_html(record: dict, images: dict[str, bytes]) -> str:
    """The self-contained report page: one line per element, sections in a fixed order."""
    out = record["outputs"]
    return "\n".join([*_head(record), *_effort_section(out, images), *_violations_section(out),
                      *trajectories_section(out, images), *_task_section(out, images),
                      *_input_quality_section(record["input_quality"]),
                      *_contact_section(out, images),
                      *_recheck_section(out), *_gate_section(out), *_controller_section(out)])


def write_report(record: dict, series, model, out_dir: str | Path, *, contact_series=None,
                 threads: int = 2) -> list[Path]:
    """Write report.html and the PNG plots into ``out_dir``; returns the paths written
    (``contact_series``: the contact replay's SeriesBins, for contact.png; ``threads``: plots
    drawn at once)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    start_ns = record["inputs"]["time_span"]["start_ns"] or 0
    names = record["configuration"]["model"]["joint_names"]
    plots: dict[str, Any] = {}  # file name → a call drawing it, in the page's order
    if series is not None and series.n:
        plots["effort.png"] = partial(effort_plot, series, names, start_ns, record["outputs"]["violations"])
        plots["utilisation.png"] = partial(utilisation_plot, series, names, start_ns)
    contact = record["outputs"].get("contact")
    if contact and contact_series is not None and contact_series.n:
        from dyn_node.core.robot.units import joint_units

        plots["contact.png"] = partial(contact_plot, contact_series, names, start_ns, contact["contact_level"],
                                       contact["episodes"], joint_units(model)["effort"])
    if record["outputs"]["trajectories"]:
        plots["trajectories.png"] = partial(trajectories_plot, record["outputs"]["trajectories"])
        if task_rows(record["outputs"]["trajectories"]):
            plots["task_limits.png"] = partial(task_plot, record["outputs"]["trajectories"])
    # Two at a time: Pillow lets go of the GIL while it shrinks and PNG-compresses an image,
    # so one plot's encoding runs beside the next one's drawing. Each image is the same bytes.
    if threads < 2:
        images: dict[str, bytes] = {name: draw() for name, draw in plots.items()}
    else:
        with ThreadPoolExecutor(max_workers=2, thread_name_prefix="dyn-audit-plot") as pool:
            jobs = {name: pool.submit(draw) for name, draw in plots.items()}
            images = {name: job.result() for name, job in jobs.items()}
    files = []
    for name, data in images.items():
        (out / name).write_bytes(data)
        files.append(out / name)
    page = out / "report.html"
    page.write_text(render_html(record, images), encoding="utf-8")
    files.append(page)
    return files
