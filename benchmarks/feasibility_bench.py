"""Section "feasibility": a 10 s 7-DoF trajectory checked at 1 ms against a bare rnea loop.

The subject is dyn_node.feasibility.check_trajectory (interpolation, RNEA at every sample, every
limit kind, the time scale, the payload margin). The baseline is what the torque part alone
costs when written by hand: a Python loop calling pinocchio.rnea on the same samples (the states
check_trajectory itself evaluates, obtained from the same interpolation). Ratio = check / loop.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from dyn_node.dynamics import Dynamics
from dyn_node.model import load_model

from .common import NotAvailable, median_time, module_available, progress

DURATION_S = 10.0
SAMPLE_PERIOD_S = 0.001


def every_limit_kind(model) -> dict:
    """joint_limits mapping that sets every limit kind on every joint (generous, so the check
    runs to the end and computes margins rather than stopping at a violation)."""
    out = {}
    for name, effort in zip(model.joint_names, model.limits.effort):
        eff = float(effort) if np.isfinite(effort) else 100.0
        out[name] = dict(has_velocity_limits=True, max_velocity=3.0,
                         has_acceleration_limits=True, max_acceleration=15.0,
                         has_jerk_limits=True, max_jerk=7500.0,
                         has_effort_limits=True, max_effort=eff,
                         max_effort_rate=1000.0 * eff, max_rms_effort=0.8 * eff, rms_window=1.0,
                         max_power=500.0, effort_speed_curve=[[0.0, eff], [3.0, 0.5 * eff]])
    return {"joint_limits": out}


def trajectory(model):
    """11 waypoints 1 s apart (positions, velocities, accelerations: quintic), inside limits."""
    from dyn_node.trajectory import validate_trajectory

    rng = np.random.default_rng(4)
    lim = model.limits
    lo = np.where(np.isfinite(lim.position_lower), lim.position_lower, -np.pi)
    hi = np.where(np.isfinite(lim.position_upper), lim.position_upper, np.pi)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    times = np.linspace(0.0, DURATION_S, 11)
    pos = mid + 0.4 * half * np.sin(times[:, None] * 0.6 + np.arange(model.nv))
    vel = 0.4 * half * 0.6 * np.cos(times[:, None] * 0.6 + np.arange(model.nv))
    acc = -0.4 * half * 0.36 * np.sin(times[:, None] * 0.6 + np.arange(model.nv))
    vel[0] = vel[-1] = 0.0
    acc[0] = acc[-1] = 0.0
    return validate_trajectory(model.joint_names, model.joint_names, times, pos, vel, acc)


def run(quick: bool = False, smoke: bool = False) -> dict:
    why = module_available("feasibility")
    if why:
        raise NotAvailable(why)
    from dyn_node.feasibility import FeasibilityOptions, check_trajectory
    from dyn_node.trajectory import interpolate, sample_times

    repeats = 1 if smoke else 3 if quick else 5
    model = load_model(builtin="panda").with_limits(None)
    model = model.with_limits(every_limit_kind(model))
    dyn = Dynamics(model)
    traj = trajectory(model)
    options = FeasibilityOptions(sample_period=SAMPLE_PERIOD_S)
    progress("feasibility", "check_trajectory on a 10 s 7-DoF trajectory at 1 ms")
    result = check_trajectory(dyn, traj, options)
    t_check, _ = median_time(lambda: check_trajectory(dyn, traj, options), repeats)

    ts = sample_times(traj.times, SAMPLE_PERIOD_S)
    Q, V, A, _ = interpolate(traj, result.interpolation if isinstance(result.interpolation, str)
                             and result.interpolation in ("quintic", "cubic", "spline") else None
                             ).evaluate(ts)
    pm = model.pin_model
    data = pm.createData()

    def loop():
        for i in range(len(ts)):
            pin.rnea(pm, data, Q[i], V[i], A[i])

    progress("feasibility", f"baseline: Python loop of pinocchio.rnea over {len(ts)} samples")
    t_loop, _ = median_time(loop, repeats)
    return dict(n_samples=int(len(ts)), nv=model.nv, duration_s=DURATION_S, repeats=repeats,
                check_s=t_check, rnea_loop_s=t_loop, ratio=t_check / t_loop,
                feasible=bool(result.feasible), time_scale=float(result.time_scale),
                interpolation=str(result.interpolation), n_points=int(result.n_points),
                what="check_trajectory (all limit kinds, time scale, payload margin) vs a Python "
                     "loop of pinocchio.rnea on the same samples")
