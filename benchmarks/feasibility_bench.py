"""Section "feasibility": a 10 s 7-DoF trajectory checked at 1 ms against a bare rnea loop.

The subject is dyn_node.feasibility.check_trajectory (interpolation, RNEA at every sample, every
limit kind, the time scale, the payload margin). The baseline is what the torque part alone
costs when written by hand: a Python loop calling pinocchio.rnea on the same samples (the states
check_trajectory itself evaluates, from its own sampler and interpolation). Ratio = check / loop.
The headline row runs the check on one thread, as the live node does; the next runs it without
the payload margin (the issues' targets name every limit kind and the time scale, not the
margin); a third runs its batched RNEA passes on every core (same result), and the last times
those passes alone: the floor under every other row.

Those rows run with freed memory kept mapped (dyn_node.allocator.retain_freed_memory, which the
dyn_node and dyn-audit entry points call): a check's sample arrays then reuse the previous
check's pages. One more row, measured first because the setting cannot be undone, runs the check
under glibc's defaults, where every check faults its arrays in afresh; each row records the
minor page faults per check.
"""
from __future__ import annotations

import os
import resource
import statistics

import numpy as np
import pinocchio as pin

from dyn_node.allocator import retain_freed_memory
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


def _rounds(subjects: dict, repeats: int) -> tuple[dict[str, list[float]], dict[str, list[int]]]:
    """Interleaved rounds (each subject once per round, after one warm-up call each): the
    machine is shared, so each figure is a median and each ratio compares figures taken side
    by side. Also the minor page faults of every call."""
    times: dict[str, list[float]] = {k: [] for k in subjects}
    faults: dict[str, list[int]] = {k: [] for k in subjects}
    for fn in subjects.values():
        fn()
    for _ in range(repeats):
        for key, fn in subjects.items():
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            t, _ = median_time(fn, 1, warmup=0)
            faults[key].append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
            times[key].append(t)
    return times, faults


