"""Section "recording": the recorder's ceiling beside raw mcap, and dyn-audit on large bags.

Recorder msgs/s against mcap.writer.Writer on the same bytes; dyn-audit on a 60 s 1 kHz bag
against mcap's reader alone (end to end and marginal), and its peak RSS on bags up to 600 s.
Method: docs/BENCHMARK_METHODS.md.
"""
from __future__ import annotations

import math
import os
import select
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .common import REPO, NotAvailable, module_available, progress, read_vm

NAMES = [f"panda_joint{i}" for i in range(1, 8)]


def _encoder():
    from mcap_ros2._dynamic import serialize_dynamic

    from dyn_node.bag.msgdefs import message_definition

    enc = serialize_dynamic("sensor_msgs/msg/JointState", message_definition("sensor_msgs/msg/JointState"))
    return enc["sensor_msgs/msg/JointState"]


def joint_state_bytes(n: int, t0_ns: int, rate_hz: float = 1000.0) -> tuple[list[bytes], list[int]]:
    """n CDR-serialized 7-DoF JointStates stamped at ``rate_hz`` from t0_ns, and their stamps."""
    encode = _encoder()
    out, stamps = [], []
    period = int(1e9 / rate_hz)
    for k in range(n):
        stamp = t0_ns + k * period
        w = 2 * math.pi * k / rate_hz  # one period per second: the motion repeats exactly
        msg = {"header": {"stamp": {"sec": stamp // 1_000_000_000, "nanosec": stamp % 1_000_000_000},
                          "frame_id": ""},
               "name": NAMES,
               "position": [0.3 * math.sin(w + i) for i in range(7)],
               "velocity": [0.3 * 2 * math.pi * math.cos(w + i) for i in range(7)],
               "effort": [5.0 * math.sin(w + i) for i in range(7)]}
        out.append(bytes(encode(msg)))
        stamps.append(stamp)
    return out, stamps


def _stamp_patched(cycle: list[bytes], n: int, t0_ns: int, rate_hz: float):
    """n messages repeating ``cycle`` (one period of a periodic motion) with fresh stamps.

    Serializing 600,000 messages one by one would dominate the bench's time budget; the motion
    is periodic, so one period is serialized and each copy gets its own header stamp, written
    straight into the CDR bytes (int32 sec, uint32 nanosec after the 4-byte encapsulation)."""
    period = int(1e9 / rate_hz)
    for k in range(n):
        stamp = t0_ns + k * period
        data = bytearray(cycle[k % len(cycle)])
        struct.pack_into("<iI", data, 4, stamp // 1_000_000_000, stamp % 1_000_000_000)
        yield bytes(data), stamp


def _recorder_ceiling(payloads, stamps, tmp: Path) -> float:
    from dyn_node.core.robot.model import load_model
    from dyn_node.bag.recorder import Recorder, RecorderConfig, TopicInfo

    urdf = load_model(builtin="panda").urdf
    d = tmp / f"rec_{time.perf_counter_ns()}"
    d.mkdir()
    t0 = time.perf_counter()
    rec = Recorder(RecorderConfig(directory=str(d), queue_size=len(payloads) + 10,
                                  queue_bytes=1 << 31), robot_description=urdf)
    rec.add_topic(TopicInfo("/joint_states", "sensor_msgs/msg/JointState"))
    for data, stamp in zip(payloads, stamps):
        rec.write("/joint_states", data, stamp, stamp)
    stats = rec.close(timeout=120.0)
    elapsed = time.perf_counter() - t0
    written = stats.topics["/joint_states"].written
    shutil.rmtree(d, ignore_errors=True)
    if written != len(payloads):
        raise RuntimeError(f"recorder wrote {written} of {len(payloads)} ({stats.error})")
    return len(payloads) / elapsed


def _raw_writer(payloads, stamps, tmp: Path, chunk_size: int) -> float:
    from mcap.writer import CompressionType, Writer

    from dyn_node.bag.msgdefs import message_definition

    path = tmp / f"raw_{time.perf_counter_ns()}.mcap"
    t0 = time.perf_counter()
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="bench")
        sid = w.register_schema("sensor_msgs/msg/JointState", "ros2msg",
                                message_definition("sensor_msgs/msg/JointState").encode())
        cid = w.register_channel("/joint_states", "cdr", sid)
        for seq, (data, stamp) in enumerate(zip(payloads, stamps)):
            w.add_message(cid, log_time=stamp, data=data, publish_time=stamp, sequence=seq)
        w.finish()
    elapsed = time.perf_counter() - t0
    path.unlink()
    return len(payloads) / elapsed


def write_bag(directory: Path, seconds: float, rate_hz: float = 1000.0) -> Path:
    """A dyn_node bag (via Recorder) with ``seconds`` of joint_states at ``rate_hz``."""
    from dyn_node.core.robot.model import load_model
    from dyn_node.bag.recorder import Recorder, RecorderConfig, TopicInfo

    urdf = load_model(builtin="panda").urdf
    rec = Recorder(RecorderConfig(directory=str(directory), fsync=False, queue_size=50_000),
                   robot_description=urdf)
    rec.add_topic(TopicInfo("/joint_states", "sensor_msgs/msg/JointState"))
    n = int(seconds * rate_hz)
    t0 = 1_700_000_000 * 1_000_000_000
    cycle, _ = joint_state_bytes(int(rate_hz), t0, rate_hz)
    for k, (data, stamp) in enumerate(_stamp_patched(cycle, n, t0, rate_hz)):
        if not rec.write("/joint_states", data, stamp, stamp):
            raise RuntimeError("bag generation dropped a message")
        if k % 10_000 == 9_999:
            while rec.stats().queued > 20_000:
                time.sleep(0.01)
    stats = rec.close(timeout=300.0)
    if stats.topics["/joint_states"].written != n:
        raise RuntimeError(f"bag generation wrote {stats.topics['/joint_states'].written} of {n}")
    return Path(stats.path)


def raw_read_rate(bag: Path) -> tuple[float, int]:
    from mcap.reader import make_reader

    n = 0
    t0 = time.perf_counter()
    for f in sorted(bag.glob("*.mcap")) if bag.is_dir() else [bag]:
        with open(f, "rb") as fh:
            for _schema, _channel, message in make_reader(fh).iter_messages():
                n += len(message.data) >= 0
    return n / (time.perf_counter() - t0), n


def run_audit(bag: Path, out: Path, timeout_s: float = 600.0) -> dict:
    """``python -m dyn_node.audit.bag_audit`` on ``bag``: wall s, peak RSS MiB (wait4), exit code.

    Past ``timeout_s`` the audit is stopped and the result says so, with the peak RSS it had
    reached (VmHWM sampled while it ran), so one slow audit cannot eat the whole bench budget.
    """
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "dyn_node.audit.bag_audit", str(bag), "--robot-model", "panda",
                             "--out", str(out)], cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, start_new_session=True)
    hwm = 0.0
    # its end is seen at once (the process's fd becomes readable), its RSS sampled every 50 ms
    pidfd = os.pidfd_open(proc.pid)
    try:
        while not select.select([pidfd], [], [], 0.05)[0]:
            try:
                hwm = max(hwm, read_vm(proc.pid, "VmHWM"))
            except (OSError, ValueError):
                pass
            if time.perf_counter() - t0 > timeout_s:
                os.killpg(proc.pid, signal.SIGKILL)
                os.wait4(proc.pid, 0)
                proc.returncode = -9
                return dict(wall_s=time.perf_counter() - t0, peak_rss_mib=hwm, rc=None,
                            finished=False)
        wall = time.perf_counter() - t0
        _, status, usage = os.wait4(proc.pid, 0)
    finally:
        os.close(pidfd)
    rc = os.waitstatus_to_exitcode(status)
    proc.returncode = rc
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    if rc not in (0, 1):
        raise NotAvailable(f"dyn_node.audit.bag_audit exited {rc}: {' | '.join(err.strip().splitlines()[-3:])}")
    return dict(wall_s=wall, peak_rss_mib=max(hwm, usage.ru_maxrss / 1024), rc=rc, finished=True)


