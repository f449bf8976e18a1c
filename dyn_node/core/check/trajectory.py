"""Joint trajectories: validation by ros2_control's rules, and interpolation as it executes them.

ros2_control's joint_trajectory_controller interpolates each segment with a quintic polynomial
when waypoints carry positions, velocities and accelerations, a cubic when they carry positions
and velocities, and linearly when they carry positions only; the feasibility check judges
exactly that (:mod:`dyn_node.core.check.execution`). ``"spline"`` (a C² cubic spline through
positions-only waypoints, zero velocity at both ends) is the retimer's path geometry only.

Times are seconds from the trajectory's start (time_from_start); arrays are in model joint order.
"""
from __future__ import annotations

import difflib
from collections import Counter
from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np

from dyn_node.errors import TrajectoryError
from dyn_node.io.text import escape, name_list

Interpolation = Literal["quintic", "cubic", "spline", "linear"]


@dataclass(frozen=True)
class Trajectory:
    """A validated trajectory in model order: times (N,) s; positions, velocities, accelerations N×nv."""

    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray | None = None
    accelerations: np.ndarray | None = None
    #: N×2 bool, per point whether its velocities and its accelerations were given (a message may
    #: leave them empty at some points; those rows of the arrays are then 0); None: as the
    #: arrays say, for every point. joint_trajectory_controller picks each segment's
    #: interpolation from the fields at its two ends (:mod:`dyn_node.core.check.execution`).
    fields: np.ndarray | None = None

    @property
    def n_points(self) -> int:
        return len(self.times)

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    @property
    def jtc_interpolation(self) -> Interpolation:
        """How ros2_control's joint_trajectory_controller interpolates it: quintic with velocities
        and accelerations, cubic with velocities, linear with positions only."""
        if self.velocities is not None and self.accelerations is not None:
            return "quintic"
        if self.velocities is not None:
            return "cubic"
        return "linear"

    def point_fields(self) -> tuple[np.ndarray, np.ndarray]:
        """Per point, whether it carries velocities and whether it carries accelerations."""
        if self.fields is not None:
            return self.fields[:, 0].copy(), self.fields[:, 1].copy()
        n = self.n_points
        return np.full(n, self.velocities is not None), np.full(n, self.accelerations is not None)

    @property
    def natural_interpolation(self) -> Interpolation:
        """:attr:`jtc_interpolation`, except positions-only → the C² spline: the retimer's path
        through untimed or positions-only waypoints. Not what the controller executes (it
        interpolates positions linearly): the check judges that
        (:mod:`dyn_node.core.check.execution`)."""
        mode = self.jtc_interpolation
        return "spline" if mode == "linear" else mode


def check_joint_names(model_joints: Sequence[str], names: Sequence[str], *,
                      ignored_joints: Sequence[str] = (), what: str) -> list[str]:
    """``names`` as a list, once it names every model joint exactly once and nothing but model
    or ``ignored_joints``; otherwise :class:`TrajectoryError` naming the problem (``what``: the
    message's kind, for the text)."""
    names = list(names)
    if not names:
        raise TrajectoryError(f"{what} has no joint names", code="empty_names")
    if len(set(names)) != len(names):
        dups = sorted(n for n, c in Counter(names).items() if c > 1)
        raise TrajectoryError(f"duplicate joint names: {name_list(dups)}", code="duplicate_names")
    known = set(model_joints) | set(ignored_joints)
    unknown = [n for n in names if n not in known]
    given = set(names)
    missing = [n for n in model_joints if n not in given]
    if unknown:
        raise TrajectoryError(f"joints not in the model: {name_list(unknown)}"
                              + _missing_and_close(unknown, missing, what), code="unknown_joints")
    if missing:
        raise TrajectoryError(f"model joints missing from the {what}: {name_list(missing)}",
                              code="missing_joints")
    return names


