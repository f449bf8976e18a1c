"""dyn_node.retime.knots: a cubic path's knots in the search (issue 39 items 2 and 3).

Paths from the waypoint panel of benchmarks/retime_panels.py (seeded); answers verified with
SciPy's polynomials and Pinocchio's rnea (benchmarks/retime_verify.py), the knots' jumps with
SciPy's cubic Hermite spline and Pinocchio's crba, the path deviation with a k-d tree of the
input's curve sampled by SciPy.
"""
from __future__ import annotations

import os
import time

import numpy as np
import pinocchio as pin
import pytest
from scipy.interpolate import CubicHermiteSpline
from scipy.spatial import cKDTree

from benchmarks.retime_verify import panda, passes, verify, waypoint_path
from dyn_node.retime import knots, retime, topp
from dyn_node.retime.path import build_path

#: issue 39's target for T ÷ T* outside the hard panel
GAP = 1.15


@pytest.fixture(scope="module")
def dyn():
    return panda()


def _panel(dyn, seed: int):
    """The waypoint panel's path of ``seed`` (benchmarks.retime_panels.waypoint_panel)."""
    rng = np.random.default_rng(seed)
    return waypoint_path(dyn, rng, int(rng.integers(5, 9)))


def _off_path(tr, out) -> float:
    """Largest distance (∞-norm over the joints) from an output point to the input's curve
    (SciPy's cubic Hermite spline through it, sampled every 1e-5 s: the sampling adds at most
    half a step's travel, < 1.5e-5 rad here)."""
    spline = CubicHermiteSpline(tr.times, tr.positions, tr.velocities)
    curve = spline(np.arange(0.0, tr.times[-1], 1e-5))
    d, _ = cKDTree(curve).query(out.positions, p=np.inf)
    return float(np.max(d))


def test_knots_jumps_and_windows_match_scipy_and_crba(dyn) -> None:
    """Each inner knot's jump of q'' is SciPy's spline's, and its window per unit ṡ² the jump
    over the ramp's share of the jerk limit or M·jump (Pinocchio's crba) over its share of the
    effort-rate limit, whichever is wider."""
    tr = _panel(dyn, 100)
    kn = knots.find(dyn, build_path(tr), moving=False)
    spline = CubicHermiteSpline(tr.times, tr.positions, tr.velocities)
    inner = tr.times[1:-1]
    jump = spline(inner + 1e-9, 2) - spline(inner - 1e-9, 2)
    np.testing.assert_allclose(kn.at, inner, rtol=0, atol=1e-12)
    np.testing.assert_allclose(kn.jump, jump, rtol=1e-5, atol=1e-6)
    lim = dyn.model.limits
    pm = dyn.model.pin_model
    for q, dq, per_x in zip(tr.positions[1:-1], jump, kn.per_x):
        M = pin.crba(pm, pm.createData(), q)
        M = np.triu(M) + np.triu(M, 1).T
        want = max(np.max(np.abs(dq) / (knots.RAMP_SHARE * lim.jerk)),
                   np.max(np.abs(M @ dq) / (knots.RAMP_SHARE * lim.effort_rate)))
        assert per_x == pytest.approx(want, rel=1e-6)


def test_precap_is_local_and_meets_its_budget(dyn) -> None:
    """The caps before the first round sit only around the knots whose ramps would stray, each
    below TOPP-RA's own ṡ² there (scaled, not flat), and leave most of the law free."""
    path = build_path(_panel(dyn, 100))
    from dyn_node.retime.path import ArcPath

    p = ArcPath(path)
    grid = np.linspace(0.0, p.length, 1001)
    rows = topp.joint_rows(dyn, p, grid, scale=0.995)
    x = topp.Reach(p, grid, rows).solve(cap=np.full(len(grid), np.inf))
    kn = knots.find(dyn, p, moving=False)
    cap = np.full(len(grid), np.inf)
    assert knots.precap(kn, grid, x, cap, 1e-4, 0.004, 0.085, 0.008)
    capped = np.isfinite(cap)
    assert 0 < capped.sum() < 0.2 * len(grid)
    near = np.min(np.abs(grid[capped][:, None] - kn.at[None, :]), axis=1)
    assert np.all(near <= 0.1 * p.length)
    assert np.all(cap[capped] < x[capped])
    # the closed form: a knot whose ṡ² would stray beyond the budget (size·x·(per_x·x)²/24 >
    # share × tolerance, the window above its floor here) is capped to within it
    over = 0
    for at, size, per_x in zip(kn.at, kn.size, kn.per_x):
        xi, ci = np.interp(at, grid, x), np.interp(at, grid, cap)
        xc = (24 * knots.PRECAP_SHARE * 1e-4 / (size * per_x**2)) ** (1 / 3)
        assert per_x * xc > 0.008
        if xi > xc:
            over += 1
            assert ci <= 0.98 * xc * (1 + 1e-12)
            assert size * ci * (per_x * ci) ** 2 / 24 <= knots.PRECAP_SHARE * 1e-4
    assert over >= 1


