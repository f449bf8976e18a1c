"""`make soak`: the demo stack at 1 kHz for a long time; memory, file descriptors, latency drift, loss.

``python -m benchmarks.soak [--minutes 30] [--domain 73] [--out soak_out/soak.json]`` runs dyn_sim
and dyn_node (recording, splitting) as children with a probe in this process, samples the node's
RSS and fds, and reports RSS slope, fd counts, per-minute latency and every loss count (their
definitions: docs/BENCHMARK_METHODS.md). Not part of the test suite.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

STAMP_STEP_NS = 1_000_000  # dyn_sim at 1 kHz: stamps 1 ms apart


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _fds(pid: int) -> int | None:
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None


def _slope_per_hour(t_s: list[float], y: list[float]) -> float:
    if len(t_s) < 3:
        return float("nan")
    a = np.polyfit(np.asarray(t_s), np.asarray(y), 1)[0]
    return float(a * 3600.0)


class Probe:
    """Subscribes to joint_states and the node's inverse dynamics; keeps only bounded state."""

    def __init__(self, node, minute_s: float = 60.0):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState

        self.lock = threading.Lock()
        self.t0 = time.time()
        self.minute_s = minute_s
        self.pending: dict[int, float] = {}     # js stamp ns -> probe receipt (s), not yet answered
        self.js_count = 0
        self.inv_count = 0
        self.inv_unmatched = 0                  # answers for stamps the probe never saw
        self.js_gaps = 0                        # missing 1 ms steps between consecutive js stamps
        self.last_js: int | None = None
        self.lat: dict[int, list[float]] = {}   # minute -> latencies (ms)
        self.hop: dict[int, list[float]] = {}   # minute -> probe js receipt -> probe answer receipt (ms)
        self.diag: dict[str, dict[str, str]] = {}
        q = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
        node.create_subscription(JointState, "joint_states", self._on_js, q)
        node.create_subscription(JointState, "/dyn_node/inverse_dynamics", self._on_inv, q)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 50)

    def _on_js(self, msg) -> None:
        now = time.time()
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        with self.lock:
            self.js_count += 1
            if self.last_js is not None and ns > self.last_js:
                steps = round((ns - self.last_js) / STAMP_STEP_NS)
                self.js_gaps += max(0, steps - 1)
            self.last_js = ns
            self.pending[ns] = now

    def _on_inv(self, msg) -> None:
        now = time.time()
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        with self.lock:
            self.inv_count += 1
            seen = self.pending.pop(ns, None)
            minute = int((now - self.t0) // self.minute_s)
            if seen is None:
                self.inv_unmatched += 1
            else:
                self.hop.setdefault(minute, []).append((now - seen) * 1e3)
            self.lat.setdefault(minute, []).append((now - ns * 1e-9) * 1e3)

    def _on_diag(self, msg) -> None:
        for s in msg.status:
            if s.name in ("dyn_node: joint_states", "dyn_node: recorder"):
                self.diag[s.name] = {kv.key: kv.value for kv in s.values}

    def unanswered(self, older_than_s: float) -> int:
        cut = time.time() - older_than_s
        with self.lock:
            return sum(1 for t in self.pending.values() if t < cut)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="soak", description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0, help="run time (default 30)")
    ap.add_argument("--domain", type=int, default=int(os.environ.get("DYN_SOAK_DOMAIN", "73")))
    ap.add_argument("--rate", type=float, default=1000.0, help="joint_states rate (Hz)")
    ap.add_argument("--split-s", type=float, default=60.0, help="record.max_bag_duration_s")
    ap.add_argument("--sample-s", type=float, default=10.0, help="RSS/fd sampling period (s)")
    ap.add_argument("--warmup-s", type=float, default=60.0, help="excluded from the RSS slope")
    ap.add_argument("--out", default="soak_out/soak.json")
    ap.add_argument("--bags", default="", help="bag parent directory (default: a temp dir)")
    args = ap.parse_args(argv)

    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from dyn_node.ros.demo import FINGERS, READY

    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    env.pop("ROS_LOCALHOST_ONLY", None)
    os.environ.update(ROS_DOMAIN_ID=env["ROS_DOMAIN_ID"], ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    bags = Path(args.bags or tempfile.mkdtemp(prefix="dyn_soak_"))
    logs = Path(args.out).parent
    logs.mkdir(parents=True, exist_ok=True)
    py = sys.executable
    sim_log = open(logs / "soak_dyn_sim.log", "w")
    node_log = open(logs / "soak_dyn_node.log", "w")
    sim = subprocess.Popen([py, "-m", "dyn_node.ros.sim_node", "--ros-args", "-p",
                            f"publish_rate_hz:={args.rate}", "-p", f"initial_positions:={list(READY)}"],
                           env=env, stdout=sim_log, stderr=subprocess.STDOUT, start_new_session=True)
    node = subprocess.Popen([py, "-m", "dyn_node.ros.node", "--ros-args", "-p", f"locked_joints:={FINGERS}",
                             "-p", "record.enabled:=true", "-p", f"record.directory:={bags}",
                             "-p", f"record.max_bag_duration_s:={args.split_s}"],
                            env=env, stdout=node_log, stderr=subprocess.STDOUT, start_new_session=True)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=args.domain)
    pnode = rclpy.create_node("soak_probe", context=ctx)
    probe = Probe(pnode)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(pnode)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    samples: list[tuple[float, float, int]] = []
    result: dict = {"minutes": args.minutes, "rate_hz": args.rate, "split_s": args.split_s,
                    "domain": args.domain, "bags": str(bags)}
    try:
        deadline = time.monotonic() + 90
        while probe.inv_count < 100 and time.monotonic() < deadline:
            if node.poll() is not None or sim.poll() is not None:
                raise RuntimeError("a child exited during start-up (see soak_*.log)")
            time.sleep(0.2)
        if probe.inv_count < 100:
            raise RuntimeError("no ~/inverse_dynamics within 90 s (see soak_*.log)")
        with probe.lock:  # start counting from here
            probe.t0 = time.time()
            probe.lat.clear()
            probe.hop.clear()
            probe.js_gaps = 0
        t_start = time.monotonic()
        end = t_start + args.minutes * 60.0
        next_report = t_start + 60.0
        while time.monotonic() < end:
            if node.poll() is not None or sim.poll() is not None:
                result["error"] = "a child exited during the soak"
                break
            rss, fds = _rss_mb(node.pid), _fds(node.pid)
            if rss is not None and fds is not None:
                samples.append((time.monotonic() - t_start, rss, fds))
            if time.monotonic() >= next_report:
                m = int((time.monotonic() - t_start) // 60) - 1
                lat = probe.lat.get(m, [])
                if lat:
                    hop = probe.hop.get(m, []) or [float("nan")]
                    print(f"[soak] minute {m + 1}: RSS {samples[-1][1]:.1f} MB, fds {samples[-1][2]}, "
                          f"latency p50 {np.percentile(lat, 50):.2f} ms p99 {np.percentile(lat, 99):.2f} ms, "
                          f"hop p50 {np.percentile(hop, 50):.2f} ms p99 {np.percentile(hop, 99):.2f} ms, "
                          f"n {len(lat)}", flush=True)
                next_report += 60.0
            time.sleep(min(args.sample_s, max(0.0, end - time.monotonic())))
        unanswered = probe.unanswered(2.0)
        diag = dict(probe.diag)
    finally:
        stop_t = {}
        for name, p in (("dyn_node", node), ("dyn_sim", sim)):
            t0 = time.monotonic()
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
            stop_t[name] = (round(time.monotonic() - t0, 3), p.returncode)
        ex.shutdown(timeout_sec=2)
        pnode.destroy_node()
        rclpy.try_shutdown(context=ctx)
        sim_log.close()
        node_log.close()
    warm = [(t, r, f) for t, r, f in samples if t >= args.warmup_s] or samples
    per_minute = []
    for m in sorted(probe.lat):
        lat = probe.lat[m]
        if len(lat) >= 10:
            hop = probe.hop.get(m, [])
            per_minute.append({"minute": m + 1, "n": len(lat), "p50_ms": float(np.percentile(lat, 50)),
                               "p99_ms": float(np.percentile(lat, 99)),
                               "hop_p50_ms": float(np.percentile(hop, 50)) if hop else None,
                               "hop_p99_ms": float(np.percentile(hop, 99)) if hop else None})
    result.update(
        rss_mb_first=samples[0][1] if samples else None, rss_mb_last=samples[-1][1] if samples else None,
        rss_slope_mb_per_h=_slope_per_hour([s[0] for s in warm], [s[1] for s in warm]),
        fds_first=samples[0][2] if samples else None, fds_last=samples[-1][2] if samples else None,
        fds_max=max((s[2] for s in samples), default=None),
        latency_per_minute=per_minute,
        p50_drift_ms=(per_minute[-1]["p50_ms"] - per_minute[0]["p50_ms"]) if len(per_minute) > 1 else None,
        p99_first_last_ms=((per_minute[0]["p99_ms"], per_minute[-1]["p99_ms"]) if per_minute else None),
        latency_minutes_summary_ms=({k: (float(np.min([x[k] for x in per_minute if x.get(k) is not None] or [np.nan])),
                                         float(np.median([x[k] for x in per_minute if x.get(k) is not None] or [np.nan])),
                                         float(np.max([x[k] for x in per_minute if x.get(k) is not None] or [np.nan])))
                                     for k in ("p50_ms", "p99_ms", "hop_p50_ms", "hop_p99_ms")}
                                    if per_minute else None),  # (min, median, max) over minutes
        probe_joint_states=probe.js_count, probe_inverse=probe.inv_count,
        probe_unanswered=unanswered, probe_js_stamp_gaps=probe.js_gaps,
        node_joint_states_diag={k: diag.get("dyn_node: joint_states", {}).get(k) for k in (
            "received_messages", "accepted_messages", "invalid_messages", "out_of_order_messages",
            "dropped_messages")},
        stop_s_rc=stop_t)
    bag_dirs = sorted(p for p in bags.iterdir() if p.is_dir()) if bags.exists() else []
    if bag_dirs:
        import yaml

        meta_path = bag_dirs[-1] / "metadata.yaml"
        if meta_path.exists():
            meta = yaml.safe_load(meta_path.read_text())
            dn = meta.get("dyn_node", {})
            result["bag"] = {"path": str(bag_dirs[-1]), "state": dn.get("state"),
                             "files": len(meta["rosbag2_bagfile_information"].get("relative_file_paths", [])),
                             "message_count": meta["rosbag2_bagfile_information"].get("message_count"),
                             "topics": dn.get("topics")}
        else:
            result["bag"] = {"path": str(bag_dirs[-1]), "error": "no metadata.yaml"}
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "latency_per_minute"}, indent=1))
    print(f"[soak] written {args.out}")
    return 0 if "error" not in result else 1


if __name__ == "__main__":
    sys.exit(main())
