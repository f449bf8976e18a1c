"""What every candidate answer of the retimer passes before it may be returned, and the uniform
stretch candidate.

:func:`judge`: the exact check (:func:`~dyn_node.core.check.feasibility.check_trajectory`, the
retimer's options and start). It evaluates every executed piece's kinematic extrema exactly and
samples the torque kinds inside every piece (issues 36 and 39), so a segment whose polynomial
swings between two passing points (a velocity reversal inside 125 µs) is its violation; the
screen between points that stood in for that before cost more than the check itself (measured:
0.11 s of a 0.45 s retime of a 10 s path) and found nothing the check passed on the bench's
panels but two tiny moves' effort rate at 99.7 % of the limit.
"""
from __future__ import annotations

import numpy as np

from dyn_node.core.check.constraints import Violation
from dyn_node.core.check.feasibility import FeasibilityOptions, FeasibilityResult, check_trajectory
from dyn_node.core.check.trajectory import Trajectory, interpolate
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.errors import TrajectoryError
from dyn_node.retime import timing
from dyn_node.retime.path import Path

#: the least growth of a stretch that the margin asks for more of (relative)
MIN_GROWTH = 1e-6
#: stretches tried past the pads when the margin asks for more (each sized by the last one's ratio)
MARGIN_TRIES = 4
#: how far over the margin a stretch may reach, relative (velocity at 1/1.005 is 0.995 × 1.00002)
MARGIN_RTOL = 1e-4
#: widenings of a stretched cubic's averaging window at most (:func:`_averaged_judged`)
WIDEN_TRIES = 2
#: the stretch's factors over the check's time scale, tried in turn (docs/retime.md: every
#: answer ≤ 1.005 × the time scale × the input's duration)
STRETCH_PADS = (1.001, 1.005)


def judge(dynamics: Dynamics, out: Trajectory, options: FeasibilityOptions,
          start) -> tuple[FeasibilityResult, list[Violation]]:
    """The exact check of ``out``: (the check, its violations); the answer may be returned
    only when the check is feasible."""
    res = check_trajectory(dynamics, out, options, start=start)
    return res, ([] if res.feasible else list(res.violations))


#: the kinds the output points carry (q̇, q̈): an overshoot of one while every point is
#: within the limit is the controller's quintic between points (third-order kinds jump at
#: every knot and are the smoothing window's to fix)
POINT_KINDS = {"velocity": "velocities", "acceleration": "accelerations"}
#: how far over its limit such a peak may be and still count as the quintic's rounding
BETWEEN_MAX = 1.05


def between(dynamics: Dynamics, out: Trajectory, found: list[Violation]) -> bool:
    """True when every one of the exact check's ``found`` is a small overshoot (≤
    :data:`BETWEEN_MAX`) of a kind the points carry while every point of that joint is within
    the limit: the quintic through them rounds a corner of the law (a switch of s̈ that the
    windows ramp over a few periods) past it. Finer points cure that; a cap would only move
    the corner (measured: test_retime_start's triangle, 1.4 % over at the switch, then caps
    moved it round for 30 rounds)."""
    names = list(dynamics.model.limits.names)
    for v in found:
        field = POINT_KINDS.get(v.kind)
        values = getattr(out, field) if field else None
        if (values is None or v.joint not in names or not v.limit > 0
                or abs(v.peak_value) / v.limit > BETWEEN_MAX
                or np.max(np.abs(values[:, names.index(v.joint)])) > v.limit):
            return False
    return bool(found)


