"""The live benchmark's measuring end: drives the publisher, receives a subject's output.

``python -m benchmarks.ros_probe --output TOPIC --subject-pid PID --rates 1000,2000 --window 3
--out result.json``: per rate, stamp-to-receipt latency p50/p99, loss and the subject's CPU share;
it stops after the first rate that loses more than 1%. Outputs are subscribed raw and only the
stamp is read, so the probe keeps up at high rates. Definitions: docs/BENCHMARK_METHODS.md.
``--start-after T``: warm up at least until wall time T (s), so that no window holds the
subject's start-up (docs/BENCHMARK_METHODS.md). ``--effort``: the publisher sends efforts too;
``--also TOPIC``: a second output (geometry_msgs/WrenchStamped) whose messages of each window
are counted (``also_loss``).
"""
from __future__ import annotations

import argparse
import json
import statistics
import struct
import subprocess
import sys
import threading
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from geometry_msgs.msg import WrenchStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from .common import percentile as _percentile, read_proc_cpu


class Receiver(Node):
    def __init__(self, topic: str, reliability: ReliabilityPolicy, msg_type: type = JointState,
                 name: str = "bench_probe") -> None:
        # no parameter services: each wake-up of the probe's executor rebuilds a wait set of its
        # subscriptions alone (six services fewer per node), the instrument's cost per message
        super().__init__(name, start_parameter_services=False)
        self.reliability = reliability
        self.stamps: list[int] = []
        self.receipts: list[int] = []
        # both types start with a std_msgs/Header, so the stamp is at the same offset
        self.create_subscription(msg_type, topic, self.on_message,
                                 QoSProfile(depth=1000, reliability=reliability), raw=True)

    def on_message(self, data: bytes) -> None:
        now = time.time_ns()
        # CDR: 4-byte encapsulation header, then header.stamp as int32 sec, uint32 nanosec.
        sec, nsec = struct.unpack_from("<iI", data, 4)
        self.stamps.append(sec * 1_000_000_000 + nsec)
        self.receipts.append(now)


def _receiver(discover: Node, topic: str, deadline: float, timeout: float,
              msg_type: type = JointState, name: str = "bench_probe") -> Receiver:
    """A Receiver on ``topic`` with its publisher's reliability, once that publisher exists."""
    infos = []
    while time.monotonic() < deadline and not infos:
        infos = discover.get_publishers_info_by_topic(topic)
        if not infos:
            time.sleep(0.05)
    if not infos:
        raise RuntimeError(f"no publisher on {topic} within {timeout:.0f} s")
    return Receiver(topic, infos[0].qos_profile.reliability, msg_type, name)


def _count_between(stamps: list[int], first: int, last: int) -> int:
    return len({s for s in stamps if first <= s <= last})


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--output", required=True)
    ap.add_argument("--subject-pid", type=int, required=True)
    ap.add_argument("--rates", default="1000,2000,4000,8000")
    ap.add_argument("--window", type=float, default=3.0)
    ap.add_argument("--repeat-first", type=int, default=1,
                    help="windows at the first rate (the figures at that rate are medians)")
    ap.add_argument("--ready-timeout", type=float, default=30.0)
    ap.add_argument("--out", required=True)
    ap.add_argument("--effort", action="store_true", help="joint_states carry efforts")
    ap.add_argument("--also", default="", help="a second output (WrenchStamped) to count")
    ap.add_argument("--start-after", type=float, default=0.0,
                    help="keep warming up until this wall time (s since the epoch)")
    args = ap.parse_args()
    result: dict = {"output_topic": args.output, "windows": []}

    pub = subprocess.Popen([sys.executable, "-m", "benchmarks.ros_publisher"]
                           + (["--effort"] if args.effort else []), stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, text=True, bufsize=1)

    def command(line: str) -> str:
        assert pub.stdin and pub.stdout
        pub.stdin.write(line + "\n")
        pub.stdin.flush()
        return pub.stdout.readline().strip()

    rclpy.init()
    discover = Node("bench_probe_discovery")
    try:
        deadline = time.monotonic() + args.ready_timeout
        receiver = _receiver(discover, args.output, deadline, args.ready_timeout)
        result["output_reliability"] = receiver.reliability.name
        also = (_receiver(discover, args.also, deadline, args.ready_timeout, WrenchStamped,
                          "bench_probe_also") if args.also else None)
        executor = SingleThreadedExecutor()
        executor.add_node(receiver)
        if also:
            executor.add_node(also)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        if command("match 1") != "matched":
            raise RuntimeError("the subject never subscribed to /joint_states")
        # Warm up until outputs come back (the subject may still be loading its model).
        while True:
            command("run 200 0.5")
            if len(receiver.stamps) >= 50 and time.time() >= args.start_after:
                break
            if time.monotonic() > deadline:
                raise RuntimeError(f"no output on {args.output} within {args.ready_timeout:.0f} s "
                                   f"({len(receiver.stamps)} received during warm-up)")
        plan = []
        for i, rate in enumerate(float(r) for r in args.rates.split(",")):
            plan += [(rate, k == 0, k == (args.repeat_first if i == 0 else 1) - 1)
                     for k in range(args.repeat_first if i == 0 else 1)]
        for rate, step, last_of_rate in plan:
            n0 = len(receiver.stamps)
            c0, w0 = read_proc_cpu(args.subject_pid), time.monotonic()
            reply = command(f"run {rate} {args.window}").split()
            c1, w1 = read_proc_cpu(args.subject_pid), time.monotonic()
            sent, first, last, elapsed = int(reply[1]), int(reply[2]), int(reply[3]), float(reply[4])
            # Drain: wait until nothing new arrives for 0.3 s (at most 3 s).
            end = time.monotonic() + 3.0
            count = len(receiver.stamps)
            quiet_since = time.monotonic()
            while time.monotonic() < end and time.monotonic() - quiet_since < 0.3:
                time.sleep(0.05)
                if len(receiver.stamps) != count:
                    count, quiet_since = len(receiver.stamps), time.monotonic()
            stamps, receipts = receiver.stamps[n0:], receiver.receipts[n0:]
            lat = {}
            for s, r in zip(stamps, receipts):
                if first <= s <= last and s not in lat:
                    lat[s] = (r - s) / 1e3
            got = len(lat)
            lats = list(lat.values())
            window = dict(target_hz=rate, sent=sent, received=got, achieved_hz=sent / elapsed,
                          loss=max(0.0, 1.0 - got / sent) if sent else float("nan"),
                          p50_us=_percentile(lats, 50), p99_us=_percentile(lats, 99),
                          mean_us=statistics.fmean(lats) if lats else float("nan"),
                          cpu_share=(c1 - c0) / (w1 - w0),
                          cpu_us_per_output=(c1 - c0) / got * 1e6 if got else float("nan"),
                          step=step)
            if also:
                n_also = _count_between(list(also.stamps), first, last)
                window.update(also_received=n_also,
                              also_loss=max(0.0, 1.0 - n_also / sent) if sent else float("nan"))
            result["windows"].append(window)
            print(json.dumps(window), file=sys.stderr, flush=True)
            if last_of_rate and any(w["loss"] > 0.01 for w in result["windows"]
                                    if w["target_hz"] == rate):
                break
        executor.shutdown(timeout_sec=1.0)
    except Exception as exc:
        result["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        try:
            command("quit")
        except (BrokenPipeError, OSError, AssertionError):
            pass
        try:
            pub.wait(timeout=5)
        except subprocess.TimeoutExpired:
            pub.kill()
        rclpy.try_shutdown()
        with open(args.out, "w") as f:
            json.dump(result, f)


if __name__ == "__main__":
    main()
