"""QoS profiles shared by the ROS adapter's publishers and the subscribers that read them."""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

#: reliable, transient-local, the last 10 kept: answers and events a late or slow reader must
#: still get in full (~/feasibility, dyn_sim's ~/applied_wrench); with depth 1 a burst overwrote
#: messages a reader had not acknowledged yet
LATCHED_HISTORY = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             history=HistoryPolicy.KEEP_LAST)
