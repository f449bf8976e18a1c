"""Scene 3: a comfortable, an aggressive and the aggressive one slowed by its time_scale, each
checked on ~/check_trajectory, sent and watched; then the core retimer's answer (retime.py)."""
from __future__ import annotations

import math

import numpy as np

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import RobotModel
from dyn_node.ros.demo.run import DemoRun, banner, say
from dyn_node.ros.demo.stack import Stack
from dyn_node.ros.demo.summary import LEVELS, Outcome, figure, status_number
from dyn_node.ros.demo.trajectories import (LEAD_S, SAFETY_FACTOR, SETTLE_S, DemoTrajectory,
                                            demo_trajectories, effort_residual, tracking_error)


def run_trajectory(stack: Stack, traj: DemoTrajectory, say) -> Outcome:
    """Send ``traj`` to start LEAD_S from now, watch the verdict and the execution."""
    model = stack.model
    o = Outcome(traj.name, traj.description, traj.duration)
    # asked first on ~/check_trajectory (checked exactly like joint_trajectory, never executed)
    v = stack.check(traj, stack.now_ns() + int(LEAD_S * 1e9))
    if v is not None:
        o.check_verdict, o.check_feasible = LEVELS.get(v.level, str(v.level)), v.feasible
        say(f"  ~/check_trajectory: {o.check_verdict}: {v.message}")
    else:
        say("  stage unavailable: check-only request (no answer on ~/check_trajectory)")
    start_ns = stack.now_ns() + int(LEAD_S * 1e9)
    end_ns = start_ns + int(traj.duration * 1e9)
    states_from = len(stack.states)
    stack.send(traj, start_ns)
    say(f"  sent '{traj.name}' ({traj.description}), starting in {LEAD_S:g} s")
    got = stack.spin_until(lambda: stack.verdict_for(start_ns) is not None, LEAD_S + 10.0)
    if got:
        recv, vals, level, msg = stack.verdict_for(start_ns)  # type: ignore[misc]
        o.verdict = LEVELS.get(level, str(level))
        o.verdict_source = "dyn_node"
        o.worst_joint = vals.get("worst_joint", "")
        o.worst_constraint = vals.get("worst_constraint", "")
        o.worst_ratio = status_number(vals, "worst_ratio")
        o.time_scale = status_number(vals, "time_scale")
        o.message = msg
        o.verdict_lead_s = start_ns * 1e-9 - recv
        say(f"  ~/feasibility: {o.verdict}: {msg} (verdict {o.verdict_lead_s:+.2f} s before start)")
    else:
        say("  stage unavailable: dyn_node feasibility verdict (no ~/feasibility answer within "
            f"{LEAD_S + 10:g} s); checking locally instead")
        _local_verdict(model, traj, o, say)

    def progress() -> None:
        now = stack.now_ns()
        t = (now - start_ns) * 1e-9
        st = stack.states[-1][1] if stack.states else "?"
        phase = "waiting" if t < 0 else ("executing" if t <= traj.duration else "settling")
        say(f"    {traj.name:<12} {phase:<9} t = {t:+.2f} s / {traj.duration:.2f} s   "
            f"controller: {st}")

    # Wait in stamp time, not wall time: on a loaded machine the simulator may deliver a burst of
    # late (but correctly stamped) samples, and dyn_node may answer late; both must be in.
    settle_ns = end_ns + int(SETTLE_S * 1e9)
    node_up = bool(stack.inv)

    def observed() -> bool:
        js_done = stack.js_last >= settle_ns
        inv_done = not node_up or stack.inv_last >= settle_ns
        return js_done and inv_done

    if not stack.spin_until(observed, traj.duration + LEAD_S + 20, progress):
        say("  (timed out waiting for samples up to the end of the trajectory; using what arrived)")
    stack.spin_until(lambda: False, 0.2)  # the last controller_status messages
    seen: list[str] = []
    for _, s in stack.states[states_from:]:
        if not seen or seen[-1] != s:
            seen.append(s)
    o.states = seen
    o.transitions = max(0, len(seen) - 1)
    keys = sorted(k for k in stack.js_q if start_ns <= k <= end_ns)
    if keys:
        o.tracking_error_rad = tracking_error(traj.validated(model.joint_names), start_ns * 1e-9,
                                              np.array(keys) * 1e-9, np.array([stack.js_q[k] for k in keys]))
        lim = model.limits.effort
        o.saturated_samples = int(sum(np.any(np.abs(stack.js[k]) >= lim * (1 - 1e-9))
                                      for k in keys if k in stack.js))
    o.residual_rms_nm, o.residual_max_nm, o.residual_samples = effort_residual(
        stack.js, stack.inv, start_ns, end_ns)
    say(f"  done: max tracking error {figure(o.tracking_error_rad)} rad, "
        f"{o.saturated_samples} saturated samples, controller states {' → '.join(seen) or '—'}")
    return o


def _local_verdict(model: RobotModel, traj: DemoTrajectory, o: Outcome, say) -> None:
    try:
        from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
    except ImportError as exc:
        say(f"  stage unavailable: local feasibility check ({exc})")
        return
    r = check_trajectory(Dynamics(model), traj.validated(model.joint_names), FeasibilityOptions())
    o.verdict = LEVELS.get(int(r.level), str(r.level))
    o.verdict_source = "local check (not dyn_node)"
    o.worst_joint, o.worst_constraint = r.worst_joint, r.worst_constraint
    o.worst_ratio, o.time_scale, o.message = r.worst_ratio, r.time_scale, r.message



def scene_trajectories(run: DemoRun, short: bool) -> None:
    """3. a comfortable, an aggressive and the aggressive one slowed by its time_scale."""
    say("")
    banner("3. trajectories")
    comfortable, aggressive = demo_trajectories(short)
    run.outcomes.append(run_trajectory(run.stack, comfortable, say))
    agg = run_trajectory(run.stack, aggressive, say)
    run.outcomes.append(agg)
    k = agg.time_scale
    if not (math.isfinite(k) and k > 0):
        run.missing("time_scale (no finite time_scale reported for the aggressive trajectory)",
                    "stage unavailable: slowed trajectory (no finite time_scale was reported)")
    else:
        slowed = aggressive.scaled(k * SAFETY_FACTOR, "slowed",
                                   f"aggressive × {k:.3f} × {SAFETY_FACTOR:g}")
        run.outcomes.append(run_trajectory(run.stack, slowed, say))
        from dyn_node.ros.demo.retime import run_retimed   # 3b: ~/retime_trajectory's answer
        o, run.retime_checks = run_retimed(run.stack, aggressive, slowed.duration, LEAD_S, run_trajectory, say)
        run.outcomes += [o] if o is not None else []
