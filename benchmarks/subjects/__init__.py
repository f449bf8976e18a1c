"""ROS processes measured by the live benchmark (each runnable with ``python -m``)."""
