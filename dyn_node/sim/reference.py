"""The reference dyn_sim's controller tracks: a trajectory as joint_trajectory_controller plays it
(start at the stamp or on receipt, a first segment from the state at receipt, JTC's interpolation
rule, the last point held). :func:`reference_from_goal` is the one place that builds it from a
goal, so it can follow the core's execution model (dyn_node/core/check) as one swap.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dyn_node.core.check.trajectory import PiecewisePolynomial, Trajectory, interpolate


@dataclass(frozen=True)
class ActiveTrajectory:
    """A trajectory being executed; times are simulation seconds.

    ``start_time`` is the trajectory's t = 0 (its stamp or the receipt time), ``received_time``
    when the simulator took it. ``first_segment`` (or None) spans [received_time, first point].
    """

    trajectory: Trajectory
    mode: str
    start_time: float
    received_time: float
    polynomial: PiecewisePolynomial
    first_segment: PiecewisePolynomial | None

    @property
    def end_time(self) -> float:
        return self.start_time + float(self.trajectory.times[-1])

    @property
    def first_point_time(self) -> float:
        return self.start_time + float(self.trajectory.times[0])

    def reference(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q_ref, q̇_ref, q̈_ref) at simulation times t (M,), each M×nv; the last point held."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        q, v, a, _ = self.polynomial.evaluate(t - self.start_time)
        if self.first_segment is not None:
            early = t < self.first_point_time
            if np.any(early):
                q0, v0, a0, _ = self.first_segment.evaluate(t[early] - self.received_time)
                q[early], v[early], a[early] = q0, v0, a0
        late = t >= self.end_time
        if np.any(late):
            # Hold the last point at rest, as the controller does once the trajectory has played.
            q[late] = self.trajectory.positions[-1]
            v[late] = 0.0
            a[late] = 0.0
        return q, v, a


def reference_from_goal(traj: Trajectory, start: float, now: float, q_now: np.ndarray,
                        v_now: np.ndarray) -> ActiveTrajectory:
    """What the controller plays for ``traj`` (model order) starting at ``start`` (simulation s),
    received at ``now`` with the robot at (``q_now``, ``v_now``)."""
    mode = traj.jtc_interpolation
    poly = interpolate(traj, mode)
    first = None
    first_abs = start + float(traj.times[0])
    if first_abs > now + 1e-12:
        # JTC: from the state at receipt to the first point, same interpolation rule.
        pos = np.vstack([q_now, traj.positions[0]])
        vel = acc = None
        if traj.velocities is not None:
            vel = np.vstack([v_now, traj.velocities[0]])
        if traj.accelerations is not None:
            # The measured state carries no acceleration; start the segment from rest in a.
            acc = np.vstack([np.zeros_like(q_now), traj.accelerations[0]])
        seg = Trajectory(times=np.array([0.0, first_abs - now]), positions=pos,
                         velocities=vel, accelerations=acc)
        first = interpolate(seg, mode)
    return ActiveTrajectory(traj, mode, start, now, poly, first)
