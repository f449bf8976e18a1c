"""T* certified against its grid (dyn_node/retime/bound.py) against things we did not write:
TOPP-RA called directly at 20,000 grid steps on a SciPy spline of the same path, with its own
velocity, acceleration and torque constraints (Pinocchio's RNEA), and the closed-form bang-bang
time; and against the retimer's own answers and TOPP-RA's optimum on the 1000-step grid."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicHermiteSpline, CubicSpline

from benchmarks.retime_panel import panel, robot
from benchmarks.retime_verify import panda, waypoint_path
from dyn_node.core.check.trajectory import Trajectory
from dyn_node.retime import retime

#: TOPP-RA's grid for the reference: 20× the retimer's
FINE = 20000


def _toppra_duration(dyn, spline, steps: int = FINE) -> float:
    """TOPP-RA 0.6.10 (seidel, interpolation discretisation) on ``spline`` (a SciPy
    piecewise polynomial, the path by its own time), from rest to rest, with the joint velocity,
    acceleration and torque limits (torque: Pinocchio's rnea plus the URDF's Coulomb friction,
    which is the model's whole friction here: no damping, no armature)."""
    import toppra.algorithm as algo
    from toppra.interpolator import AbstractGeometricPath

    from test_retime import toppra_joint_constraints

    m = dyn.model
    assert not np.any(m.pin_model.armature) and not np.any(dyn.friction_coefficients[1])
    derivs = [spline.derivative(k) if k else spline for k in range(4)]

    class _Path(AbstractGeometricPath):
        def __call__(self, s, order=0):
            return derivs[order](np.atleast_1d(np.asarray(s, dtype=float)))

        @property
        def dof(self):
            return m.nv

        @property
        def path_interval(self):
            return np.array([spline.x[0], spline.x[-1]])

    cons = toppra_joint_constraints(m, dyn.friction_coefficients[0])
    grid = np.linspace(spline.x[0], spline.x[-1], steps + 1)
    inst = algo.TOPPRA(cons, _Path(), gridpoints=grid, solver_wrapper="seidel",
                       parametrizer="ParametrizeConstAccel")
    out = inst.compute_trajectory(0, 0)
    assert out is not None
    return float(out.duration)


@pytest.fixture(scope="module")
def panda_case():
    """The retime panel's first Panda path (libfranka's acceleration and jerk limits, effort
    at 40 %): positions only, so the path is SciPy's clamped cubic spline through them."""
    dyn = robot("panda")
    tr = panel(dyn, 1, 1)[0]
    spline = CubicSpline(tr.times, tr.positions, bc_type="clamped")
    return dyn, tr, spline, retime(dyn, tr)


def test_panda_bound_below_toppra_at_20000_steps(panda_case) -> None:
    """T* ≤ TOPP-RA's optimum at 20,000 steps (which approaches the true optimum from either
    side), ≤ TOPP-RA's own 1000-step optimum, ≤ the answer, and within 2 % of it (0.995)."""
    dyn, tr, spline, res = panda_case
    fine = _toppra_duration(dyn, spline)
    assert res.feasible and res.bound_steps >= 1000
    assert res.lower_bound <= fine
    assert res.lower_bound <= res.grid_optimum <= res.duration_out
    assert res.lower_bound >= 0.98 * fine
    assert f"T* {res.lower_bound:.4g} s (certified, {res.bound_steps} steps)" in res.message


def test_without_certify_the_answer_is_the_same_and_t_star_is_nan(panda_case) -> None:
    """``certify=False`` (the gate's retime mode) skips only the bound: the same answer, the
    same grid optimum, no T* claimed."""
    dyn, tr, _spline, res = panda_case
    quick = retime(dyn, tr, certify=False)
    assert np.isnan(quick.lower_bound) and quick.bound_steps == 0
    assert quick.grid_optimum == res.grid_optimum and quick.duration_out == res.duration_out
    np.testing.assert_array_equal(quick.trajectory.positions, res.trajectory.positions)
    assert f"T* not certified (grid optimum {res.grid_optimum:.4g} s)" in quick.message


@pytest.fixture(scope="module")
def long_case():
    """Issue 39's 250-waypoint path (benchmarks/retime_panels.py's hard panel, seed 300):
    cubic points passed at speed (Catmull-Rom velocities), so the path is SciPy's Hermite
    cubic through them. T* and TOPP-RA's grid optimum as the retimer computes them (its
    search on this path takes minutes on a loaded machine and is not what is tested here)."""
    from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
    from dyn_node.retime import bound
    from dyn_node.retime.path import build_path
    from dyn_node.retime.retimer import _bound, _search_paths

    dyn = panda()
    tr = waypoint_path(dyn, np.random.default_rng(300), 250, spread=0.4, step=0.3)
    spline = CubicHermiteSpline(tr.times, tr.positions, tr.velocities)
    path = build_path(tr)
    parts = _search_paths(dyn, path, 1000)
    lower, steps = bound.for_retime(dyn, path, parts, 1000, lambda p: 0.0)
    k = check_trajectory(dyn, tr, FeasibilityOptions(compute_payload_margin=False)).time_scale
    return dyn, spline, lower, _bound(dyn, path, parts, 1000, None), k * tr.duration


def test_long_path_bound_below_toppra_and_the_stretch(long_case) -> None:
    """On the path where TOPP-RA's 1000-step optimum was not a bound (issue 39: above TOPP-RA
    at 20,000 steps), T* is below TOPP-RA at 20,000 steps and below the uniform stretch (a
    timing the exact check passes, from rest to rest like every motion T* bounds)."""
    dyn, spline, lower, grid_optimum, stretch = long_case
    fine = _toppra_duration(dyn, spline)
    assert grid_optimum > fine
    assert lower <= fine
    assert lower <= stretch
    # the loosest path measured (a sharp corner at every knot, 16 stages per piece): 0.878 of
    # the reference (docs/retime.md, Known limits)
    assert 0.85 * fine <= lower


def test_one_joint_bang_bang_closed_form() -> None:
    """Rest to rest over 2 rad with velocity 1 rad/s and acceleration 2 rad/s² (positions
    only: a clamped cubic, q' = 0 at both ends, retimed by arc length): the minimum time is
    D/v + v/a = 2.5 s; T* is at most that and within 0.01 % of it (on a straight line the
    relaxation's variations vanish: what remains is the widening for rounding)."""
    from test_retime import one_joint

    dyn = one_joint(a=2.0)
    tr = Trajectory(times=np.zeros(2), positions=np.array([[0.0], [2.0]]))
    res = retime(dyn, tr, uniform_fallback=False)
    assert res.feasible
    assert 2.5 * (1 - 1e-4) <= res.lower_bound <= 2.5
    assert res.lower_bound <= res.duration_out


def test_one_joint_bound_holds_on_a_coarse_grid() -> None:
    """The same move on a 10-step grid: TOPP-RA's grid optimum is a first-order grid
    error away, T* stays below the closed form and within 1 % of it."""
    from test_retime import one_joint

    dyn = one_joint(a=2.0)
    tr = Trajectory(times=np.array([0.0, 3.0]), positions=np.array([[0.0], [2.0]]),
                    velocities=np.zeros((2, 1)), accelerations=np.zeros((2, 1)))
    res = retime(dyn, tr, grid_points=10, uniform_fallback=False)
    assert res.lower_bound <= 2.5 <= res.duration_out
    assert res.lower_bound >= 2.5 * 0.99


def test_panel_looseness() -> None:
    """On the retime bench's Panda panel (its first three paths) T* is within 2 % of TOPP-RA's
    1000-step optimum (measured 0.993–0.997; 0.987–0.997 on the first ten) and below every
    answer."""
    dyn = robot("panda")
    for tr in panel(dyn, 3, 1):
        res = retime(dyn, tr)
        assert res.feasible
        assert 0.98 * res.grid_optimum <= res.lower_bound <= res.grid_optimum
        assert res.lower_bound <= res.duration_out


def test_relaxed_passes_are_linear_programs() -> None:
    """The compiled passes (reach.relaxed_backward, relaxed_forward) against SciPy's linprog on
    random stages: each controllable set is [min x, max x] over the stage's polygon in (ū, x)
    (its rows, 0 ≤ x ≤ xmax, x + 2Δū in the next set), each reachable set [min, max] of
    x + 2Δū over the polygon with x in the previous reachable set; ours contain them, widened
    by at most the 1e-10 relative (plus 1e-12) they are widened by for rounding."""
    from scipy.optimize import linprog

    from dyn_node.retime import reach

    rng = np.random.default_rng(7)
    n, m = 6, 5
    # random rows, plus |ū| ≤ 1 so that every polygon is bounded
    al = np.column_stack([rng.normal(size=(n, m)), np.ones(n), -np.ones(n)])
    be = np.column_stack([rng.normal(size=(n, m)), np.zeros((n, 2))])
    ga = np.column_stack([-1.0 - rng.random((n, m)), np.full((n, 2), -1.0)])
    xmax = 0.5 + rng.random(n + 1)
    d = 0.05 + 0.1 * rng.random(n)
    K = np.zeros((n + 1, 2))
    K[n] = [0.3, 0.5]
    assert reach.relaxed_backward(al, be, ga, xmax, d, K) == -1
    # the rows bind: some set is narrower than [0, xmax]
    assert np.any(K[:n, 1] < xmax[:n] - 1e-3) and np.any(K[:n, 0] > 1e-3)

    def extremes(c, A, b, bounds):
        lo = linprog(c, A_ub=A, b_ub=b, bounds=bounds, method="highs")
        hi = linprog(-np.asarray(c), A_ub=A, b_ub=b, bounds=bounds, method="highs")
        assert lo.status == 0 and hi.status == 0
        return lo.fun, -hi.fun

    def close(ours, lo, hi):
        assert ours[0] <= lo + 1e-12 and ours[1] >= hi - 1e-12
        assert ours[0] >= lo - 2e-10 * abs(lo) - 2e-12 and ours[1] <= hi + 2e-10 * abs(hi) + 2e-12

    for i in range(n):
        # (ū, x): rows, x + 2Δū within K[i + 1]
        A = np.vstack([np.column_stack([al[i], be[i]]), [2 * d[i], 1.0], [-2 * d[i], -1.0]])
        b = np.concatenate([-ga[i], [K[i + 1, 1], -K[i + 1, 0]]])
        close(K[i], *extremes([0.0, 1.0], A, b, [(None, None), (0.0, xmax[i])]))
    R = np.full((n + 1, 2), np.nan)
    R[0] = K[0]
    assert reach.relaxed_forward(al, be, ga, K, d, R) == -1
    for i in range(n):
        A = np.vstack([np.column_stack([al[i], be[i]]), [2 * d[i], 1.0], [-2 * d[i], -1.0]])
        b = np.concatenate([-ga[i], [K[i + 1, 1], -K[i + 1, 0]]])
        close(R[i + 1], *extremes([2 * d[i], 1.0], A, b, [(None, None), (R[i, 0], R[i, 1])]))
