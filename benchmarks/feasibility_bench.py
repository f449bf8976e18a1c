"""Section "feasibility": a 10 s 7-DoF trajectory checked at 1 ms against a bare rnea loop.

Ratio = check_trajectory ÷ a Python loop of pinocchio.rnea over the same samples; one thread as
the node runs it, plus rows without the margin, on every core, and the torque passes alone. Every
figure comes from fresh child processes, since the loop's speed varies between processes. Rows
and method: docs/BENCHMARK_METHODS.md.
"""
from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin

from dyn_node.core.live.allocator import retain_freed_memory
from dyn_node.core.check import task_motion
from dyn_node.core.compiled import kernels, rigid_kernels
from dyn_node.core.robot.dynamics import gravity_tables

from . import frames_bench, task_feasibility
from .common import NotAvailable, median_time, module_available, progress
from .feasibility_subject import DURATION_S, SAMPLE_PERIOD_S, every_limit_kind, setup as _setup, trajectory  # noqa: F401 - re-exported

#: fresh processes the figures are taken over (see run())
PROCESSES = 3


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


def _measure(mode: str, repeats: int) -> dict:
    """In a fresh process (argv: ``measure <mode> <repeats>``): every subject in interleaved
    rounds, with freed memory kept mapped (``retain``, as the node runs) or under glibc's
    defaults (``default``). Per subject: the median time (s) and minor page faults per call;
    per check: its median ratio to the loop over the rounds."""
    applied = retain_freed_memory() if mode == "retain" else False
    F, dyn, traj, options, loop, (Q, V, A) = _setup()
    cores = os.cpu_count() or 1

    def rnea_passes(threads: int, payload: bool = True):
        # the torque work inside the check: its terms (gravity, viscous, inertial: the time scale
        # needs them) and with the payload margin τ per kg more. One thread: the compiled frame
        # pass the check takes; several: Pinocchio's batched RNEA on OpenMP threads, the route
        # the check takes for a model the kernels cannot take
        def compiled():
            task_motion.joint_terms(dyn, Q, V, A, payload_torque=payload)

        def pinocchio():
            dyn.terms_batch(Q, V, A, threads)
            if payload:
                F._unit_payload_dynamics(dyn).rnea_batch(Q, V, A, threads)
        return compiled if threads == 1 else pinocchio

    tables, G = gravity_tables(dyn._pm), np.empty((dyn.nv, len(Q)), order="F")
    pool, Z = pin.ModelPool(dyn._pm, 1), np.zeros_like(Q)

    def gravity_kernel():
        rigid_kernels.gravity_rows(Q, *tables, G.T)

    def gravity_rnea():
        # what the check used before the kernel: Pinocchio's RNEA at v = a = 0
        pin.rneaInParallel(1, pool, Q.T, Z.T, Z.T, G)

    subjects = {"check": lambda: F.check_trajectory(dyn, traj, options["check"]),
                "check_nm": lambda: F.check_trajectory(dyn, traj, options["check_nm"]),
                "check_mt": lambda: F.check_trajectory(dyn, traj, options["check_mt"]),
                "check_nm_mt": lambda: F.check_trajectory(dyn, traj, options["check_nm_mt"]),
                "loop": loop, "passes": rnea_passes(1), "passes_mt": rnea_passes(cores),
                "passes_nm": rnea_passes(1, payload=False),
                "gravity_kernel": gravity_kernel, "gravity_rnea": gravity_rnea,
                **frames_bench.subjects(dyn.model, Q, V, A)}
    if mode == "retain":
        # not beside the default-heap rows: its larger arrays raise glibc's dynamic mmap
        # threshold, which would hide the page faults those rows exist to show
        subjects.update(_task_subjects(F, dyn, traj, options))
    times, faults = _rounds(subjects, repeats)
    return dict(mode=mode, applied=bool(applied),
                median_s={k: statistics.median(v) for k, v in times.items()},
                faults={k: int(statistics.median(v)) for k, v in faults.items()},
                ratio={k: statistics.median(t / base for t, base in zip(v, times["loop"]))
                       for k, v in times.items() if k != "loop"})


def _task(F, dyn, traj, options):
    """Issue 18's subject (see task_feasibility): (its Dynamics, subjects) or why not available."""
    return task_feasibility.setup(F, every_limit_kind(dyn.model), traj, options)


def _task_subjects(F, dyn, traj, options) -> dict:
    task = _task(F, dyn, traj, options)
    return {} if isinstance(task, str) else task[1]


def _task_row(F, dyn, traj, options, runs: list[dict]) -> dict:
    task = _task(F, dyn, traj, options)
    if isinstance(task, str):
        return task_feasibility.row(runs, None, task)
    result = F.check_trajectory(task[0], traj, options["check"])
    return task_feasibility.row(runs, result, task_feasibility.coverage_gap(result))


