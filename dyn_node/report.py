"""report.html for an audit: one self-contained page (no network fetches) plus the plots as PNGs.

Verdict at the top; per-joint effort vs limit over time with the ±limit envelope; utilisation heat
map (joint × time); violations table; each trajectory's time scale and margins; input-quality
findings; re-check and latency. Plots are drawn with matplotlib's Agg backend through the
object-oriented API (no pyplot global state) and embedded as base64 ``data:`` URIs.
"""
from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

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


def _e(x: Any) -> str:
    return html.escape("" if x is None else str(x))


def _num(x: Any, fmt: str = "{:.4g}") -> str:
    if x is None:
        return "—"
    if isinstance(x, str):
        return "∞" if x == "inf" else ("−∞" if x == "-inf" else _e(x))
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, (int, float)):
        return fmt.format(x) if isinstance(x, float) else str(x)
    return _e(x)


def _png(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def _centres(series, start_ns: int) -> np.ndarray:
    n = series.n
    return ((series.t0 - start_ns) + (np.arange(n) + 0.5) * series.width) * 1e-9


def effort_plot(series, joint_names: Sequence[str], start_ns: int, violations: list[dict]) -> bytes:
    """Per joint: the band of RNEA torque (min..max per time bin) and the ±limit envelope."""
    nv = len(joint_names)
    fig = Figure(figsize=(11, 1.55 * nv + 0.8))
    axes = fig.subplots(nv, 1, sharex=True, squeeze=False)[:, 0]
    t = _centres(series, start_ns)
    n = series.n
    for j, ax in enumerate(axes):
        lo, hi, lim = series.tau_min[:n, j], series.tau_max[:n, j], series.limit[:n, j]
        have = series.count[:n] > 0
        lo = np.where(have, lo, np.nan)
        hi = np.where(have, hi, np.nan)
        ax.fill_between(t, lo, hi, color="#2f6db5", alpha=0.55, linewidth=0, step="mid",
                        label="model torque (min–max per bin)")
        ax.plot(t, (lo + hi) / 2, color="#1b3f6b", linewidth=0.6)
        meas = series.measured[:n, j]
        if np.isfinite(meas).any():
            ax.plot(t, meas, color="#e08a00", linewidth=0.9, drawstyle="steps-mid",
                    label="|measured effort| (max per bin)")
        finite = have & np.isfinite(lim)
        if finite.any():
            env = np.where(finite, lim, np.nan)
            ax.plot(t, env, color="#b3261e", linewidth=1.2, drawstyle="steps-mid", label="±effort limit")
            ax.plot(t, -env, color="#b3261e", linewidth=1.2, drawstyle="steps-mid")
            top = np.nanmax(np.abs(np.concatenate([lo[have], hi[have], env[finite],
                                                   meas[np.isfinite(meas)]])))
            ax.set_ylim(-1.15 * top, 1.15 * top)
        for v in violations:
            if v["joint"] == joint_names[j] and v["kind"] == "effort":
                ax.axvspan(v["start_s"], max(v["end_s"], v["start_s"] + series.width * 1e-9),
                           color="#b3261e", alpha=0.18)
        ax.set_ylabel(f"{joint_names[j]}\nN·m", fontsize=8)
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.3)
    handles = {}
    for ax in axes:
        for h, lbl in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lbl, h)
    axes[0].legend(handles.values(), handles.keys(), loc="upper right", fontsize=8, ncol=3)
    axes[-1].set_xlabel("time since bag start (s)")
    fig.suptitle("Effort vs limit over time (shaded red: effort violations)", fontsize=11)
    fig.tight_layout()
    return _png(fig)


def utilisation_plot(series, joint_names: Sequence[str], start_ns: int) -> bytes:
    """Heat map of the largest utilisation (|τ| / limit) per joint and time bin."""
    n = series.n
    u = np.where(series.count[:n, None] > 0, series.util[:n], np.nan).T
    fig = Figure(figsize=(11, 0.42 * len(joint_names) + 1.6))
    ax = fig.subplots()
    t = _centres(series, start_ns)
    x0 = t[0] - series.width * 0.5e-9 if n else 0.0
    x1 = t[-1] + series.width * 0.5e-9 if n else 1.0
    vmax = max(1.2, float(np.nanmax(u)) if np.isfinite(u).any() else 1.2)
    im = ax.imshow(u, aspect="auto", interpolation="nearest", cmap="RdYlGn_r", vmin=0.0, vmax=vmax,
                   extent=(x0, x1, len(joint_names) - 0.5, -0.5))
    ax.set_yticks(range(len(joint_names)))
    ax.set_yticklabels(joint_names, fontsize=8)
    ax.set_xlabel("time since bag start (s)")
    cb = fig.colorbar(im, ax=ax, pad=0.01)
    cb.set_label("utilisation (1 = at the limit)", fontsize=8)
    cb.ax.axhline(1.0, color="k", linewidth=1.0)
    ax.set_title("Effort utilisation, joint × time (max per bin)", fontsize=11)
    fig.tight_layout()
    return _png(fig)


