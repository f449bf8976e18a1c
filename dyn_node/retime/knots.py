"""The knots of a cubic path (points with velocities, no accelerations: C¹ only) in the search.

q'' jumps at every knot, so a motion with ṡ > 0 there jumps in q̈ by Δq''·ṡ², which no
smoothing of the law spreads. The search's output is averaged in joint space over a window W
(candidates.averaged), W the least that ramps every knot's jump within the jerk and
effort-rate limits (candidates.knot_window): both the jump and W go as ṡ² at the knot, and
the average strays from the curve by ~Δq̈·W²/24, so as ṡ⁶. Here, in closed form:

- :func:`precap`: before the first round, ṡ² capped at each knot (and only around it, over the
  law's smoothing windows) where its own jump, ramped over its own window, would stray beyond
  a share of the path tolerance (issue 39: after a failed round instead, each round's caps
  slowed the whole law, and a 250-waypoint path was cut after one round);
- :func:`averaged`: the round's output averaged over W sized by the *smoothed* law's ṡ² at
  each knot (the box filter lifts ṡ at a knot where TOPP-RA's ṡ² dips: sized by TOPP-RA's, the
  jumps outgrew W and the effort rate failed round after round: 16 rounds, 1.67 × T* on the
  waypoint panel's seed 100).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dyn_node.core.check.trajectory import Trajectory
from dyn_node.retime import candidates, timing
from dyn_node.retime.path import ArcPath

#: the share of the path tolerance a knot's own ramp may take when ṡ² is capped before the
#: first round (the global window is the largest knot's, and the points add their own)
PRECAP_SHARE = 0.5
#: the share of the jerk and effort-rate limits a knot's ramp may take (the law's own rate
#: of τ along the path adds to it there)
RAMP_SHARE = 0.75
#: the least half-width (grid cells) of a knot's cap
CAP_CELLS = 8


@dataclass(frozen=True)
class Knots:
    """A cubic path's inner knots in the search's coordinate (s, or ℓ by arc length), the
    configuration there, the unit (ArcPath) or plain tangent, and the jump of q'' across the
    path; ``per_x``: each knot's window W per unit ṡ² (W = per_x·ṡ², candidates.knot_window's
    rule without its floor) and ``size``: its largest |Δq''| (rad per unit ṡ²)."""

    at: np.ndarray
    q: np.ndarray
    d1: np.ndarray
    jump: np.ndarray
    per_x: np.ndarray
    size: np.ndarray


def find(dynamics, path, moving: bool) -> Knots | None:
    """The knots of ``path`` when the search must average at them: a timed cubic path from
    rest with inner knots (None otherwise)."""
    base = path.base if isinstance(path, ArcPath) else path
    if (moving or base.untimed or base.nominal.natural_interpolation != "cubic"
            or len(base.pp.breaks) < 3):
        return None
    sk = base.pp.breaks[1:-1]
    eps = 1e-9 * max(1.0, float(base.pp.breaks[-1]))
    q, d1, d2 = base.derivatives(sk)
    jump = d2 - base.derivatives(sk - eps)[2]
    at = sk
    if isinstance(path, ArcPath):
        # by arc length only the part of q'' across the path jumps: (q'' − t(t·q''))/|q'|²
        n = np.linalg.norm(d1, axis=1, keepdims=True)
        d1 = d1 / n
        jump = (jump - d1 * np.sum(d1 * jump, axis=1, keepdims=True)) / n**2
        at = path.arc_of(sk)
    lim = dynamics.model.limits
    per_x = np.zeros(len(sk))
    with np.errstate(divide="ignore", invalid="ignore"):
        if np.any(np.isfinite(lim.jerk)):
            r = np.where(np.isfinite(lim.jerk), np.abs(jump) / (RAMP_SHARE * lim.jerk), 0.0)
            per_x = np.maximum(per_x, np.nanmax(r, axis=1))
        if np.any(np.isfinite(lim.effort_rate)):
            # the jump of τ is M·Δq̈ exactly (the velocity terms are continuous)
            z = np.zeros_like(q)
            dtau = np.abs(dynamics.rnea_batch(q, z, jump) - dynamics.rnea_batch(q, z, z))
            r = np.where(np.isfinite(lim.effort_rate), dtau / (RAMP_SHARE * lim.effort_rate), 0.0)
            per_x = np.maximum(per_x, np.nanmax(r, axis=1))
    return Knots(at, q, d1, jump, per_x, np.max(np.abs(jump), axis=1))


def precap(kn: Knots, grid: np.ndarray, x: np.ndarray, cap: np.ndarray, tolerance: float,
           period: float, w: float, w2: float) -> bool:
    """Cap ṡ² around each knot whose own ramp (jump Δq''·ṡ² over W = per_x·ṡ², at least two
    output periods) would stray more than :data:`PRECAP_SHARE` of ``tolerance``: deviation
    ≈ size·ṡ²·W²/24, solved for ṡ², with ṡ² the law's smoothed over the windows w, w2 (the box
    filter lifts ṡ where TOPP-RA's dips at a knot). The cap is TOPP-RA's own ṡ² scaled around
    the knot, over the windows: a flat one would cut the peaks beside a dip. True when set."""
    budget = 24 * PRECAP_SHARE * tolerance
    with np.errstate(divide="ignore", invalid="ignore"):
        # W = per_x·x above the floor 2·period; below it W is the floor: x = budget/(size·W²)
        xs = np.where(kn.per_x > 0, (budget / (kn.size * kn.per_x**2)) ** (1 / 3), np.inf)
        floor = 2 * period
        xs = np.where(kn.per_x * xs < floor, budget / (kn.size * floor**2), xs)
    lw = timing.law(grid, x)
    t = np.linspace(0.0, lw.duration + w + w2, 4 * len(grid))
    s_o, sd_o = timing.smoothed(lw, w, t, w2, orders=2)
    xk = np.maximum(np.interp(kn.at, grid, x), np.interp(kn.at - lw.origin, s_o, sd_o) ** 2)
    changed = False
    for at, xc, xn in zip(kn.at, xs, xk):
        if not (xc < xn):
            continue
        i = int(np.searchsorted(grid, at))
        cells = _cells(grid, i, math.sqrt(xn) * (w + w2))
        lo, hi = max(0, i - cells), min(len(x), i + cells + 1)
        cap[lo:hi] = np.minimum(cap[lo:hi], x[lo:hi] * (0.98 * xc / xn))
        changed = True
    return changed


def _cells(grid: np.ndarray, i: int, reach: float) -> int:
    """Grid cells within ``reach`` (s) of grid point ``i``, at least :data:`CAP_CELLS`."""
    ds = float(grid[min(i, len(grid) - 1)] - grid[max(i - 1, 0)]) or float(grid[1] - grid[0])
    return max(CAP_CELLS, int(math.ceil(reach / ds)))


def averaged(dynamics, kn: Knots, grid: np.ndarray, x: np.ndarray, cap: np.ndarray,
             lw: timing.Law, w: float, w2: float, out: Trajectory, dev: float, period: float,
             tolerance: float) -> tuple[Trajectory | None, float]:
    """``out`` averaged in joint space over the window that ramps every knot's jump of q̈
    within the jerk and effort-rate limits at the smoothed law's ṡ² there (candidates.averaged).
    (None, dev) when that strays beyond ``tolerance``: ṡ² is then capped around the knots whose
    ramps stray (by the cube root of the excess) for the next round."""
    s_o, sd_o = timing.smoothed(lw, w, out.times, w2, orders=2)
    xk = np.maximum(np.interp(kn.at, grid, x), np.interp(kn.at - lw.origin, s_o, sd_o) ** 2)
    W = max(2 * period, float(np.max(kn.per_x * xk)))
    avg, more = candidates.averaged(dynamics, out, period, tolerance - dev, W)
    if avg is not None:
        return avg, dev + more
    # beyond the path tolerance: the deviation goes as the jumps cubed (W ∝ Δq̈, deviation
    # ∝ Δq̈·W²), the jumps as ṡ²: capped at the knots whose own ramp over W strays most
    factor = 0.9 * max((tolerance - dev) / more, 0.0) ** (1 / 3)
    own, wide = kn.size * xk * W**2 / 24, kn.per_x * xk
    for at, xn, o, wk in zip(kn.at, xk, own, wide):
        if o < 0.25 * np.max(own) and wk < 0.5 * W:
            continue
        i = int(np.searchsorted(grid, at))
        cells = _cells(grid, i, math.sqrt(xn) * (w + w2))
        lo, hi = max(0, i - cells), min(len(x), i + cells + 1)
        cap[lo:hi] = np.minimum(cap[lo:hi], x[lo:hi] * factor)
    return None, dev
