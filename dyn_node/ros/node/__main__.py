"""``python -m dyn_node.ros.node``: the node's process entry."""
from dyn_node.ros.node import main

main()
