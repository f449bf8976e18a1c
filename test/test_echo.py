"""``python -m dyn_node.ros.echo``: the venv user's ``ros2 topic echo`` (README quick start)."""
from __future__ import annotations

import subprocess

import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from conftest import Collected, js, python_cmd, t_msg

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _run_until_exit(cp, publish, timeout_s: float = 30.0) -> tuple[int, str, str]:
    """Publish (each 50 ms, waiting on the child) until the child exits; its (rc, out, err)."""
    deadline = timeout_s / 0.05
    while deadline > 0:
        publish()
        try:
            cp.proc.wait(timeout=0.05)
            break
        except subprocess.TimeoutExpired:
            deadline -= 1
    return cp.stop()


@pytest.mark.timeout(90)
def test_echo_prints_messages_as_yaml(ros_context, spawn):
    node = rclpy.create_node("echo_probe", context=ros_context)
    try:
        pub = node.create_publisher(type(js([], [])), "/echo_test/joint_states", 10)
        msg = js(["a", "b"], [0.25, -1.5], [0.0, 2.0], [3.5, -0.125], stamp=12.5)
        cp = spawn(python_cmd("dyn_node.ros.echo", "/echo_test/joint_states", "-n", "2",
                              "--timeout", "30"))
        rc, out, err = _run_until_exit(cp, lambda: pub.publish(msg))
        assert rc == 0, err
        docs = [d for d in yaml.safe_load_all(out) if d is not None]
        assert len(docs) == 2
        assert docs[0] == {"header": {"stamp": {"sec": 12, "nanosec": 500_000_000}, "frame_id": ""},
                           "name": ["a", "b"], "position": [0.25, -1.5], "velocity": [0.0, 2.0],
                           "effort": [3.5, -0.125]}

        # A latched topic with a byte field (DiagnosticStatus.level): read latched, level an int.
        diag_pub = node.create_publisher(DiagnosticArray, "/echo_test/feasibility", LATCHED)
        arr = DiagnosticArray()
        arr.header.stamp = t_msg(3.0)
        arr.status = [DiagnosticStatus(level=DiagnosticStatus.ERROR, name="dyn_node: x",
                                       message="infeasible", hardware_id="panda",
                                       values=[KeyValue(key="time_scale", value="1.5")])]
        diag_pub.publish(arr)  # once, before the echo starts
        cp = spawn(python_cmd("dyn_node.ros.echo", "/echo_test/feasibility", "-n", "1",
                              "--timeout", "30"))
        rc, out, err = _run_until_exit(cp, lambda: None)
        assert rc == 0, err
        doc, = [d for d in yaml.safe_load_all(out) if d is not None]
        assert doc["status"] == [{"level": 2, "name": "dyn_node: x", "message": "infeasible",
                                  "hardware_id": "panda",
                                  "values": [{"key": "time_scale", "value": "1.5"}]}]
    finally:
        node.destroy_node()


@pytest.mark.timeout(60)
def test_echo_without_publisher_says_so(spawn):
    cp = spawn(python_cmd("dyn_node.ros.echo", "/echo_test/nobody", "--timeout", "1"))
    rc, out, err = cp.proc.wait(timeout=50), *cp.proc.communicate()
    assert rc == 1 and out == ""
    assert err.strip() == "echo: no publisher on /echo_test/nobody within 1 s"


@pytest.mark.timeout(60)
def test_echo_stopped_by_sigterm_exits_quietly(ros_context, spawn):
    """``timeout 2 python -m dyn_node.ros.echo /x`` once ended in a traceback (rclpy's SIGTERM
    handler shuts the context down under the spin)."""
    import signal

    from rclpy.node import Node

    cp = spawn(python_cmd("dyn_node.ros.echo", "/echo_test/sigterm"))
    node = Node("echo_sigterm_test", context=ros_context)
    try:   # its node in the graph: rclpy (and its signal handler) is up, it waits for a publisher
        assert Collected().wait(lambda: "dyn_node_echo" in node.get_node_names(), 30.0)
    finally:
        node.destroy_node()
    rc = cp.stop(signal.SIGTERM, timeout=30.0)
    assert rc == (0, "", ""), rc[2]
