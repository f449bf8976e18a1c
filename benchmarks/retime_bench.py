"""The "retime" section: dyn_node.retime against T*, the uniform stretch and TOPP-RA's own output.

A seeded panel of random paths per robot: 6 waypoints inside the position limits (10–90 % of each
range) whose spline keeps gravity under 80 % of the torque limits, timed as a planner would
(each step at 1.5× the slowest joint's velocity-limited time), positions only (the check's C²
spline). Limits: torque at 40 % of the URDF's; Panda: libfranka's acceleration and jerk maxima,
1000 N·m/s effort rate; UR5 (no published acceleration/jerk maxima): 8 rad/s², 4000 rad/s³,
1000 N·m/s. TOPP-RA's own pass (its joint velocity, acceleration and torque constraints, its
default spline output) is sampled at 100 Hz and checked by our check, side by side. The path
tolerance (1e-4 rad) is measured with SciPy (:func:`distance_to_path`), not by the retimer.

    python -m benchmarks.retime_bench --paths 10   # a small panel
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from typing import Any

import numpy as np

from .common import progress
from .retime_panel import PANDA_ACC, PANDA_JERK, panel, robot  # noqa: F401 - re-exported

def toppra_pass(dyn, tr, gridpoints: np.ndarray | None = None):
    """TOPP-RA's own time-optimal pass (velocity, acceleration, torque by Pinocchio's RNEA) and
    its output (its spline) sampled at 100 Hz as points with positions, velocities,
    accelerations."""
    import pinocchio as pin
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as tc

    from dyn_node.core.check.trajectory import Trajectory

    pm = dyn.pin_model
    data = pm.createData()
    lim = dyn.model.limits
    path = ta.SplineInterpolator(tr.times, tr.positions, bc_type="clamped")
    cons = [tc.JointVelocityConstraint(np.column_stack([-lim.velocity, lim.velocity])),
            tc.JointAccelerationConstraint(np.column_stack([-lim.acceleration, lim.acceleration])),
            tc.JointTorqueConstraint(lambda q, v, a: pin.rnea(pm, data, q, v, a),
                                     np.column_stack([-lim.effort, lim.effort]),
                                     np.zeros(len(lim.effort)))]
    inst = algo.TOPPRA(cons, path, gridpoints=gridpoints, solver_wrapper="seidel")
    jt = inst.compute_trajectory(0, 0)
    if jt is None:
        return None
    t = np.linspace(0.0, jt.duration, max(2, int(np.ceil(jt.duration * 100)) + 1))
    return Trajectory(times=t, positions=jt(t), velocities=jt(t, 1), accelerations=jt(t, 2))


def one(dyn, tr) -> dict:
    from dyn_node.core.check.feasibility import check_trajectory
    from dyn_node.retime import retime

    t0 = time.perf_counter()
    res = retime(dyn, tr)
    wall = time.perf_counter() - t0
    row = dict(feasible=res.feasible, method=res.method, duration_in=tr.duration,
               duration=res.duration_out, uniform=res.duration_uniform, lower_bound=res.lower_bound,
               gap=res.gap, rounds=res.rounds, wall_s=wall,
               deviation=distance_to_path(tr, res.trajectory) if res.feasible else float("nan"),
               recheck=bool(res.feasible and check_trajectory(dyn, res.trajectory).feasible))
    tp = toppra_pass(dyn, tr)
    if tp is not None:
        c = check_trajectory(dyn, tp)
        worst: dict[str, float] = {}
        for v in c.violations:
            worst[v.kind] = max(worst.get(v.kind, 0.0), abs(v.peak_value) / v.limit)
        row.update(toppra_duration=tp.duration, toppra_violations=worst)
    return row


def distance_to_path(tr, out) -> float:
    """Largest distance (∞-norm, rad) from 4000 samples of the controller's quintic through the
    output's points (SciPy's BPoly) to the input's curve (SciPy's clamped CubicSpline, the
    check's curve for positions only), the nearest of 200,001 curve samples refined locally."""
    from scipy.interpolate import BPoly, CubicSpline
    from scipy.spatial import cKDTree

    curve = CubicSpline(tr.times, tr.positions, bc_type="clamped")
    s = np.linspace(0.0, tr.duration, 200_001)
    tree = cKDTree(curve(s))
    quintic = BPoly.from_derivatives(out.times, np.stack([out.positions, out.velocities,
                                                          out.accelerations], axis=1))
    q = quintic(np.linspace(0.0, out.duration, 4000))
    _, near = tree.query(q, p=np.inf)
    worst = 0.0
    for qi, i in zip(q, near):
        fine = np.linspace(s[max(i - 1, 0)], s[min(i + 1, len(s) - 1)], 41)
        worst = max(worst, float(np.min(np.max(np.abs(curve(fine) - qi), axis=1))))
    return worst


