"""The geometric path a retiming follows, and the input checks at the boundary.

A timed trajectory's path is the curve the feasibility check interpolates for it (its natural
interpolation, :func:`dyn_node.core.trajectory.interpolate`), parameterised by its own time s.
Untimed waypoints (every ``time_from_start`` zero) get the C² cubic spline through them with
zero velocity at both ends, parameterised by the cumulative chord length (the ∞-norm of each
step: rad or m), which is the same spline the check assumes for a positions-only trajectory.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dyn_node.core.trajectory import PiecewisePolynomial, Trajectory, interpolate
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
        q, d1, d2, _ = self.pp.evaluate(np.clip(s, self.pp.breaks[0], self.pp.breaks[-1]))
        return q, d1, d2


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