def _missing_and_close(unknown: Sequence[str], missing: Sequence[str], what: str) -> str:
    """``; model joints missing from the <what>: …`` and, for the first few unknown names, the
    closest missing joint (as the limits parser suggests a key)."""
    if not missing:
        return ""
    hints = []
    for n in unknown[:5]:
        close = difflib.get_close_matches(str(n)[:200], missing, n=1, cutoff=0.6)
        if close:
            hints.append(f"'{escape(str(n))}' → '{escape(close[0])}'")
    return (f"; model joints missing from the {what}: {name_list(missing)}"
            + (f" (did you mean {', '.join(hints)}?)" if hints else ""))


def _rows_matrix(rows: Sequence[Sequence[float]], field: str, required: bool, nj: int, n_pts: int,
                 given: dict[str, np.ndarray]) -> np.ndarray | None:
    """Rows of any lengths (validate_trajectory's general case): None when an optional field is
    empty at every point; else the N×nj matrix (an empty point's row zeros, ``given[field]`` says
    which points had it). Each point's field empty or one per joint, as the controller validates
    it (joint_trajectory_controller.cpp validate_trajectory_point_field, allow_empty)."""
    lengths = {len(r) for r in rows}
    if not required and lengths == {0}:
        return None
    for i, r in enumerate(rows):
        if len(r) != nj and (required or len(r)):
            raise TrajectoryError(f"point {i}: {len(r)} {field} for {nj} joints", code="length_mismatch")
    given[field] = np.array([len(r) > 0 for r in rows])
    return np.asarray([r if len(r) else [0.0] * nj for r in rows], dtype=float).reshape(n_pts, nj)


def validate_trajectory(model_joints: Sequence[str], names: Sequence[str],
                        times: Sequence[float], positions: Sequence[Sequence[float]],
                        velocities: Sequence[Sequence[float]] | None = None,
                        accelerations: Sequence[Sequence[float]] | None = None,
                        min_points: int = 2, ignored_joints: Sequence[str] = (),
                        efforts: Sequence[Sequence[float]] | None = None) -> Trajectory:
    """Check a trajectory as joint_trajectory_controller does, plus dyn_node's own rules.

    ``velocities``/``accelerations`` are per-point sequences, each empty or one value per name,
    consistently across points; ``efforts`` (not used: dyn_node computes the torque) each empty or
    one per name, as the controller requires. Names in ``ignored_joints`` (the model's locked joints) may appear
    and their values are dropped, as for joint_states. Raises :class:`TrajectoryError` naming the
    first problem found.
    """
    names = check_joint_names(model_joints, names, ignored_joints=ignored_joints, what="trajectory")
    n_pts = len(times)
    if n_pts == 0:
        raise TrajectoryError("trajectory has no points", code="empty_points")
    if n_pts < min_points:
        raise TrajectoryError(f"trajectory has {n_pts} point(s); at least {min_points} are needed "
                              "to check motion", code="too_few_points")
    if len(positions) != n_pts:
        raise TrajectoryError(f"{len(positions)} position rows for {n_pts} times", code="length_mismatch")
    nj = len(names)
    order = np.array([names.index(n) for n in model_joints])
    for i, r in enumerate(() if efforts is None else efforts):
        if len(r) and len(r) != nj:
            raise TrajectoryError(f"point {i}: {len(r)} effort for {nj} joints (joint_trajectory_"
                                  "controller refuses an effort neither empty nor one per joint)",
                                  code="length_mismatch")

    given: dict[str, np.ndarray] = {}

    def matrix(rows: Sequence[Sequence[float]] | None, field: str, required: bool) -> np.ndarray | None:
        if rows is None:
            if required:
                raise TrajectoryError(f"trajectory has no {field}", code="length_mismatch")
            return None
        if not required and not len(rows):
            return None
        if len(rows) != n_pts:
            raise TrajectoryError(f"{len(rows)} {field} rows for {n_pts} times", code="length_mismatch")
        if isinstance(rows, np.ndarray) and rows.ndim == 2 and rows.shape[1] == nj > 0:
            # one N×nj array (a message's rows, convert.trajectory_arrays): every point full, the
            # same checks without a Python loop over the rows (~1 ms of a 100-point gate goal)
            given[field] = np.ones(n_pts, dtype=bool)
            m = np.asarray(rows, dtype=float)
        else:
            m = _rows_matrix(rows, field, required, nj, n_pts, given)
            if m is None:
                return None
        if not np.all(np.isfinite(m)):
            i, j = np.argwhere(~np.isfinite(m))[0]
            raise TrajectoryError(f"point {i}: {field} of {names[j]} is {m[i, j]}", code="non_finite")
        return m[:, order]

    t = np.asarray(times, dtype=float)
    if not np.all(np.isfinite(t)):
        raise TrajectoryError("time_from_start is not finite", code="non_finite")
    if t[0] < 0:
        raise TrajectoryError(f"first time_from_start is negative ({t[0]} s)", code="bad_times")
    steps = np.diff(t)
    if np.any(steps <= 0):
        i = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise TrajectoryError(f"time_from_start not strictly increasing at point {i} "
                              f"({t[i - 1]:.6g} s then {t[i]:.6g} s)", code="bad_times")
    p = matrix(positions, "positions", True)
    v = matrix(velocities, "velocities", False) if velocities is not None else None
    a = matrix(accelerations, "accelerations", False) if accelerations is not None else None
    if a is not None and v is None:
        raise TrajectoryError("accelerations given without velocities", code="length_mismatch")
    gv = given.get("velocities", np.full(n_pts, v is not None))
    ga = given.get("accelerations", np.full(n_pts, a is not None))
    if np.any(ga & ~gv):
        # no branch of the controller's spline interpolates it (trajectory.cpp
        # interpolate_between_points, lines 315-406 at jazzy ed360c9)
        i = int(np.flatnonzero(ga & ~gv)[0])
        raise TrajectoryError(f"point {i}: accelerations given without velocities",
                              code="length_mismatch")
    mixed = (v is not None and not gv.all()) or (a is not None and not ga.all())
    return Trajectory(times=t, positions=p, velocities=v, accelerations=a,
                      fields=np.column_stack([gv, ga]) if mixed else None)