def wall_time(dyn, repeats: int) -> dict:
    """Ours vs TOPP-RA's own pass on a 10 s 7-DoF path, both on a 1000-step grid, timed in
    turn (one of each per repeat, medians: a shared machine's load falls on all alike): the
    retime from scratch, the retime given the input's check (as dyn-check passes it), and the
    two exact checks inside a retime (the input's without the payload margin, the answer's in
    full), which are the retimer's share a faster check speeds up."""
    from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
    from dyn_node.core.check.trajectory import Trajectory
    from dyn_node.retime import retime

    tr = panel(dyn, 1, seed=99, n_waypoints=10)[0]
    tr = Trajectory(times=tr.times * (10.0 / tr.duration), positions=tr.positions)
    grid = np.linspace(0.0, tr.duration, 1001)
    res = retime(dyn, tr)
    given = check_trajectory(dyn, tr)
    plain = FeasibilityOptions(compute_payload_margin=False)
    subjects = {"retime_s": lambda: retime(dyn, tr),
                "retime_given_s": lambda: retime(dyn, tr, input_check=given),
                "toppra_s": lambda: toppra_pass(dyn, tr, grid),
                "input_check_s": lambda: check_trajectory(dyn, tr, plain),
                "answer_check_s": lambda: check_trajectory(dyn, res.trajectory)}
    times: dict[str, list[float]] = {k: [] for k in subjects}
    for rep in range(repeats + 1):            # the first round warms up, untimed
        for key, fn in subjects.items():
            t0 = time.perf_counter()
            fn()
            if rep:
                times[key].append(time.perf_counter() - t0)
    out = {k: statistics.median(v) for k, v in times.items()}
    checks = out["input_check_s"] + res.rounds * out["answer_check_s"]
    return dict(out, ratio=out["retime_s"] / out["toppra_s"],
                ratio_given=out["retime_given_s"] / out["toppra_s"], rounds=res.rounds,
                checks_s=checks, check_share=checks / out["retime_s"], repeats=repeats,
                load_average=os.getloadavg()[0])


def summarize(rows: list[dict]) -> dict:
    ok = [r for r in rows if r["feasible"]]
    gaps = [r["gap"] for r in ok]
    unif = [r["duration"] / r["uniform"] for r in ok if np.isfinite(r["uniform"])]
    kinds: dict[str, list[float]] = {}
    for r in rows:
        for k, v in r.get("toppra_violations", {}).items():
            kinds.setdefault(k, []).append(v)
    return dict(
        paths=len(rows), feasible=len(ok), rechecked=sum(r["recheck"] for r in ok),
        within_tolerance=sum(r["deviation"] <= 1e-4 for r in ok),
        deviation_max=max((r["deviation"] for r in ok), default=None),
        optimal=sum(r["method"] == "optimal" for r in ok),
        gap_median=statistics.median(gaps) if gaps else None,
        gap_p95=float(np.percentile(gaps, 95)) if gaps else None,
        vs_uniform_median=statistics.median(unif) if unif else None,
        vs_uniform_p95=float(np.percentile(unif, 95)) if unif else None,
        vs_uniform_max=max(unif, default=None),
        stretch_won=sum(r["method"] == "uniform" for r in ok),
        wall_median_s=statistics.median(r["wall_s"] for r in rows),
        wall_p95_s=float(np.percentile([r["wall_s"] for r in rows], 95)),
        wall_max_s=max(r["wall_s"] for r in rows),
        toppra_violating={k: dict(paths=len(v), median_ratio=statistics.median(v), max_ratio=max(v))
                          for k, v in sorted(kinds.items())})


