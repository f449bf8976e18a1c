"""dyn_node: can the actuators deliver the motion being asked for?"""

__version__ = "0.1.0"