@dataclass(frozen=True)
class PiecewisePolynomial:
    """Per-segment polynomials: ``coeffs[s, k, j]`` multiplies (t − breaks[s])**k for joint j.

    Evaluation holds the first and last positions outside [breaks[0], breaks[-1]] with zero
    derivatives, as a controller holds the last point after the trajectory ends.
    """

    breaks: np.ndarray
    coeffs: np.ndarray

    def evaluate(self, t: np.ndarray | float, orders: int = 4) -> tuple[np.ndarray, ...]:
        """(q, q̇, q̈, q⃛) at times t (M,), each M×nv; the first ``orders`` of them only (the
        retimer's rounds need one to three)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        seg = np.clip(np.searchsorted(self.breaks, t, side="right") - 1, 0, len(self.coeffs) - 1)
        s = np.clip(t - self.breaks[seg], 0.0, self.breaks[seg + 1] - self.breaks[seg])[:, None]
        c = self.coeffs[seg]  # M × (deg+1) × nv
        deg = c.shape[1] - 1
        out = []
        for d in range(orders):
            acc = np.zeros((len(t), c.shape[2]))
            for k in range(deg, d - 1, -1):
                fac = float(np.prod(np.arange(k - d + 1, k + 1))) if d else 1.0
                acc = acc * s + fac * c[:, k, :]
            out.append(acc)
        outside = (t < self.breaks[0]) | (t > self.breaks[-1])
        if np.any(outside):
            for d in range(1, orders):
                out[d][outside] = 0.0
        return tuple(out)


def _quintic(p0, v0, a0, p1, v1, a1, T):
    T = T[:, None]
    c3 = (20 * (p1 - p0) - (8 * v1 + 12 * v0) * T - (3 * a0 - a1) * T**2) / (2 * T**3)
    c4 = (30 * (p0 - p1) + (14 * v1 + 16 * v0) * T + (3 * a0 - 2 * a1) * T**2) / (2 * T**4)
    c5 = (12 * (p1 - p0) - 6 * (v1 + v0) * T + (a1 - a0) * T**2) / (2 * T**5)
    return np.stack([p0, v0, a0 / 2, c3, c4, c5], axis=1)


def _cubic(p0, v0, p1, v1, T):
    T = T[:, None]
    c2 = (3 * (p1 - p0) - (2 * v0 + v1) * T) / T**2
    c3 = (2 * (p0 - p1) + (v0 + v1) * T) / T**3
    return np.stack([p0, v0, c2, c3], axis=1)


def clamped_spline_velocities(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Knot velocities of the C² cubic spline through (t, p) with zero velocity at both ends."""
    n = len(t)
    v = np.zeros_like(p)
    if n <= 2:
        return v
    h = np.diff(t)
    # Tridiagonal system for interior knots (Thomas algorithm: O(n), fine for 100k points).
    lower = h[1:]                  # coefficient of v[i-1] in row i (i = 1..n-2)
    diag = 2 * (h[:-1] + h[1:])
    upper = h[:-1]                 # coefficient of v[i+1]
    rhs = 3 * (h[1:, None] * (p[1:-1] - p[:-2]) / h[:-1, None]
               + h[:-1, None] * (p[2:] - p[1:-1]) / h[1:, None])
    m = n - 2
    cp = np.empty(m)
    dp = np.empty_like(rhs)
    cp[0] = upper[0] / diag[0]
    dp[0] = rhs[0] / diag[0]
    for i in range(1, m):
        den = diag[i] - lower[i] * cp[i - 1]
        cp[i] = upper[i] / den
        dp[i] = (rhs[i] - lower[i] * dp[i - 1]) / den
    x = np.empty_like(rhs)
    x[-1] = dp[-1]
    for i in range(m - 2, -1, -1):
        x[i] = dp[i] - cp[i] * x[i + 1]
    v[1:-1] = x
    return v


