"""The robot: its model and limits, settings, rigid-body dynamics, units and the diagnostic status."""