def run(quick: bool = False, smoke: bool = False) -> dict:
    why = module_available("feasibility")
    if why:
        raise NotAvailable(why)
    from dyn_node import feasibility as F

    repeats = 1 if smoke else 5 if quick else 9
    model = load_model(builtin="panda").with_limits(None)
    model = model.with_limits(every_limit_kind(model))
    dyn = Dynamics(model)
    traj = trajectory(model)
    cores = os.cpu_count() or 1
    options = F.FeasibilityOptions(sample_period=SAMPLE_PERIOD_S, threads=1)
    options_mt = F.FeasibilityOptions(sample_period=SAMPLE_PERIOD_S, threads=cores)
    options_nm = F.FeasibilityOptions(sample_period=SAMPLE_PERIOD_S, threads=1,
                                      compute_payload_margin=False)
    progress("feasibility", "check_trajectory on a 10 s 7-DoF trajectory at 1 ms")
    result = F.check_trajectory(dyn, traj, options)
    result_mt = F.check_trajectory(dyn, traj, options_mt)
    if result_mt.to_dict() | {"compute_time_s": 0} != result.to_dict() | {"compute_time_s": 0}:
        raise RuntimeError("check_trajectory gave different results with 1 and "
                           f"{cores} threads")

    # the very states the check evaluates (its sampler and interpolation: every segment's
    # ends included, so an interior waypoint appears twice)
    pp = F.interpolate(traj, result.interpolation)
    smp = F._sample(traj.times, SAMPLE_PERIOD_S, options.max_samples)
    Q, V, A = F._evaluate(pp.coeffs, pp.breaks, smp, 3)
    pm = model.pin_model
    data = pm.createData()

    def loop():
        for i in range(len(Q)):
            pin.rnea(pm, data, Q[i], V[i], A[i])

    def rnea_passes(threads: int, payload: bool = True):
        # the batched RNEA work inside the check: gravity and full (the time scale needs both),
        # and with the payload margin a third with 1 kg more
        def f():
            dyn.terms_batch(Q, V, A, threads)
            if payload:
                F._unit_payload_dynamics(dyn).rnea_batch(Q, V, A, threads)
        return f

    progress("feasibility", f"baseline: Python loop of pinocchio.rnea over {len(Q)} samples; "
                            f"check with 1 and {cores} threads")
    subjects = {"check": lambda: F.check_trajectory(dyn, traj, options),
                "check_nm": lambda: F.check_trajectory(dyn, traj, options_nm),
                "check_mt": lambda: F.check_trajectory(dyn, traj, options_mt),
                "loop": loop, "passes": rnea_passes(1), "passes_mt": rnea_passes(cores),
                "passes_nm": rnea_passes(1, payload=False)}
    # first with glibc's default heap settings, then as the node runs (dyn_node.allocator:
    # freed memory kept mapped); the setting is process-wide and cannot be undone, so in order
    progress("feasibility", "the check without the margin under glibc's default heap settings")
    default = {"check_nm": subjects["check_nm"], "loop": loop}
    times_default, faults_default = _rounds(default, repeats)
    applied = retain_freed_memory()
    progress("feasibility", "the same rounds with freed memory kept mapped, as the node runs"
                            if applied else "heap setting not available here (not glibc)")
    times, faults = _rounds(subjects, repeats)
    med = {k: statistics.median(v) for k, v in times.items()}
    med_default = {k: statistics.median(v) for k, v in times_default.items()}
    return dict(n_samples=int(len(Q)), nv=model.nv, duration_s=DURATION_S, repeats=repeats,
                check_s=med["check"], rnea_loop_s=med["loop"], ratio=med["check"] / med["loop"],
                threads=1, cores=cores,
                check_no_margin_s=med["check_nm"], ratio_no_margin=med["check_nm"] / med["loop"],
                heap_retained=bool(applied),
                page_faults_per_check=int(statistics.median(faults["check_nm"])),
                check_no_margin_default_heap_s=med_default["check_nm"],
                rnea_loop_default_heap_s=med_default["loop"],
                ratio_no_margin_default_heap=med_default["check_nm"] / med_default["loop"],
                page_faults_per_check_default_heap=int(statistics.median(faults_default["check_nm"])),
                what_default_heap="the check without the margin under glibc's default heap "
                                  "settings (each check faults its arrays in afresh), rounds "
                                  "before the rows above, against the loop in the same rounds",
                rnea_passes_no_margin_s=med["passes_nm"],
                check_all_cores_s=med["check_mt"], ratio_all_cores=med["check_mt"] / med["loop"],
                rnea_passes_s=med["passes"], rnea_passes_all_cores_s=med["passes_mt"],
                feasible=bool(result.feasible), time_scale=float(result.time_scale),
                interpolation=str(result.interpolation), n_points=int(result.n_points),
                what="check_trajectory on one thread (as the node runs it: all limit kinds, "
                     "time scale, payload margin; freed memory kept mapped) vs a Python loop of "
                     "pinocchio.rnea on the same samples",
                what_no_margin="the same check without the payload margin "
                               "(FeasibilityOptions(compute_payload_margin=False)): every limit "
                               "kind and the time scale, what the targets name",
                what_all_cores=f"the same check with FeasibilityOptions(threads={cores}): "
                               f"its batched RNEA passes on {cores} OpenMP threads and the RMS "
                               "time-scale search and payload margin on a second Python thread "
                               "(identical result, checked) vs the same one-thread Python loop",
                what_rnea_passes="the three batched RNEA passes alone (gravity, full, 1 kg "
                                 "payload) that the check makes, on 1 thread and on all cores: "
                                 "the floor of the check with the margin",
                what_rnea_passes_no_margin="the two batched RNEA passes alone (gravity, full) "
                                           "that the time scale needs, on 1 thread: the floor "
                                           "of the check without the margin")
