"""Scene 3b: a transfer over a TCP speed limit, said before execution with its time_scale;
the transfer slowed by it passes (check-only requests: nothing moves)."""
from __future__ import annotations

import math
import time
from typing import Any

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.ros.demo.run import DemoRun, banner, say
from dyn_node.ros.demo.summary import figure, status_number
from dyn_node.ros.demo.trajectories import DEMO_TASK_LIMITS, LEAD_S, SAFETY_FACTOR, TASK_PLACE, task_transfer


def task_checks(unlimited: Any, fast: Any, fast_place: dict[str, str] | None, slowed: Any,
                k: float) -> list[tuple[bool, str]]:
    """The task-limits scene's acceptance: ``unlimited``, the local check of the transfer without
    the TCP limit (FeasibilityResult); ``fast`` / ``slowed``, dyn_node's verdicts (client.Verdict
    or None) before and after slowing by ``k``; ``fast_place``: the values of its
    ``…/panda_hand`` status on ~/feasibility."""
    out = [(unlimited.feasible, f"fast transfer: within every joint limit without the TCP limit "
                                f"(local check: {unlimited.message})")]
    if fast is None:
        return out + [(False, "fast transfer: no verdict from dyn_node on ~/check_trajectory")]
    peak = (figure(status_number(fast_place, "frame_speed_peak"), ".3g") + " m/s" if fast_place
            else "no panda_hand status")
    out.append((not fast.feasible and fast.worst_joint == TASK_PLACE
                and fast.worst_constraint == "frame_speed" and 1.0 < fast.time_scale < math.inf
                and fast_place is not None,
                f"fast transfer: infeasible before execution on the TCP speed (worst {fast.worst_joint} "
                f"{fast.worst_constraint}, peak {peak} of 0.25 m/s), time_scale {figure(fast.time_scale, '.4g')}"))
    if slowed is None:
        return out + [(False, "slowed transfer: no verdict from dyn_node on ~/check_trajectory")]
    out.append((slowed.feasible, f"slowed transfer (× {figure(k, '.4g')}): feasible ({slowed.message})"))
    return out


def scene_task_limits(run: DemoRun) -> None:
    """3b. a transfer inside every joint limit but over the 250 mm/s TCP speed: dyn_node (given
    config/demo_task_limits.yaml as limits_file for this scene) says so before execution with its
    time_scale, and the transfer slowed by it passes. Check-only requests: nothing moves."""
    say("")
    banner("3b. task limits: a TCP speed limit of 250 mm/s (config/demo_task_limits.yaml)")
    stack = run.stack
    if len(run.children) < 2 or not run.children[1].alive() or not DEMO_TASK_LIMITS.is_file():
        run.missing("task-limits scene (no dyn_node, or config/demo_task_limits.yaml missing)")
        return
    from dyn_node.core.check.feasibility import check_trajectory

    t0 = time.monotonic()
    fast = task_transfer()
    unlimited = check_trajectory(Dynamics(stack.model), fast.validated(stack.model.joint_names))
    why = stack.set_node_parameters(limits_file=str(DEMO_TASK_LIMITS))
    if why:
        run.missing(f"task-limits scene (limits_file not taken: {why})")
        return
    try:
        start = stack.now_ns() + int(LEAD_S * 1e9)
        v_fast = stack.check(fast, start)
        place = v_fast.status_values(TASK_PLACE) if v_fast is not None else None  # from the response
        k = v_fast.time_scale if v_fast is not None else math.nan
        say(f"  {fast.name} ({fast.description}), checked before execution: "
             + (f"{v_fast.message} [time_scale {figure(k, '.4g')}]" if v_fast else "no verdict"))
        slowed = fast.scaled(k * SAFETY_FACTOR, "slowed transfer", f"× {k:.3f} × {SAFETY_FACTOR:g}") \
            if math.isfinite(k) and k > 0 else None
        v_slow = stack.check(slowed, stack.now_ns() + int(LEAD_S * 1e9)) if slowed else None
        if v_slow is not None:
            say(f"  {slowed.name} ({slowed.description}): {v_slow.message}")
        run.extra_verdicts += (v_fast is not None) + (v_slow is not None)
        run.task_checks = task_checks(unlimited, v_fast, place, v_slow, k * SAFETY_FACTOR)
    finally:
        stack.set_node_parameters(limits_file="")  # the scenes after this one run without it
    for ok, text in run.task_checks:
        say(f"  [{'PASS' if ok else 'FAIL'}] {text}")
    say(f"  (scene 3b: {time.monotonic() - t0:.1f} s)")