def trajectories_plot(trajs: list[dict]) -> bytes:
    """Time scale k per trajectory (k ≤ 1 feasible) and the payload margin."""
    fig = Figure(figsize=(11, 3.2))
    ax1, ax2 = fig.subplots(1, 2)
    idx = [t["index"] for t in trajs]
    ks = [_finite(t.get("time_scale")) for t in trajs]
    colors = ["#1e7d3a" if t["feasible"] else "#b3261e" for t in trajs]
    kplot = [k if k is not None else 0.0 for k in ks]
    ax1.bar(idx, kplot, color=colors)
    for i, t in zip(idx, trajs):
        if t.get("time_scale") == "inf":
            ax1.annotate("∞", (i, 0), ha="center", va="bottom", color="#b3261e", fontsize=12)
        elif not t["accepted"]:
            ax1.annotate("rejected", (i, 0), ha="center", va="bottom", color="#b3261e", fontsize=7,
                         rotation=90)
    ax1.axhline(1.0, color="k", linewidth=1, linestyle="--")
    ax1.set_xlabel("trajectory #")
    ax1.set_ylabel("time scale k")
    ax1.set_title("Time scale (≤ 1: feasible)", fontsize=10)
    pm = [_finite(t.get("payload_margin_kg")) for t in trajs]
    ax2.bar(idx, [p if p is not None else 0.0 for p in pm],
            color=["#1e7d3a" if (p or 0) >= 0 else "#b3261e" for p in pm])
    for i, t in zip(idx, trajs):
        if t.get("payload_margin_kg") == "-inf":
            ax2.annotate("−∞", (i, 0), ha="center", va="top", color="#b3261e", fontsize=12)
    ax2.axhline(0.0, color="k", linewidth=1)
    ax2.set_xlabel("trajectory #")
    ax2.set_ylabel("kg")
    ax2.set_title("Payload margin", fontsize=10)
    from matplotlib.ticker import MaxNLocator

    for ax in (ax1, ax2):
        ax.grid(alpha=0.3, axis="y")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    fig.tight_layout()
    return _png(fig)


def _finite(x: Any) -> float | None:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) else None


def _img(data: bytes, alt: str) -> str:
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{base64.b64encode(data).decode()}">'


