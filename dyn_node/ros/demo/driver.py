"""``make demo``: the model table, then the whole loop over DDS with an independent simulator.

What it runs and prints, and its exit codes: README "The demo". The pure parts (poses, table,
trajectories, residual and tracking statistics) import no ROS; the rclpy client is imported only
when the stack runs.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

from dyn_node.core.robot.model import RobotModel, load_model
from dyn_node.ros.demo.audit import scene_audit
from dyn_node.ros.demo.gate import scene_gate
from dyn_node.ros.demo.retime import LIMIT_MARGIN as RETIME_LIMIT_MARGIN
from dyn_node.ros.demo.moves import scene_trajectories
from dyn_node.ros.demo.output import where_line
from dyn_node.ros.demo.press import PRESS_SCENE_FILE, scene_press
from dyn_node.ros.demo.processes import Child, module_available
from dyn_node.ros.demo.push import PUSH_S, scene_push
from dyn_node.ros.demo.run import DemoRun, banner, say
from dyn_node.ros.demo.stack import Stack, Unavailable, on_signal
from dyn_node.ros.demo.summary import acceptance, summary_table
from dyn_node.ros.demo.task_limits import scene_task_limits
from dyn_node.ros.demo.trajectories import FINGERS, READY, TRACKING_TOLERANCE, DemoTrajectory, model_table


def run_demo(args: argparse.Namespace) -> int:
    run = DemoRun(Path(args.out).resolve(), time.monotonic())
    run.out.mkdir(parents=True, exist_ok=True)
    run.logs.mkdir(exist_ok=True)
    say(where_line(run.out))
    model = load_model(builtin="panda")
    banner("1. the model")
    say(model_table(model))
    if args.table_only:
        return 0
    try:
        scene_stack(run, model, args.domain)
        scene_trajectories(run, args.short)
        scene_task_limits(run)
        scene_push(run, args.short)
        scene_press(run, say, banner, DemoTrajectory)
        if run.stack is not None and run.verdict_stamps:
            run.extra_verdicts += run.stack.count_verdicts(run.verdict_stamps)
        if len(run.children) > 1 and run.children[1].alive():
            run.bag_path = run.stack.call_stop_recording()
        _save_samples(run.stack, run.out)
    finally:
        _stop_stack(run)
    say(f"stack stopped ({run.elapsed():.1f} s)")
    if not args.short:  # processes of its own: ~30 s more
        scene_gate(run)
    scene_summary(run)
    scene_audit(run)
    return _finish(run, strict=args.strict)


def scene_stack(run: DemoRun, model: RobotModel, domain: int) -> None:
    """2. dyn_sim and dyn_node as child processes, and this process's view of them (Stack)."""
    say("")
    banner(f"2. the stack (ROS_DOMAIN_ID={domain}, localhost only; logs in {run.logs})")
    # DYN_DEMO_RUN marks the children so a test can prove none is left behind.
    run.env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1", DYN_DEMO_RUN=str(run.out))
    run.env.pop("ROS_LOCALHOST_ONLY", None)
    children = run.children
    children.append(Child("dyn_sim", [sys.executable, "-m", "dyn_node.ros.sim_node", "--ros-args",
                                      "-p", f"initial_positions:={list(READY)}",
                                      "-p", f"apply_wrench_hold:={PUSH_S}",
                                      "-p", f"scene_file:={PRESS_SCENE_FILE}",
                                      # the controller's topic, where dyn_node and this client meet
                                      "-r", "/joint_trajectory_controller/joint_trajectory:=/joint_trajectory"],
                          run.env, run.logs / "dyn_sim.log"))
    node_ok = module_available("dyn_node.ros.node")
    if node_ok:
        children.append(Child("dyn_node", [
            sys.executable, "-m", "dyn_node.ros.node", "--ros-args",
            "-p", f"locked_joints:={FINGERS}",
            "-p", f"tracking_tolerance:={TRACKING_TOLERANCE}",
            "-p", f"retime.limit_margin:={RETIME_LIMIT_MARGIN}",  # room for dyn_sim's feedback
            "-p", "record.enabled:=true", "-p", f"record.directory:={run.bag_dir}"],
            run.env, run.logs / "dyn_node.log"))
    else:
        run.missing("dyn_node (module dyn_node.ros.node missing)",
                    "stage unavailable: dyn_node (module dyn_node.ros.node missing); the simulator runs alone")
    stack = run.stack = Stack(model, domain, run.out, say)
    say("waiting for dyn_sim's joint_states …")
    if not stack.spin_until(lambda: len(stack.js) > 50, 60):
        raise Unavailable(f"dyn_sim published no joint_states within 60 s:\n{children[0].tail()}")
    say(f"  dyn_sim up ({run.elapsed():.1f} s)")
    if node_ok:
        say("waiting for dyn_node to load the model from /robot_description and answer …")
        if stack.spin_until(lambda: len(stack.inv) > 50, 60):
            say(f"  dyn_node up ({run.elapsed():.1f} s)")
        else:
            run.missing("dyn_node (no ~/inverse_dynamics within 60 s)",
                        "stage unavailable: dyn_node (no ~/inverse_dynamics within 60 s):\n"
                        + children[1].tail())
    # Let the subscriptions to joint_trajectory match before sending: dyn_sim's, dyn_node's
    # and, when it records, the recorder's (discovered a little later), so the bag has all.
    stack.spin_until(lambda: stack.traj_pub.get_subscription_count() >= len(children), 10)
    if node_ok:
        stack.spin_until(lambda: stack.traj_pub.get_subscription_count() >= 3, 3)




