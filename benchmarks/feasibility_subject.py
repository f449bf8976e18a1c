"""The feasibility benchmark's subject, shared by feasibility_bench and frames_bench (each
imports it; neither imports the other's measurements): a 10 s Panda trajectory, every limit kind
on every joint, and the check's own sampled states with a Pinocchio RNEA loop over them."""
from __future__ import annotations

import os

import numpy as np
import pinocchio as pin

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import load_model

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
    from dyn_node.core.check.trajectory import validate_trajectory

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


def setup():
    """The subject and the baseline: (feasibility module, dynamics, trajectory, options by
    name, the loop over the check's own states, those states)."""
    from dyn_node.core.check import feasibility as F

    model = load_model(builtin="panda").with_limits(None)
    model = model.with_limits(every_limit_kind(model))
    dyn = Dynamics(model)
    traj = trajectory(model)
    cores = os.cpu_count() or 1
    options = {"check": F.FeasibilityOptions(sample_period=SAMPLE_PERIOD_S, threads=1),
               "check_mt": F.FeasibilityOptions(sample_period=SAMPLE_PERIOD_S, threads=cores),
               "check_nm": F.FeasibilityOptions(sample_period=SAMPLE_PERIOD_S, threads=1,
                                                compute_payload_margin=False),
               "check_nm_mt": F.FeasibilityOptions(sample_period=SAMPLE_PERIOD_S, threads=cores,
                                                   compute_payload_margin=False)}
    # the very states the check evaluates (its sampler and interpolation: every segment's
    # ends included, so an interior waypoint appears twice)
    pp = F.interpolate(traj, traj.natural_interpolation)
    smp = F._sample(traj.times, SAMPLE_PERIOD_S, options["check"].max_samples)
    Q, V, A = F._evaluate(pp.coeffs, pp.breaks, smp, 3)
    pm = model.pin_model
    data = pm.createData()

    def loop():
        for i in range(len(Q)):
            pin.rnea(pm, data, Q[i], V[i], A[i])

    return F, dyn, traj, options, loop, (Q, V, A)
