"""Live replay: a bag played into the node under use_sim_time gives the audit's verdicts.

The bag's messages are published as the raw bytes recorded, in log-time order, each preceded by a
/clock message carrying its log time (what `ros2 bag play --clock` does). The node runs with
use_sim_time, so its clock is the bag's. Its torques must equal the outputs recorded in the bag
bit for bit, and its feasibility verdict must equal what dyn-audit computed from the bag alone.
"""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import Stepper, kv  # noqa: E402
from test_audit import MS, T0, make_bag, trajectory_msg  # noqa: E402

from dyn_node.audit.bag_audit import AuditOptions, run_audit  # noqa: E402


def _bag_messages(bag: Path) -> list[tuple[str, int, bytes]]:
    from mcap.reader import make_reader

    out = []
    for f in sorted(bag.glob("*.mcap")):
        with open(f, "rb") as fh:
            for _schema, channel, message in make_reader(fh).iter_messages(log_time_order=True):
                out.append((channel.topic, message.log_time, bytes(message.data)))
    return out


@pytest.mark.timeout(120)
def test_replay_under_sim_time_matches_audit(ros_context, tmp_path):
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message
    from diagnostic_msgs.msg import DiagnosticArray
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory

    from dyn_node.ros.node import DynNode

    n = 400
    bag = make_bag(tmp_path / "bag", n=n, outputs=True,
                   trajectories=[(200, trajectory_msg(T0 + 200 * MS)),
                                 (300, trajectory_msg(T0 + 300 * MS, scale=0.25))])
    audit = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "audit"), report=False))
    verdicts = audit.record["outputs"]["trajectories"]
    assert len(verdicts) == 2 and {v["feasible"] for v in verdicts} == {True, False}

    messages = _bag_messages(bag)
    recorded = {}  # stamp → recorded effort of the node's inverse dynamics
    for topic, _t, data in messages:
        if topic == "/dyn_node/inverse_dynamics":
            m = deserialize_message(data, JointState)
            recorded[(m.header.stamp.sec, m.header.stamp.nanosec)] = list(m.effort)
    assert len(recorded) == n

    node = DynNode(context=ros_context, parameter_overrides=[
        Parameter("robot_model", value="panda"), Parameter("use_sim_time", value=True)])
    player = Node("bag_player", context=ros_context)
    clock_pub = player.create_publisher(Clock, "/clock", 10)
    js_pub = player.create_publisher(JointState, "joint_states", 10)
    traj_pub = player.create_publisher(JointTrajectory, "joint_trajectory", 10)
    replayed: dict[tuple[int, int], list[float]] = {}
    feasibility: list[DiagnosticArray] = []
    player.create_subscription(JointState, "/dyn_node/inverse_dynamics",
                               lambda m: replayed.__setitem__(
                                   (m.header.stamp.sec, m.header.stamp.nanosec), list(m.effort)), 1000)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    player.create_subscription(DiagnosticArray, "/dyn_node/feasibility", feasibility.append, latched)
    steps = Stepper(ros_context, (node, player))
    spin_until = steps.until

    try:
        assert spin_until(lambda: js_pub.get_subscription_count() >= 1
                          and traj_pub.get_subscription_count() >= 1
                          and clock_pub.get_subscription_count() >= 1, 30.0)
        sent_js = 0
        last_clock = 0
        for topic, log_time, data in messages:
            if topic not in ("/joint_states", "/joint_trajectory"):
                continue
            clock = Clock()
            clock.clock.sec, clock.clock.nanosec = divmod(log_time, 1_000_000_000)
            clock_pub.publish(clock)
            last_clock = log_time
            if topic == "/joint_states":
                js_pub.publish(data)
                sent_js += 1
                # one at a time: the node answers each before the next, as at the recorded rate
                assert spin_until(lambda: len(replayed) >= sent_js, 10.0), sent_js
            else:
                before = len(feasibility)
                traj_pub.publish(data)
                assert spin_until(lambda: len(feasibility) > before, 30.0)
        # the node's time is the bag's: the last /clock it was given, not the wall clock
        assert spin_until(lambda: node.get_clock().now().nanoseconds == last_clock, 5.0)
    finally:
        steps.close()

    assert replayed.keys() == recorded.keys()
    assert all(replayed[k] == recorded[k] for k in recorded)  # bit for bit
    assert len(feasibility) == 2
    for live, verdict in zip(feasibility, verdicts):
        summary = next(s for s in live.status if s.name == "dyn_node: trajectory feasibility")
        vals = kv(summary)
        assert (vals["feasible"] == "true") == verdict["feasible"]
        assert float(vals["time_scale"]) == verdict["time_scale"]
        assert float(vals["worst_ratio"]) == verdict["worst_ratio"]
        assert vals["worst_joint"] == verdict["worst_joint"]
        assert vals["worst_constraint"] == verdict["worst_constraint"]
        stamp_ns = live.header.stamp.sec * 1_000_000_000 + live.header.stamp.nanosec
        assert stamp_ns == verdict["stamp_ns"]


