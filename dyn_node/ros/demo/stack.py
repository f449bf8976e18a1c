"""The ROS side of the demo (an rclpy client beside dyn_sim and dyn_node) and its interrupt flag."""
from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from dyn_node.core.robot.model import RobotModel
from dyn_node.ros.demo.trajectories import DemoTrajectory


_INTERRUPTED = threading.Event()


def on_signal(signum, frame) -> None:
    """Ctrl-C / SIGTERM: set a flag that the wait loops turn into KeyboardInterrupt.

    Raising straight from the handler is unsafe: if the signal lands while rclpy converts a
    message, pybind11 turns the KeyboardInterrupt into a RuntimeError. A second signal raises
    at once (the user insists).
    """
    if _INTERRUPTED.is_set():
        raise KeyboardInterrupt
    _INTERRUPTED.set()


def check_interrupted() -> None:
    if _INTERRUPTED.is_set():
        raise KeyboardInterrupt


class Unavailable(Exception):
    """A stage that cannot run here; the message says which and why."""


class Stack:
    """The ROS side of the demo: an rclpy client beside dyn_sim and dyn_node."""

    def __init__(self, model: RobotModel, domain: int, out: Path, log: Any):
        import rclpy
        from rclpy.context import Context
        from rclpy.node import Node
        from dyn_node.ros.qos import LATCHED_HISTORY
        from rclpy.signals import SignalHandlerOptions
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        self.rclpy = rclpy
        self.model = model
        self.say = log
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node("dyn_node_demo", context=self.ctx)
        from rclpy.executors import SingleThreadedExecutor

        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.js: dict[int, np.ndarray] = {}       # stamp ns → measured effort (model order)
        self.js_q: dict[int, np.ndarray] = {}     # stamp ns → q
        self.inv: dict[int, np.ndarray] = {}      # stamp ns → dyn_node RNEA effort
        self.js_last = self.inv_last = 0          # newest stamps seen (ns)
        self.verdicts: list[tuple[float, Any]] = []
        self.states: list[tuple[float, str]] = []
        n = model.nv

        def on_js(m: JointState) -> None:
            try:
                s = model.to_model_order(m.name, m.position, m.velocity, m.effort)
            except Exception:
                return
            k = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
            self.js_q[k] = s.q
            self.js_last = max(self.js_last, k)
            if s.effort is not None:
                self.js[k] = s.effort

        def on_inv(m: JointState) -> None:
            if len(m.effort) == n:
                idx, _ = model.mapping(m.name)
                k = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
                self.inv[k] = np.asarray(m.effort)[idx]
                self.inv_last = max(self.inv_last, k)

        self.node.create_subscription(JointState, "joint_states", on_js, 1000)
        self.node.create_subscription(JointState, "/dyn_node/inverse_dynamics", on_inv, 1000)
        self.node.create_subscription(
            DiagnosticArray, "/dyn_node/feasibility",
            lambda m: self.verdicts.append((time.time(), m)), LATCHED_HISTORY)
        self.node.create_subscription(
            DiagnosticStatus, "/dyn_node/controller_status",
            lambda m: self.states.append((time.time(), next(
                (kv.value for kv in m.values if kv.key == "state"), "?"))), 100)
        self.traj_pub = self.node.create_publisher(JointTrajectory, "joint_trajectory", 10)
        from dyn_node.ros.client import DynClient

        self.client = DynClient(self.node)  # each trajectory is checked on ~/check_trajectory first

    def spin_until(self, cond, timeout: float, progress=None) -> bool:
        deadline = time.monotonic() + timeout
        last = 0.0
        while not cond():
            check_interrupted()
            if time.monotonic() > deadline:
                return False
            self.ex.spin_once(timeout_sec=0.02)
            if progress is not None and time.monotonic() - last > 0.5:
                last = time.monotonic()
                progress()
        return True

    def now_ns(self) -> int:
        return time.time_ns()

    def check(self, traj: DemoTrajectory, start_ns: int, timeout: float = 15.0) -> Any:
        """dyn_node's verdict (client.Verdict) on ``traj`` from ~/check_trajectory, or None."""
        fut = self.client.check_async(self.message(traj, start_ns), timeout=timeout, from_current_state=True)
        self.spin_until(fut.done, timeout)
        return fut.result() if fut.done() and fut.exception() is None else None

    def retime(self, traj: DemoTrajectory, start_ns: int, timeout: float = 30.0) -> Any:
        """dyn_node's retiming (client.Retimed) of ``traj`` from ~/retime_trajectory, or None."""
        fut = self.client.retime_async(self.message(traj, start_ns), timeout=timeout, from_current_state=True)
        self.spin_until(fut.done, timeout)
        return fut.result() if fut.done() and fut.exception() is None else None

    def send(self, traj: DemoTrajectory, start_ns: int) -> None:
        self.traj_pub.publish(self.message(traj, start_ns))

    def message(self, traj: DemoTrajectory, start_ns: int) -> Any:
        from builtin_interfaces.msg import Duration, Time
        from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

        msg = JointTrajectory(joint_names=list(self.model.joint_names))
        msg.header.stamp = Time(sec=start_ns // 10**9, nanosec=start_ns % 10**9)
        zero = [[0.0] * self.model.nv] * len(traj.times)
        vel, acc = getattr(traj, "velocities", zero), getattr(traj, "accelerations", zero)
        for t, p, v, a in zip(traj.times, traj.positions, vel, acc):
            ns = int(round(t * 1e9))
            msg.points.append(JointTrajectoryPoint(
                positions=list(p), velocities=list(v), accelerations=list(a),
                time_from_start=Duration(sec=ns // 10**9, nanosec=ns % 10**9)))
        return msg

    def set_node_parameters(self, timeout: float = 10.0, **values: Any) -> str:
        """Set dyn_node's parameters; "" when it took them, else why not."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        cli = self.node.create_client(SetParameters, "/dyn_node/set_parameters")
        try:
            if not cli.wait_for_service(timeout_sec=timeout):
                return "no /dyn_node/set_parameters service"
            req = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg()
                                                    for k, v in values.items()])
            fut = cli.call_async(req)
            self.spin_until(fut.done, timeout)
            if not fut.done() or fut.result() is None:
                return "no answer"
            bad = [r.reason for r in fut.result().results if not r.successful]
            return "; ".join(bad)
        finally:
            self.node.destroy_client(cli)

    def verdict_for(self, start_ns: int) -> tuple[float, dict[str, str], int, str] | None:
        for recv, arr in self.verdicts:
            if arr.header.stamp.sec * 10**9 + arr.header.stamp.nanosec != start_ns:
                continue
            for st in arr.status:
                if st.name.endswith("trajectory feasibility"):
                    return recv, {kv.key: kv.value for kv in st.values}, int.from_bytes(st.level, "little") \
                        if isinstance(st.level, bytes) else int(st.level), st.message
        return None

    def count_verdicts(self, stamps: list[int], timeout: float = 5.0) -> int:
        """How many of the trajectories stamped ``stamps`` have their ~/feasibility verdict, the
        late ones awaited up to ``timeout`` s (under load one came after its scene had looked)."""
        self.spin_until(lambda: all(self.verdict_for(ns) is not None for ns in stamps), timeout)
        return sum(self.verdict_for(ns) is not None for ns in stamps)

    def close(self) -> None:
        try:
            self.node.destroy_node()
        finally:
            self.rclpy.try_shutdown(context=self.ctx)

    def call_stop_recording(self, timeout: float = 5.0) -> str | None:
        from std_srvs.srv import Trigger

        cli = self.node.create_client(Trigger, "/dyn_node/stop_recording")
        if not cli.wait_for_service(timeout_sec=timeout):
            return None
        fut = cli.call_async(Trigger.Request())
        self.spin_until(fut.done, timeout)
        if fut.done() and fut.result() is not None and fut.result().success:
            return fut.result().message
        return None
