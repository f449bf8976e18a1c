"""The live benchmark's joint_states source: 7-DoF Panda JointStates at a commanded rate.

Driven over stdin/stdout by benchmarks/ros_probe.py, one command per line:
  ``match N``            wait until N subscribers are matched, answer ``matched``
  ``run RATE SECONDS``   publish at RATE Hz for SECONDS, answer
                         ``done SENT FIRST_STAMP_NS LAST_STAMP_NS ELAPSED_S``
  ``quit``
Each header stamp is the wall-clock time of its publish in ns, strictly increasing, so a stamp
identifies its message (the sequence tag) and stamp-to-receipt is the end-to-end latency.
Reliable QoS, depth 10: what joint_state_broadcaster offers.

``--effort``: also send efforts, the Panda model's inverse dynamics of each sample (a robot
moving freely, so an external-torque observer sees no contact), with the trajectory's time
taken from the wall clock (as the stamps) so that velocity, acceleration and effort agree at
every rate.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from typing import Callable

import rclpy
from rclpy.node import Node
from sensor_msgs.msg import JointState

NAMES = [f"panda_joint{i}" for i in range(1, 8)]
HOME = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]


def model_effort() -> Callable[[list[float], list[float], list[float]], list[float]]:
    """τ = RNEA(q, q̇, q̈) of the built-in Panda in NAMES order (dyn_node's own model)."""
    import numpy as np
    import pinocchio as pin

    from dyn_node.core.robot.model import load_model

    model = load_model(builtin="panda")
    assert list(model.joint_names) == NAMES, model.joint_names
    pm = model.pin_model
    data = pm.createData()
    return lambda q, v, a: pin.rnea(pm, data, np.array(q), np.array(v), np.array(a)).tolist()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--effort", action="store_true", help="send the model's efforts too")
    effort = model_effort() if ap.parse_args().effort else None
    rclpy.init()
    node = Node("bench_joint_state_publisher")
    pub = node.create_publisher(JointState, "/joint_states", 10)
    msg = JointState()
    msg.name = NAMES
    last_ns = 0
    seq = 0
    t0_ns = time.time_ns()
    for line in sys.stdin:
        cmd = line.split()
        if not cmd:
            continue
        if cmd[0] == "quit":
            break
        if cmd[0] == "match":
            want, deadline = int(cmd[1]), time.monotonic() + 60
            while pub.get_subscription_count() < want and time.monotonic() < deadline:
                rclpy.spin_once(node, timeout_sec=0.05)
            print("matched" if pub.get_subscription_count() >= want else "timeout", flush=True)
            continue
        rate, seconds = float(cmd[1]), float(cmd[2])
        period = 1.0 / rate
        n_target = int(round(rate * seconds))
        sent, first = 0, 0
        t0 = time.perf_counter()
        next_t = t0
        while sent < n_target:
            now = time.perf_counter()
            if now < next_t:
                if next_t - now > 2e-4:
                    time.sleep(next_t - now - 1e-4)
                continue
            # Falling far behind (a descheduled publisher) restarts the schedule instead of
            # sending a burst that would measure the burst, not the rate.
            next_t = max(next_t + period, now - 10 * period)
            seq += 1
            # stamped after the effort is computed: the latency measured is the subjects' alone
            t = (time.time_ns() - t0_ns) * 1e-9 if effort else seq * 1e-3
            msg.position = [h + 0.3 * math.sin(t + i) for i, h in enumerate(HOME)]
            msg.velocity = [0.3 * math.cos(t + i) for i in range(7)]
            if effort:
                msg.effort = effort(msg.position, msg.velocity,
                                    [-0.3 * math.sin(t + i) for i in range(7)])
            stamp = time.time_ns()
            if stamp <= last_ns:
                stamp = last_ns + 1
            last_ns = stamp
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            pub.publish(msg)
            if sent == 0:
                first = stamp
            sent += 1
        elapsed = time.perf_counter() - t0
        print(f"done {sent} {first} {last_ns} {elapsed:.6f}", flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
