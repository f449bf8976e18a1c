"""The demo's retiming scene: the aggressive trajectory sent to dyn_node's
``~/retime_trajectory`` (from the robot's current state, as for execution), and the trajectory of
its answer sent with its velocities and accelerations at every point and executed: dyn_node must
call it feasible before it starts and the simulator must not saturate while it runs.

The demo's dyn_node runs with ``retime.limit_margin`` :data:`LIMIT_MARGIN`: a time-optimal answer
runs the torque at its limit, and dyn_sim's tracking feedback needs room on top of it.
:func:`from_answer` and :func:`retime_checks` are pure; :func:`run_retimed` needs the demo's
running Stack and is handed the demo's ``run_trajectory`` (this module does not import the demo).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from dyn_node.core.check.trajectory import Trajectory

#: the demo node's ``retime.limit_margin``: at 100 % of the torque limit dyn_sim's PD saturates;
#: the demo's uniform slowdown keeps a like margin (× 1.05 in time: inertial torques ÷ 1.1)
LIMIT_MARGIN = 0.85


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


def from_answer(answer: Any, joint_names: list[str]) -> RetimedTrajectory | None:
    """The trajectory of a ``~/retime_trajectory`` answer (client.Retimed), or None when it has
    none (not accepted, no feasible timing, or not in the model's joint order)."""
    if answer is None or not (answer.accepted and answer.feasible):
        return None
    msg = answer.trajectory
    if list(msg.joint_names) != list(joint_names) or len(msg.points) < 2:
        return None
    rows = lambda xs: tuple(tuple(float(x) for x in r) for r in xs)  # noqa: E731
    pts = msg.points
    return RetimedTrajectory(
        "retimed", tuple(p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts),
        rows(p.positions for p in pts),
        f"aggressive retimed by ~/retime_trajectory: {answer.duration_in:.3g} s → "
        f"{answer.duration_out:.3g} s, T* {answer.lower_bound:.3g} s",
        rows(p.velocities for p in pts), rows(p.accelerations for p in pts))


def answer_line(answer: Any) -> str:
    """The demo's printout of a ``~/retime_trajectory`` answer."""
    if answer is None:
        return "no answer"
    if not answer.accepted:
        return f"not retimed ({answer.reason}): {answer.message}"
    return (f"{'retimed' if answer.feasible else 'no feasible timing'}: {answer.duration_in:.3g} s -> "
            f"{answer.duration_out:.3g} s (uniform {answer.duration_uniform:.3g} s, T* "
            f"{answer.lower_bound:.3g} s): {answer.message}")


def retime_checks(answer: Any, outcome: Any | None, slowed_s: float) -> list[tuple[bool, str]]:
    """PASS lines: the service's answer is a retimed trajectory that passed the node's exact check
    and is no slower than the uniform slowdown the demo runs (``slowed_s``); live: feasible before
    it started, no saturated sample, no saturated or deviating controller state."""
    ok = bool(answer is not None and answer.accepted and answer.feasible and answer.verdict is not None
              and answer.verdict.feasible and answer.duration_out <= slowed_s)
    got = f"{answer.duration_out:.3g} s" if ok else (answer_line(answer) if answer is not None else "no answer")
    checks = [(ok, f"retimed: ~/retime_trajectory's answer passes the exact check ({got}; the "
                   f"uniformly slowed one takes {slowed_s:.3g} s)")]
    if outcome is None:
        return checks + [(False, "retimed: not executed (no retimed trajectory in the answer)")]
    bad = {"saturated", "deviating"} & set(outcome.states)
    checks.append((outcome.verdict in ("OK", "WARN") and outcome.saturated_samples == 0 and not bad,
                   f"retimed: executed without a live violation (~/feasibility {outcome.verdict}, "
                   f"{outcome.saturated_samples} saturated samples, controller states "
                   f"{' → '.join(outcome.states) or '—'})"))
    return checks


def run_retimed(stack: Any, aggressive: Any, slowed_s: float, lead_s: float,
                run_trajectory: Callable[..., Any], say: Callable[[str], None]
                ) -> tuple[Any | None, list[tuple[bool, str]]]:
    """Ask ``~/retime_trajectory``, send its answer and watch; the outcome (None when nothing was
    sent) and the PASS lines."""
    answer = stack.retime(aggressive, stack.now_ns() + int(lead_s * 1e9))
    say("  ~/retime_trajectory: " + answer_line(answer))
    traj = from_answer(answer, list(stack.model.joint_names))
    outcome = run_trajectory(stack, traj, say) if traj is not None else None
    return outcome, retime_checks(answer, outcome, slowed_s)
