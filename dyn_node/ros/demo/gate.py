"""The demo's gate scene: a planner-like client (a control_msgs FollowJointTrajectory action client,
as MoveIt's would be) sends three goals through dyn_node's gate to dyn_sim, the controller:

1. a comfortable move through a gate in ``reject`` mode: forwarded, SUCCESSFUL;
2. a move ~3× too fast for joint 1's speed limit, same gate: ABORTED with INVALID_GOAL and the
   verdict line as error_string; dyn_sim never moved;
3. the same fast move through a gate in ``retime`` mode: retimed, SUCCESSFUL, no actuator at its
   torque limit; its duration printed against the uniform slowdown's. Skipped (said so) while
   ``dyn_node.retime`` is not installed.

It runs its own dyn_sim and dyn_node processes in the namespace ``/gate_demo`` after the main
stack has stopped (or alone: ``python -m dyn_node.ros.demo.gate``). :func:`gate_scene` returns
(ok, text) check lines like the other scenes.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from dyn_node.ros.demo.processes import Child
from dyn_node.ros.demo.run import DemoRun, banner, say
from dyn_node.ros.demo.trajectories import FINGERS, READY

ARM = [f"panda_joint{i}" for i in range(1, 8)]
NS = "/gate_demo"
CONTROLLER = f"{NS}/joint_trajectory_controller/follow_joint_trajectory"


def _moved(dq: float) -> list[float]:
    q = list(READY)
    q[0] += dq
    return q


def _children(env: dict[str, str], logs: Path, retime: bool) -> list[Any]:
    py = [sys.executable, "-m"]
    out = [Child("gate_sim", py + ["dyn_node.ros.sim_node", "--ros-args", "-r", f"__ns:={NS}",
                                   "-p", f"initial_positions:={list(READY)}", "-p", "constraints.goal_time:=2.0"],
                 env, logs / "gate_dyn_sim.log")]
    from dyn_node.ros.demo.retime import LIMIT_MARGIN

    for mode in ("reject", "retime") if retime else ("reject",):
        # a time-optimal retiming runs a torque at its limit: room for dyn_sim's tracking feedback
        margin = ["-p", f"retime.limit_margin:={LIMIT_MARGIN}"] if mode == "retime" else []
        out.append(Child(f"gate_{mode}", py + [
            "dyn_node.ros.node", "--ros-args", "-r", f"__ns:={NS}", "-r", f"__node:=gate_{mode}",
            "-p", f"locked_joints:={FINGERS}", "-p", f"gate.controller_action:={CONTROLLER}",
            "-p", f"gate.mode:={mode}", *margin], env, logs / f"gate_{mode}.log"))
    return out


class _Watch:
    """joint_states, decision records and the gates' readiness, collected on a node of this process."""

    def __init__(self, ctx: Any, modes: tuple[str, ...]):
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String

        self.node = Node("gate_demo_watch", context=ctx)
        self.lock = threading.Lock()
        self.js: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.records: list[dict] = []
        self.receipts: dict[str, list[float]] = {m: [] for m in modes}  # of ~/inverse_dynamics
        self.node.create_subscription(JointState, f"{NS}/joint_states", self._on_js, 1000)
        for m in modes:
            self.node.create_subscription(String, f"{NS}/gate_{m}/gate_decisions", self._on_record,
                                          QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
            self.node.create_subscription(JointState, f"{NS}/gate_{m}/inverse_dynamics",
                                          lambda _m, k=m: self._tick(k), 10)

    def _on_js(self, m: Any) -> None:
        with self.lock:
            self.js.append((m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
                            np.array(m.position[:7]), np.array(m.effort[:7])))

    def _on_record(self, m: Any) -> None:
        with self.lock:
            self.records.append(json.loads(m.data))

    def _tick(self, mode: str) -> None:
        self.receipts[mode].append(time.monotonic())

    def ready(self) -> bool:
        """Every gate keeps up with joint_states (:func:`~dyn_node.ros.fjt_client.steady`)."""
        from dyn_node.ros.fjt_client import steady

        return all(steady(r, time.monotonic()) for r in self.receipts.values())

    def since(self, t: float) -> list[tuple[float, np.ndarray, np.ndarray]]:
        with self.lock:
            return [s for s in self.js if s[0] >= t]

    def decision(self, mode: str) -> dict | None:
        with self.lock:
            found = [r for r in self.records if r["event"] == "decision" and r["mode"] == mode]
        return found[-1] if found else None


def _wait(cond: Callable[[], bool], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    ev = threading.Event()
    while not cond():
        if time.monotonic() > deadline:
            return False
        ev.wait(0.05)  # polling what the executor thread collects
    return True


def _goal(q1: list[float], duration: float) -> Any:
    from dyn_node.ros.fjt_client import goal, quintic

    return goal(**quintic(list(READY), q1, duration), names=ARM)


def _home() -> Any:
    """Back to READY from wherever the robot is: its first point 1 s ahead, so the controller runs
    a segment from the robot's state to it (a first point due at once away from the robot would
    be a jump, which the gate refuses)."""
    from dyn_node.ros.fjt_client import goal, quintic

    q = quintic(list(READY), list(READY), 1.0)
    return goal(**{**q, "times": [t + 1.0 for t in q["times"]]}, names=ARM)


def _scene_goals(clients: dict[str, Any], watch: _Watch, limits: np.ndarray, say) -> list[tuple[bool, str]]:
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    R = FollowJointTrajectory.Result
    checks: list[tuple[bool, str]] = []
    c = clients["reject"]
    status, res = c.result(c.send(_goal(_moved(0.2), 1.5)))
    ok = (status, res.error_code) == (GoalStatus.STATUS_SUCCEEDED, R.SUCCESSFUL)
    checks.append((ok, f"gate: feasible goal forwarded → {res.error_string!r} (error_code {res.error_code})"))
    say(("PASS " if ok else "FAIL ") + checks[-1][1])
    back = c.result(c.send(_home()))[0] == GoalStatus.STATUS_SUCCEEDED
    t_sent = time.time()
    status, res = c.result(c.send(_goal(_moved(0.5), 0.15)))
    _wait(lambda: len(watch.since(t_sent)) > 500, 20.0)
    q = np.array([s[1] for s in watch.since(t_sent)])
    # within 1 mrad (the previous goal still settling), where the goal asked for 0.5 rad
    still = len(q) > 500 and float(np.abs(q - q[0]).max()) < 1e-3
    ok = back and status == GoalStatus.STATUS_ABORTED and res.error_code == R.INVALID_GOAL and still
    checks.append((ok, f"gate (reject): infeasible goal → ABORTED, INVALID_GOAL, {res.error_string!r}; "
                       f"dyn_sim never moved ({len(q)} joint_states after it, max change "
                       f"{float(np.abs(q - q[0]).max()) if len(q) else float('nan'):.1e} rad)"))
    say(("PASS " if ok else "FAIL ") + checks[-1][1])
    if "retime" not in clients:
        return checks
    c = clients["retime"]
    t_sent = time.time()
    status, res = c.result(c.send(_goal(_moved(0.5), 0.15)))
    t_done = time.time()  # joint_states up to the goal's end (a starved dyn_sim delivers them late)
    _wait(lambda: any(s[0] >= t_done for s in watch.since(t_sent)), 20.0)
    rec = watch.decision("retime") or {}
    peak = max((float(np.max(np.abs(s[2]) / limits)) for s in watch.since(t_sent)), default=float("nan"))
    ok = (status, res.error_code, rec.get("decision")) == (GoalStatus.STATUS_SUCCEEDED, R.SUCCESSFUL, "retimed") \
        and peak < 1.0
    checks.append((ok, f"gate (retime): the same goal retimed {rec.get('duration_in') or float('nan'):.3f} s → "
                       f"{rec.get('duration_out') or float('nan'):.3f} s (uniform slowdown "
                       f"{rec.get('duration_uniform') or float('nan'):.3f} s) → {res.error_string!r}; "
                       f"peak torque {peak * 100:.0f}% of the limit"
                       + ("" if rec.get("decision") in (None, "retimed") else f"; the gate said: {rec.get('verdict')}")))
    say(("PASS " if ok else "FAIL ") + checks[-1][1])
    return checks


def gate_scene(env: dict[str, str], logs: Path, say: Callable[[str], None]) -> tuple[list[tuple[bool, str]], list[str]]:
    """Run the scene; (check lines, unavailable parts)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from dyn_node.core.robot.model import load_model
    from dyn_node.ros.fjt_client import FjtClient

    retime = importlib.util.find_spec("dyn_node.retime") is not None
    unavailable = [] if retime else ["gate retime goal (dyn_node.retime not installed)"]
    modes = ("reject", "retime") if retime else ("reject",)
    children = _children(env, logs, retime)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(env.get("ROS_DOMAIN_ID", "0")))
    watch = _Watch(ctx, modes)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(watch.node)
    stop = threading.Event()
    def _spin() -> None:
        while not stop.is_set() and ctx.ok():
            ex.spin_once(timeout_sec=0.05)

    spin = threading.Thread(target=_spin, daemon=True)
    spin.start()
    clients = {m: FjtClient(ctx, f"{NS}/gate_{m}/follow_joint_trajectory", f"gate_demo_{m}") for m in modes}
    try:
        for c in clients.values():
            c.wait_for_server(90.0)
        if not _wait(watch.ready, 90.0):
            return [(False, "gate: the gates did not load the model and keep up with joint_states "
                            "within 90 s")], unavailable
        limits = np.asarray(load_model(builtin="panda").limits.effort, dtype=float)  # model order = ARM
        return _scene_goals(clients, watch, limits, say), unavailable
    finally:
        for c in clients.values():
            c.close()
        stop.set()
        spin.join(timeout=5.0)
        ex.shutdown()
        watch.node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        for ch in reversed(children):
            ch.stop()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="demo_out/gate", help="directory for the processes' logs")
    ap.add_argument("--domain", type=int, default=int(os.environ.get("ROS_DOMAIN_ID", "42")))
    args = ap.parse_args(argv)
    logs = Path(args.out)
    logs.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    env.pop("ROS_LOCALHOST_ONLY", None)
    checks, unavailable = gate_scene(env, logs, print)
    for part in unavailable:
        print(f"unavailable: {part}")
    return 0 if all(ok for ok, _ in checks) else 2


def scene_gate(run: DemoRun) -> None:
    """3d. a planner-like client sends goals through dyn_node's gate to dyn_sim (ros/demo/gate.py)."""
    say("")
    banner("3d. dyn_node between a planner and the controller: the FollowJointTrajectory gate")
    checks, missing = gate_scene(run.env, run.logs, say)
    run.push_checks += checks  # scene checks shown with the push's in the summary
    for what in missing:
        run.missing(what)


if __name__ == "__main__":
    raise SystemExit(main())
