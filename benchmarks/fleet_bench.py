"""Section "fleet": dyn-fleet's throughput on local Ray with 1 and 2 workers, and what Ray costs.

Steady-state bags/s over warm passes (the first pass, which starts the workers, is reported as
cold), scaling efficiency, Ray's start-up and per-bag overhead, and a worker's peak RSS on short
and long bags. Definitions: docs/BENCHMARK_METHODS.md.
"""
from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path

from .common import NotAvailable, module_available, progress


def _bags(directory: Path, n: int, seconds: float) -> list[Path]:
    from .recording_bench import write_bag

    return [write_bag(directory / f"b{k:03d}", seconds) for k in range(n)]


def _jobs(bags: list[Path], out: Path):
    from dyn_node.fleet import engine as fleet

    cfg = fleet.FleetConfig(robot_model="panda")  # as the recording section's dyn-audit runs
    h = fleet.config_hash(cfg)
    return [fleet.BagJob(str(b), fleet.bag_id(b), str(out), cfg, h) for b in bags]


def _measure(workers: int, jobs, n_msgs: int, warm_passes: int) -> dict:
    from dyn_node.fleet import engine as fleet

    t0 = time.perf_counter()
    with fleet.Engine(workers=workers) as engine:
        start_s = time.perf_counter() - t0
        passes = []
        for _ in range(1 + warm_passes):
            t = time.perf_counter()
            outs = fleet.run_jobs(engine, jobs)
            wall = time.perf_counter() - t
            bad = [o.row["error"] for o in outs if o.row["verdict"] == "error"]
            if bad:
                raise RuntimeError(f"fleet bench bag not ok: {bad[0]}")
            passes.append(dict(wall_s=wall, task_s=sum(o.row["audit_s"] for o in outs)))
    cold = passes[0]
    warm = sorted(passes[1:], key=lambda p: p["wall_s"])[warm_passes // 2]  # the median pass
    n = len(jobs)
    return dict(workers=workers, ray_start_s=start_s, cold_wall_s=cold["wall_s"],
                warm_wall_s=warm["wall_s"], warm_task_s=warm["task_s"],
                bags_per_s=n / warm["wall_s"], msgs_per_s=n_msgs / warm["wall_s"],
                cold_bags_per_s=n / cold["wall_s"],
                per_bag_overhead_s=(warm["wall_s"] * workers - warm["task_s"]) / n,
                mean_task_s=warm["task_s"] / n)


def _rss(jobs_short, jobs_long) -> dict:
    """One worker audits the short bags, then the long ones; VmHWM after each (MiB)."""
    from dyn_node.fleet import engine as fleet

    def audited_with_hwm(job):  # pickled by value: runs in the worker
        from dyn_node.fleet.engine import audit_bag

        out = audit_bag(job)
        for line in open("/proc/self/status"):
            if line.startswith(("VmHWM:", "VmRSS:")):
                out.row["vm_" + line.split(":")[0][2:].lower()] = int(line.split()[1]) / 1024
        out.row["pid"] = os.getpid()
        return out

    with fleet.Engine(workers=1) as engine:
        outs = fleet.run_jobs(engine, list(jobs_short) + list(jobs_long), fn=audited_with_hwm)
    if len({o.row["pid"] for o in outs}) != 1:
        raise RuntimeError("the RSS measurement needs one worker process for every bag")
    hwm = [o.row["vm_hwm"] for o in outs]
    k = len(jobs_short)
    return dict(hwm_after_short_mib=max(hwm[:k]), hwm_after_long_mib=max(hwm),
                rss_after_long_mib=outs[-1].row["vm_rss"],
                growth=max(hwm) / max(hwm[:k]) - 1.0, per_bag_hwm_mib=hwm)


def run(quick: bool = False, smoke: bool = False) -> dict:
    why = module_available("fleet.engine")
    if why:
        raise NotAvailable(why)
    import importlib.util

    if importlib.util.find_spec("ray") is None:  # not imported here: dyn_node.fleet.engine imports it
        raise NotAvailable("ray not installed")
    n, seconds = (4, 0.5) if smoke else (12, 3.0) if quick else (24, 10.0)
    short_s, n_rss = (0.5, 2) if smoke else (3.0, 2) if quick else (6.0, 3)
    with tempfile.TemporaryDirectory(prefix="dyn_fleet_bench_") as tmpname:
        tmp = Path(tmpname)
        progress("fleet", f"writing {n} bags of {seconds:g} s at 1 kHz")
        bags = _bags(tmp / "fleet", n, seconds)
        n_msgs = n * int(seconds * 1000)
        jobs = _jobs(bags, tmp / "out")
        rows = []
        for w in (1, 2):
            progress("fleet", f"{w} worker(s): Ray start, a cold pass and warm passes over {n} bags")
            rows.append(_measure(w, jobs, n_msgs, 1 if smoke else 3))
        one, two = rows
        progress("fleet", f"peak RSS per worker: {n_rss} bags of {short_s:g} s, then of {10 * short_s:g} s")
        short = _jobs(_bags(tmp / "short", n_rss, short_s), tmp / "out_rss")
        long_ = _jobs(_bags(tmp / "long", n_rss, 10 * short_s), tmp / "out_rss")
        rss = _rss(short, long_)
    return dict(n_bags=n, bag_seconds=seconds, n_messages=n_msgs, rows=rows,
                scaling_efficiency=two["msgs_per_s"] / (2 * one["msgs_per_s"]),
                ray_start_s=statistics.median(r["ray_start_s"] for r in rows),
                rss=dict(rss, short_s=short_s, long_s=10 * short_s, bags_each=n_rss),
                cores=os.cpu_count())
