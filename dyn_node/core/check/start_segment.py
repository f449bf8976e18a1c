"""The segment from a moving robot's state to a first point ahead: its share of the time scale.

Its start velocity is the robot's and does not scale with k, so no per-sample law covers it: the
segment (the execution model's, :meth:`dyn_node.core.check.execution.Execution.first_segment`)
is checked directly at each trial k (walk, then bisection). The check itself is passed in
(``check``: :func:`dyn_node.core.check.feasibility._check`), so this module does not depend on it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np

from dyn_node.errors import TrajectoryError
from dyn_node.core.check.trajectory import Trajectory

#: ``start_segment`` when the first point is at t = 0 (nothing runs before it)
START_NONE = "none (first point at t = 0)"
START_CHECKED = "checked"
#: why the start segment was not checked, when the node or the audit had no usable state
NO_CURRENT_STATE = "no current state within stale_timeout"


@dataclass(frozen=True)
class StartState:
    """The robot's state when a trajectory arrived, in model order: q and q̇ of the last accepted
    joint_states (q̇ = 0 when it carried no velocity; q̈ = 0 is assumed, as
    joint_trajectory_controller does), and its age in s."""

    positions: np.ndarray
    velocities: np.ndarray
    age_s: float
    #: the controller's last commanded accelerations, when the state is its desired state
    #: (``interpolate_from_desired_state``); None for a measured state
    accelerations: np.ndarray | None = None


def current_state(last: tuple[int, np.ndarray, np.ndarray] | None, now_ns: int,
                  stale_timeout: float) -> StartState | None:
    """The state a trajectory received at ``now_ns`` starts from: ``last`` = (receipt time ns,
    q, q̇) of the last accepted joint_states, when it is at most ``stale_timeout`` s old (None
    otherwise: :data:`NO_CURRENT_STATE`). The node passes receipt times, the audit the log times
    the node recorded with them, so a replay starts from the same state."""
    if last is None:
        return None
    age = (now_ns - last[0]) * 1e-9
    if not 0.0 <= age <= stale_timeout:
        return None
    return StartState(positions=np.asarray(last[1], dtype=float),
                      velocities=np.asarray(last[2], dtype=float), age_s=age)


#: The search: the walk's step factor from the given timing, the relative bracket width the
#: bisection stops at, the smallest k walked down to, and how far above the first k tried the
#: walk up looks before answering "no slowdown helps".
WALK, RTOL, FLOOR, REACH = 2.0, 1e-6, 1e-6, 1e3


@dataclass(frozen=True)
class StartSegment:
    """``execution`` (:class:`dyn_node.core.check.execution.Execution`) begins with a segment
    from the robot's moving state; ``options`` the check's, ``period`` the main check's
    (possibly raised) sample period; ``whole``: a kind reaches back across samples (RMS), so
    each trial checks the whole stretched execution rather than the segment alone."""

    check: Callable[..., Any]
    dynamics: Any
    execution: Any
    options: Any
    period: float
    whole: bool

    def trial(self, k: float) -> Any:
        """The verdict at k (the trajectory k times slower, the robot's state unchanged)."""
        if self.whole:
            plain = replace(self.options, compute_payload_margin=False)
            return self.check(self.dynamics, self.execution.stretched(k), plain, search_start=False)
        return self.check(self.dynamics, self.execution.first_segment(k),
                          replace(self.options, sample_period=self.period * k,
                                  compute_payload_margin=False))

    def time_scale(self, k_rest: float, feasible: bool) -> tuple[float, str, str] | None:
        """The time scale when the segment's share exceeds ``k_rest`` (the rest's, from the
        per-sample laws: the rest is feasible exactly for k ≥ k_rest): (k, joint, kind that
        fails just below k), or None when k_rest stands.

        From the given timing (k = 1, whose verdict is ``feasible``) the search walks by factors
        of 2 towards the boundary, down to k_rest when feasible, up (at most ``REACH``×) when
        not, then bisects the last step to a relative width of 1e-6 and answers its feasible
        end: the smallest k such that every k′ from k to the given timing (when feasible) is, on
        the walk's grid; a stretch narrower than a factor of 2 that the walk steps over is not
        seen."""
        trials: dict[float, Any] = {}

        def ok(k: float) -> bool:
            try:
                trials[k] = self.trial(k)
            except TrajectoryError:   # motion beyond any physical range at this k: not feasible
                trials[k] = None
                return False
            return trials[k].feasible

        bracket = _walk_down(ok, k_rest) if feasible else _walk_up(ok, k_rest)
        if bracket is None:
            return None
        lo, hi = bracket
        if hi is None:
            return (math.inf, *_worst_violation(trials[lo]))
        while hi / lo - 1.0 > RTOL:
            mid = math.sqrt(lo * hi)
            if ok(mid):
                hi = mid
            else:
                lo = mid
        return (hi, *_worst_violation(trials[lo]))


def _walk_down(ok: Callable[[float], bool], k_rest: float) -> tuple[float, float] | None:
    """From a feasible k = 1 down by factors of 2: the bracket (infeasible, feasible), or None
    when the rest's bound (or none at all) stands."""
    hi, lo = 1.0, None
    kt = hi / WALK
    while kt > max(k_rest, FLOOR):
        if not ok(kt):
            lo = kt
            break
        hi, kt = kt, kt / WALK
    if lo is None:
        if k_rest <= 0 or ok(k_rest):
            return None
        lo = k_rest
    return lo, hi


def _walk_up(ok: Callable[[float], bool], k_rest: float) -> tuple[float, float | None] | None:
    """From an infeasible timing up by factors of 2: the bracket (infeasible, feasible; None
    when nothing up to ``REACH``× is), or None when the rest binds (or rounding at k = 1)."""
    base = max(1.0, k_rest)
    if ok(base):
        return None
    lo, hi = base, None
    kt = base * WALK
    while kt <= base * REACH:
        if ok(kt):
            hi = kt
            break
        lo, kt = kt, kt * WALK
    return lo, hi


def stretched(traj: Trajectory, k: float) -> Trajectory:
    """``traj`` run k times slower: times × k, velocities ÷ k, accelerations ÷ k²."""
    return Trajectory(times=traj.times * k, positions=traj.positions,
                      velocities=None if traj.velocities is None else traj.velocities / k,
                      accelerations=None if traj.accelerations is None else traj.accelerations / (k * k),
                      fields=traj.fields)


def _worst_violation(r: Any) -> tuple[str, str]:
    if r is None or not r.violations:
        return "", ""
    v = max(r.violations, key=lambda v: abs(v.peak_value) / v.limit if v.limit > 0 else math.inf)
    return v.joint, v.kind
