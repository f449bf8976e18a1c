"""report.html for ``dyn-check --out``: the checked trajectory itself, not a bag's report.

Verdict and the time scale first; then, per joint, position, velocity, acceleration, jerk and
torque over the trajectory's time against their limits (±, or the position range), with the
violations shaded and their peaks marked; the per-joint peak ratios; the violations; and, with
task limits, each task kind's curve against its limit. Nothing about bags (no joint_states,
chunks or log times). Callers add sections of their own (e.g. the retiming) with ``sections``.
Plots use the audit report's Pillow canvas (no matplotlib import per file).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from dyn_node.audit.report_html import _e, _img, _num, _table
from dyn_node.audit.report_plots import _BLUE, _RED, _S, _Axes, _blend, _Canvas, _legend, _nice_ticks

#: (column title, limit kind drawn, violation kinds shaded in it)
QUANTITIES: tuple[tuple[str, str, tuple[str, ...]], ...] = (
    ("position", "position", ("position",)),
    ("velocity", "velocity", ("velocity",)),
    ("acceleration", "acceleration", ("acceleration", "deceleration")),
    ("jerk", "jerk", ("jerk",)),
    ("torque", "effort", ("effort", "effort_rate", "rms_effort", "power", "effort_speed")),
)
PLOT_POINTS = 1500  # samples over the whole trajectory (plus every waypoint)

#: a caller's section: (FileVerdict, Checker) → HTML pieces and the images they embed
Section = Callable[[Any, Any], tuple[list[str], dict[str, bytes]]]


@dataclass(frozen=True)
class Curves:
    """The trajectory as the check interpolates it, sampled for plotting: t (M,), and per
    quantity of :data:`QUANTITIES` an M×nv array."""

    t: np.ndarray
    values: dict[str, np.ndarray]


def sample_curves(traj: Any, result: Any, dynamics: Any, *, points: int = PLOT_POINTS) -> Curves:
    """q, q̇, q̈, q⃛ of the interpolation the check used, on a uniform grid plus the waypoints,
    and the torque there as the check computes it (:func:`on_demand.inverse_dynamics`)."""
    from dyn_node.core.check import on_demand
    from dyn_node.core.check.trajectory import interpolate

    ex = getattr(result, "execution", None)
    if ex is not None:      # what the check judged: the motion as the controller executes it
        pp, knots = ex.pp, ex.knots.times
    else:
        pp, knots = interpolate(traj, result.interpolation or None), traj.times
    t = np.union1d(np.linspace(float(knots[0]), float(knots[-1]), points), knots)
    q, v, a, j = pp.evaluate(t)
    tau = on_demand.inverse_dynamics(dynamics, q, v, a)
    return Curves(t, {"position": q, "velocity": v, "acceleration": a, "jerk": j, "torque": tau})


def _limits(model: Any, kind: str, j: int) -> tuple[float, float] | None:
    lim = model.limits
    if kind == "position":
        lo, hi = float(lim.position_lower[j]), float(lim.position_upper[j])
        return (lo, hi) if np.isfinite(lo) and np.isfinite(hi) and not lim.continuous[j] else None
    x = float(getattr(lim, kind)[j])
    return (-x, x) if np.isfinite(x) and x > 0 else None


def _over(t: np.ndarray, y: np.ndarray, lim: tuple[float, float] | None) -> list[tuple[float, float]]:
    """The time intervals where ``y`` is outside ``lim`` (each run of samples over it)."""
    if lim is None:
        return []
    out = np.r_[False, (y < lim[0]) | (y > lim[1]), False].astype(np.int8)
    edges = np.flatnonzero(np.diff(out))
    return [(float(t[a]), float(t[b - 1])) for a, b in zip(edges[0::2], edges[1::2])]


def trajectory_plot(curves: Curves, model: Any, violations: Sequence[Any], *, time_scale: float) -> bytes:
    """One row per joint, one column per quantity: the curve (blue), its limits (red dashed),
    the time it is over them shaded (for kinds with no line of their own, such as the effort rate,
    the violation's span) and each violation's peak marked × on the curve."""
    from dyn_node.core.robot.units import joint_units

    names, units = list(model.joint_names), joint_units(model)
    nv, ncol = len(names), len(QUANTITIES)
    W, row, top, left, right, gap = 1180, 118, 76, 112, 10, 46
    H = top + nv * row + 42
    cv = _Canvas(W, H)
    k_text = (f"time scale k = {time_scale:.3g}" + (" (feasible)" if time_scale <= 1 else
              f": must run {time_scale:.3g}× slower") if np.isfinite(time_scale)
              else "no time scale makes it feasible")
    cv.text(W / 2, 6, f"The trajectory over its time, against the limits ({k_text})", 11, "ma")
    _legend(cv, left, 40, [("value", _BLUE, "line"), ("limit", _RED, "line"),
                           ("over a limit (× its peak)", _blend(_RED, 0.2), "area")])
    t = curves.t
    xlim = (float(t[0]), float(t[-1]) if t[-1] > t[0] else float(t[0]) + 1.0)
    xticks = _nice_ticks(*xlim, n=4)
    col_w = (W - left - right - gap * (ncol - 1)) / ncol
    for c, (title, kind, shaded) in enumerate(QUANTITIES):
        x0 = left + c * (col_w + gap)
        cv.text(x0 + col_w / 2, top - 12, title, 9, "ms")
        for j in range(nv):
            y = curves.values[title][:, j]
            lim = _limits(model, kind, j)
            vals = np.concatenate([y[np.isfinite(y)], np.asarray(lim or (), dtype=float)])
            lo, hi = (float(vals.min()), float(vals.max())) if vals.size else (-1.0, 1.0)
            pad = 0.08 * (hi - lo) or max(abs(hi), 1.0) * 0.5  # a constant: a readable band round it
            ylim = (lo - pad, hi + pad)
            y_top = top + j * row
            ax = _Axes(cv, (x0, y_top, x0 + col_w, y_top + row - 18), xlim, ylim)
            for a, b in _over(t, y, lim):
                ax.vspan(a, b, _blend(_RED, 0.2))
            for v in violations:  # kinds with no line here (effort rate, power, ...): their span
                if v.joint == names[j] and v.kind in shaded and v.kind != kind:
                    ax.vspan(v.first_time_s, max(v.first_time_s + v.duration_s, v.peak_time_s), _blend(_RED, 0.2))
            ax.grid(xticks, _nice_ticks(*ylim, n=4), xlabels=j == nv - 1)
            for bound in lim or ():
                ax.hline(bound, _RED, 1.2, dash=True)
            ax.line(t, y, _BLUE, 1.2)
            for v in violations:  # the peak, marked on the curve (a violation's value may be |x|)
                if v.joint == names[j] and v.kind in shaded:
                    at = float(np.interp(v.peak_time_s, t, y))
                    cv.text(float(ax.px(v.peak_time_s)) / _S, float(ax.py(at)) / _S, "×", 10, "mm", _RED)
            ax.frame()
            if c == 0:
                cv.text(6, y_top + (row - 18) / 2, names[j], 7.5, "lm")
            cv.text(x0 + 3, y_top + 6, units[kind][j], 6.5, "lm")
    cv.text(left + (W - left - right) / 2, H - 12, "time from the trajectory's start (s)", 9, "ms")
    return cv.png()


def _head(record: dict) -> list[str]:
    from dyn_node.audit.report import _CSS

    v, m = record["verdict"], record["configuration"]["model"]
    path = record["inputs"]["files"][0]
    t = (record["outputs"]["trajectories"] or [{}])[0]
    word = {"feasible": ("ok", "FEASIBLE"), "violations": ("bad", "INFEASIBLE")}.get(v["result"], ("unusable", "NOT CHECKED"))
    if v["result"] == "violations" and not t.get("accepted"):
        word = ("bad", "REJECTED")  # refused before any check: nothing was evaluated
    p = ["<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
         f"<title>dyn-check: {_e(Path(path).name)}</title><style>{_CSS}</style></head><body><main>",
         f"<h1>dyn-check report — <code>{_e(path)}</code></h1>",
         f"<div class='verdict {word[0]}' id='verdict'>{word[1]}<small>{_e(v['summary'])}</small></div>"]
    if v.get("findings"):
        p.append("<ul>" + "".join(f"<li>{_e(f)}</li>" for f in v["findings"]) + "</ul>")
    facts = [("Model", f"{_e(m['name'])} ({m['dof']} DoF); URDF sha256 <code>{_e(m['urdf_sha256'])}</code>"),
             ("File", f"{_e(path)} ({_e(record['inputs'].get('format') or '?')}), {_num(t.get('n_points'))} "
                      f"points, {_num(t.get('duration_s'), '{:.4g}')} s, {_e(t.get('interpolation') or '—')} interpolation"),
             ("Time scale k", _num(t.get("time_scale")) + " (the duration × k is the fastest feasible timing)"),
             ("Largest ratio", f"{_e(t.get('worst_joint') or '—')} {_e(t.get('worst_constraint') or '')} "
                               f"{_num(t.get('worst_ratio'))}"),
             ("Overrides", _e(", ".join(f"{k}={x}" for k, x in record["configuration"]["overrides"].items()) or "none")),
             ("Tool", f"dyn-check {_e(record['tool']['version'])}; {_e(record['timestamps']['finished_utc'])}")]
    return p + ["<table class='facts'>" + "".join(f"<tr><td>{k}</td><td>{x}</td></tr>" for k, x in facts) + "</table>"]


def _peaks_table(result: Any, model: Any) -> str:
    kinds = [k for k in ("position", "velocity", "acceleration", "deceleration", "jerk", "effort",
                         "effort_rate", "rms_effort", "power", "effort_speed")
             if any((result.per_joint[n].get(k) or {}).get("ratio") is not None for n in model.joint_names)]

    def cell(n: str, k: str) -> str:
        r = (result.per_joint[n].get(k) or {}).get("ratio")
        return "—" if r is None else (f"<b style='color:#b3261e'>{r * 100:.1f}%</b>" if r > 1 else f"{r * 100:.1f}%")
    return _table(["joint", *kinds], [[_e(n), *(cell(n, k) for k in kinds)] for n in model.joint_names],
                  range(1, len(kinds) + 1))


def _violations_table(result: Any) -> str:
    if not result.violations:
        return "<p>No limit exceeded.</p>"
    return _table(["place", "kind", "first over at (s)", "peak at (s)", "peak value", "limit", "unit", "over for (s)"],
                  [[_e(v.joint), _e(v.kind), _num(v.first_time_s, "{:.4f}"), _num(v.peak_time_s, "{:.4f}"),
                    _num(v.peak_value), _num(v.limit), _e(v.unit), _num(v.duration_s, "{:.4f}")]
                   for v in result.violations], (2, 3, 4, 5, 7))


def render_check_html(record: dict, verdict: Any, checker: Any, *,
                      sections: Sequence[Section] = ()) -> tuple[str, dict[str, bytes]]:
    """The page and the images it embeds (also written beside it)."""
    from dyn_node.audit.report import task_plot, task_rows

    parts, images = _head(record), {}
    o = verdict.outcome
    if o is not None and o.result is not None and o.trajectory is not None:
        r = o.result
        images["trajectory.png"] = trajectory_plot(sample_curves(o.trajectory, r, checker.dynamics),
                                                   checker.model, r.violations, time_scale=r.time_scale)
        parts += ["<h2 id='trajectory'>The trajectory against the limits</h2>",
                  _img(images["trajectory.png"], "position, velocity, acceleration, jerk and torque per joint over time"),
                  "<h2 id='peaks'>Peak / limit per joint</h2>", _peaks_table(r, checker.model),
                  "<h2 id='violations'>Violations</h2>", _violations_table(r)]
        entries = record["outputs"]["trajectories"]
        if task_rows(entries):
            images["task_limits.png"] = task_plot(entries)
            parts += ["<h2 id='task-limits'>Task limits</h2>",
                      _img(images["task_limits.png"], "task kinds over the trajectory's time against their limits")]
    else:
        parts.append("<p>The file could not be checked (see the verdict above): nothing to plot.</p>")
    for section in sections:
        html_parts, imgs = section(verdict, checker)
        parts += html_parts
        images.update(imgs)
    parts += ["<p class='muted'>Times are seconds from the trajectory's first point. Every number is "
              "defined in evidence.json → metric_definitions.</p>", "</main></body></html>"]
    return "\n".join(parts), images


def write_check_report(record: dict, verdict: Any, checker: Any, out_dir: Path, *,
                       sections: Sequence[Section] = ()) -> list[Path]:
    """Write report.html and its PNGs into ``out_dir``; returns the paths written."""
    page, images = render_check_html(record, verdict, checker, sections=sections)
    files = []
    for name, data in images.items():
        (out_dir / name).write_bytes(data)
        files.append(out_dir / name)
    (out_dir / "report.html").write_text(page, encoding="utf-8")
    return files + [out_dir / "report.html"]
