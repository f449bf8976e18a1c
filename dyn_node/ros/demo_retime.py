"""The demo's retiming scene: the aggressive trajectory retimed by the core retimer
(:func:`dyn_node.retime.retime`, the same call dyn-check --retime makes), sent with its
velocities and accelerations at every point, and executed: dyn_node must call it feasible before
it starts and the simulator must not saturate while it runs.

:func:`retimed` and :func:`retime_checks` are pure; :func:`run_retimed` needs the demo's running
Stack and is handed the demo's ``run_trajectory`` (this module does not import the demo).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.trajectory import Trajectory
from dyn_node.retime import RetimeResult, retime


@dataclass(frozen=True)
class RetimedTrajectory:
    """What the demo's Stack sends and tracks: like its DemoTrajectory, plus q̇ and q̈ per point
    (model order)."""

    name: str
    times: tuple[float, ...]
    positions: tuple[tuple[float, ...], ...]
    description: str
    velocities: tuple[tuple[float, ...], ...]
    accelerations: tuple[tuple[float, ...], ...]

    @property
    def duration(self) -> float:
        return self.times[-1]

    def validated(self, joint_names: Any = None) -> Trajectory:
        return Trajectory(times=np.array(self.times), positions=np.array(self.positions),
                          velocities=np.array(self.velocities),
                          accelerations=np.array(self.accelerations))


#: TOPP-RA's share of each limit here: a time-optimal answer runs the torque at its limit, and
#: the simulator's tracking feedback needs room on top (at 100 % it saturates); the demo's
#: uniform slowdown keeps a like margin (× 1.05 in time: inertial torques ÷ 1.1)
HEADROOM = 0.85


def retimed(model: Any, aggressive: Any) -> tuple[RetimedTrajectory | None, RetimeResult]:
    """The aggressive trajectory (a DemoTrajectory) retimed; None when no retiming passed."""
    res = retime(Dynamics(model), aggressive.validated(model.joint_names), limit_margin=HEADROOM)
    if not res.feasible:
        return None, res
    out = res.trajectory

    def rows(a: np.ndarray) -> tuple[tuple[float, ...], ...]:
        return tuple(tuple(float(x) for x in r) for r in a)

    return RetimedTrajectory(
        "retimed", tuple(float(t) for t in out.times), rows(out.positions),
        f"aggressive retimed ({res.method}): {res.duration_in:.3g} s → {res.duration_out:.3g} s, "
        f"T* {res.lower_bound:.3g} s", rows(out.velocities), rows(out.accelerations)), res


def retime_checks(res: RetimeResult, outcome: Any | None, slowed_s: float) -> list[tuple[bool, str]]:
    """PASS lines: the retimer's answer passed the exact check and is no slower than the uniform
    slowdown the demo runs (``slowed_s``); live: feasible before it started, no saturated
    sample, no saturated or deviating controller state."""
    checks = [(bool(res.feasible and res.check is not None and res.check.feasible
                    and res.duration_out <= slowed_s),
               f"retimed: the core retimer's answer passes the exact check ({res.method}, "
               f"{res.duration_out:.3g} s; the uniformly slowed one takes {slowed_s:.3g} s; "
               f"T* {res.lower_bound:.3g} s)")]
    if outcome is None:
        return checks + [(False, "retimed: not executed (no retiming)")]
    bad = {"saturated", "deviating"} & set(outcome.states)
    checks.append((outcome.verdict in ("OK", "WARN") and outcome.saturated_samples == 0 and not bad,
                   f"retimed: executed without a live violation (~/feasibility {outcome.verdict}, "
                   f"{outcome.saturated_samples} saturated samples, controller states "
                   f"{' → '.join(outcome.states) or '—'})"))
    return checks


def run_retimed(stack: Any, aggressive: Any, slowed_s: float,
                run_trajectory: Callable[..., Any], say: Callable[[str], None]
                ) -> tuple[Any | None, list[tuple[bool, str]]]:
    """Retime, send and watch; the outcome (None when not sent) and the PASS lines."""
    traj, res = retimed(stack.model, aggressive)
    say(f"  core retimer: {res.message}")
    outcome = run_trajectory(stack, traj, say) if traj is not None else None
    return outcome, retime_checks(res, outcome, slowed_s)
