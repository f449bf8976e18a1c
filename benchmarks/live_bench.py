"""Section "live": stamp-to-output latency, loss, CPU share and memory of ROS subjects.

Each subject runs as its own process (own session, so it can be signalled as a group) on an own
ROS_DOMAIN_ID with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST; benchmarks.ros_probe drives the
joint_states publisher and measures. Subjects run one after another on the same machine in the
same run, so their ratios are comparable. The venv's Python re-executes itself once at start
(the ROS wheels' .pth sets LD_LIBRARY_PATH) with execve, which keeps the PID; the PID measured is
checked against /proc/<pid>/cmdline.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from . import detection
from .common import REPO, NotAvailable, progress, read_vm


def bench_domain() -> int:
    return int(os.environ.get("DYN_BENCH_DOMAIN") or os.environ.get("DYN_TEST_DOMAIN") or 63)


def ros_env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("ROS_LOCALHOST_ONLY", None)
    env.update(ROS_DOMAIN_ID=str(bench_domain()), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    # The repo root on the path so `-m benchmarks...` and `-m dyn_node...` work from anywhere.
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _dyn_node_reason() -> str | None:
    return _missing("ros/node")


def _recording_reason() -> str | None:
    return _missing("ros/node", "ros/recording.py", "bag/recorder.py")


def _contact_reason() -> str | None:
    # a node that does not publish the outputs yet is reported by the probe ("no publisher on")
    return _missing("ros/node", "core/contacts/contact_monitor.py")


def _missing(*paths: str) -> str | None:
    """Why a subject cannot run: the first of ``paths`` (under dyn_node/) that does not exist."""
    for rel in paths:
        if not (REPO / "dyn_node" / rel).exists():
            return f"dyn_node/{rel} does not exist"
    return None


def subjects(record_dir: str) -> list[dict]:
    py = sys.executable
    return [
        dict(key="bare", name="(a) bare rclpy republisher",
             what="subscribe joint_states, publish the same message on ~/out",
             cmd=[py, "-m", "benchmarks.subjects.bare_republisher"],
             output="/bare_republisher/out", module="benchmarks.subjects.bare_republisher",
             reason=None),
        dict(key="minimal", name="(b) minimal hand-written node",
             what="subscribe, pinocchio rnea + gravity, publish two JointStates",
             cmd=[py, "-m", "benchmarks.subjects.minimal_node", "panda"],
             output="/minimal_node/inverse_dynamics", module="benchmarks.subjects.minimal_node",
             reason=None),
        dict(key="dyn_node", name="(c) dyn_node",
             what="python -m dyn_node.ros.node -p robot_model:=panda (all checks, diagnostics)",
             cmd=[py, "-m", "dyn_node.ros.node", "--ros-args", "-p", "robot_model:=panda"],
             output="/dyn_node/inverse_dynamics", module="dyn_node.ros.node", reason=_dyn_node_reason()),
        dict(key="dyn_node_record", name="(d) dyn_node, recording on",
             what="as (c) with record.enabled:=true (MCAP, zstd) into a temporary directory",
             cmd=[py, "-m", "dyn_node.ros.node", "--ros-args", "-p", "robot_model:=panda",
                  "-p", "record.enabled:=true", "-p", f"record.directory:={record_dir}"],
             output="/dyn_node/inverse_dynamics", module="dyn_node.ros.node",
             reason=_recording_reason()),
        dict(key="dyn_node_contact", name="(e) dyn_node, contact observer on",
             what="as (c) with joint_states carrying efforts (the model's, a free motion): the "
                  "momentum observer, ~/external_torque (timed) and ~/external_wrench (counted), "
                  "dyn_node: contact and energy",
             cmd=[py, "-m", "dyn_node.ros.node", "--ros-args", "-p", "robot_model:=panda"],
             output="/dyn_node/external_torque", module="dyn_node.ros.node",
             probe_args=["--effort", "--also", "/dyn_node/external_wrench"],
             reason=_contact_reason()),
    ]


def minimal_fed_efforts(subj: dict) -> dict:
    """(b) on (e)'s input: the same joint_states with efforts, so the contact pairs differ only
    in the subject (the publisher computes the efforts and sends larger messages)."""
    return dict(subj["minimal"], key="minimal_effort", name="(b) minimal node, fed efforts",
                probe_args=["--effort"])


def _stop(proc: subprocess.Popen) -> tuple[int | None, str]:
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGINT)
        except ProcessLookupError:
            pass
    try:
        _, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
    return proc.returncode, err or ""


def _wait_cmdline(pid: int, module: str, timeout: float = 10.0) -> None:
    """Confirm the PID runs the subject (after the bootstrapper's execve) before measuring it."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            raise NotAvailable("subject exited at start")
        if module.encode() in cmd:
            return
        time.sleep(0.02)
    raise NotAvailable(f"PID {pid} does not run {module}")


#: runs of (c) and (d) the recording overhead is the median over (the first pair is the main rows)
RECORDING_PAIRS = 3
#: no window starts before this long after the subject was started (s): about 3 s in, the
#: subject's DDS participant sends its first periodic discovery announcement, and a window
#: holding it saw one delivery stall of 240–330 ms (docs/BENCHMARK_METHODS.md)
SETTLE_S = 5.0
#: runs of (b) fed efforts and (e) one after the other that the contact observer's p99 ratio is
#: the median over (all apart from the rows above: (b)'s row is measured without efforts)
CONTACT_PAIRS = 5


def _median(xs: list[float]) -> float:
    xs = sorted(xs)
    n = len(xs)
    return xs[n // 2] if n % 2 else (xs[n // 2 - 1] + xs[n // 2]) / 2


def run_subject(s: dict, rates: str, window: float, ready_timeout: float, repeat_first: int,
                settle_s: float = SETTLE_S) -> dict:
    row = dict(key=s["key"], subject=s["name"], what=s["what"], output_topic=s["output"])
    if s["reason"]:
        row["status"] = f"not available: {s['reason']}"
        return row
    env = ros_env()
    started = time.time()
    proc = subprocess.Popen(s["cmd"], cwd=REPO, env=env, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    with tempfile.NamedTemporaryFile(suffix=".json") as out:
        try:
            _wait_cmdline(proc.pid, s["module"])
            probe = subprocess.run([sys.executable, "-m", "benchmarks.ros_probe", "--output", s["output"],
                                    "--subject-pid", str(proc.pid), "--rates", rates,
                                    "--window", str(window), "--ready-timeout", str(ready_timeout),
                                    "--repeat-first", str(repeat_first),
                                    "--start-after", str(started + settle_s),
                                    "--out", out.name, *s.get("probe_args", [])],
                                   cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                   text=True, timeout=ready_timeout + 60 + 10 * window * (len(rates.split(",")) + repeat_first))
            result = json.loads(Path(out.name).read_text() or "{}")
            if proc.poll() is None:
                row["vm_hwm_mib"] = read_vm(proc.pid, "VmHWM")
                row["vm_rss_mib"] = read_vm(proc.pid, "VmRSS")
        except NotAvailable as exc:
            result = {"error": str(exc)}
        except subprocess.TimeoutExpired:
            result = {"error": "probe timed out"}
        finally:
            rc, err = _stop(proc)
    if result.get("error"):
        tail = " | ".join(err.strip().splitlines()[-3:])
        row["status"] = f"not available: {result['error']}" + (f" (subject stderr: {tail})" if tail else "")
        row["windows"] = result.get("windows", [])
        return row
    if not result.get("windows"):
        row["status"] = f"not available: probe produced no result ({probe.stderr.strip()[-300:]})"
        return row
    row["status"] = "ok"
    row["windows"] = result["windows"]
    row["output_reliability"] = result.get("output_reliability")
    rate0 = result["windows"][0]["target_hz"]
    first = [w for w in result["windows"] if w["target_hz"] == rate0]
    sent, got = sum(w["sent"] for w in first), sum(w["received"] for w in first)
    row.update(p50_us_1k=_median([w["p50_us"] for w in first]),
               p99_us_1k=_median([w["p99_us"] for w in first]),
               cpu_share_1k=_median([w["cpu_share"] for w in first]),
               cpu_us_per_output_1k=_median([w["cpu_us_per_output"] for w in first]),
               loss_1k=1.0 - got / sent if sent else float("nan"),
               achieved_hz_1k=_median([w["achieved_hz"] for w in first]), windows_1k=len(first))
    if all("also_received" in w for w in first):
        also = sum(w["also_received"] for w in first)
        row["also_loss_1k"] = 1.0 - also / sent if sent else float("nan")
    held = [w["achieved_hz"] for w in result["windows"] if w["loss"] == 0.0]
    row["max_rate_no_loss_hz"] = max(held) if held else 0.0
    row["exit_code"] = rc
    return row


def _alternate(subj: dict, keys: tuple[str, str], runs: int, window: float, repeat_first: int,
               label: str, first: int = 2) -> list[tuple[dict, dict]]:
    """``runs`` runs of two subjects one after the other at 1 kHz: the pairs (both ok);
    ``first``: the number of the first pair in the progress lines (2: the rows were the first)."""
    out = []
    for n in range(runs):
        progress("live", f"{label}: pair {n + first}/{runs + first - 1} of {' and '.join(keys)} at 1 kHz")
        a, b = (run_subject(subj[k], "1000", window, ready_timeout=30.0,
                            repeat_first=repeat_first) for k in keys)
        if a.get("status") == "ok" and b.get("status") == "ok":
            out.append((a, b))
    return out


def run(quick: bool = False, smoke: bool = False) -> dict:
    """``quick``: 1 and 4 kHz, 1.5 s windows; ``smoke``: the bare republisher only, one 0.5 s
    window at 500 Hz (tests only, figures meaningless)."""
    rates = "500" if smoke else "1000,4000" if quick else "1000,2000,4000,8000"
    window = 0.5 if smoke else 1.5 if quick else 3.0
    repeat_first = 1 if quick or smoke else 3
    out: dict = dict(rates=rates, window_s=window, repeats_1k=repeat_first, domain=bench_domain(),
                     rows=[])
    pairs: list[tuple[dict, dict]] = []
    with tempfile.TemporaryDirectory(prefix="dyn_bench_rec_") as rec:
        every = subjects(rec)
        for s in every[:1 if smoke else None]:
            progress("live", f"{s['name']} (rates {rates} Hz, {window} s each)")
            row = run_subject(s, rates, window, ready_timeout=30.0, repeat_first=repeat_first,
                              settle_s=0.0 if smoke else SETTLE_S)
            progress("live", f"{s['name']}: {row['status']}")
            out["rows"].append(row)
        by = {r["key"]: r for r in out["rows"] if r.get("status") == "ok"}
        # Recording's cost is a few percent of a process CPU share that itself drifts by more
        # than that between runs minutes apart, and (e) runs minutes after (b) on a shared
        # machine, so those pairs run again, alternately, at 1 kHz only, and their figures are
        # medians over the pairs.
        subj = {s["key"]: s for s in every}
        if "dyn_node" in by and "dyn_node_record" in by:
            pairs = [(by["dyn_node"], by["dyn_node_record"])] + _alternate(
                subj, ("dyn_node", "dyn_node_record"), 0 if quick else RECORDING_PAIRS - 1,
                window, repeat_first, "recording overhead")
        subj["minimal_effort"] = minimal_fed_efforts(subj)
        contact = _alternate(subj, ("minimal_effort", "dyn_node_contact"), 1 if quick else CONTACT_PAIRS,
                             window, repeat_first, "contact observer cost", first=1) \
            if {"minimal", "dyn_node_contact"} <= set(by) else []
    cmp: dict = {}
    if "dyn_node" in by and "minimal" in by:
        cmp["p99_dyn_node_over_minimal_1k"] = by["dyn_node"]["p99_us_1k"] / by["minimal"]["p99_us_1k"]
        cmp["p50_dyn_node_over_minimal_1k"] = by["dyn_node"]["p50_us_1k"] / by["minimal"]["p50_us_1k"]
        cmp["max_rate_dyn_node_over_minimal"] = (
            by["dyn_node"]["max_rate_no_loss_hz"] / by["minimal"]["max_rate_no_loss_hz"]
            if by["minimal"]["max_rate_no_loss_hz"] else float("nan"))
    if contact:
        ratios = [e["p99_us_1k"] / b["p99_us_1k"] for b, e in contact]
        cmp["p99_contact_over_minimal_1k"] = _median(ratios)
        out["p99_contact_over_minimal_1k_by_pair"] = ratios
        # "no loss" has to hold in every run, so the worst run's loss is the figure
        runs_e = [e for _, e in contact] + [by["dyn_node_contact"]]
        cmp["loss_contact_1k"] = max(e["loss_1k"] for e in runs_e)
        cmp["loss_contact_wrench_1k"] = max(e.get("also_loss_1k", float("nan")) for e in runs_e)
        if "dyn_node" in by:
            cmp["p99_contact_over_dyn_node_1k"] = (by["dyn_node_contact"]["p99_us_1k"]
                                                   / by["dyn_node"]["p99_us_1k"])
    if "minimal" in by and "bare" in by:
        cmp["p99_minimal_over_bare_1k"] = by["minimal"]["p99_us_1k"] / by["bare"]["p99_us_1k"]
    pairs = [(c, d) for c, d in pairs if c["cpu_share_1k"] > 0 and c["cpu_us_per_output_1k"] > 0]
    if pairs:
        share = [d["cpu_share_1k"] / c["cpu_share_1k"] - 1.0 for c, d in pairs]
        # Per message answered: not flattered when the recording node answers fewer messages.
        per_output = [d["cpu_us_per_output_1k"] / c["cpu_us_per_output_1k"] - 1.0 for c, d in pairs]
        cmp["recording_cpu_overhead_1k"] = _median(share)
        cmp["recording_cpu_per_output_overhead_1k"] = _median(per_output)
        out["recording_cpu_overhead_1k_by_pair"] = share
    out["comparisons"] = cmp
    if not smoke:   # the simulated stack's pushes take minutes: not in the harness smoke test
        progress("live", "detection latency (benchmarks.contact_bench)")
        out["detection"] = detection.run(quick=quick, smoke=smoke)
        progress("live", f"detection latency: {out['detection']['status']}")
    return out
