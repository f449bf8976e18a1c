"""Latency the FollowJointTrajectory gate adds: from the client's ``send_goal`` to the downstream
server's goal callback, through dyn_node's gate (``gate.mode reject``, a feasible 100-point
7-DoF Panda goal, so every goal is checked and forwarded) and through a bare rclpy action proxy
that forwards without checking, same run, interleaved in blocks. The downstream is a sink that
answers at once and returns the instant its goal callback ran (CLOCK_REALTIME, one machine).

    python -m benchmarks.run --only gate

Run as ``python -m benchmarks.gate_bench --sink`` / ``--proxy`` it is the sink / the proxy.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib.util
import os
import subprocess
import sys
import time
from typing import Iterator

from .common import REPO, NotAvailable, progress
from .live_bench import _stop, ros_env
from .services_bench import _stats

SINK_GATE = "/bench_sink_gate/follow_joint_trajectory"
SINK_PROXY = "/bench_sink_proxy/follow_joint_trajectory"
PROXY = "/bench_proxy/follow_joint_trajectory"
GATE = "/bench_gate/follow_joint_trajectory"
POINTS = 100
ARM = [f"panda_joint{i}" for i in range(1, 8)]


def _goal():
    from dyn_node.ros.demo import READY
    from dyn_node.ros.fjt_client import goal, quintic

    q1 = list(READY)
    q1[0] += 0.3
    q1[3] += 0.2
    return goal(**quintic(list(READY), q1, 2.0, POINTS), names=ARM)


def _latencies(client, g, n: int, warmup: int) -> list[float]:
    """Seconds from send_goal to the sink's goal callback, one goal at a time."""
    out = []
    for i in range(warmup + n):
        t0 = time.time_ns()
        sent = client.send(g, timeout=30.0)
        if not sent.handle.accepted:
            raise RuntimeError(f"goal not accepted through {client.thread.action}")
        _, result = client.result(sent, timeout=30.0)
        if result.error_code != 0:
            raise RuntimeError(f"goal failed through {client.thread.action}: {result.error_string}")
        if i >= warmup:
            out.append((int(result.error_string) - t0) * 1e-9)
    return out


