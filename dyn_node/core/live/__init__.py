"""The live monitor of joint states: windows, results, tracking a trajectory, drops, sample allocation."""
