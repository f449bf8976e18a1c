"""dyn_sim as users run it: a separate process, talked to over DDS with rclpy only."""
from __future__ import annotations

import signal
from typing import Callable

import numpy as np
import pytest

from conftest import Stepper, python_cmd
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import builtin_urdf, load_model

READY = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]
ARM = [f"panda_joint{i}" for i in range(1, 8)]


def sim_cmd(*params: str) -> list[str]:
    args = ["--ros-args", "-p", f"initial_positions:={READY}"]
    for p in params:
        args += ["-p", p]
    return python_cmd("dyn_node.ros.sim_node", *args)


def spin_until(ctx, node, cond: Callable[[], bool], timeout: float, what: str) -> None:
    """Spin ``node`` (which outlives the call) until cond(); AssertionError naming ``what`` if not."""
    steps = Stepper(ctx, (node,), step_s=0.05)
    try:
        if not steps.until(cond, timeout):
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
    finally:
        steps.close(destroy_nodes=False)


def probe(ctx):
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    node = Node("sim_probe", context=ctx)
    got: dict[str, list] = {"js": [], "desc": []}
    node.create_subscription(JointState, "joint_states", got["js"].append, 1000)
    node.create_subscription(String, "robot_description", got["desc"].append,
                             QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                        reliability=ReliabilityPolicy.RELIABLE))
    return node, got


@pytest.mark.timeout(60)
def test_joint_states_at_configured_rate_and_latched_description(ros_context, spawn):
    proc = spawn(sim_cmd("publish_rate_hz:=250.0"))
    node, got = probe(ros_context)
    try:
        spin_until(ros_context, node, lambda: got["desc"] and len(got["js"]) >= 150, 30,
                   "robot_description and 150 joint_states")
    finally:
        node.destroy_node()
    # Latched: received although the probe subscribed after dyn_sim published it once.
    assert got["desc"][0].data == builtin_urdf("panda")
    js = got["js"]
    assert list(js[0].name) == ARM + ["panda_finger_joint1", "panda_finger_joint2"]
    stamps_ns = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in js])
    # Stamps advance by exactly the publish period of simulation time (250 Hz → 4 ms).
    assert set(np.diff(stamps_ns).tolist()) == {4_000_000}
    # Holding still at READY with feedforward: measured effort is the gravity torque, which
    # Pinocchio computes independently of MuJoCo.
    last = js[-1]
    np.testing.assert_allclose(last.position[:7], READY, atol=1e-9)
    g = Dynamics(load_model(builtin="panda")).gravity(np.array(READY))
    np.testing.assert_allclose(last.effort[:7], g, atol=1e-6)
    rc, _, err = proc.stop(signal.SIGTERM)
    assert rc == 0, err


@pytest.mark.timeout(60)
def test_executes_trajectory_and_rejects_bad_one(ros_context, spawn):
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    proc = spawn(sim_cmd())
    node, got = probe(ros_context)
    pub = node.create_publisher(JointTrajectory, "/joint_trajectory_controller/joint_trajectory", 10)
    target = list(READY)
    target[0] += 0.3
    target[3] += 0.2

    def traj(times: list[float], points: list[list[float]]) -> JointTrajectory:
        msg = JointTrajectory(joint_names=ARM)  # zero stamp: start on receipt
        for t, p in zip(times, points):
            msg.points.append(JointTrajectoryPoint(
                positions=p, time_from_start=Duration(sec=int(t), nanosec=int((t % 1) * 1e9))))
        return msg

    try:
        spin_until(ros_context, node, lambda: len(got["js"]) >= 10 and pub.get_subscription_count() > 0,
                   30, "dyn_sim to come up")
        pub.publish(traj([0.5, 0.4], [target, READY]))  # times not increasing: rejected
        pub.publish(traj([0.6], [target]))              # from the current state to target
        spin_until(ros_context, node,
                   lambda: np.abs(np.array(got["js"][-1].position[:7]) - target).max() < 1e-3
                   and np.abs(got["js"][-1].velocity[:7]).max() < 1e-2,
                   30, "the robot to reach the trajectory's point")
    finally:
        node.destroy_node()
    js = got["js"]
    pos = np.array([m.position[:7] for m in js])
    # It moved along the commanded direction only (joints 1 and 4) and did not overshoot badly.
    assert np.abs(pos[:, [1, 2, 4, 5, 6]] - np.array(READY)[[1, 2, 4, 5, 6]]).max() < 0.05
    assert pos[:, 0].max() < target[0] + 0.05
    rc, out, err = proc.stop(signal.SIGINT)
    assert rc == 0, err
    log = out + err
    assert "trajectory rejected (planning error, bad_times)" in log
    assert "executing trajectory: 1 points" in log


