"""The Python client, at the name DESIGN.md gives it: re-exported from the ROS adapter
(:mod:`dyn_node.ros.client`), where it lives because it imports rclpy."""
from dyn_node.ros.client import (BlockingCallError, DynClient, DynClientError, NotRunningError, Retimed,
                                 RequestRejected, RequestTimeout, Verdict, Violation,
                                 states_message, trajectory_message)

__all__ = ["BlockingCallError", "DynClient", "DynClientError", "NotRunningError", "Retimed",
           "RequestRejected", "RequestTimeout", "Verdict", "Violation", "states_message",
           "trajectory_message"]