def stretch(dynamics: Dynamics, path: Path, traj: Trajectory, k: float,
            options: FeasibilityOptions, start, period: float, moving_start: bool,
            dense, tolerance: float, margin: float = 1.0) -> dict | None:
    """The input stretched by the check's time scale × :data:`STRETCH_PADS`, further when its
    worst ratio is over :func:`stretch_share` (``margin``: the retimer's limit margin, which a
    stretched answer keeps like the optimal one, so a controller keeps its feedback room), resampled as
    quintic points on the path (s = t/k; positions, velocities, accelerations), else, when the
    path's acceleration jumps at a knot (cubic points) so that no quintic follows it, the
    input's own points stretched (their interpolation is the one the check's k is of); each
    judged (:func:`judge`). With a moving start state the input's own points only."""
    from dyn_node.core.check.start_segment import stretched

    k = max(k, 1e-9) if k > 0 else 1.0
    cubic = traj.velocities is not None and traj.accelerations is None
    # a cubic's q̈ jumps at its knots: averaged first (a quintic that follows the path does not)
    hows = ([] if moving_start else ["averaged", "path"] if cubic else ["path"])
    hows += ["own"] if traj.velocities is not None else []
    share = stretch_share(margin)
    tries = [(pad, how) for how in hows for pad in (*STRETCH_PADS, *[None] * MARGIN_TRIES)]
    needs: dict[str, float] = {}
    for pad, how in tries:
        if pad is None:  # past the pads: as far as the last try said the margin needs
            if how not in needs or needs[how] <= STRETCH_PADS[-1]:
                continue
            pad = needs[how]
        elif needs.get(how, 0.0) > pad:
            continue         # the smaller pad's candidate needs more than this pad gives
        kk = k * pad
        if how == "own":
            out, dev = stretched(traj, kk), 0.0
        elif how == "averaged":
            got = _averaged_judged(dynamics, stretched(traj, kk), period, tolerance, options,
                                   start)
            if got is None:
                continue
            out, dev, res, over = got
        else:
            grid = np.linspace(path.pp.breaks[0], path.pp.breaks[-1], 2)
            lw = timing.law(grid, np.full(2, 1.0 / kk**2))
            out, dev = dense(path, lw, 0.0, period)
            if out is None:
                continue
        if how != "averaged":
            try:
                res, over = judge(dynamics, out, options, start)
            except TrajectoryError:
                continue
        if res.feasible and res.worst_ratio <= share:
            return dict(trajectory=out, check=res, method="uniform", deviation=dev)
        # over the share: velocity's ratio falls as 1/k, every other kind's at least as fast
        # once its static part is below the share (a few tries cover the rest)
        grow = res.time_scale if not res.feasible else res.worst_ratio / share * (1.0 + MIN_GROWTH)
        needs[how] = pad * max(grow, 1.0 + MIN_GROWTH)
    return None


def _averaged_judged(dynamics: Dynamics, traj: Trajectory, period: float, tolerance: float,
                     options: FeasibilityOptions, start) -> tuple | None:
    """The stretched cubic averaged (:func:`averaged`) and judged, its window widened (at most
    :data:`WIDEN_TRIES` times, by the worst ratio) while only jerk or effort rate is over:
    the knots' ramps at 90 % of those limits leave nothing for the motion's own rate of τ
    beside them (issue 39's 250-waypoint path: 1.09–1.11× at 1.001 and 1.005 × k).
    (out, deviation, check, over) or None."""
    widen = 1.0
    for _ in range(WIDEN_TRIES + 1):
        out, dev = averaged(dynamics, traj, period, tolerance, widen=widen)
        if out is None:
            return None
        try:
            res, over = judge(dynamics, out, options, start)
        except TrajectoryError:
            return None
        found = over
        if not found or any(v.kind not in ("jerk", "effort_rate") for v in found):
            break
        widen *= min(1.5, max(abs(v.peak_value) / v.limit for v in found)) * 1.05
    return out, dev, res, over


def stretch_share(margin: float) -> float:
    """The largest ratio to a limit a stretched answer may reach: ``margin`` to 1e-4 relative
    (:data:`MARGIN_RTOL`, so dyn-check's 0.995 is kept by the last pad, 1.005 × k, as the
    optimal answer keeps its margin to TOPP-RA's grid)."""
    return min(1.0, float(margin) * (1.0 + MARGIN_RTOL))


