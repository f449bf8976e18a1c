"""The simulated robot: MuJoCo model from the URDF and the simulator (no rclpy; the node is ros.sim_node)."""
