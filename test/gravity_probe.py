"""A process of its own that feeds dyn_node joint_states and times its ``~/gravity_torque``
answers, so what the test process does (building and parsing huge requests) cannot hold them.

Run as ``python test/gravity_probe.py NODE JOINT_STATES PERIOD_S JOINT=POS ...`` (NODE: the node's
fully qualified name, JOINT_STATES: the topic it listens to): publishes joint_states
every PERIOD_S (header stamp = wall-clock time of publishing), prints ``ready`` once answers come,
and on a line ``stop`` on stdin prints one JSON line: ``sent`` (wall times of the joint_states
published) and ``got`` ([receipt wall time, the answer's stamp] of each gravity_torque), then
exits. The answer's stamp is its input's, so receipt − stamp is each message's round trip.
"""
from __future__ import annotations

import json
import sys
import threading
import time


def main(argv: list[str]) -> int:
    import rclpy
    from builtin_interfaces.msg import Time
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState

    ns, js_topic, period = argv[0], argv[1], float(argv[2])
    joints = [a.split("=") for a in argv[3:]]
    names, q = [n for n, _ in joints], [float(p) for _, p in joints]
    rclpy.init()
    node = rclpy.create_node("gravity_probe")
    sent: list[float] = []
    got: list[tuple[float, float]] = []
    lock = threading.Lock()
    first = threading.Event()

    def on_gravity(msg: JointState) -> None:
        with lock:
            got.append((time.time(), msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9))
        first.set()

    node.create_subscription(JointState, f"{ns}/gravity_torque", on_gravity, 1000)
    pub = node.create_publisher(JointState, js_topic, 100)

    def tick() -> None:
        now = time.time()
        sec = int(now)
        msg = JointState(name=names, position=q, velocity=[0.0] * len(q))
        msg.header.stamp = Time(sec=sec, nanosec=int((now - sec) * 1e9))
        pub.publish(msg)
        with lock:
            sent.append(now)

    node.create_timer(period, tick)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    first.wait()  # ready once answers flow (the test's own deadline bounds this)
    print("ready", flush=True)
    for line in sys.stdin:
        if line.strip() == "stop":
            break
    with lock:
        print(json.dumps({"sent": sent, "got": got}), flush=True)
    ex.shutdown(timeout_sec=2.0)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