def knot_window(dynamics: Dynamics, q: np.ndarray, v: np.ndarray, a_lo: np.ndarray,
                a_hi: np.ndarray, period: float) -> float:
    """The window that ramps each jump of q̈ (a_lo → a_hi at states q, v; rows) within 90 % of
    the jerk and effort-rate limits; at least two output periods."""
    lim = dynamics.model.limits
    W = 2 * period
    if not len(q):
        return W
    with np.errstate(divide="ignore", invalid="ignore"):
        if np.any(np.isfinite(lim.jerk)):
            r = np.where(np.isfinite(lim.jerk), np.abs(a_hi - a_lo) / (0.9 * lim.jerk), 0)
            W = max(W, float(np.nanmax(r)))
        if np.any(np.isfinite(lim.effort_rate)):
            dtau = np.abs(dynamics.rnea_batch(q, v, a_hi) - dynamics.rnea_batch(q, v, a_lo))
            r = np.where(np.isfinite(lim.effort_rate), dtau / (0.9 * lim.effort_rate), 0)
            W = max(W, float(np.nanmax(r)))
    return W


def averaged(dynamics: Dynamics, traj: Trajectory, period: float, tolerance: float,
             W: float | None = None, widen: float = 1.0) -> tuple[Trajectory | None, float]:
    """``traj`` (cubic points, already stretched) averaged over a moving window W in joint space,
    as quintic points every ≤ ``period``: q̄(t) = (1/W)∫_{t−W}^{t} q, held at its ends, so the
    motion starts and ends at rest and lasts W longer. Its velocity and acceleration are
    averages of the input's (within the same limits), and each jump of q̈ at a knot (the cubic
    is C¹ only: no quintic follows it) becomes a ramp of length W, W sized so that the jumps
    stay within 90 % of the jerk and effort-rate limits. (None, dev) when q̄ strays more than
    ``tolerance`` from the input's curve (measured at the window's centre). ``widen``: W × this
    (the knots' own window when W is not given)."""
    pp = interpolate(traj, traj.jtc_interpolation)
    b, c = pp.breaks, pp.coeffs
    if W is None:
        knots = b[1:-1]
        a_lo = pp.evaluate(np.maximum(knots - 1e-12 * (1 + abs(b[-1])), b[0]), orders=3)[2]
        q, v, a_hi = pp.evaluate(knots, orders=3)
        W = knot_window(dynamics, q, v, a_lo, a_hi, period) * widen
    # the antiderivative F of q, piece by piece (local coefficients c_k/(k+1), constants summed)
    deg = c.shape[1]
    C = np.zeros((c.shape[0], deg + 1, c.shape[2]))
    C[:, 1:, :] = c / np.arange(1, deg + 1)[None, :, None]
    h = np.diff(b)
    ends = np.einsum("sk,skj->sj", h[:, None] ** np.arange(deg + 1)[None, :], C)
    C[1:, 0, :] = np.cumsum(ends, axis=0)[:-1]
    q0, q1, F1 = traj.positions[0], traj.positions[-1], np.sum(ends, axis=0)

    def F(t):
        seg = np.clip(np.searchsorted(b, t, side="right") - 1, 0, len(h) - 1)
        r = np.clip(t - b[seg], 0.0, h[seg])[:, None]
        val = np.einsum("mk,mkj->mj", r ** np.arange(deg + 1)[None, :], C[seg])
        before, after = t < b[0], t > b[-1]
        val[before] = (q0 * (t[before] - b[0])[:, None])
        val[after] = F1 + q1 * (t[after] - b[-1])[:, None]
        return val

    def Q(t, order):
        out = pp.evaluate(t, orders=order + 1)[order]
        if order == 0:
            out[t < b[0]], out[t > b[-1]] = q0, q1
        return out

    total = b[-1] - b[0] + W
    n = max(2, int(np.ceil(total / period)) + 1)
    t = b[0] + np.linspace(0.0, total, n)
    P = (F(t) - F(t - W)) / W
    V = (Q(t, 0) - Q(t - W, 0)) / W
    A = (Q(t, 1) - Q(t - W, 1)) / W
    mid = np.linspace(b[0], b[-1] + W, 4 * n)
    dev = float(np.max(np.abs((F(mid) - F(mid - W)) / W - Q(mid - W / 2, 0))))
    if dev > tolerance:
        return None, dev
    return Trajectory(times=t - b[0], positions=P, velocities=V, accelerations=A), dev
