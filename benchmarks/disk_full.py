"""What a full disk costs the live node: dyn_sim at 1 kHz into dyn_node recording onto a small
tmpfs (mounted here: needs root), node CPU and ``dropped_messages`` before and after the
recorder fails with ENOSPC.

``python -m benchmarks.disk_full [--size-kb 8192] [--window-s 9] [--domain 74]``; prints one
JSON object. Not part of the test suite (issue 27, bad input item 2).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


def _cpu_s(pid: int) -> float:
    """User + system CPU time of a process, in seconds (/proc/<pid>/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class _Diagnostics:
    """A probe on its own context and thread, keeping the last ``dyn_node: joint_states`` and
    ``dyn_node: recorder`` values seen on /diagnostics."""

    def __init__(self, domain: int) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.lock = threading.Lock()
        self.values: dict[str, dict[str, str]] = {}
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node("disk_full_probe", context=self.ctx)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on, 100)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        threading.Thread(target=self.executor.spin, daemon=True).start()

    def _on(self, msg) -> None:
        with self.lock:
            for s in msg.status:
                if s.name in ("dyn_node: joint_states", "dyn_node: recorder"):
                    self.values[s.name] = {kv.key: kv.value for kv in s.values}

    def get(self, status: str, key: str) -> str | None:
        with self.lock:
            return self.values.get(status, {}).get(key)

    def close(self) -> None:
        import rclpy
        self.executor.shutdown(timeout_sec=2)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def _window(pid: int, diag: _Diagnostics, seconds: float) -> dict[str, float]:
    """Node CPU (cores) and the growth of dropped/received joint_states over ``seconds``."""
    def counts() -> tuple[int, int]:
        return (int(diag.get("dyn_node: joint_states", "dropped_messages") or 0),
                int(diag.get("dyn_node: joint_states", "received_messages") or 0))
    d0, r0 = counts()
    c0, t0 = _cpu_s(pid), time.monotonic()
    time.sleep(seconds)
    d1, r1 = counts()
    c1, t1 = _cpu_s(pid), time.monotonic()
    return {"cpu_cores": round((c1 - c0) / (t1 - t0), 3), "dropped": d1 - d0,
            "received_per_s": round((r1 - r0) / (t1 - t0), 1), "seconds": round(t1 - t0, 2)}


def _wait(pred, timeout_s: float, what: str, procs) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if not all(p.alive() for p in procs):
            raise RuntimeError(f"a child exited while waiting for {what}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out waiting for {what}")
        time.sleep(0.2)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="disk_full", description=__doc__.splitlines()[0])
    ap.add_argument("--size-kb", type=int, default=8192, help="tmpfs size for the bags")
    ap.add_argument("--window-s", type=float, default=9.0, help="measurement window (s)")
    ap.add_argument("--domain", type=int, default=int(os.environ.get("DYN_TEST_DOMAIN", "74")))
    args = ap.parse_args(argv)
    from dyn_node.ros.demo import FINGERS, READY, Child

    def python_cmd(module: str, *params: str) -> list[str]:
        return [sys.executable, "-m", module, "--ros-args", *params]

    mnt = Path(tempfile.mkdtemp(prefix="dyn_disk_full_"))
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={args.size_kb}k", "tmpfs", str(mnt)],
                       capture_output=True, text=True)
    if r.returncode:
        print(f"disk_full: cannot mount a tmpfs: {r.stderr.strip()}", file=sys.stderr)
        return 2
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("ROS_LOCALHOST_ONLY", None)
    log_dir = Path(tempfile.mkdtemp(prefix="dyn_disk_full_logs_"))
    sim = Child("dyn_sim", python_cmd("dyn_node.ros.sim_node", "-p", "publish_rate_hz:=1000.0",
                                      "-p", f"initial_positions:={list(READY)}"), env, log_dir / "sim.log")
    node = Child("dyn_node", python_cmd("dyn_node.ros.node", "-p", f"locked_joints:={FINGERS}",
                                        "-p", "record.enabled:=true", "-p", f"record.directory:={mnt}"),
                 env, log_dir / "node.log")
    diag = _Diagnostics(args.domain)
    result: dict = {"tmpfs_kb": args.size_kb, "rate_hz": 1000, "logs": str(log_dir)}
    try:
        _wait(lambda: int(diag.get("dyn_node: joint_states", "received_messages") or 0) > 2000,
              120, "joint_states to flow", (sim, node))
        result["recording"] = _window(node.proc.pid, diag, args.window_s)
        _wait(lambda: diag.get("dyn_node: recorder", "state") == "error", 300,
              "the recorder to fail", (sim, node))
        time.sleep(1.0)  # past the failure itself
        result["after_enospc"] = _window(node.proc.pid, diag, args.window_s)
        result["recorder_dropped"] = diag.get("dyn_node: recorder", "dropped_messages")
    finally:
        node.stop()
        sim.stop()
        diag.close()
        bags = [d for d in mnt.iterdir() if d.is_dir()]
        if bags:
            result["bag_files"] = sorted(f.name for f in bags[0].iterdir())
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)
        mnt.rmdir()
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