def interpolate(traj: Trajectory, mode: Interpolation | None = None) -> PiecewisePolynomial:
    """Piecewise polynomial through the waypoints; ``mode`` defaults to the natural one."""
    mode = mode or traj.natural_interpolation
    t, p = traj.times, traj.positions
    if len(t) == 1:  # hold a single point
        return PiecewisePolynomial(np.array([t[0], t[0] + 1e-9]), p[None, :1, :].copy())
    T = np.diff(t)
    p0, p1 = p[:-1], p[1:]
    if mode == "linear":
        coeffs = np.stack([p0, (p1 - p0) / T[:, None]], axis=1)
    elif mode == "spline":
        v = clamped_spline_velocities(t, p)
        coeffs = _cubic(p0, v[:-1], p1, v[1:], T)
    elif mode == "cubic":
        if traj.velocities is None:
            raise TrajectoryError("cubic interpolation needs velocities", code="length_mismatch")
        v = traj.velocities
        coeffs = _cubic(p0, v[:-1], p1, v[1:], T)
    elif mode == "quintic":
        if traj.velocities is None or traj.accelerations is None:
            raise TrajectoryError("quintic interpolation needs velocities and accelerations",
                                  code="length_mismatch")
        v, a = traj.velocities, traj.accelerations
        coeffs = _quintic(p0, v[:-1], a[:-1], p1, v[1:], a[1:], T)
    else:
        raise ValueError(f"unknown interpolation {mode!r}")
    return PiecewisePolynomial(breaks=t.copy(), coeffs=coeffs)


