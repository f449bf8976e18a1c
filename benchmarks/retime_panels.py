"""The retime section's waypoint and hard panels (issue 39), each answer verified independently
(benchmarks/retime_verify.py: SciPy's polynomials through the returned points sampled inside
every segment, Pinocchio's rnea).

- waypoint: 5–8 timed waypoints passed at speed (Catmull-Rom velocities, cubic points), each
  step 1.2× the slowest joint's velocity-limited time; libfranka's acceleration and jerk
  limits, effort at 40 % of the URDF's, effort rate 1,000 N·m/s (seeds 100 + i).
- hard: a waypoint passed at 0.3× and at 1e-3× the Catmull-Rom speed (seeds 200 + i), a
  250-waypoint path (a walk of steps up to 0.3 rad; both in the middle 40 % of each range,
  where the cubic stays inside the limits), tiny moves of 1e-6 and 1e-9 rad, and untimed waypoints that turn back.

    python -m benchmarks.retime_panels --paths 10
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from .retime_verify import panda, passes, verify, waypoint_path


def waypoint_panel(dyn, n: int) -> list[tuple[str, object]]:
    out = []
    for i in range(n):
        rng = np.random.default_rng(100 + i)
        out.append((f"waypoints seed {100 + i}", waypoint_path(dyn, rng, int(rng.integers(5, 9)))))
    return out


def hard_panel(dyn, n: int) -> list[tuple[str, object]]:
    from dyn_node.core.check.trajectory import Trajectory

    out = []
    for i in range(max(1, n // 4)):
        for share in (0.3, 1e-3):
            tr = waypoint_path(dyn, np.random.default_rng(200 + i), 6, spread=0.4)
            v = tr.velocities.copy()
            v[3] *= share
            out.append((f"near stop {share:g}× seed {200 + i}",
                        Trajectory(times=tr.times, positions=tr.positions, velocities=v)))
    out.append(("250 waypoints seed 300", waypoint_path(dyn, np.random.default_rng(300), 250,
                                                        spread=0.4, step=0.3)))
    q = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.6, 0.8])
    z = np.zeros((2, 7))
    for step in (1e-6, 1e-9):
        out.append((f"tiny {step:g} rad", Trajectory(times=np.array([0.0, 1.0]),
                                                     positions=np.stack([q, q + step]),
                                                     velocities=z, accelerations=z)))
    b = q + np.array([0.8, 0.3, -0.4, 0.5, 0.6, 0.3, -0.9])
    out.append(("turn back (untimed)", Trajectory(times=np.zeros(3),
                                                  positions=np.stack([q, b, q + 1e-3]))))
    return out


def one(dyn, name: str, tr) -> dict:
    from dyn_node.retime import retime

    t0 = time.perf_counter()
    res = retime(dyn, tr)
    wall = time.perf_counter() - t0
    k, d_in = res.input_check.time_scale, res.input_check.duration_s
    row = dict(name=name, waypoints=int(tr.n_points), feasible=res.feasible, method=res.method,
               duration=res.duration_out, stretch=k * d_in, lower_bound=res.lower_bound,
               wall_s=wall, verified=False, worst={})
    if res.feasible:
        rep = verify(dyn, res.trajectory)
        row.update(verified=passes(rep), worst=rep,
                   within_target=bool(res.duration_out <= 1.005 * k * d_in + 1e-12))
    return row


def summarize(rows: list[dict]) -> dict:
    ok = [r for r in rows if r["feasible"]]
    vs = [r["duration"] / r["stretch"] for r in ok if np.isfinite(r["stretch"])]
    gap = [r["duration"] / r["lower_bound"] for r in ok if r["lower_bound"] > 0]
    walls = [r["wall_s"] for r in rows]

    def pct(x, p):
        return float(np.percentile(x, p)) if x else None

    return dict(paths=len(rows), feasible=len(ok), verified=sum(r["verified"] for r in ok),
                within_target=sum(r.get("within_target", False) for r in ok),
                vs_stretch_median=statistics.median(vs) if vs else None,
                vs_stretch_p95=pct(vs, 95), vs_stretch_max=max(vs, default=None),
                gap_median=statistics.median(gap) if gap else None, gap_p95=pct(gap, 95),
                wall_median_s=statistics.median(walls), wall_p95_s=pct(walls, 95),
                wall_max_s=max(walls), stretch_won=sum(r["method"] == "uniform" for r in ok))


def run(n: int, progress=None) -> dict:
    dyn = panda()
    out = {}
    for panel, build in (("waypoint", waypoint_panel), ("hard", hard_panel)):
        rows = []
        for i, (name, tr) in enumerate(build(dyn, n)):
            rows.append(one(dyn, name, tr))
            if progress:
                r = rows[-1]
                progress("retime", f"{panel} {i + 1}: {name}: {r['method']} "
                         f"{r['duration']:.4g} s, stretch {r['stretch']:.4g} s, "
                         f"wall {r['wall_s']:.2f} s")
        out[panel] = dict(summary=summarize(rows), rows=rows)
    return out


def render_md(res: dict) -> list[str]:
    def f(x, d=3):
        return "–" if x is None else f"{x:.{d}f}"

    lines = ["| panel | paths | pass the check | verified (SciPy + Pinocchio) | ≤ 1.005 k·T_in | "
             "T/stretch median | p95 | max | T/T* median | p95 | wall median (s) | p95 | max | "
             "stretch won |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in ("waypoint", "hard"):
        s = res[name]["summary"]
        lines.append(f"| {name} | {s['paths']} | {s['feasible']} | {s['verified']} | "
                     f"{s['within_target']} | {f(s['vs_stretch_median'])} | "
                     f"{f(s['vs_stretch_p95'])} | {f(s['vs_stretch_max'])} | "
                     f"{f(s['gap_median'])} | {f(s['gap_p95'])} | {f(s['wall_median_s'], 2)} | "
                     f"{f(s['wall_p95_s'], 2)} | {f(s['wall_max_s'], 2)} | {s['stretch_won']} |")
    lines += ["", "Hard panel, path by path:", "", "| path | method | T (s) | stretch (s) | "
              "T* (s) | wall (s) | verified |", "|---|---|---|---|---|---|---|"]
    for r in res["hard"]["rows"]:
        lines.append(f"| {r['name']} | {r['method']} | {r['duration']:.4g} | "
                     f"{r['stretch']:.4g} | {r['lower_bound']:.4g} | {r['wall_s']:.2f} | "
                     f"{r['verified']} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paths", type=int, default=20)
    args = ap.parse_args(argv)
    from .common import progress

    res = run(args.paths, progress)
    print(json.dumps({k: v["summary"] for k, v in res.items()}, indent=1, default=float))
    print("\n".join(render_md(res)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