@pytest.mark.parametrize("seed, rounds_before", [(100, 16), (104, 18)])
def test_waypoint_path_answered_by_the_search_near_the_bound(dyn, seed: int,
                                                             rounds_before: int) -> None:
    """Seeds 100 and 104 of the waypoint panel: the joint-space window was sized by TOPP-RA's
    ṡ² at the knots, where it dips and the smoothed law's does not: the effort rate failed
    round after round (16 and 18 rounds, 1.67× and 1.19× T*, 9 and 7 s). Now the search
    answers in a few rounds within 1.15 × T*, verified independently and within the path
    tolerance of the input's curve."""
    tr = _panel(dyn, seed)
    t0 = time.perf_counter()
    res = retime(dyn, tr)
    wall = time.perf_counter() - t0
    assert res.feasible and res.method == "optimal", res.message
    assert res.rounds <= 3 < rounds_before
    assert res.duration_out <= GAP * res.lower_bound
    assert res.duration_out <= 1.005 * res.input_check.time_scale * tr.duration
    assert passes(verify(dyn, res.trajectory))
    assert _off_path(tr, res.trajectory) <= 1e-4 + 1.5e-5
    assert wall < 20.0


def test_a_static_load_near_a_limit_is_searched_at_the_limits(dyn) -> None:
    """Seed 109 of the waypoint panel: gravity takes more than 99.5 % of an effort limit
    somewhere on the curve, so the rows × 0.995 leave no timing at all; the search gave up,
    the stretch (286.9 s) failed too, and nothing was answered after 86 s. Now the search runs
    at the limits themselves (the exact check still decides): answered within 1.15 × T*."""
    tr = _panel(dyn, 109)
    res = retime(dyn, tr)
    assert res.feasible and res.method == "optimal", res.message
    assert res.duration_out <= GAP * res.lower_bound
    assert passes(verify(dyn, res.trajectory))
    assert _off_path(tr, res.trajectory) <= 1e-4 + 1.5e-5


def test_pieces_also_cut_at_given_knots(dyn) -> None:
    """path.pieces(path, also): the path cut at the given knots too, each piece the input's
    own cubic there (SciPy's spline), from knot to knot."""
    from dyn_node.retime.path import pieces

    tr = waypoint_path(dyn, np.random.default_rng(300), 12, spread=0.4, step=0.3)
    path = build_path(tr)
    parts = pieces(path, np.array([4, 8]))
    assert [p.pp.breaks[0] for p in parts] == [tr.times[0], tr.times[4], tr.times[8]]
    assert parts[-1].pp.breaks[-1] == tr.times[-1]
    spline = CubicHermiteSpline(tr.times, tr.positions, tr.velocities)
    for p in parts:
        s = np.linspace(p.pp.breaks[0], p.pp.breaks[-1], 101)
        np.testing.assert_allclose(p.positions(s), spline(s), rtol=0, atol=1e-12)


@pytest.mark.skipif(os.environ.get("DYN_RELIABILITY_FULL") != "1",
                    reason="long run (~1 min with the verification): DYN_RELIABILITY_FULL=1")
def test_250_waypoints_answered_by_the_search(dyn) -> None:
    """The hard panel's 250-waypoint path (seed 300): the search was cut at the stretch's
    202 s (its knots' caps under one window slowed the whole law) and the stretch itself failed
    (nothing answered after 90–180 s). Searched in pieces of 5 segments it answers in about
    half the stretch, verified independently and within the tolerance of the input's curve."""
    tr = waypoint_path(dyn, np.random.default_rng(300), 250, spread=0.4, step=0.3)
    res = retime(dyn, tr)
    stretch = res.input_check.time_scale * tr.duration
    assert res.feasible and res.method == "optimal", res.message
    assert res.duration_out <= 0.6 * stretch
    assert res.lower_bound <= res.duration_out <= 1.5 * res.lower_bound
    assert passes(verify(dyn, res.trajectory))
    assert _off_path(tr, res.trajectory) <= 1e-4 + 1.5e-5


@pytest.mark.skipif(os.environ.get("DYN_RELIABILITY_FULL") != "1",
                    reason="long run (~1 min with the verification): DYN_RELIABILITY_FULL=1")
def test_250_waypoints_stretch_widens_its_window(dyn, monkeypatch) -> None:
    """The same path's stretch (the answer when the search fails, here made to fail): its
    averaging window at 90 % of the limits left the effort rate 1.09× between points at
    1.001 × k and 1.11× at the points at 1.005 × k, and every stretch failed. Widened by the
    worst ratio it passes at the first pad, verified independently."""
    from dyn_node.retime import retimer

    monkeypatch.setattr(retimer, "_by_pieces", lambda *a, **k: None)
    tr = waypoint_path(dyn, np.random.default_rng(300), 250, spread=0.4, step=0.3)
    res = retime(dyn, tr)
    k = res.input_check.time_scale
    assert res.feasible and res.method == "uniform", res.message
    assert res.duration_out <= 1.005 * k * tr.duration
    assert passes(verify(dyn, res.trajectory))
    assert _off_path(tr, res.trajectory) <= 1e-4 + 1.5e-5
