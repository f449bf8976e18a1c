"""Retiming from a moving start state: the optimal search against the uniform stretch.

Panel: benchmarks/retime_bench.py's random paths and limits (Panda, UR5), each made a quintic
through its waypoints (SciPy's clamped cubic spline's velocities and accelerations there, same
times). The robot runs it; at a seeded instant in its first half the rest arrives again as a new
goal (the waypoints ahead, times from that instant; `start=` the spline's q, q̇ there): the case a
moving start exists for (a replanned goal, the gate's retime mode). Per case: the method
used, duration ÷ the uniform stretch's, duration ÷ T*, the exact check with the start;
``blocked``: the check's "no slowdown helps" (e.g. the spline's own speed there above a limit:
nothing is returned).

Command: `python -m benchmarks.retime_start_bench --paths 10`.
"""
from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from .retime_panel import panel, robot


def cases(dyn, n_paths: int, seed: int) -> list:
    """(trajectory ahead, StartState) per panel path (see the module docstring)."""
    from scipy.interpolate import CubicSpline

    from dyn_node.core.check.feasibility import StartState
    from dyn_node.core.check.trajectory import Trajectory

    rng = np.random.default_rng(seed + 100)
    out = []
    for tr in panel(dyn, n_paths, seed):
        t, P = tr.times, tr.positions
        spline = CubicSpline(t, P, bc_type="clamped")
        now = float(t[-1] * (0.1 + 0.4 * rng.random()))
        k = int(np.searchsorted(t, now, side="right"))
        ahead = Trajectory(times=t[k:] - now, positions=P[k:].copy(),
                           velocities=spline(t[k:], 1), accelerations=spline(t[k:], 2))
        out.append((ahead, StartState(positions=spline(now), velocities=spline(now, 1),
                                      age_s=0.0)))
    return out


def one(dyn, traj, start) -> dict:
    from dyn_node.core.check.feasibility import check_trajectory
    from dyn_node.retime import retime

    t0 = time.perf_counter()
    res = retime(dyn, traj, start=start)
    wall = time.perf_counter() - t0
    ok = res.feasible and check_trajectory(dyn, res.trajectory, start=start).feasible
    return dict(method=res.method, feasible=bool(ok), blocked=bool(res.blocked),
                duration=res.duration_out,
                uniform=res.duration_uniform, lower_bound=res.lower_bound,
                vs_uniform=res.duration_out / res.duration_uniform, gap=res.gap, wall_s=wall)


def summarize(rows: list[dict]) -> dict:
    ratio = np.array([r["vs_uniform"] for r in rows if math.isfinite(r["vs_uniform"])])
    gap = np.array([r["gap"] for r in rows if math.isfinite(r["gap"])])
    return dict(cases=len(rows), pass_check=sum(r["feasible"] for r in rows),
                blocked=sum(r["blocked"] for r in rows),
                optimal=sum(r["method"] == "optimal" for r in rows),
                vs_uniform_median=float(np.median(ratio)), vs_uniform_max=float(np.max(ratio)),
                gap_median=float(np.median(gap)), gap_p95=float(np.percentile(gap, 95)),
                wall_median_s=float(np.median([r["wall_s"] for r in rows])))


def run(paths: int) -> dict:
    out = {}
    for name, seed in (("panda", 1), ("ur5", 2)):
        dyn = robot(name)
        out[name] = summarize([one(dyn, tr, st) for tr, st in cases(dyn, paths, seed)])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paths", type=int, default=10)
    args = ap.parse_args(argv)
    print(json.dumps(run(args.paths), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
