"""Parsing trajectory files (dyn-check's input): a 7-joint trajectory with positions,
velocities and accelerations written as JSON, YAML and CSV, read by
``dyn_node.audit.trajectory_files.read_trajectory`` (bounded, strict parsers; line numbers
looked up only on error). Each format is read in a fresh process, so the peak RSS (VmHWM) is
that read's; wall time is the median of ``repeats`` reads in that process. The size cap is lifted
(as ``dyn-check --max-file-mb``): 100,000 points are the point cap, their JSON and YAML over 16 MB."""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from .common import REPO

FORMATS = ("json", "yaml", "csv")
CHILD = r"""
import json, statistics, sys, time
from dyn_node.audit.trajectory_files import read_trajectory
path, repeats = sys.argv[1], int(sys.argv[2])
times = []
for _ in range(repeats):
    t0 = time.perf_counter()
    tf = read_trajectory(path, max_bytes=1 << 31)  # as --max-file-mb 2147: the 100k-point JSON is 40 MB
    times.append(time.perf_counter() - t0)
hwm = next((int(l.split()[1]) / 1024 for l in open("/proc/self/status") if l.startswith("VmHWM")), None)
print(json.dumps({"s": statistics.median(times), "points": len(tf.times), "vm_hwm_mib": hwm}))
"""


def _write(dest: Path, n: int) -> dict[str, Path]:
    from dyn_node.audit.trajectory_files import TrajectoryFile, format_trajectory

    names = [f"panda_joint{i}" for i in range(1, 8)]
    tf = TrajectoryFile("bench", "json", names, [i * 1e-3 for i in range(n)],
                        [[0.1 + 1e-6 * i * (j + 1) for j in range(7)] for i in range(n)],
                        [[0.01 * (j + 1) for j in range(7)]] * n, [[0.0] * 7] * n)
    out = {}
    for fmt in FORMATS:
        p = dest / f"traj.{fmt}"
        p.write_text(format_trajectory(tf, fmt))
        out[fmt] = p
    return out


def run(quick: bool = False, smoke: bool = False) -> dict:
    n = 200 if smoke else 20_000 if quick else 100_000
    repeats = 1 if smoke else 3
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for fmt, path in _write(Path(tmp), n).items():
            r = subprocess.run([sys.executable, "-c", CHILD, str(path), str(repeats)],
                               capture_output=True, text=True, cwd=str(REPO), timeout=1800)
            if r.returncode != 0:
                rows.append({"format": fmt, "status": f"failed: {r.stderr.strip()[-300:]}"})
                continue
            res = json.loads(r.stdout.strip().splitlines()[-1])
            rows.append({"format": fmt, "status": "ok", "bytes": path.stat().st_size,
                         "read_s": res["s"], "points": res["points"],
                         "vm_hwm_mib": res["vm_hwm_mib"]})
    return {"n_points": n, "joints": 7, "repeats": repeats, "rows": rows}
