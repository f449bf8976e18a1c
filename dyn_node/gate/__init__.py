"""The FollowJointTrajectory gate's decisions, pure (no rclpy): check a goal like an executed
trajectory and forward, reject or retime it (docs/gate.md). The ROS side is
:mod:`dyn_node.ros.gate`."""