@pytest.mark.timeout(60)
def test_fast_mode_publishes_clock(ros_context, spawn):
    from rosgraph_msgs.msg import Clock

    proc = spawn(sim_cmd("real_time:=false", "publish_rate_hz:=100.0"))
    node, got = probe(ros_context)
    clocks: list = []
    node.create_subscription(Clock, "/clock", clocks.append, 100)
    try:
        spin_until(ros_context, node, lambda: len(clocks) >= 20 and len(got["js"]) >= 20, 30,
                   "/clock and joint_states")
    finally:
        node.destroy_node()
    t = np.array([c.clock.sec + c.clock.nanosec * 1e-9 for c in clocks])
    assert np.all(np.diff(t) > 0)
    # Simulation time from 0, in 10 ms publish steps.
    np.testing.assert_allclose(np.round(t / 0.01) * 0.01, t, atol=2e-9)
    rc, _, err = proc.stop(signal.SIGINT)
    assert rc == 0, err


def _byte_fields(ros_type, prefix: str = "") -> set[str]:
    """Every byte (octet) and uint8 field of a message type, nested messages and sequences
    included, as "<type>.<field>" (read from rosidl's own type definitions)."""
    import importlib

    from rosidl_parser.definition import AbstractNestedType, BasicType, NamespacedType

    out: set[str] = set()
    for name, slot in zip(ros_type.get_fields_and_field_types(), ros_type.SLOT_TYPES):
        while isinstance(slot, AbstractNestedType):
            slot = slot.value_type
        if isinstance(slot, BasicType) and slot.typename in ("octet", "uint8"):
            out.add(f"{ros_type.__name__}.{name}")
        elif isinstance(slot, NamespacedType):
            nested = getattr(importlib.import_module(".".join(slot.namespaces)), slot.name)
            out |= _byte_fields(nested)
    return out


@pytest.mark.timeout(60)
def test_byte_fields_written_by_dyn_node_and_dyn_sim(ros_context):
    """The byte fields our publishers and services write: exactly DiagnosticStatus.level and
    SelfTest's passed, both set through ros_convert.to_byte (rclpy sends a garbage byte for a
    bool). rclpy's own parameter topic and services are not ours. A new output with a byte
    field must be added here, and converted the same way."""
    from rclpy.parameter import Parameter

    from dyn_node.ros.node import DynNode
    from dyn_node.ros.sim_node import SimNode

    nodes = [DynNode("bytes_node", context=ros_context, namespace="/bytes",
                     parameter_overrides=[Parameter("robot_model", value="planar_2link")]),
             SimNode(context=ros_context, namespace="/bytes",
                     parameter_overrides=[Parameter("robot_model", value="planar_2link"),
                                          Parameter("publish_rate_hz", value=1.0)])]
    try:
        types = set()
        for node in nodes:
            types |= {p.msg_type for p in node.publishers if p.topic_name != "/parameter_events"}
            for srv in node.services:
                if srv.srv_type.__module__.split(".")[0] not in ("rcl_interfaces", "type_description_interfaces"):
                    types |= {srv.srv_type.Request, srv.srv_type.Response}
        assert {t.__name__ for t in types} >= {"JointState", "DiagnosticArray", "DiagnosticStatus",
                                                "JointTrajectory", "String", "SelfTest_Response"}
        found = set().union(*(_byte_fields(t) for t in types))
        assert found == {"DiagnosticStatus.level", "SelfTest_Response.passed"}
    finally:
        for node in reversed(nodes):
            node.destroy_node()


def stamp_ns(m) -> int:
    return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec


def wrench_of(m) -> np.ndarray:
    f, t = m.wrench.force, m.wrench.torque
    return np.array([f.x, f.y, f.z, t.x, t.y, t.z])


def wrench_msg(frame: str, x):
    from geometry_msgs.msg import WrenchStamped

    msg = WrenchStamped()
    msg.header.frame_id = frame
    f, m = msg.wrench.force, msg.wrench.torque
    f.x, f.y, f.z, m.x, m.y, m.z = (float(v) for v in x)
    return msg


def pushing(ros_context, spawn, *params: str):
    """dyn_sim started with ``params``, a probe with ~/applied_wrench, and a ~/apply_wrench
    publisher, once dyn_sim is up: (process, probe node, joint_states, applied, publisher)."""
    from geometry_msgs.msg import WrenchStamped

    proc = spawn(sim_cmd(*params))
    node, got = probe(ros_context)
    applied = applied_probe(node)
    pub = node.create_publisher(WrenchStamped, "/dyn_sim/apply_wrench", 10)
    try:
        spin_until(ros_context, node, lambda: len(got["js"]) >= 5 and pub.get_subscription_count() > 0,
                   30, "dyn_sim to come up")
    except AssertionError:
        node.destroy_node()
        raise
    return proc, node, got, applied, pub


