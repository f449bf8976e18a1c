"""dyn_sim's ROS adapter: :mod:`~dyn_node.ros.sim.node` (the node and its process entry, started as
``dyn_sim`` or ``python -m dyn_node.ros.sim_node``), :mod:`~dyn_node.ros.sim.action` (the
joint_trajectory_controller's interfaces) and :mod:`~dyn_node.ros.sim.physics` (scene, contact
truth, physics status). The simulation itself is :mod:`dyn_node.sim` (no rclpy)."""
