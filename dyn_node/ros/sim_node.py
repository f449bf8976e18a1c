"""``dyn_sim`` and ``python -m dyn_node.ros.sim_node``: the simulator node's entry, kept at this
path for the console script and scripts; the node lives in :mod:`dyn_node.ros.sim.node`."""
from dyn_node.ros.sim.node import SimNode, main

__all__ = ["SimNode", "main"]

if __name__ == "__main__":
    raise SystemExit(main())