def applied_probe(node) -> list:
    """dyn_sim's ~/applied_wrench, as it arrives (transient-local, like its publisher)."""
    from geometry_msgs.msg import WrenchStamped

    from dyn_node.ros.qos import LATCHED_HISTORY

    got: list = []
    node.create_subscription(WrenchStamped, "/dyn_sim/applied_wrench", got.append, LATCHED_HISTORY)
    return got


@pytest.mark.timeout(60)
@pytest.mark.parametrize("hold_steps,rate", [(50, 500.0), (5, 100.0)])
def test_applied_wrench_ends_when_the_hold_runs_out(ros_context, spawn, hold_steps, rate):
    """A push held for ``hold_steps`` 1 ms steps: ~/applied_wrench says it began and, that many
    steps later to the nanosecond, that it ended (a zero wrench at the same link); also when the
    whole push fits between two joint_states (5 steps at 100 Hz: 10 steps a sample)."""
    _, node, got, applied, pub = pushing(ros_context, spawn, f"apply_wrench_hold:={hold_steps / 1000}",
                                         f"publish_rate_hz:={rate}")
    try:
        pub.publish(wrench_msg("panda_hand", [0.0, -12.0, 0.0, 0.0, 0.0, 0.0]))
        spin_until(ros_context, node, lambda: len(applied) >= 2, 30, "the push to start and end")
    finally:
        node.destroy_node()
    assert [m.header.frame_id for m in applied] == ["panda_hand", "panda_hand"]
    np.testing.assert_array_equal(wrench_of(applied[0]), [0.0, -12.0, 0.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(wrench_of(applied[1]), np.zeros(6))
    assert stamp_ns(applied[1]) - stamp_ns(applied[0]) == hold_steps * 1_000_000


@pytest.mark.timeout(90)
def test_apply_wrench_round_trip(ros_context, spawn):
    """~/apply_wrench over DDS: an unknown frame_id is logged and counted and the simulation keeps
    publishing; a push at the flange settles to effort = g(q) − J_localᵀ·wrench (the controller
    holding the robot against it; Pinocchio's g and Jacobian at the published q); a zero wrench
    ends it (effort = g(q) again)."""
    import pinocchio as pin

    model = load_model(builtin="panda")
    dyn = Dynamics(model)
    pm = model.pin_model
    pdata = pm.createData()
    flange = pm.getFrameId("panda_link8")
    w = np.array([6.0, -4.0, 20.0, 0.0, 0.0, 0.5])

    def held(push: np.ndarray, tol: float) -> Callable[[], bool]:
        def cond() -> bool:
            if not got["js"]:
                return False
            last = got["js"][-1]
            q = np.array(last.position[:7])
            J = pin.computeFrameJacobian(pm, pdata, q, flange, pin.ReferenceFrame.LOCAL)
            expect = dyn.gravity(q) - J.T @ push
            return (np.abs(np.array(last.velocity[:7])).max() < 1e-6
                    and np.abs(np.array(last.effort[:7]) - expect).max() < tol)
        return cond

    proc, node, got, applied, pub = pushing(ros_context, spawn, "apply_wrench_hold:=60.0",
                                            "publish_rate_hz:=100.0")
    try:
        pub.publish(wrench_msg("panda_link9", w))
        pub.publish(wrench_msg("panda_link8", w))
        spin_until(ros_context, node, held(w, 1e-4), 30, "the robot to settle against the push")
        pushed_q = np.array(got["js"][-1].position[:7])
        pub.publish(wrench_msg("panda_link8", np.zeros(6)))
        spin_until(ros_context, node, held(np.zeros(6), 1e-4), 30, "the robot to settle after the push")
    finally:
        node.destroy_node()
    # the push moved the robot (it is held by a PD controller, not infinitely stiff)
    assert np.abs(pushed_q - READY).max() > 1e-3
    # ~/applied_wrench: the push (not the rejected one) stamped with the step it began acting on:
    # the state published at that stamp is still at rest, the next one moves
    assert [m.header.frame_id for m in applied] == ["panda_link8", "panda_link8"]
    start, end = (stamp_ns(m) for m in applied)
    np.testing.assert_array_equal(wrench_of(applied[0]), w)
    np.testing.assert_array_equal(wrench_of(applied[1]), np.zeros(6))
    v_at = {stamp_ns(m): np.abs(np.array(m.velocity[:7])).max() for m in got["js"]}
    after = min(t for t in v_at if t > start)
    assert v_at[start] < 1e-9 < 1e-6 < v_at[after]
    assert start < end <= stamp_ns(got["js"][-1])
    np.testing.assert_allclose(got["js"][-1].position[:7], READY, atol=1e-6)
    rc, out, err = proc.stop(signal.SIGINT)
    assert rc == 0, err
    log = out + err
    assert "apply_wrench rejected (state error, unknown_frame): 'panda_link9' is not a link" in log
    assert "(1 rejected so far)" in log
    assert "apply_wrench: 21.3 N, 0.5 N·m at panda_link8 (MuJoCo body panda_link8) for 60 s" in log
