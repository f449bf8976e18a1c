"""The node's start-up lines, read from its log output on /rosout: one ``model ready`` line on
every model path (a model parameter, the robot_description topic, a parameter change) and one
``first joint_states accepted`` line per model (issue 27: a correct start used to print nothing)."""
from __future__ import annotations

import hashlib
import xml.etree.ElementTree as ET

import pytest
import rclpy
from rcl_interfaces.msg import Log
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from conftest import Collected, Spinner, js
from dyn_node.core.robot.model import builtin_urdf
from dyn_node.ros.node import DynNode

PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]
FINGERS = ["panda_finger_joint1", "panda_finger_joint2"]  # locked in the built-in panda
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
ROSOUT = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL)


class LogHarness(Collected):
    """A probe that collects the node's /rosout lines (subscribed before the node exists, so
    its constructor's lines are caught too), then the node itself."""

    def __init__(self, ctx, namespace: str, overrides: list[Parameter]):
        super().__init__(("log",))
        self.ctx = ctx
        self.probe = rclpy.create_node("probe", namespace=namespace, context=ctx)
        logger = namespace.strip("/") + ".dyn_node"
        collect = self.collector("log")
        self.probe.create_subscription(
            Log, "/rosout", lambda m: collect(m.msg) if m.name == logger else None, ROSOUT)
        self.js_pub = self.probe.create_publisher(JointState, "joint_states", 10)
        self.desc_pub = self.probe.create_publisher(String, "robot_description", LATCHED)
        self.node = DynNode(namespace=namespace, context=ctx, parameter_overrides=overrides)
        self.spinner = Spinner(ctx, (self.node, self.probe))
        assert self.wait(lambda: self.js_pub.get_subscription_count() >= 1), "discovery"

    def lines(self, prefix: str) -> list[str]:
        with self.cond:
            return [m for m in self.got["log"] if m.startswith(prefix)]

    def wait_lines(self, prefix: str, n: int) -> list[str]:
        assert self.wait(lambda: len(self.lines(prefix)) >= n), (
            f"fewer than {n} lines {prefix!r}: {self.got['log']}")
        return self.lines(prefix)

    def close(self) -> None:
        self.spinner.stop()
        self.node.destroy_node()
        self.probe.destroy_node()


def test_model_parameter_path_and_parameter_change(module_ros_context, tmp_path):
    lim = tmp_path / "panda_limits.yaml"
    lim.write_bytes(b"joint_limits:\n  panda_joint1:\n    has_velocity_limits: true\n"
                    b"    max_velocity: 2.0\n")
    digest = hashlib.sha256(lim.read_bytes()).hexdigest()[:12]
    h = LogHarness(module_ros_context, "/startup_a", [
        Parameter("robot_model", value="panda"), Parameter("limits_file", value=str(lim)),
        Parameter("payload.mass", value=1.5), Parameter("payload.com", value=[0.0, 0.0, 0.1]),
        Parameter("payload.frame", value="panda_link7"), Parameter("include_friction", value=False)])
    try:
        line, = h.wait_lines("model ready:", 1)
        assert line.startswith("model ready: panda from ")
        assert ", 7 DoF, joints " + ", ".join(PANDA_JOINTS) + ";" in line
        assert f"; limits {lim} (sha256 {digest}) over the URDF;" in line
        assert "; payload 1.5 kg at [0, 0, 0.1] m in panda_link7;" in line
        assert line.endswith("; friction off; recording off")
        assert h.lines("first joint_states") == []  # nothing accepted yet
        for k in range(3):
            h.js_pub.publish(js(PANDA_JOINTS + FINGERS, [0.1] * 9, [0.0] * 9,
                                stamp=5.0 + k * 0.001))
        first, = h.wait_lines("first joint_states accepted", 1)
        assert first == ("first joint_states accepted for panda: stamp 5.000000 s, 7 model "
                         "joints (2 other names ignored: locked or unknown joints); answering "
                         "on ~/gravity_torque and ~/inverse_dynamics")
        # A parameter that rebuilds the model: a new line with the new payload, and a new
        # first-message line for the new model; a parameter that does not: no line.
        h.node.set_parameters([Parameter("diagnostics_period", value=0.5)])
        h.node.set_parameters([Parameter("payload.mass", value=2.0)])
        second = h.wait_lines("model ready:", 2)[1]
        assert "; payload 2 kg at [0, 0, 0.1] m in panda_link7;" in second
        h.js_pub.publish(js(PANDA_JOINTS, [0.1] * 7, [0.0] * 7, stamp=6.0))
        again = h.wait_lines("first joint_states accepted", 2)[1]
        assert again.startswith("first joint_states accepted for panda: stamp 6.000000 s, 7 "
                                "model joints;")
        assert len(h.lines("model ready:")) == 2 and len(h.lines("first joint_states")) == 2
    finally:
        h.close()


def test_topic_path_with_recording_on(module_ros_context, tmp_path):
    planar = builtin_urdf("planar_2link")
    dynamics = [d.attrib for d in ET.fromstring(planar).iter("dynamics")]
    has_friction = any(float(a.get(k, 0)) for a in dynamics for k in ("damping", "friction"))
    h = LogHarness(module_ros_context, "/startup_b", [
        Parameter("record.enabled", value=True), Parameter("record.directory", value=str(tmp_path))])
    try:
        assert h.lines("model ready:") == []  # no model yet: waiting for the topic
        h.desc_pub.publish(String(data=planar))
        line, = h.wait_lines("model ready:", 1)
        bag, = [p for p in tmp_path.iterdir() if p.is_dir()]
        name = ET.fromstring(planar).get("name")
        assert line.startswith(f"model ready: {name} from topic:robot_description, 2 DoF, joints ")
        assert "; limits URDF; payload none; " in line
        assert line.endswith(("; friction on" if has_friction else
                              "; friction on (the URDF has none)") + f"; recording {bag}")
    finally:
        h.close()


@pytest.mark.parametrize("n_joints", [3, 20])
def test_joint_list_is_capped(n_joints):
    """A long joint list is shortened (12 names, then the count of the rest)."""
    from dyn_node.core.robot.model import load_model
    from dyn_node.ros.startup_log import model_ready_line

    links = "".join(f"<link name='l{i}'><inertial><mass value='1'/><inertia ixx='0.1' ixy='0' "
                    "ixz='0' iyy='0.1' iyz='0' izz='0.1'/></inertial></link>"
                    for i in range(n_joints + 1))
    joints = "".join(f"<joint name='j{i}' type='revolute'><parent link='l{i}'/><child link="
                     f"'l{i + 1}'/><axis xyz='0 0 1'/><limit effort='1' velocity='1' lower='-1' "
                     "upper='1'/></joint>" for i in range(n_joints))
    model = load_model(urdf=f"<robot name='chain'>{links}{joints}</robot>")
    line = model_ready_line(model, limits_file="", limits_text=None, friction=True,
                            recording="off")
    shown = [f"j{i}" for i in range(min(n_joints, 12))]
    tail = f" (+{n_joints - 12} more)" if n_joints > 12 else ""
    assert f", {n_joints} DoF, joints {', '.join(shown)}{tail}; limits URDF;" in line
