"""Timing, machine description and small helpers shared by the benchmark sections."""
from __future__ import annotations

import importlib.metadata
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
SYSTEM_PYTHON = "/usr/bin/python3"


class NotAvailable(Exception):
    """A subject that cannot run here; the message is the reason shown in the row."""


def progress(section: str, text: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {section}: {text}", file=sys.stderr, flush=True)


def median_time(fn: Callable[[], object], repeats: int, warmup: int = 1) -> tuple[float, list[float]]:
    """Median wall time (s) of ``fn()`` over ``repeats`` runs after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _mem_total_gib() -> float:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) / 1024 / 1024
    except OSError:
        pass
    return float("nan")


def system_pykdl() -> tuple[bool, str]:
    """Whether Debian's python3-pykdl imports under the system interpreter, and its version or why not."""
    if not Path(SYSTEM_PYTHON).exists():
        return False, f"{SYSTEM_PYTHON} does not exist"
    p = subprocess.run([SYSTEM_PYTHON, "-c", "import PyKDL; print(getattr(PyKDL, '__version__', '?'))"],
                       capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"}, timeout=30)
    if p.returncode == 0:
        return True, p.stdout.strip()
    policy = ""
    try:
        q = subprocess.run(["apt-cache", "policy", "python3-pykdl"], capture_output=True, text=True,
                           timeout=30)
        cand = [l.split(":", 1)[1].strip() for l in q.stdout.splitlines() if "Candidate:" in l]
        policy = f" (apt candidate {cand[0]}; make bench does not install it)" if cand else ""
    except (OSError, subprocess.SubprocessError):
        pass
    return False, "python3-pykdl not installed for " + SYSTEM_PYTHON + policy


def machine_info() -> dict:
    import numpy

    kdl_ok, kdl_ver = system_pykdl()
    return {
        "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)),
        "memory_gib": round(_mem_total_gib(), 1),
        "kernel": platform.release(),
        "python": platform.python_version(),
        "versions": {
            "python": platform.python_version(),
            "numpy": numpy.__version__,
            "pinocchio": _version("pin"),
            "mujoco": _version("mujoco"),
            "rclpy": _version("ros-jazzy-rclpy") if _version("ros-jazzy-rclpy") != "not installed"
            else _version("rclpy"),
            "mcap": _version("mcap"),
            "mcap-ros2-support": _version("mcap-ros2-support"),
            "dyn_node": _version("dyn_node"),
            "PyKDL (system python3)": kdl_ver if kdl_ok else "not installed",
        },
    }


def percentile(xs: list[float], p: float) -> float:
    """The ``p``-th percentile (0-100) of ``xs`` by the nearest rank (an observed value)."""
    xs = sorted(xs)
    if not xs:
        return float("nan")
    k = min(len(xs) - 1, max(0, int(round(p / 100 * (len(xs) - 1)))))
    return xs[k]


def module_available(name: str) -> str | None:
    """None if ``dyn_node.<name>`` imports, else the reason it does not."""
    try:
        __import__(f"dyn_node.{name}")
    except Exception as exc:  # any import failure means the subject is not ready yet
        return f"dyn_node.{name} not importable: {type(exc).__name__}: {exc}"
    return None


def read_proc_cpu(pid: int) -> float:
    """utime + stime of a process in seconds, from /proc/<pid>/stat."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    # After the ")" of the command name: state is field 3, utime 14 and stime 15 (1-based).
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def read_vm(pid: int, key: str = "VmHWM") -> float:
    """A /proc/<pid>/status memory figure in MiB (VmHWM = peak resident set size)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")