@pytest.mark.timeout(120)
def test_audit_of_the_nodes_own_bag_checks_the_start_segment_as_the_node_did(ros_context, tmp_path):
    """The node records joint_states (the robot moving away from the first point) and two
    trajectories whose first point lies 0.5 s ahead, one while it knows the state and one after
    stale_timeout; dyn-audit starts each from the last joint_states recorded before it (within
    stale_timeout), so its verdicts, keys and the re-check equal what the node published."""
    from builtin_interfaces.msg import Duration
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from dyn_node.ros.node import DynNode

    node = DynNode(context=ros_context, parameter_overrides=[
        Parameter("robot_model", value="planar_2link"), Parameter("stale_timeout", value=30.0),
        Parameter("record.enabled", value=True), Parameter("record.directory", value=str(tmp_path))])
    player = Node("start_segment_player", context=ros_context)
    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    js_pub = player.create_publisher(JointState, "joint_states", reliable)
    traj_pub = player.create_publisher(JointTrajectory, "joint_trajectory", 10)
    gravity: list[JointState] = []
    verdicts: list[DiagnosticArray] = []
    player.create_subscription(JointState, "/dyn_node/gravity_torque", gravity.append, reliable)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    player.create_subscription(DiagnosticArray, "/dyn_node/feasibility", verdicts.append, latched)
    steps = Stepper(ros_context, (node, player))
    spin_until = steps.until

    def trajectory(sec: int) -> JointTrajectory:
        m = JointTrajectory()
        m.header.stamp.sec = sec
        m.joint_names = ["joint1", "joint2"]
        for t, q in ((0.5, [0.5, 0.3]), (2.0, [1.5, 0.8])):
            m.points.append(JointTrajectoryPoint(
                positions=q, velocities=[0.0, 0.0], accelerations=[0.0, 0.0],
                time_from_start=Duration(sec=int(t), nanosec=int(round((t % 1) * 1e9)))))
        return m

    try:
        bridge = node.recording
        assert spin_until(lambda: js_pub.get_subscription_count() >= 1
                          and traj_pub.get_subscription_count() >= 1
                          and player.count_publishers("/dyn_node/feasibility") >= 1, 30.0)
        for k in range(5):
            js = JointState(name=["joint1", "joint2"], position=[0.0 - 0.0025 * k, 0.3],
                            velocity=[-2.5, 0.0])
            js.header.stamp.sec, js.header.stamp.nanosec = 100, 1_000_000 * k
            js_pub.publish(js)
            assert spin_until(lambda: len(gravity) > k, 10.0), k
        traj_pub.publish(trajectory(200))
        assert spin_until(lambda: len(verdicts) >= 1, 30.0)
        # the same trajectory once the last state is older than stale_timeout
        assert node.set_parameters([Parameter("stale_timeout", value=0.001)])[0].successful
        spin_until(lambda: False, 0.05)
        traj_pub.publish(trajectory(201))
        assert spin_until(lambda: len(verdicts) >= 2, 30.0)
        ok, path = bridge.stop()
        assert ok, path
    finally:
        node.recording.close()
        steps.close()

    live = [kv(v.status[0]) | {"message": v.status[0].message,
                                                            "level": v.status[0].level}
            for v in verdicts]
    assert live[0]["start_segment"] == "checked" and live[0]["feasible"] == "false"
    assert live[1]["start_segment"] == "not_checked (no current state within stale_timeout)"
    assert live[1]["feasible"] == "true" and live[1]["level"] == bytes([1])
    audit = run_audit(AuditOptions(bag=path, out=str(tmp_path / "audit"), report=False))
    entries = audit.record["outputs"]["trajectories"]
    assert len(entries) == 2
    for got, want in zip(entries, live):
        assert got["start_segment"] == want["start_segment"]
        assert got["message"] == want["message"]
        assert got["time_scale"] == float(want["time_scale"])
        assert (got["start_state_age_s"] is None) == (want["start_state_age_s"] == "nan")
        if got["start_state_age_s"] is not None:
            assert got["start_state_age_s"] == float(want["start_state_age_s"])
    rc = audit.record["outputs"]["recheck"]["/dyn_node/feasibility"]
    assert rc["matched"] == 2 and rc["identical"] is True, rc
