"""The retime benchmark's panel, shared by retime_bench and retime_start_bench: each robot with
acceleration, jerk, 40 % effort and effort-rate limits, and random timed paths inside them."""
from __future__ import annotations

import numpy as np

PANDA_ACC = [15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0]
PANDA_JERK = [7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0]


def robot(name: str):
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.robot.model import load_model

    m = load_model(builtin=name)
    n = m.nv
    acc = PANDA_ACC if name == "panda" else [8.0] * n
    jerk = PANDA_JERK if name == "panda" else [4000.0] * n
    lim = {j: {"has_acceleration_limits": True, "max_acceleration": a, "has_jerk_limits": True,
               "max_jerk": jk, "has_effort_limits": True, "max_effort": 0.4 * float(e),
               "max_effort_rate": 1000.0}
           for j, a, jk, e in zip(m.limits.names, acc, jerk, m.limits.effort)}
    return Dynamics(m.with_limits({"joint_limits": lim}))


def panel(dyn, n_paths: int, seed: int, n_waypoints: int = 6) -> list:
    """``n_paths`` random timed paths (see the module docstring)."""
    from dyn_node.core.check.trajectory import Trajectory, interpolate

    rng = np.random.default_rng(seed)
    lim = dyn.model.limits
    lo, hi = lim.position_lower, lim.position_upper
    out = []
    while len(out) < n_paths:
        P = lo + (hi - lo) * (0.1 + 0.8 * rng.random((n_waypoints, dyn.model.nv)))
        steps = np.max(np.abs(np.diff(P, axis=0)) / lim.velocity, axis=1) * 1.5
        tr = Trajectory(times=np.concatenate(([0.0], np.cumsum(steps))), positions=P)
        q = interpolate(tr, "spline").evaluate(np.linspace(0, tr.duration, 200))[0]
        if np.all(np.abs(dyn.gravity_batch(q)) < 0.8 * lim.effort) and \
                np.all((q > lo) & (q < hi)):
            out.append(tr)
    return out
