"""The geometric path a retiming follows, and the input checks at the boundary.

A timed trajectory's path is the curve the feasibility check interpolates for it (its natural
interpolation, :func:`dyn_node.core.check.trajectory.interpolate`), parameterised by its own time s.
Untimed waypoints (every ``time_from_start`` zero) get the C² cubic spline through them with
zero velocity at both ends, parameterised by the cumulative chord length (the ∞-norm of each
step: rad or m), which is the same spline the check assumes for a positions-only trajectory.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dyn_node.core.check.trajectory import PiecewisePolynomial, Trajectory, interpolate
from dyn_node.errors import TrajectoryError


@dataclass(frozen=True)
class Path:
    """q(s) for s in [0, length]; ``nominal``: a trajectory whose natural interpolation is
    exactly this curve with time = s (the input itself when it is timed)."""

    pp: PiecewisePolynomial
    nominal: Trajectory
    untimed: bool

    @property
    def length(self) -> float:
        return float(self.pp.breaks[-1] - self.pp.breaks[0])

    @property
    def nv(self) -> int:
        return int(self.pp.coeffs.shape[2])

    def derivatives(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, q', q'') at path positions s (M,), each M×nv."""
        return self.pp.evaluate(np.clip(s, self.pp.breaks[0], self.pp.breaks[-1]), orders=3)

    def positions(self, s: np.ndarray) -> np.ndarray:
        return self.pp.evaluate(np.clip(s, self.pp.breaks[0], self.pp.breaks[-1]), orders=1)[0]


def validate_input(traj: Trajectory) -> None:
    """:class:`TrajectoryError` for what no retiming can take: too few points, non-finite
    values, times that are neither all zero (untimed) nor strictly increasing from ≥ 0."""
    if traj.n_points < 2:
        raise TrajectoryError(f"trajectory has {traj.n_points} point(s); at least 2 are needed "
                              "to retime", code="too_few_points")
    for name, arr in (("time_from_start", traj.times), ("positions", traj.positions),
                      ("velocities", traj.velocities), ("accelerations", traj.accelerations)):
        if arr is not None and not np.all(np.isfinite(arr)):
            raise TrajectoryError(f"{name} not finite", code="non_finite")
    t = traj.times
    if is_untimed(traj):
        return
    if t[0] < 0 or np.any(np.diff(t) <= 0):
        raise TrajectoryError("time_from_start must be all zero (untimed waypoints) or strictly "
                              "increasing from ≥ 0", code="bad_times")


def is_untimed(traj: Trajectory) -> bool:
    return bool(np.all(traj.times == 0.0))


def is_still(traj: Trajectory) -> bool:
    """Every point at the first point's position: nothing to move."""
    return bool(np.all(traj.positions == traj.positions[0]))


def build_path(traj: Trajectory) -> Path:
    """The path of a validated, not still trajectory (see the module docstring)."""
    if not is_untimed(traj):
        return Path(pp=interpolate(traj, traj.natural_interpolation), nominal=traj, untimed=False)
    P = traj.positions
    keep = np.concatenate(([True], np.any(np.diff(P, axis=0) != 0.0, axis=1)))
    P = P[keep]                                   # repeated waypoints add nothing to the curve
    s = np.concatenate(([0.0], np.cumsum(np.max(np.abs(np.diff(P, axis=0)), axis=1))))
    nominal = Trajectory(times=s, positions=P)    # positions only: the clamped C² spline
    return Path(pp=interpolate(nominal, "spline"), nominal=nominal, untimed=True)



#: a waypoint passed at most this share of its neighbourhood's speed (∞-norm of q') is a stop:
#: the path turns back there or nearly (a cusp), which no parameterisation by arc length
#: resolves on a grid, and stopping costs next to nothing against passing that slowly
NEAR_STOP = 1e-2


def stops(path: Path) -> np.ndarray:
    """Interior knots where the path stops or nearly (:data:`NEAR_STOP`): waypoints at rest
    with quintic segments (q' = q'' = 0), turns back of a spline (q' = 0 by symmetry) and
    waypoints passed at a tiny share of the neighbouring speeds; the path is (nearly) singular
    there and may turn back."""
    b = path.pp.breaks
    if len(b) < 3:
        return np.zeros(0, dtype=int)
    knot = np.max(np.abs(path.derivatives(b)[1]), axis=1)
    mid = np.max(np.abs(path.derivatives(0.5 * (b[1:] + b[:-1]))[1]), axis=1)
    near = np.maximum(np.maximum(mid[:-1], mid[1:]), np.maximum(knot[:-2], knot[2:]))
    return np.flatnonzero(knot[1:-1] <= NEAR_STOP * near) + 1


def pieces(path: Path, also: np.ndarray | None = None) -> list[Path]:
    """The path cut at its :func:`stops` (and at the knots ``also``): each piece the same
    polynomials between two of them (a path of its own, from rest to rest)."""
    inner = set(stops(path).tolist()) | set(() if also is None else np.asarray(also).tolist())
    cuts = [0, *sorted(inner), len(path.pp.breaks) - 1]
    nom = path.nominal
    out = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        pp = PiecewisePolynomial(path.pp.breaks[a:b + 1].copy(), path.pp.coeffs[a:b].copy())
        sl = slice(a, b + 1) if len(nom.times) == len(path.pp.breaks) else slice(None)
        sub = Trajectory(times=nom.times[sl], positions=nom.positions[sl],
                         velocities=None if nom.velocities is None else nom.velocities[sl],
                         accelerations=None if nom.accelerations is None else nom.accelerations[sl])
        out.append(Path(pp=pp, nominal=sub, untimed=path.untimed))
    return out


