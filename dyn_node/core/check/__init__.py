"""The feasibility check of a trajectory: the constraint kinds and their registry, force laws, frames and task motion, the start segment, on-demand checks."""
