"""TOPP-RA (toppra 0.6.10) over the exact check's first- and second-order joint kinds.

Along q(s) with x = ṡ² and u = s̈ (ṡ ≥ 0): q̇ = q'ṡ, q̈ = q'u + q''x, and the torque the check
computes is τ = a(s)·u + b(s)·x + c(s) + w(s)·ṡ with a = M q' (+armature), b = M q'' + C(q, q')q'
(+armature), c = g + Coulomb·sign(q') (payload in the model) and w = damping·q'. Rows, all linear
in (u, x): ±q̈ ≤ acceleration; −sign(q')·q̈ ≤ deceleration (the check's |q̈| where q̇·q̈ < 0:
exact, the row is slack when q̇·q̈ ≥ 0); ±τ ≤ effort; and x ≤ (velocity/|q'|)². The viscous
term w·ṡ is not linear in x: the retiming drops it (the exact check afterwards sees it), the
lower bound relaxes it to its most favourable value over the velocity-limited ṡ range, so the
bound stays a bound.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.retime.path import Path


@dataclass(frozen=True)
class Rows:
    """a·u + b·x + c ≤ g at every grid point (arrays (N+1)×m, g (m,)), and x ≤ xmax (N+1,)."""

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    g: np.ndarray
    xmax: np.ndarray


def joint_rows(dynamics: Dynamics, path: Path, grid: np.ndarray, *, scale: float = 1.0,
               lower_bound: bool = False) -> Rows:
    """The rows of the joint kinds at the grid, limits multiplied by ``scale``."""
    lim = dynamics.model.limits
    q, d1, d2 = path.derivatives(grid)
    with np.errstate(divide="ignore"):
        xv = np.min(np.where(np.abs(d1) > 0, (lim.velocity * scale / np.abs(d1)) ** 2, np.inf),
                    axis=1)
    A, B, C, G = [], [], [], []

    def add(a, b, c, g):
        A.append(a), B.append(b), C.append(c), G.append(np.full(a.shape[1], g) if np.isscalar(g)
                                                        else g)

    cols = np.isfinite(lim.acceleration)
    for sign in ((1.0, -1.0) if cols.any() else ()):
        add(sign * d1[:, cols], sign * d2[:, cols], 0 * d1[:, cols], lim.acceleration[cols] * scale)
    cols = np.isfinite(lim.deceleration)
    if cols.any():
        sg = -np.sign(d1[:, cols])
        add(sg * d1[:, cols], sg * d2[:, cols], 0 * d1[:, cols], lim.deceleration[cols] * scale)
    cols = np.isfinite(lim.effort)
    if cols.any():
        zero = np.zeros_like(q)
        a = dynamics.terms_batch(q, zero, d1).inertial
        terms = dynamics.terms_batch(q, d1, d2)
        b, c = terms.inertial, terms.static
        w = dynamics.friction_coefficients[0] * d1
        lo_w = hi_w = np.zeros_like(w)
        if lower_bound and np.any(w):
            # w·ṡ lies between 0 and w·√xv: each side takes its most favourable end
            sq = np.sqrt(np.minimum(xv, 1e12))[:, None]
            lo_w, hi_w = np.minimum(0.0, w * sq), np.maximum(0.0, w * sq)
        L = lim.effort[cols] * scale
        add(a[:, cols], b[:, cols], (c + lo_w)[:, cols], L)
        add(-a[:, cols], -b[:, cols], -(c + hi_w)[:, cols], L)
    if not A:
        z = np.zeros((len(grid), 1))
        return Rows(z, z, z, np.ones(1), xv)
    return Rows(np.hstack(A), np.hstack(B), np.hstack(C), np.concatenate(G), xv)


def solve(path: Path, grid: np.ndarray, rows: Rows, *, cap: np.ndarray | None = None,
          sd_start: float = 0.0, free_ends: bool = False) -> np.ndarray | None:
    """TOPP-RA's time-optimal x = ṡ² at the grid (N+1,), None when the path is not
    controllable (no timing meets the rows, e.g. gravity alone above an effort limit).

    ``free_ends``: where the path itself stops (q' = 0 at an end) the robot is at rest at any
    ṡ, so ṡ is left free there (the bound: else a first-order grid error of the forced ṡ = 0).
    The retiming keeps ṡ = 0 at the ends: its smoothing window starts from ṡ = 0."""
    import toppra.algorithm as algo          # scipy behind it: imported when retiming only

    xmax = rows.xmax if cap is None else np.minimum(rows.xmax, cap)
    cons = _constraint(rows, np.minimum(xmax, 1e12), path.nv)
    inst = algo.TOPPRA([cons], _toppra_path(path), gridpoints=grid, solver_wrapper="seidel",
                       parametrizer="ParametrizeConstAccel")
    ends = np.max(np.abs(path.derivatives(grid[[0, -1]])[1]), axis=1)
    sd_end = 0.0
    if free_ends and ends[1] == 0.0:
        # every row is free of u where q' = 0: ṡ² up to the tightest of them
        sd_end = math.sqrt(_free_end_x(rows, xmax)) * (1 - 1e-9)
    if free_ends and ends[0] == 0.0 and sd_start == 0.0:
        K = inst.compute_controllable_sets(sd_end, sd_end)
        if np.all(np.isfinite(K[0])):
            sd_start = math.sqrt(max(K[0, 1], 0.0)) * (1 - 1e-9)
    sdd, sd, _ = inst.compute_parameterization(sd_start, sd_end)
    if sd is None or not np.all(np.isfinite(sd)):
        return None
    return np.maximum(np.asarray(sd, dtype=float), 0.0) ** 2


def _free_end_x(rows: Rows, xmax: np.ndarray) -> float:
    b, room = rows.b[-1], rows.g - rows.c[-1]
    if np.any(room < 0):
        return 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        lim = np.where(b > 0, room / b, np.inf)
    return float(min(np.min(lim), xmax[-1], 1e12))


def duration(grid: np.ndarray, x: np.ndarray) -> float:
    """The time of x = ṡ² on the grid, ṡ affine in time per step (constant s̈)."""
    sd = np.sqrt(np.maximum(x, 0.0))
    den = sd[:-1] + sd[1:]
    if np.any(den <= 0):
        return math.inf
    return float(np.sum(2 * np.diff(grid) / den))


def _constraint(rows: Rows, xmax: np.ndarray, dof: int):
    from toppra.constraint import DiscretizationType, LinearConstraint
    from toppra.constraint.linear_constraint import canlinear_colloc_to_interpolate

    class _Linear(LinearConstraint):
        def __init__(self) -> None:
            super().__init__()
            self.dof = dof
            self.set_discretization_type(DiscretizationType.Interpolation)
            self.identical = True

        def compute_constraint_params(self, path, gridpoints, *args, **kwargs):
            m = rows.g.shape[0]
            xb = np.column_stack([np.zeros_like(xmax), xmax])
            return canlinear_colloc_to_interpolate(rows.a, rows.b, rows.c, np.eye(m), rows.g,
                                                   None, xb, gridpoints, identical=True)

    return _Linear()


def _toppra_path(path: Path):
    from toppra.interpolator import AbstractGeometricPath

    class _P(AbstractGeometricPath):
        def __call__(self, s, order=0):
            s = np.atleast_1d(np.asarray(s, dtype=float))
            return path.derivatives(s)[order] if order < 3 else path.pp.evaluate(s)[3]

        @property
        def dof(self):
            return path.nv

        @property
        def path_interval(self):
            return np.array([path.pp.breaks[0], path.pp.breaks[-1]])

    return _P()

