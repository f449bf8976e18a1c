"""From ṡ² on a grid to output points: the time law, its smoothing, the points.

TOPP-RA's answer is bang-bang in s̈ (constant per grid step): unbounded jerk and effort rate
where s̈ switches. The law s(t) is therefore averaged over a moving window of width w (a box
filter, in closed form): s̈ becomes piecewise linear, its jumps become ramps of length w, and
the motion takes exactly w longer (it starts and ends at rest); a second short window w2 (two
output periods) rounds the ramps' corners so that the jerk is continuous too. For one joint with velocity,
acceleration and jerk limits this is the time-optimal S-curve when w = acceleration/jerk
(D/v + v/a + a/j), and with many joints it bounds the jerk and effort rate of every switch at
once. The output points sample the averaged law at a fixed period; each carries q(s), q'ṡ and
q''ṡ² + q's̈, so the controller's quintic between points stays on the path (measured).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dyn_node.core.check.trajectory import Trajectory, interpolate
from dyn_node.retime.path import Path


@dataclass(frozen=True)
class Law:
    """s(t) with s̈ constant on each grid step: grid s, ṡ, s̈ per step, t at the grid, and the
    first and second integrals of s at the grid (for the window averages)."""

    s: np.ndarray
    sd: np.ndarray
    u: np.ndarray
    t: np.ndarray
    integral: np.ndarray
    integral2: np.ndarray
    #: the path's s at the law's s = 0 (the grid's start)
    origin: float = 0.0
    #: ṡ before t = 0: 0 (at rest there), or a moving robot's own ṡ₀ (the law extended back
    #: at that constant speed, so that the window averages start from it)
    lead: float = 0.0

    @property
    def duration(self) -> float:
        return float(self.t[-1])


def law(grid: np.ndarray, x: np.ndarray, lead: float = 0.0) -> Law:
    sd = np.sqrt(np.maximum(x, 0.0))
    ds = np.diff(grid)
    dt = 2 * ds / np.maximum(sd[:-1] + sd[1:], 1e-300)
    u = (sd[1:] - sd[:-1]) / dt
    t = np.concatenate(([0.0], np.cumsum(dt)))
    rel = grid - grid[0]
    step = rel[:-1] * dt + sd[:-1] * dt**2 / 2 + u * dt**3 / 6
    integral = np.concatenate(([0.0], np.cumsum(step)))
    step2 = integral[:-1] * dt + rel[:-1] * dt**2 / 2 + sd[:-1] * dt**3 / 6 + u * dt**4 / 24
    return Law(s=rel, sd=sd, u=u, t=t, integral=integral,
               integral2=np.concatenate(([0.0], np.cumsum(step2))), origin=float(grid[0]),
               lead=float(lead))


def _levels(lw: Law, t: np.ndarray, keys: tuple[int, ...]) -> dict[int, np.ndarray]:
    """The law at times t by derivative order (``keys`` of them): −2 (∫∫s), −1 (∫s), 0 (s),
    1 (ṡ), 2 (s̈); before t = 0 at the constant ṡ = ``lw.lead`` through s = 0 (at rest when
    0), at the end after T."""
    i = np.clip(np.searchsorted(lw.t, t, side="right") - 1, 0, len(lw.u) - 1)
    r = np.clip(t - lw.t[i], 0.0, None)
    before, after = t < 0, t > lw.t[-1]
    end = lw.s[-1]
    s0, v, u = lw.s[i], lw.sd[i], lw.u[i]
    past = np.clip(t - lw.t[-1], 0.0, None)
    law_at = {
        2: lambda: u, 1: lambda: np.maximum(v + u * r, 0.0),
        0: lambda: s0 + v * r + u * r**2 / 2,
        -1: lambda: lw.integral[i] + s0 * r + v * r**2 / 2 + u * r**3 / 6,
        -2: lambda: (lw.integral2[i] + lw.integral[i] * r + s0 * r**2 / 2 + v * r**3 / 6
                     + u * r**4 / 24),
    }
    ld, tb = lw.lead, np.minimum(t, 0.0)
    # before t = 0: s = lead·t and its integrals from t = 0
    head = {2: 0.0, 1: ld, 0: ld * tb, -1: ld * tb**2 / 2, -2: ld * tb**3 / 6}
    tail = {2: lambda: 0.0, 1: lambda: 0.0, 0: lambda: end,
            -1: lambda: lw.integral[-1] + end * past,
            -2: lambda: lw.integral2[-1] + lw.integral[-1] * past + end * past**2 / 2}
    return {k: np.where(before, head[k], np.where(after, tail[k](), law_at[k]())) for k in keys}


def smoothed(lw: Law, w: float, t: np.ndarray, w2: float = 0.0, orders: int = 3
             ) -> tuple[np.ndarray, ...]:
    """s, ṡ, s̈ of the law averaged over [t − w, t], then over [t − w2, t] (0: no average);
    the motion lasts T + w + w2. Two windows make s̈ continuous (jerk bounded and continuous,
    which the controller's quintic between points follows without overshoot). ``orders``: how
    many of s, ṡ, s̈ are wanted."""
    widths = [x for x in (w, w2) if x > 0]
    shifts = [(0.0, 1.0)]
    for width in widths:
        shifts = [(sh + d, sg * (-1.0 if d else 1.0) / width) for sh, sg in shifts
                  for d in (0.0, width)]
    n = len(widths)
    keys = tuple(d - n for d in range(orders))
    lev = {sh: _levels(lw, t - sh, keys) for sh, _ in shifts}
    return tuple(sum(sg * lev[sh][d - n] for sh, sg in shifts) for d in range(orders))


def points(path: Path, lw: Law, w: float, period: float, w2: float = 0.0) -> Trajectory:
    """The output trajectory: points every ≤ ``period`` s."""
    total = lw.duration + w + w2
    n = max(2, int(np.ceil(total / period)) + 1)
    t = np.linspace(0.0, total, n)
    s, sd, sdd = smoothed(lw, w, t, w2)
    s = np.clip(s, path.pp.breaks[0] - lw.origin, lw.s[-1])
    q, d1, d2 = path.derivatives(s + lw.origin)
    return Trajectory(times=t, positions=q, velocities=d1 * sd[:, None],
                      accelerations=d2 * (sd**2)[:, None] + d1 * sdd[:, None])


def deviation(path: Path, lw: Law, w: float, out: Trajectory, w2: float = 0.0,
              per_segment: int = 4) -> float:
    """Largest |q| difference (any joint) between the controller's quintic through the output
    points and the path at the same instants, at ``per_segment`` points inside each segment."""
    t = out.times
    frac = np.arange(1, per_segment + 1) / (per_segment + 1)
    r = np.diff(t)[:, None] * frac[None, :]                     # segments × per_segment
    tm = (t[:-1, None] + r).ravel()
    coeffs = interpolate(out, "quintic").coeffs                  # segments × 6 × nv
    # every segment's samples at once: Σ_k c_k r^k (no search for the segment)
    q_out = np.matmul(r[:, :, None] ** np.arange(coeffs.shape[1]), coeffs).reshape(len(tm), -1)
    s = np.clip(smoothed(lw, w, tm, w2, orders=1)[0], path.pp.breaks[0] - lw.origin, lw.s[-1])
    q_path = path.positions(s + lw.origin)
    return float(np.max(np.abs(q_out - q_path)))


def switch_window(dynamics, path: Path, grid: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """The windows that spread every jump of q̈ (over the jerk limit) and of τ (over the
    effort rate limit) between neighbouring grid steps: the starting widths, before the exact
    check (0 without such limits)."""
    lim = dynamics.model.limits
    if not (np.any(np.isfinite(lim.jerk)) or np.any(np.isfinite(lim.effort_rate))):
        return 0.0, 0.0
    mid = 0.5 * (grid[:-1] + grid[1:])
    xm = 0.5 * (x[:-1] + x[1:])
    lw = law(grid, x)
    q, d1, d2 = path.derivatives(mid)
    acc = d2 * xm[:, None] + d1 * lw.u[:, None]
    jerk = rate = 0.0
    jumps = np.abs(np.diff(acc, axis=0))
    if np.any(np.isfinite(lim.jerk)) and len(jumps):
        jerk = float(np.max(jumps / lim.jerk))
    if np.any(np.isfinite(lim.effort_rate)) and len(jumps):
        tau = dynamics.rnea_batch(q, d1 * np.sqrt(xm)[:, None], acc)
        rate = float(np.max(np.abs(np.diff(tau, axis=0)) / lim.effort_rate))
    return jerk, rate