def from_current_state(traj: Trajectory, positions: np.ndarray, velocities: np.ndarray) -> Trajectory:
    """``traj`` as joint_trajectory_controller executes it when its first point lies ahead
    (``time_from_start`` > 0): the robot's current state prepended as a point at t = 0 with the
    measured q and q̇ and q̈ = 0, so the first segment runs from that state to the first point.

    The prepended point carries what every point carries: velocities always (cubic), and
    accelerations (0) when the points have them (quintic). A positions-only trajectory keeps
    the knot velocities of its own C² spline (:func:`clamped_spline_velocities`, computed
    without the prepended point): the points after the first move exactly as without a start
    state, and the start segment is the cubic from the measured velocity to the spline's.
    """
    t = traj.times
    if not t[0] > 0:
        raise ValueError("the first point is at t = 0: there is no segment from the current state")
    q0 = np.asarray(positions, dtype=float).reshape(1, -1)
    v0 = np.asarray(velocities, dtype=float).reshape(1, -1)
    if q0.shape[1] != traj.positions.shape[1] or v0.shape != q0.shape:
        raise ValueError(f"current state has {q0.shape[1]} positions and {v0.shape[1]} velocities "
                         f"for {traj.positions.shape[1]} joints")
    vel = traj.velocities if traj.velocities is not None else clamped_spline_velocities(t, traj.positions)
    acc = None if traj.accelerations is None else np.vstack([np.zeros_like(q0), traj.accelerations])
    return Trajectory(times=np.concatenate(([0.0], t)), positions=np.vstack([q0, traj.positions]),
                      velocities=np.vstack([v0, vel]), accelerations=acc)


#: When the sample budget makes segments coarser, each keeps at least the fewer of
#: MIN_SEGMENT_STEPS steps (a segment is one polynomial, derivatives of degree ≤ 4, whose peaks
#: that many uniform steps resolve) and steps of MAX_STEP_GROWTH × the sample period; a
#: trajectory that cannot give every segment that much is refused as too long to check.
MIN_SEGMENT_STEPS = 32
MAX_STEP_GROWTH = 4.0


def segment_steps(times: np.ndarray, period: float, max_samples: int,
                  min_steps: np.ndarray | None = None) -> np.ndarray:
    """Steps per segment: ⌈T/period⌉ each and at least ``min_steps`` (per segment; default 1:
    a segment shorter than the period is sampled inside too); when the samples (steps + 1 per
    segment) would exceed ``max_samples``, the segments with most steps give up steps first:
    all are capped at the largest count that fits, none below its floor (see
    :data:`MIN_SEGMENT_STEPS`; ``min_steps`` is a wish, not a floor), so a short segment keeps
    its resolution however long the rest is. Raises :class:`TrajectoryError` (``too_long``)
    when the floors alone do not fit."""
    T = np.diff(times)
    least = np.ones(len(T)) if min_steps is None else np.maximum(1.0, min_steps)
    with np.errstate(over="ignore", invalid="ignore"):
        want = np.maximum(least, np.ceil(T / period - 1e-9))
        floor = np.minimum(want, np.minimum(float(MIN_SEGMENT_STEPS),
                                            np.maximum(1.0, np.ceil(T / (MAX_STEP_GROWTH * period)))))
    budget = max_samples - len(T)
    if want.sum() <= budget:
        return want.astype(np.int64)
    if floor.sum() > budget:
        raise TrajectoryError(
            f"trajectory too long to check: {len(T)} segments over {float(times[-1] - times[0]):.6g} s "
            f"need {want.sum():.3g} samples at {period * 1e3:.3g} ms, and the bound of {max_samples} "
            f"samples cannot give each segment {MIN_SEGMENT_STEPS} steps or steps of "
            f"{MAX_STEP_GROWTH:g}× that period (raise max_samples or split the trajectory)",
            code="too_long")
    lo, hi = 1, int(min(want.max(), budget))     # the largest cap c whose counts fit
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if np.maximum(floor, np.minimum(want, mid)).sum() <= budget:
            lo = mid
        else:
            hi = mid - 1
    return np.maximum(floor, np.minimum(want, lo)).astype(np.int64)