def run(*, quick: bool = False, smoke: bool = False, paths: int | None = None) -> dict:
    n = paths or (3 if smoke else 15 if quick else 50)
    out: dict[str, Any] = {"paths_per_robot": n}
    for name, seed in (("panda", 1), ("ur5", 2)):
        dyn = robot(name)
        rows = []
        for i, tr in enumerate(panel(dyn, n, seed)):
            rows.append(one(dyn, tr))
            progress("retime", f"{name} {i + 1}/{n}: {rows[-1]['method']} gap {rows[-1]['gap']:.3f}")
        out[name] = dict(summary=summarize(rows), rows=rows)
    from .retime_panels import run as panels  # issue 39's waypoint and hard panels

    out["panels"] = panels(3 if smoke else 8 if quick else 20, progress)
    out["wall"] = wall_time(robot("panda"), 1 if smoke else 7)
    from .retime_start_bench import run as moving_start  # it builds on this module's panel

    progress("retime", f"moving start: {n} cases per robot")
    out["moving_start"] = moving_start(n)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paths", type=int, default=10)
    args = ap.parse_args(argv)
    res = run(paths=args.paths)
    print(json.dumps({k: (v["summary"] if isinstance(v, dict) and "summary" in v else v)
                      for k, v in res.items()}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


def render_md(res: dict) -> str:
    """The section's tables (docs/BENCHMARKS.md)."""
    def f(x, d=3):
        return "–" if x is None else f"{x:.{d}f}"

    lines = [f"Panel: {res['paths_per_robot']} random paths per robot (module docstring of "
             "benchmarks/retime_bench.py). Targets: all pass, gap median ≤ 1.05, p95 ≤ 1.15, "
             "÷ uniform median ≤ 0.90.", "",
             "| robot | pass the exact check | within 1e-4 (SciPy) | optimal (not the fallback) | "
             "T/T* median | T/T* p95 | T/uniform median | p95 | max | retime median (s) | p95 | "
             "max |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in ("panda", "ur5"):
        s = res[name]["summary"]
        lines.append(f"| {name} | {s['rechecked']}/{s['paths']} | {s['within_tolerance']} | "
                     f"{s['optimal']} | {f(s['gap_median'])} | {f(s['gap_p95'])} | "
                     f"{f(s['vs_uniform_median'])} | {f(s.get('vs_uniform_p95'))} | "
                     f"{f(s.get('vs_uniform_max'))} | {f(s['wall_median_s'], 2)} | "
                     f"{f(s.get('wall_p95_s'), 2)} | {f(s.get('wall_max_s'), 2)} |")
    if res.get("panels"):
        from .retime_panels import render_md as panels_md

        lines += ["", "Issue 39's panels (benchmarks/retime_panels.py; Panda, libfranka's "
                  "acceleration and jerk, effort at 40 %, effort rate 1,000 N·m/s; each answer "
                  "verified with SciPy and Pinocchio):", "", *panels_md(res["panels"])]
    lines += ["", "TOPP-RA's own output (velocity, acceleration, torque constraints; its spline "
              "sampled at 100 Hz) checked by our check: paths violating each kind, median and "
              "largest peak ÷ limit.", "", "| robot | kind | paths | median | max |",
              "|---|---|---|---|---|"]
    for name in ("panda", "ur5"):
        for kind, v in res[name]["summary"]["toppra_violating"].items():
            lines.append(f"| {name} | {kind} | {v['paths']} | {v['median_ratio']:.3f} | "
                         f"{v['max_ratio']:.3f} |")
    w = res["wall"]
    lines += ["", f"Wall time on a 10 s 7-DoF Panda path (medians of {w['repeats']}, each subject "
              f"in turn; 1-min load average {w['load_average']:.1f}): retime "
              f"{w['retime_s']:.3f} s vs TOPP-RA's own pass {w['toppra_s']:.3f} s (same path, "
              f"1000-step grid): {w['ratio']:.1f}× (target ≤ 3×, "
              f"{'met' if w['ratio'] <= 3 else 'not met'}); given the input's check (as "
              f"dyn-check passes it) {w['retime_given_s']:.3f} s, {w['ratio_given']:.1f}×. "
              f"{w['rounds']} exact check(s) of the answer; the exact checks (the input's "
              f"{w['input_check_s']:.3f} s, without the payload margin; the answer's "
              f"{w['answer_check_s']:.3f} s) are {100 * w['check_share']:.0f} % of the retime "
              "(docs/retime.md, Known limits)."]
    ms = res.get("moving_start")
    if ms:
        lines += ["", "From a moving start state (the panel's paths made quintic, the robot caught "
                  "partway through and the rest sent as a new goal; benchmarks/retime_start_bench.py):", "",
                  "| robot | cases | pass the exact check (with the start) | blocked | optimal | "
                  "T/uniform median | T/T* median | T/T* p95 |", "|---|---|---|---|---|---|---|---|"]
        for name in ("panda", "ur5"):
            m = ms[name]
            lines.append(f"| {name} | {m['cases']} | {m['pass_check']} | {m['blocked']} | {m['optimal']} | "
                         f"{f(m['vs_uniform_median'])} | {f(m['gap_median'])} | {f(m['gap_p95'])} |")
    return "\n".join(lines)
