"""The pure core: model, limits, dynamics, trajectories, the feasibility check and its constraint kinds, the live monitor. Never imports rclpy."""