@dataclass(frozen=True)
class _Breaks:
    breaks: np.ndarray


class ArcPath:
    """``path`` by its arc length ℓ (2-norm of q', rad or m): where q' vanishes at an end the
    path is singular in s (q' ∝ (s − s₀)²), but regular in ℓ (|dq/dℓ| = 1), so TOPP-RA's grid
    and the smoothing window see a path that starts and stops like any other.

    q_ℓ = q'/|q'|, q_ℓℓ = (q'' − q_ℓ (q_ℓ·q''))/|q'|²; s(ℓ) from a table of ℓ(s)
    (cumulative Simpson), inverted by cubic Hermite interpolation with the exact slope
    ds/dℓ = 1/|q'| at the table's points, and in a cell next to q' = 0 (infinite slope) by
    the power law ℓ − ℓ₀ ∝ (s − s₀)^p whose p the cell's ends give (p = |q'|·Δs/Δℓ: 2 where q'
    vanishes linearly, 3 at a stop's double zero). The points stay exactly on the path
    whatever its error, and q(s(ℓ)) agrees with q_ℓ and q_ℓℓ to O(h⁴), so the controller's
    quintic through points that carry them does not swing between them (a linear inverse,
    piecewise constant ds/dℓ, made it overshoot the points' acceleration by up to 1 %).
    """

    def __init__(self, path: Path, samples: int = 2001):
        self.base = path
        # closer near the ends (spacing ∝ distance to them, smoothstep), where q' → 0 and
        # s(ℓ) is least smooth
        u = np.linspace(0.0, 1.0, samples)
        s0, s1 = path.pp.breaks[0], path.pp.breaks[-1]
        s = s0 + (s1 - s0) * u * u * (3 - 2 * u)
        s[-1] = s1
        speed = np.linalg.norm(path.pp.evaluate(s, orders=2)[1], axis=1)
        mid = np.linalg.norm(path.pp.evaluate(0.5 * (s[1:] + s[:-1]), orders=2)[1], axis=1)
        self._s = s
        self._l = np.concatenate(([0.0], np.cumsum(np.diff(s) * (speed[:-1] + 4 * mid
                                                                   + speed[1:]) / 6)))
        # q' vanishes at an end to rounding (1e-17, not 0): a Hermite cell there would swing
        # by its huge slope, so it counts as zero
        self._speed = np.where(speed > 1e-9 * speed.max(), speed, 0.0)
        self.pp = _Breaks(np.array([0.0, float(self._l[-1])]))
        self.nominal, self.untimed = path.nominal, path.untimed

    @property
    def length(self) -> float:
        return float(self._l[-1])

    @property
    def nv(self) -> int:
        return self.base.nv

    def derivatives(self, ell: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ell = np.clip(np.atleast_1d(np.asarray(ell, dtype=float)), 0.0, self._l[-1])
        # nudged inside: at the ends q' = 0 exactly and the direction is its limit
        eps = 1e-9 * self._l[-1]
        inside = (ell >= eps) & (ell <= self._l[-1] - eps)
        s = self._s_of(np.where(inside, ell, np.clip(ell, eps, self._l[-1] - eps)))
        q, d1, d2 = self.base.derivatives(s)
        if not inside.all():
            q[~inside] = self.positions(ell[~inside])
        n = np.linalg.norm(d1, axis=1, keepdims=True)
        n = np.maximum(n, 1e-300)
        t = d1 / n
        q2 = (d2 - t * np.sum(t * d2, axis=1, keepdims=True)) / n**2
        return q, t, q2

    def arc_of(self, s: np.ndarray) -> np.ndarray:
        """ℓ at the base path's s (from the table: linear between its points)."""
        return np.interp(s, self._s, self._l)

    def positions(self, ell: np.ndarray) -> np.ndarray:
        ell = np.clip(np.atleast_1d(np.asarray(ell, dtype=float)), 0.0, self._l[-1])
        return self.base.positions(self._s_of(ell))

    def _s_of(self, ell: np.ndarray) -> np.ndarray:
        """s(ℓ) for ℓ in [0, length] (the class docstring's inverse)."""
        L, S, v = self._l, self._s, self._speed
        k = np.clip(np.searchsorted(L, ell, side="right") - 1, 0, len(L) - 2)
        h, ds = L[k + 1] - L[k], S[k + 1] - S[k]
        v0, v1 = v[k], v[k + 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.clip(np.where(h > 0, (ell - L[k]) / h, 0.0), 0.0, 1.0)
            # Hermite with the slopes ds/dℓ = 1/|q'| (times the cell's Δℓ)
            t2, t3 = t * t, t * t * t
            out = (S[k] * (2 * t3 - 3 * t2 + 1) + (t3 - 2 * t2 + t) * h / v0
                   + S[k + 1] * (-2 * t3 + 3 * t2) + (t3 - t2) * h / v1)
            # next to q' = 0: ℓ − ℓ₀ ∝ (s − s₀)^p, p from the other end's |q'|
            start = (v0 == 0) & (v1 > 0)
            end = (v1 == 0) & (v0 > 0)
            out = np.where(start, S[k] + ds * t ** (h / (v1 * ds)), out)
            out = np.where(end, S[k + 1] - ds * (1 - t) ** (h / (v0 * ds)), out)
        return np.where((v0 == 0) & (v1 == 0), S[k] + t * ds, out)
