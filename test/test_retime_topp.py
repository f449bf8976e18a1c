"""The retimer's reused TOPP-RA instance (:class:`dyn_node.retime.topp.Reach`) under caps on ṡ²
against TOPP-RA run from scratch with the cap inside its own rows (its LP's x bound)."""
from __future__ import annotations

import numpy as np
import toppra.algorithm as algo

from dyn_node.retime import topp
from dyn_node.retime.path import ArcPath, build_path
from test_retime import ur5, ur5_traj


def _direct(path, grid, rows, cap):
    """TOPP-RA's own controllable sets and forward pass, the cap in the x bound of its LP."""
    cons = topp._constraint(rows, np.minimum(np.minimum(rows.xmax, cap), 1e12), path.nv)
    inst = algo.TOPPRA([cons], topp._toppra_path(path), gridpoints=grid,
                       solver_wrapper="seidel", parametrizer="ParametrizeConstAccel")
    _, sd, _ = inst.compute_parameterization(0.0, 0.0)
    return np.asarray(sd) ** 2


def test_caps_on_a_reused_instance_match_toppra_from_scratch() -> None:
    dyn = ur5()
    path = ArcPath(build_path(ur5_traj()))
    grid = np.linspace(0.0, path.length, 401)
    rows = topp.joint_rows(dyn, path, grid, scale=0.995)
    reach = topp.Reach(path, grid, rows)
    x0 = reach.solve()
    assert np.allclose(x0, _direct(path, grid, rows, np.full(len(grid), np.inf)),
                       rtol=1e-9, atol=1e-12)
    cap = np.full(len(grid), np.inf)
    # two successive caps, the second below the first's region: each a partial backward pass
    for lo, hi in ((250, 300), (60, 90)):
        cap[lo:hi] = np.minimum(cap[lo:hi], 0.5 * x0[lo:hi])
        x = reach.solve(cap=cap)
        ref = _direct(path, grid, rows, cap)
        assert np.allclose(x, ref, rtol=1e-9, atol=1e-12)
        assert np.all(x[lo:hi] <= cap[lo:hi] * (1 + 1e-12))
        assert topp.duration(grid, x) > topp.duration(grid, x0)
    # a cap no timing can meet from rest (ṡ² below zero): not controllable
    assert reach.solve(cap=np.full(len(grid), -1.0)) is None