def _measure_in_child(mode: str, repeats: int) -> dict:
    out = subprocess.run([sys.executable, "-m", "benchmarks.feasibility_bench", "measure", mode,
                          str(repeats)], capture_output=True, text=True, timeout=600,
                         cwd=Path(__file__).resolve().parents[1])
    if out.returncode:
        raise RuntimeError(f"measuring child ({mode}) failed: {out.stderr.strip()[-500:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def run(quick: bool = False, smoke: bool = False) -> dict:
    why = module_available("core.check.feasibility")
    if why:
        raise NotAvailable(why)

    repeats = 1 if smoke else 5 if quick else 9
    processes = 1 if smoke else PROCESSES
    F, dyn, traj, options, _, (Q, _, _) = _setup()
    cores = os.cpu_count() or 1
    progress("feasibility", "check_trajectory on a 10 s 7-DoF trajectory at 1 ms")
    result = F.check_trajectory(dyn, traj, options["check"])
    result_mt = F.check_trajectory(dyn, traj, options["check_mt"])
    if result_mt.to_dict() | {"compute_time_s": 0} != result.to_dict() | {"compute_time_s": 0}:
        raise RuntimeError("check_trajectory gave different results with 1 and "
                           f"{cores} threads")
    # The loop's speed differs between processes far more than the check's, so one process can
    # flatter either side: every figure is the median over several fresh processes of that
    # process's medians, and each ratio the
    # median over processes of the per-round ratios. One more process runs under glibc's
    # default heap settings (the setting is process-wide and cannot be undone).
    runs = []
    for n in range(processes):
        progress("feasibility", f"process {n + 1}/{processes}: {repeats} interleaved rounds of "
                                f"the checks, the loop over {len(Q)} samples and the RNEA passes")
        runs.append(_measure_in_child("retain", repeats))
    progress("feasibility", "one more process under glibc's default heap settings")
    default = _measure_in_child("default", repeats)

    def med(key: str) -> float:
        return statistics.median(r["median_s"][key] for r in runs)

    def ratio(key: str) -> float:
        return statistics.median(r["ratio"][key] for r in runs)

    return dict(task=_task_row(F, dyn, traj, options, runs),
                n_samples=int(len(Q)), nv=dyn.nv, duration_s=DURATION_S, repeats=repeats,
                processes=processes,
                check_s=med("check"), rnea_loop_s=med("loop"), ratio=ratio("check"),
                threads=1, cores=cores,
                check_no_margin_s=med("check_nm"), ratio_no_margin=ratio("check_nm"),
                ratio_no_margin_by_process=[r["ratio"]["check_nm"] for r in runs],
                rnea_loop_by_process_s=[r["median_s"]["loop"] for r in runs],
                heap_retained=all(r["applied"] for r in runs),
                page_faults_per_check=int(statistics.median(r["faults"]["check_nm"] for r in runs)),
                heap={"default": dict(check_s=default["median_s"]["check_nm"],
                                      loop_s=default["median_s"]["loop"],
                                      ratio=default["ratio"]["check_nm"],
                                      faults=default["faults"]["check_nm"]),
                      "retain": dict(check_s=runs[0]["median_s"]["check_nm"],
                                     loop_s=runs[0]["median_s"]["loop"],
                                     ratio=runs[0]["ratio"]["check_nm"],
                                     faults=runs[0]["faults"]["check_nm"])},
                what_heap="the check without the margin in one fresh process, against the loop "
                          "in the same process: glibc's default heap settings, then (the first "
                          "of the processes above) freed memory kept mapped",
                rnea_passes_no_margin_s=med("passes_nm"), ratio_passes_no_margin=ratio("passes_nm"),
                check_all_cores_s=med("check_mt"), ratio_all_cores=ratio("check_mt"),
                check_no_margin_all_cores_s=med("check_nm_mt"),
                ratio_no_margin_all_cores=ratio("check_nm_mt"),
                what_no_margin_all_cores=f"the check without the margin with "
                                         f"FeasibilityOptions(threads={cores}) (what dyn-audit "
                                         "could use offline; the node keeps one thread so that "
                                         "joint_states keep a core) vs the same one-thread loop",
                rnea_passes_s=med("passes"), rnea_passes_all_cores_s=med("passes_mt"),
                ratio_passes=ratio("passes"), ratio_passes_all_cores=ratio("passes_mt"),
                feasible=bool(result.feasible), time_scale=float(result.time_scale),
                interpolation=str(result.interpolation), n_points=int(result.n_points),
                what="check_trajectory on one thread (as the node runs it: all limit kinds, "
                     "time scale, payload margin; freed memory kept mapped) vs a Python loop of "
                     "pinocchio.rnea on the same samples",
                what_no_margin="the same check without the payload margin "
                               "(FeasibilityOptions(compute_payload_margin=False)): every limit "
                               "kind and the time scale, what the targets name",
                what_all_cores=f"the same check with FeasibilityOptions(threads={cores}): "
                               "its RMS time-scale search and payload margin on a second Python "
                               "thread (the compiled torque pass stays on one) "
                               "(identical result, checked) vs the same one-thread Python loop",
                what_rnea_passes="the torque work alone that the check with the margin makes "
                                 "(torque terms and τ per kg of payload): the compiled frame pass "
                                 "the check takes, on 1 thread / Pinocchio's batched RNEA (the "
                                 "route for models the kernels cannot take) on all cores",
                what_rnea_passes_no_margin="the torque terms alone that the time scale needs (the "
                                           "compiled frame pass the check takes: gravity, viscous "
                                           "and inertial terms), on 1 thread: the floor of the "
                                           "check without the margin",
                gravity_kernel_s=med("gravity_kernel"), gravity_rnea_s=med("gravity_rnea"),
                ratio_gravity_kernel=ratio("gravity_kernel"),
                ratio_gravity_rnea=ratio("gravity_rnea"),
                what_gravity="g(q) on the same states, 1 thread: the compiled kernel the check "
                             "uses (kernels.gravity_rows) and Pinocchio's batched RNEA at "
                             "v = a = 0 (what it used before)",
                frame_kernels_s=med("frame_kernels"), ratio_frame_kernels=ratio("frame_kernels"),
                frame_kinematics_s=med("frame_kinematics"),
                ratio_frame_kinematics=ratio("frame_kinematics"),
                what_frame_kernels=frames_bench.WHAT)


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "measure":
        print(json.dumps(_measure(sys.argv[2], int(sys.argv[3]))))
    else:
        raise SystemExit("usage: python -m benchmarks.feasibility_bench measure retain|default "
                         "REPEATS")
