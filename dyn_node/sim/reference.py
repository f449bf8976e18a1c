"""The reference dyn_sim's controller tracks: a trajectory as joint_trajectory_controller plays it,
taken from the core's execution model (:func:`dyn_node.core.check.execution.execute`: start at the
stamp or on receipt, a past stamp inside the trajectory, the segment from the state at receipt,
each segment's interpolation from the fields at its ends, the last point held), so that what
dyn_sim executes is what dyn_node's check judged. :func:`reference_from_goal` is the one place
that builds it from a goal.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dyn_node.core.check.execution import Execution, Timing, execute
from dyn_node.core.check.start_segment import StartState
from dyn_node.core.check.trajectory import Trajectory


@dataclass(frozen=True)
class ActiveTrajectory:
    """A trajectory being executed; times are simulation seconds.

    ``start_time`` is the trajectory's t = 0 (its stamp or the receipt time), ``received_time``
    when the simulator took it, which is the execution model's t = 0 (``execution``).
    """

    trajectory: Trajectory
    mode: str
    start_time: float
    received_time: float
    execution: Execution

    @property
    def end_time(self) -> float:
        return self.start_time + float(self.trajectory.times[-1])

    @property
    def first_point_time(self) -> float:
        return self.start_time + float(self.trajectory.times[0])

    def reference(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q_ref, q̇_ref, q̈_ref) at simulation times t (M,), each M×nv; the last point held at
        rest, exactly (the polynomial's value at its end may differ from it by rounding)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        q, v, a, _ = self.execution.pp.evaluate(t - self.received_time)
        late = t >= self.end_time
        if np.any(late):
            q[late] = self.trajectory.positions[-1]
            v[late] = 0.0
            a[late] = 0.0
        return q, v, a


def reference_from_goal(traj: Trajectory, start: float, now: float, q_now: np.ndarray,
                        v_now: np.ndarray) -> ActiveTrajectory:
    """What the controller plays for ``traj`` (model order) starting at ``start`` (simulation s:
    its stamp, or ``now`` for a zero stamp), received at ``now`` with the robot at (``q_now``,
    ``v_now``)."""
    state = StartState(positions=np.asarray(q_now, dtype=float), velocities=np.asarray(v_now, dtype=float),
                       age_s=0.0)
    # a zero stamp starts on receipt; a stamp equal to the receipt is the same start
    timing = Timing(stamp_s=0.0 if start == now else float(start), receipt_s=float(now))
    ex = execute(traj, state, timing)
    return ActiveTrajectory(traj, ex.interpolation, start, now, ex)
