"""Subject (b): the minimal node a user would write by hand instead of running dyn_node.

Subscribe to joint_states, reorder by name, estimate acceleration by finite differences of the
velocity over header stamps, call pinocchio.rnea and computeGeneralizedGravity, publish two
JointStates (``~/gravity_torque`` and ``~/inverse_dynamics``) with the input's stamp. No checks,
no diagnostics, no recording.
"""
from __future__ import annotations

import sys

import numpy as np
import pinocchio as pin
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from sensor_msgs.msg import JointState

from dyn_node.core.robot.model import load_model


class MinimalNode(Node):
    def __init__(self, robot: str) -> None:
        super().__init__("minimal_node")
        model = load_model(builtin=robot)
        self.pm = model.pin_model
        self.data = self.pm.createData()
        self.names = list(model.joint_names)
        self.prev: tuple[float, np.ndarray] | None = None
        self.pub_g = self.create_publisher(JointState, "~/gravity_torque", 10)
        self.pub_id = self.create_publisher(JointState, "~/inverse_dynamics", 10)
        self.create_subscription(JointState, "joint_states", self.on_joint_states, 10)

    def on_joint_states(self, msg: JointState) -> None:
        idx = [msg.name.index(n) for n in self.names]
        q = np.array([msg.position[i] for i in idx])
        v = np.array([msg.velocity[i] for i in idx])
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        a = np.zeros_like(v)
        if self.prev is not None and t > self.prev[0]:
            a = (v - self.prev[1]) / (t - self.prev[0])
        self.prev = (t, v)
        g = pin.computeGeneralizedGravity(self.pm, self.data, q)
        tau = pin.rnea(self.pm, self.data, q, v, a)
        for pub, effort in ((self.pub_g, g), (self.pub_id, tau)):
            out = JointState()
            out.header = msg.header
            out.name = self.names
            out.position = q.tolist()
            out.velocity = v.tolist()
            out.effort = effort.tolist()
            pub.publish(out)


def main() -> None:
    rclpy.init(args=sys.argv)
    robot = sys.argv[1] if len(sys.argv) > 1 and not sys.argv[1].startswith("-") else "panda"
    node = MinimalNode(robot)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
