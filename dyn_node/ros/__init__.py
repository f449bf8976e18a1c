"""The ROS 2 adapter: the nodes, message conversion, the recording bridge, the client library and the demo. The only subpackage that imports rclpy."""
