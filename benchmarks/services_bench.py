"""Round trip of a ``~/check_trajectory`` call (10-point 7-DoF Panda trajectory) against the
floor: a bare rclpy service of the same type in a process of its own that answers an empty
response at once, both called from this process, one call at a time, in the same run.

    python -m benchmarks.run --only services

Run as ``python -m benchmarks.services_bench --serve-empty NAME`` it is that bare server.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import threading
import time

import numpy as np

from .common import REPO, NotAvailable, percentile, progress
from .live_bench import _stop, ros_env

FLOOR_SERVICE = "/bench_empty/check_trajectory"


def _trajectory():
    from dyn_node.ros.client import trajectory_message
    from dyn_node.ros.demo import READY

    t = np.linspace(0.0, 2.0, 10)
    P = np.array(READY) + 0.1 * np.sin(np.pi * t / 2.0)[:, None]
    z = np.zeros_like(P)
    return trajectory_message([f"panda_joint{i}" for i in range(1, 8)], t, P, z, z)


def _round_trips(cli, request, n: int, warmup: int) -> list[float]:
    """Seconds per call, each sent after the previous one's response (spun by a thread)."""
    out = []
    for i in range(warmup + n):
        done = threading.Event()
        t0 = time.perf_counter()
        fut = cli.call_async(request)
        fut.add_done_callback(lambda _f: done.set())
        if not done.wait(30.0):
            raise RuntimeError(f"no response from {cli.srv_name} within 30 s")
        if i >= warmup:
            out.append(time.perf_counter() - t0)
        if not fut.result().accepted and cli.srv_name != FLOOR_SERVICE:
            raise RuntimeError(f"check not accepted: {fut.result().reason}")
    return out


def _core_check_s(traj, n: int) -> float:
    """Median time of the answer's core work in this process (on_demand.check, same trajectory)."""
    from dyn_node.core.check import on_demand
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.robot.model import load_model
    from dyn_node.core.robot.settings import Settings
    from dyn_node.ros.convert import trajectory_arrays

    from .common import median_time

    from dyn_node.core.live.allocator import retain_freed_memory

    retain_freed_memory()  # as the node's main() does: repeated checks reuse their pages
    dyn, settings = Dynamics(load_model(builtin="panda")), Settings(robot_model="panda")
    args = trajectory_arrays(traj)
    return median_time(lambda: on_demand.check(dyn, settings, *args), repeats=max(n // 10, 5))[0]


def _stats(xs: list[float]) -> dict:
    return {"n": len(xs), "median_ms": statistics.median(xs) * 1e3, "p99_ms": percentile(xs, 99) * 1e3,
            "min_ms": min(xs) * 1e3}


def run(quick: bool = False, smoke: bool = False) -> dict:
    try:
        import rclpy
        from dyn_node_interfaces.srv import CheckTrajectory
        from rclpy.executors import SingleThreadedExecutor
    except ImportError as exc:
        raise NotAvailable(f"rclpy or dyn_node_interfaces not importable: {exc}") from exc
    n = 20 if smoke else 200 if quick else 1000
    env = ros_env()
    procs = [subprocess.Popen([sys.executable, "-m", "dyn_node.ros.node", "--ros-args", "-p",
                               "robot_model:=panda"], cwd=REPO, env=env, start_new_session=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True),
             subprocess.Popen([sys.executable, "-m", "benchmarks.services_bench", "--serve-empty",
                               FLOOR_SERVICE], cwd=REPO, env=env, start_new_session=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)]
    saved = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    os.environ.update(ROS_DOMAIN_ID=env["ROS_DOMAIN_ID"], ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node("services_bench", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        spin = threading.Thread(target=ex.spin, daemon=True)
        spin.start()
        check = node.create_client(CheckTrajectory, "/dyn_node/check_trajectory")
        floor = node.create_client(CheckTrajectory, FLOOR_SERVICE)
        for cli in (check, floor):
            if not cli.wait_for_service(timeout_sec=60.0):
                raise NotAvailable(f"{cli.srv_name} did not come up within 60 s")
        request = CheckTrajectory.Request(trajectory=_trajectory())
        progress("services", f"{n} calls each, alternating blocks of {max(n // 10, 1)}")
        got: dict[str, list[float]] = {"check": [], "floor": []}
        block = max(n // 10, 1)
        for b in range(n // block):  # interleaved, so a slow spell of the machine hits both alike
            for key, cli in (("check", check), ("floor", floor)):
                got[key] += _round_trips(cli, request, block, warmup=5 if b == 0 else 0)
        ex.shutdown(timeout_sec=1.0)
        result = {"calls": n, "points": 10, "joints": 7, "check": _stats(got["check"]),
                  "floor": _stats(got["floor"]), "core_check_ms": _core_check_s(request.trajectory, n) * 1e3}
        result["ratio_median"] = result["check"]["median_ms"] / result["floor"]["median_ms"]
        result["ratio_p99"] = result["check"]["p99_ms"] / result["floor"]["p99_ms"]
        return result
    finally:
        rclpy.shutdown(context=ctx)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        for p in procs:
            _stop(p)


def _serve_empty(name: str) -> None:
    """The floor: a service of the same type that answers an empty response at once."""
    import rclpy
    from dyn_node_interfaces.srv import CheckTrajectory

    rclpy.init()
    node = rclpy.create_node("bench_empty")
    node.create_service(CheckTrajectory, name, lambda _req, resp: resp)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--serve-empty", required=True)
    _serve_empty(ap.parse_args().serve_empty)