def run(quick: bool = False, smoke: bool = False) -> dict:
    why = module_available("bag.recorder")
    if why:
        raise NotAvailable(why)
    from dyn_node.bag.recorder import RecorderConfig

    out: dict = {}
    n = 1000 if smoke else 20_000 if quick else 100_000
    repeats = 1 if smoke else 3 if quick else 5
    with tempfile.TemporaryDirectory(prefix="dyn_bench_") as tmpname:
        tmp = Path(tmpname)
        progress("recording", f"preparing {n} serialized JointStates")
        t0 = 1_700_000_000 * 1_000_000_000
        cycle, _ = joint_state_bytes(1000, t0)
        payloads, stamps = map(list, zip(*_stamp_patched(cycle, n, t0, 1000.0)))
        progress("recording", f"Recorder ceiling vs raw mcap Writer, {n} messages × {repeats}")
        rec_rates, raw_rates = [], []
        for _ in range(repeats):  # interleaved so drift hits both alike
            rec_rates.append(_recorder_ceiling(payloads, stamps, tmp))
            raw_rates.append(_raw_writer(payloads, stamps, tmp, RecorderConfig().chunk_size))
        rec_rate, raw_rate = sorted(rec_rates)[len(rec_rates) // 2], sorted(raw_rates)[len(raw_rates) // 2]
        out["writer"] = dict(n_messages=n, repeats=repeats, recorder_msgs_per_s=rec_rate,
                             raw_mcap_msgs_per_s=raw_rate, ratio=rec_rate / raw_rate,
                             what="Recorder.write → writer thread → close, zstd, vs mcap Writer.add_message")
        del payloads, stamps

        audit: dict = {}
        out["audit"] = audit
        small_s, big_s, huge_s = ((0.2, 1.0, 2.0) if smoke else (1.0, 6.0, 60.0) if quick
                                  else (1.0, 60.0, 600.0))
        progress("recording", f"writing bags of {small_s:g} s, {big_s:g} s, {huge_s:g} s at 1 kHz")
        bags = {s: write_bag(tmp / f"bag_{int(s)}", s) for s in (small_s, big_s, huge_s)}
        rates = []
        for _ in range(repeats):
            r, count = raw_read_rate(bags[big_s])
            rates.append(r)
        rate = sorted(rates)[len(rates) // 2]
        n_small = raw_read_rate(bags[small_s])[1]
        # bag_messages counts joint_states plus the robot_description copy the recorder adds.
        audit.update(bag_seconds=big_s, bag_messages=count, raw_read_msgs_per_s=rate,
                     bag_mib=sum(f.stat().st_size for f in bags[big_s].glob("*.mcap")) / 2**20)
        why = module_available("audit.bag_audit")
        if why:
            audit["status"] = f"not available: {why}"
            return out
        progress("recording", f"dyn_node.audit.bag_audit on the {small_s:g} s and {big_s:g} s bags")
        walls: dict[float, list[float]] = {small_s: [], big_s: []}
        rss: dict[str, float] = {}
        # Five rounds in a full run (an audit of the 60 s bag is short): the
        # median of five resists a busy core better than the median of three.
        for k in range(1 if quick or smoke else 5):
            for s in (small_s, big_s):
                r = run_audit(bags[s], tmp / f"audit_{s:g}", timeout_s=120.0)
                if not r["finished"]:
                    raise NotAvailable(f"dyn_node.audit.bag_audit did not finish a {s:g} s bag in 120 s")
                walls[s].append(r["wall_s"])
                rss[f"{s:g} s"] = max(rss.get(f"{s:g} s", 0.0), r["peak_rss_mib"])
            if sum(walls[big_s]) > 40.0:  # slow audit: fewer repeats, stay within the budget
                break
        budget = 60.0 if smoke or quick else 240.0
        progress("recording", f"dyn_node.audit.bag_audit on the {huge_s:g} s bag (peak RSS; stopped after {budget:.0f} s)")
        huge = run_audit(bags[huge_s], tmp / "audit_huge", timeout_s=budget)
        rss[f"{huge_s:g} s" + ("" if huge["finished"] else f" (stopped after {budget:.0f} s)")] = huge["peak_rss_mib"]
        w_small = sorted(walls[small_s])[len(walls[small_s]) // 2]
        w_big = sorted(walls[big_s])[len(walls[big_s]) // 2]
        n_big = count
        end_to_end = n_big / w_big
        marginal = (n_big - n_small) / (w_big - w_small) if w_big > w_small else float("nan")
        audit.update(status="ok", audit_wall_s=w_big, audit_small_wall_s=w_small,
                     small_bag_seconds=small_s, audit_repeats=len(walls[big_s]),
                     audit_msgs_per_s_end_to_end=end_to_end, audit_msgs_per_s_marginal=marginal,
                     ratio_end_to_end=end_to_end / rate, ratio_marginal=marginal / rate,
                     peak_rss_mib=rss, huge_bag_seconds=huge_s, huge_bag_wall_s=huge["wall_s"],
                     huge_bag_finished=huge["finished"],
                     huge_bag_mib=sum(f.stat().st_size for f in bags[huge_s].glob("*.mcap")) / 2**20)
    return out