def _table(head: Sequence[str], rows: list[Sequence[str]], num_cols: Sequence[int] = ()) -> str:
    out = ["<table><thead><tr>", *(f"<th>{_e(h)}</th>" for h in head), "</tr></thead><tbody>"]
    for r in rows:
        out.append("<tr>" + "".join(f'<td class="num">{c}</td>' if i in num_cols else f"<td>{c}</td>"
                                    for i, c in enumerate(r)) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def render_html(record: dict, images: dict[str, bytes]) -> str:
    v, inp, cfg, out, iq = (record["verdict"], record["inputs"], record["configuration"],
                            record["outputs"], record["input_quality"])
    cls = {"feasible": "ok", "violations": "bad"}.get(v["result"], "unusable")
    title = {"feasible": "FEASIBLE — no violations", "violations": "VIOLATIONS FOUND"}.get(
        v["result"], "UNUSABLE INPUT")
    p: list[str] = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width,initial-scale=1'>",
        f"<title>dyn-audit: {_e(Path(inp['bag']).name)}</title><style>{_CSS}</style></head><body><main>",
        f"<h1>dyn-audit report — <code>{_e(inp['bag'])}</code></h1>",
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

    p.append("<h2 id='effort'>Effort vs limit</h2>")
    pj = out["effort"]["per_joint"]
    p.append(_table(["joint", "peak utilisation", "at t (s)", "torque at peak (N·m)", "limit (N·m)"],
                    [[_e(r["joint"]), _num(None if r["peak_utilisation"] is None else
                                           r["peak_utilisation"] * 100, "{:.1f}%"),
                      _num(r["peak_time_s"], "{:.3f}"), _num(r["peak_torque_nm"]),
                      _num(r["effort_limit_nm"])] for r in pj], (1, 2, 3, 4)))
    if "effort.png" in images:
        p.append(_img(images["effort.png"], "per-joint effort vs limit over time"))
    if "utilisation.png" in images:
        p.append("<h2 id='utilisation'>Utilisation heat map</h2>")
        p.append(_img(images["utilisation.png"], "utilisation heat map, joint by time"))
    if "effort.png" not in images:
        p.append("<p class='muted'>No accepted joint_states: no effort plots.</p>")

    p.append("<h2 id='violations'>Violations</h2>")
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
        p.append("<p>No live limit violations (effort, position, velocity).</p>")

    p.append("<h2 id='trajectories'>Trajectories</h2>")
    trajs = out["trajectories"]
    if trajs:
        rows = []
        for t in trajs:
            pill = ("<span class='pill ok'>feasible</span>" if t["feasible"] else
                    "<span class='pill bad'>" + ("infeasible" if t["accepted"] else "rejected") + "</span>")
            rows.append([str(t["index"]), _num(t["time_s"], "{:.3f}"), pill, _num(t.get("time_scale")),
                         _num(t.get("payload_margin_kg")), _e(t.get("worst_joint")),
                         _e(t.get("worst_constraint")), _num(t.get("worst_ratio")),
                         _num(t.get("n_points")), _num(t.get("duration_s")), _e(t.get("message"))])
        p.append(_table(["#", "at t (s)", "verdict", "time scale k", "payload margin (kg)", "worst joint",
                         "constraint", "worst ratio", "points", "duration (s)", "message"], rows,
                        (1, 3, 4, 7, 8, 9)))
        if "trajectories.png" in images:
            p.append(_img(images["trajectories.png"], "time scale and payload margin per trajectory"))
    else:
        p.append("<p>No trajectories in the bag.</p>")

    p.append("<h2 id='input-quality'>Input quality</h2>")
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

    p.append("<h2 id='recheck'>Re-check of the node's outputs</h2>")
    if out["recheck"]:
        p.append(_table(["topic", "matched", "unmatched", "largest |difference|", "identical"],
                        [[_e(t), str(d["matched"]), str(d.get("unmatched", 0)),
                          _num(d["max_abs_difference"], "{:.3g}"), _num(d.get("identical"))]
                         for t, d in out["recheck"].items()], (1, 2, 3)))
    else:
        p.append("<p class='muted'>The bag holds no outputs of the node to re-check.</p>")
    if out["latency"]:
        p.append(_table(["latency", "count", "p50 (ms)", "p95 (ms)", "p99 (ms)", "max (ms)"],
                        [[_e(k), str(d["count"]), *(_num(None if d.get(q) is None else d[q] * 1e3, "{:.3f}")
                                                    for q in ("p50", "p95", "p99", "max"))]
                         for k, d in out["latency"].items()], (1, 2, 3, 4, 5)))
    cs = out["controller_states"]
    p.append("<h2 id='controller'>Controller states (replayed)</h2>")
    p.append("<p>" + (_e(", ".join(f"{k}: {t:.3f} s" for k, t in cs.get("replayed_time_in_state_s", {}).items()))
                      or "none") + "</p>")
    p.append("<p class='muted'>Every number is defined in evidence.json → metric_definitions. Times are "
             "seconds since the bag's first message (log time).</p>")
    p.append("</main></body></html>")
    return "\n".join(p)


def write_report(record: dict, series, model, out_dir: str | Path) -> list[Path]:
    """Write report.html and the PNG plots into ``out_dir``; returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images: dict[str, bytes] = {}
    start_ns = record["inputs"]["time_span"]["start_ns"] or 0
    names = record["configuration"]["model"]["joint_names"]
    if series is not None and series.n:
        images["effort.png"] = effort_plot(series, names, start_ns, record["outputs"]["violations"])
        images["utilisation.png"] = utilisation_plot(series, names, start_ns)
    if record["outputs"]["trajectories"]:
        images["trajectories.png"] = trajectories_plot(record["outputs"]["trajectories"])
    files = []
    for name, data in images.items():
        (out / name).write_bytes(data)
        files.append(out / name)
    page = out / "report.html"
    page.write_text(render_html(record, images), encoding="utf-8")
    files.append(page)
    return files