def _check_ms(g, n: int) -> float:
    """Median time of the gate's decision on the same goal, in this process."""
    from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
    from dyn_node.core.robot.model import load_model
    from dyn_node.core.robot.settings import Settings
    from dyn_node.core.check.trajectory import validate_trajectory
    from dyn_node.gate.decision import GateOptions, decide
    from dyn_node.ros.convert import trajectory_arrays

    from .common import median_time

    s = Settings(robot_model="panda")
    model = load_model(builtin="panda")
    dyn = Dynamics(model, DynamicsOptions(include_friction=s.include_friction))
    traj = validate_trajectory(model.joint_names, *trajectory_arrays(g.trajectory))
    from dyn_node.core.check.feasibility import FeasibilityOptions
    opts = FeasibilityOptions(sample_period=s.sample_period, effort_warn_ratio=s.effort_warn_ratio)
    return median_time(lambda: decide(dyn, traj, GateOptions(), start=None, check_options=opts),
                       repeats=max(n // 10, 5))[0] * 1e3


@contextlib.contextmanager
def _this_process_on(env: dict[str, str]) -> Iterator[None]:
    """This process's rclpy on the children's domain and discovery range, for the block."""
    keys = ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")
    saved = {k: os.environ.get(k) for k in keys}
    os.environ.update({k: env[k] for k in keys})
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _measure(n: int) -> dict:
    """The interleaved blocks; the servers are up."""
    import rclpy

    from dyn_node.ros.fjt_client import FjtClient

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    clients = {}
    try:
        clients = {"gate": FjtClient(ctx, GATE, "gate_bench_gate"), "proxy": FjtClient(ctx, PROXY, "gate_bench_proxy")}
        for c in clients.values():
            c.wait_for_server(60.0)
        g = _goal()
        block = max(n // 10, 1)
        progress("gate", f"{n} goals each, alternating blocks of {block}")
        got: dict[str, list[float]] = {"gate": [], "proxy": []}
        for b in range(n // block):  # interleaved: a slow spell of the machine hits both alike
            for key, c in clients.items():
                got[key] += _latencies(c, g, block, warmup=5 if b == 0 else 0)
        return {"goals": n, "points": POINTS, "joints": 7, "gate": _stats(got["gate"]),
                "proxy": _stats(got["proxy"]), "check_ms": _check_ms(g, n)}
    finally:
        for c in clients.values():
            c.close()
        rclpy.shutdown(context=ctx)


def run(quick: bool = False, smoke: bool = False) -> dict:
    if importlib.util.find_spec("control_msgs") is None:
        raise NotAvailable("control_msgs not importable (make builds it into the venv)")
    n = 10 if smoke else 100 if quick else 400
    env = ros_env()
    logs = REPO / "bench_out"
    logs.mkdir(exist_ok=True)

    def spawn(log: str, *args: str) -> subprocess.Popen:
        # output to a file: a pipe nobody reads fills up (the gate logs each decision) and blocks
        with open(logs / f"gate_{log}.log", "w") as f:
            return subprocess.Popen([sys.executable, "-m", *args], cwd=REPO, env=env, start_new_session=True,
                                    stdout=f, stderr=subprocess.STDOUT, text=True)

    procs = [spawn("sink", "benchmarks.gate_bench", "--sink"), spawn("proxy", "benchmarks.gate_bench", "--proxy"),
             spawn("dyn_node", "dyn_node.ros.node", "--ros-args", "-r", "__node:=bench_gate",
                   "-p", "robot_model:=panda", "-p", f"gate.controller_action:={SINK_GATE}")]
    try:
        with _this_process_on(env):
            result = _measure(n)
        result["added_median_ms"] = result["gate"]["median_ms"] - result["proxy"]["median_ms"]
        result["added_p99_ms"] = result["gate"]["p99_ms"] - result["proxy"]["p99_ms"]
        result["target_met"] = result["added_median_ms"] <= result["check_ms"] + 2.0
        return result
    finally:
        for p in procs:
            _stop(p)


def _spin_forever(node, threads: int = 4) -> None:
    import rclpy
    from rclpy.executors import MultiThreadedExecutor

    ex = MultiThreadedExecutor(num_threads=threads)
    ex.add_node(node)
    try:
        ex.spin()
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def _sink() -> None:
    """Two downstream servers: each goal accepted, its goal callback's instant returned at once."""
    import rclpy
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionServer, GoalResponse
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup

    rclpy.init()
    node = rclpy.create_node("bench_sink")
    seen: dict[int, int] = {}

    def on_goal(goal):
        seen[id(goal)] = time.time_ns()
        return GoalResponse.ACCEPT

    def execute(handle):
        handle.succeed()
        return FollowJointTrajectory.Result(error_string=str(seen.pop(id(handle.request))))

    servers = [ActionServer(node, FollowJointTrajectory, name, execute, goal_callback=on_goal,
                            callback_group=MutuallyExclusiveCallbackGroup()) for name in (SINK_GATE, SINK_PROXY)]
    _spin_forever(node)
    del servers


def _proxy() -> None:
    """The baseline: forwards each goal (goal response, then the result) without looking at it,
    with the gate's machinery (a server in its own group, the client on its own thread)."""
    import rclpy
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionServer, GoalResponse
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup

    from dyn_node.ros.fjt_client import ClientThread, wait_future

    rclpy.init()
    node = rclpy.create_node("bench_proxy")
    down = ClientThread(node.context, SINK_PROXY, "bench_proxy_client")
    handles: dict[int, object] = {}

    def on_goal(goal):
        down.client.wait_for_server(timeout_sec=5.0)
        handle = wait_future(down.call(lambda: down.client.send_goal_async(goal), 30.0), 30.0, "goal response")
        handles[id(goal)] = handle
        return GoalResponse.ACCEPT if handle.accepted else GoalResponse.REJECT

    def execute(handle):
        res = wait_future(down.call(handles.pop(id(handle.request)).get_result_async, 30.0), 30.0, "result")
        handle.succeed()
        return res.result

    server = ActionServer(node, FollowJointTrajectory, PROXY, execute, goal_callback=on_goal,
                          callback_group=MutuallyExclusiveCallbackGroup())
    _spin_forever(node)
    del server


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--sink", action="store_true")
    g.add_argument("--proxy", action="store_true")
    args = ap.parse_args()
    _sink() if args.sink else _proxy()
