"""Subject (a): a bare rclpy node that republishes every JointState it receives on ``~/out``.

The floor of the live path: one subscription, one publish, no computation. Same QoS as the
benchmark publisher (reliable, depth 10, like joint_state_broadcaster's).
"""
from __future__ import annotations

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from sensor_msgs.msg import JointState


class BareRepublisher(Node):
    def __init__(self) -> None:
        super().__init__("bare_republisher")
        self.pub = self.create_publisher(JointState, "~/out", 10)
        self.create_subscription(JointState, "joint_states", self.pub.publish, 10)


def main() -> None:
    rclpy.init()
    node = BareRepublisher()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