def _save_samples(stack: Stack, out: Path) -> None:
    """Raw observations, for looking into any figure of the summary afterwards."""
    js_k = sorted(stack.js)
    inv_k = sorted(stack.inv)
    np.savez_compressed(out / "samples.npz", js_stamp_ns=np.array(js_k, dtype=np.int64),
                        js_q=np.array([stack.js_q[k] for k in js_k]),
                        js_effort=np.array([stack.js[k] for k in js_k]),
                        inv_stamp_ns=np.array(inv_k, dtype=np.int64),
                        inv_effort=np.array([stack.inv[k] for k in inv_k]))


def _stop_stack(run: DemoRun) -> None:
    if run.stack is not None:
        run.stack.close()
    for c in reversed(run.children):
        rc = c.stop()
        if rc not in (0, -signal.SIGINT, 130):
            say(f"  {c.name} exited with {rc}; last lines of {c.log_path}:\n{c.tail()}")


def scene_summary(run: DemoRun) -> None:
    """4. what was observed per trajectory, the acceptance checks and the effort residual."""
    say("")
    banner("4. summary")
    outcomes = run.outcomes
    say(summary_table(outcomes))
    run.checks = acceptance(outcomes) + run.task_checks + run.push_checks + run.retime_checks
    say("")
    for ok, text in run.checks:
        say(f"  [{'PASS' if ok else 'FAIL'}] {text}")
    feas = [o for o in outcomes if o.verdict in ("OK", "WARN") and o.residual_samples]
    if feas:
        rms = math.sqrt(sum(o.residual_rms_nm ** 2 * o.residual_samples for o in feas)
                        / sum(o.residual_samples for o in feas))
        say(f"  live effort residual MuJoCo (measured) − Pinocchio (dyn_node) on feasible "
             f"trajectories: RMS {rms:.4f} N·m, max {max(o.residual_max_nm for o in feas):.4f} N·m "
             f"over {sum(o.residual_samples for o in feas)} samples")



def _finish(run: DemoRun, *, strict: bool) -> int:
    """summary.json, the closing lines, and the exit code: 2 if a check failed, 3 if a stage
    was unavailable and ``strict``, else 0."""
    (run.out / "summary.json").write_text(json.dumps(
        {"outcomes": [o.__dict__ for o in run.outcomes], "checks": [[ok, t] for ok, t in run.checks],
         "unavailable": run.unavailable, "bag": run.bag_path,
         "wall_time_s": run.elapsed()}, indent=2, default=str))
    say(f"summary: {run.out / 'summary.json'}")
    if run.unavailable:
        say("unavailable stages: " + "; ".join(run.unavailable))
    say(f"demo finished in {run.elapsed():.1f} s")
    if any(not ok for ok, _ in run.checks):
        return 2
    return 3 if (run.unavailable and strict) else 0

def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="dyn_node_demo", description=__doc__.split("\n")[0])
    p.add_argument("--short", action="store_true", help="shorter trajectories (CI)")
    p.add_argument("--out", default="demo_out", help="output directory (bag, audit, logs)")
    p.add_argument("--domain", type=int, default=int(os.environ.get("DYN_DEMO_DOMAIN", 0)) or
                   60 + os.getpid() % 40, help="ROS_DOMAIN_ID for the demo's processes")
    p.add_argument("--table-only", action="store_true", help="print the model table and stop")
    p.add_argument("--strict", action="store_true",
                   help="exit 3 when a stage was unavailable (default: report it and exit 0)")
    args = p.parse_args(argv)

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        return run_demo(args)
    except KeyboardInterrupt:
        print("\ninterrupted: the stack has been stopped", flush=True)
        return 130
    except Unavailable as exc:
        print(f"stage unavailable: {exc}", flush=True)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
