"""The reliability fault matrix at the ROS level (issue 9): overload, clock trouble, late join and
QoS, parameter faults, shutdown races. Results and reproduction commands are in RELIABILITY.md.

CI-sized by default (under about two minutes on a busy 2-core machine); ``DYN_RELIABILITY_FULL=1``
raises the shutdown repetitions to 100 per signal and the overload to 5 bursts.
Run: ``DYN_TEST_DOMAIN=73 python -m pytest -q test/test_reliability.py``.
"""
from __future__ import annotations

import math
import os
import random
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
import yaml
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectory

from conftest import Collected, Spinner, js, kv, python_cmd, t_msg, t_s
from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.core.robot.model import builtin_urdf, load_model
from dyn_node.ros.node import DynNode
from dyn_node.ros.convert import RawTrajectory, encode_joint_trajectory_cdr

FULL = os.environ.get("DYN_RELIABILITY_FULL") == "1"
PANDA = load_model(builtin="panda")
NAMES = list(PANDA.joint_names)
Q0 = np.array([0.1, -0.4, 0.2, -1.8, 0.3, 1.5, -0.2])
V0 = np.linspace(-0.3, 0.3, 7)
DYN = Dynamics(PANDA, DynamicsOptions(include_friction=True))
RELIABLE = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)
BEST_EFFORT = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
OK, WARN, ERROR, STALE = b"\x00", b"\x01", b"\x02", b"\x03"


def js_values(p: "Probe") -> dict[str, str] | None:
    """The values of the panda node's last ``dyn_node: joint_states`` status on the probe's
    "diag" subscription (None before the first)."""
    sts = p.statuses("diag", "dyn_node: joint_states", "panda")
    return kv(sts[-1][1] if isinstance(sts[-1], tuple) else sts[-1]) if sts else None


def js_taken(p: "Probe") -> tuple[int, int]:
    """(received_messages, dropped_messages) of the last status; (-1, -1) before the first."""
    v = js_values(p)
    return (int(v["received_messages"]), int(v["dropped_messages"])) if v else (-1, -1)


def js_settled(p: "Probe", timeout: float = 30.0) -> tuple[int, int]:
    """:func:`js_taken` once the three statuses after more than three new diagnostics arrays
    agree on it."""
    n_diag = len(p.got["diag"])

    def agree() -> bool:
        sts = p.statuses("diag", "dyn_node: joint_states", "panda")[-3:]
        c = {(kv(st)["received_messages"], kv(st)["dropped_messages"])
             for st in (x[1] if isinstance(x, tuple) else x for x in sts)}
        return len(p.got["diag"]) > n_diag + 3 and len(sts) == 3 and len(c) == 1
    assert p.wait(agree, timeout), js_values(p)
    return js_taken(p)


class Probe(Collected):
    """A node that collects what it is told to subscribe to; its executor spins in a thread
    (together with any in-process node under test)."""

    def __init__(self, ctx: Context, name: str, nodes: tuple = ()):
        super().__init__()
        self.node = rclpy.create_node(name, context=ctx)
        self.spinner = Spinner(ctx, (self.node, *nodes))

    def sub(self, key: str, msg_type, topic: str, qos, stamp_receipt: bool = False) -> None:
        self.got[key] = []
        self.node.create_subscription(msg_type, topic, self.collector(key, stamp_receipt), qos)

    def statuses(self, key: str, name: str, hardware_id: str | None = None) -> list:
        with self.cond:
            arrays = list(self.got[key])
        out = []
        for item in arrays:
            t, arr = item if isinstance(item, tuple) else (None, item)
            for s in arr.status:
                if s.name == name and (hardware_id is None or s.hardware_id == hardware_id):
                    out.append((t, s) if t is not None else s)
        return out

    def close(self, *nodes) -> None:
        self.spinner.stop()
        for n in nodes:
            n.destroy_node()
        self.node.destroy_node()


@pytest.fixture(scope="module")
def ctx(module_ros_context):
    return module_ros_context


# --- overload -------------------------------------------------------------------------------
BURST_PUBLISHER = textwrap.dedent("""
    import math, select, sys, time
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    topic, names = sys.argv[1], sys.argv[2].split(",")
    rate, burst_s, bursts, pause_s = (float(x) for x in sys.argv[3:7])
    q0 = [float(x) for x in sys.argv[7].split(",")]
    v0 = [float(x) for x in sys.argv[8].split(",")]
    rclpy.init()
    node = rclpy.create_node("burst_publisher")
    pub = node.create_publisher(JointState, topic, QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    deadline = time.monotonic() + 30
    while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.01)
    msg = JointState(name=names)

    def tag(seq):  # sequence-tagged: stamp.sec = 1000 + sequence number; q, v derived from it
        msg.header.stamp.sec = 1000 + seq
        msg.position = [q + 0.01 * math.sin(0.1 * seq + k) for k, q in enumerate(q0)]
        msg.velocity = [v + 0.01 * math.cos(0.1 * seq + k) for k, v in enumerate(v0)]
        return msg

    # Slow samples until the test says "go", so the node has taken at least one before the
    # bursts: drops are counted from the first sample the node takes from a publisher (a gap
    # before it cannot be seen), and the publisher's match alone does not mean the node's has.
    print("READY", flush=True)
    sent = 0
    while not select.select([sys.stdin], [], [], 0.05)[0]:
        pub.publish(tag(sent)); sent += 1
    sys.stdin.readline()  # "stop"
    print("PRIMED", sent, flush=True)
    sys.stdin.readline()  # "go"
    t_begin = time.perf_counter()
    for b in range(int(bursts)):
        t0, n0 = time.perf_counter(), sent
        while (el := time.perf_counter() - t0) < burst_s:
            due = n0 + int(el * rate) + 1
            while sent < due:
                pub.publish(tag(sent)); sent += 1
        t1 = time.perf_counter()
        while time.perf_counter() - t1 < pause_s:
            rclpy.spin_once(node, timeout_sec=0.01)
    for _ in range(20):  # a slow tail, so a loss at the very end is followed by a later sample
        pub.publish(tag(sent)); sent += 1
        rclpy.spin_once(node, timeout_sec=0.01)
    print("SENT", sent, time.perf_counter() - t_begin, flush=True)
    node.destroy_node(); rclpy.try_shutdown()
""")


def _seq_state(seq: int) -> tuple[np.ndarray, np.ndarray]:
    k = np.arange(7)
    return Q0 + 0.01 * np.sin(0.1 * seq + k), V0 + 0.01 * np.cos(0.1 * seq + k)


def _long_trajectory_cdr(n: int, stamp: Time) -> bytes:
    """A smooth n-point JointTrajectory (1 ms apart, positions and velocities) as CDR bytes."""
    t = np.arange(1, n + 1) * 1e-3
    w = 2 * np.pi / 20.0
    P = Q0 + 0.3 * np.sin(w * t)[:, None] * np.linspace(0.5, 1.0, 7)
    V = 0.3 * w * np.cos(w * t)[:, None] * np.linspace(0.5, 1.0, 7)
    ns = np.round(t * 1e9).astype(np.int64)
    raw = RawTrajectory(stamp, b"", NAMES, list(t), [(int(x // 10**9), int(x % 10**9)) for x in ns],
                        (P, V, np.zeros((n, 0)), np.zeros((n, 0))))
    return encode_joint_trajectory_cdr(raw, np.zeros((n, 0)))


@pytest.mark.timeout(150)
def test_overload_5khz_bursts_during_100k_point_check(ctx, spawn):
    ns = "/ovl"
    bursts = 5 if FULL else 2
    node = spawn(python_cmd("dyn_node.ros.node", "--ros-args", "-r", f"__ns:={ns}", "-p", "robot_model:=panda",
                            "-p", "acceleration_source:=zero", "-p", "diagnostics_period:=0.1",
                            "-p", "qos_depth:=10"))
    p = Probe(ctx, "ovl_probe")
    try:
        p.sub("grav", JointState, f"{ns}/dyn_node/gravity_torque", RELIABLE)
        p.sub("inv", JointState, f"{ns}/dyn_node/inverse_dynamics", RELIABLE)
        p.sub("diag", DiagnosticArray, "/diagnostics", 1000, stamp_receipt=True)
        p.sub("feas", DiagnosticArray, f"{ns}/dyn_node/feasibility", LATCHED)
        traj_pub = p.node.create_publisher(JointTrajectory, f"{ns}/joint_trajectory", 1)
        fmt = lambda a: ",".join(repr(float(x)) for x in a)  # noqa: E731
        pub = spawn([sys.executable, "-c", BURST_PUBLISHER, f"{ns}/joint_states", ",".join(NAMES), "5000", "1.0",
                     str(bursts), "0.3", fmt(Q0), fmt(V0)], stdin=subprocess.PIPE)
        assert pub.proc.stdout.readline().strip() == "READY", pub.stop()[2]

        def counts():
            v = js_values(p)
            if v is None:
                return None
            return (int(v["received_messages"]), int(v["dropped_messages"]), int(v["invalid_messages"]),
                    int(v["out_of_order_messages"]))

        # priming goes on until the probe has an answer too: its subscription to the node's
        # outputs can match later than the node's to the publisher (once, on a loaded machine,
        # priming ended before it and no answer came until the bursts)
        assert p.wait(lambda: traj_pub.get_subscription_count() >= 1
                      and (c := counts()) is not None and c[0] >= 1 and len(p.got["grav"]) > 0,
                      60), node.stop()[2]
        pub.proc.stdin.write("stop\n")
        pub.proc.stdin.flush()
        line = pub.proc.stdout.readline().split()
        assert line and line[0] == "PRIMED", pub.stop()[2]
        primed = int(line[1])

        r0, d0 = js_settled(p)   # the priming counts
        # Samples published before the node's reader matched the publisher (the publisher's own
        # match can come first; on a loaded machine by several priming periods) are invisible:
        # no sequence gap precedes the first one taken. They are exactly the samples before the
        # first one the node took, which is at or before the first answer the probe saw.
        unseen = primed - r0 - d0
        with p.cond:
            first_answered = min(m.header.stamp.sec - 1000 for m in p.got["grav"])
        assert 0 <= unseen <= first_answered, (primed, r0, d0, first_answered)
        data = _long_trajectory_cdr(100_000, Time(sec=5, nanosec=0))
        traj_pub.publish(data)
        t_go = time.monotonic()
        pub.proc.stdin.write("go\n")
        pub.proc.stdin.flush()
        line = pub.proc.stdout.readline().split()
        t_done = time.monotonic()
        assert line and line[0] == "SENT", pub.stop()[2]
        sent, took = int(line[1]), float(line[2])

        # wait (bounded) for the counts to cover what was sent: the last samples may still sit in
        # the node's reader queue while the 100k-point check and a busy machine compete for CPU
        p.wait(lambda: (c := counts()) is not None and c[0] + c[1] >= sent - unseen, 60)
        # let one more diagnostics period pass so a late count would show up
        n_diag = len(p.got["diag"])
        p.wait(lambda: len(p.got["diag"]) > n_diag + 3, 5)
        received, dropped, invalid, ooo = counts()
        assert p.wait(lambda: any(kv(s).get("n_points") == "100000" for a in p.got["feas"] for s in a.status), 90)
        t_feas = time.monotonic()
        levels = [(t, s.level, s.message) for t, s in p.statuses("diag", "dyn_node: joint_states", "panda")
                  if t_go <= t <= t_done + 1.0]
        print(f"overload: sent {sent} ({unseen} before the node's reader matched) in {took:.2f} s ({sent / took:.0f} Hz), node received {received}, "
              f"dropped {dropped}, invalid {invalid}, out of order {ooo}; answered "
              f"{len(p.got['grav'])}; 100k-point verdict {t_feas - t_go:.1f} s after the first burst "
              f"(bursts ended after {t_done - t_go:.1f} s); levels while sending "
              f"{sorted({lv[0] for _, lv, _ in levels})}")
        # Accounting: every sample from the first one the node took on is either received or
        # counted as dropped (gaps in the DDS publication sequence numbers), never both.
        accountable = sent - unseen
        assert 0 < received <= accountable and received + dropped == accountable, \
            (sent, unseen, received, dropped)
        assert invalid == 0 and ooo == 0
        # torques correct for everything processed (acceleration_source zero: RNEA(q, v, 0))
        with p.cond:
            grav, inv = list(p.got["grav"]), list(p.got["inv"])
        assert grav and inv
        for m in grav:
            q, _ = _seq_state(m.header.stamp.sec - 1000)
            np.testing.assert_allclose(m.effort, DYN.gravity(q), rtol=0, atol=1e-9)
        for m in inv:
            q, v = _seq_state(m.header.stamp.sec - 1000)
            np.testing.assert_allclose(m.effort, DYN.rnea(q, v, np.zeros(7)), rtol=0, atol=1e-9)
        if dropped:
            assert any(lv == WARN and "dropped" in msg for _, lv, msg in levels), levels
    finally:
        p.close()
        rc, _, err = node.stop(signal.SIGINT)
        assert "Traceback" not in err, err


@pytest.mark.timeout(120)
def test_two_publisher_flood_counts_a_lower_bound_then_exact_again(ctx, spawn):
    """Two publishers flood joint_states into a 10-deep history: the node counts the middleware's
    lost events, which never over-count (on Fast DDS they miss history overwrites, so the count
    is a lower bound). One publisher leaves; after a few samples the node is back on sequence
    numbers, and the next flood from the remaining publisher is accounted exactly."""
    ns = "/two"
    node = spawn(python_cmd("dyn_node.ros.node", "--ros-args", "-r", f"__ns:={ns}", "-p", "robot_model:=panda",
                            "-p", "acceleration_source:=zero", "-p", "diagnostics_period:=0.1",
                            "-p", "qos_depth:=10"))
    p = Probe(ctx, "two_probe")
    try:
        p.sub("diag", DiagnosticArray, "/diagnostics", 1000)
        pubs = [p.node.create_publisher(JointState, f"{ns}/joint_states", RELIABLE) for _ in range(2)]
        msg = JointState(name=NAMES, position=list(Q0), velocity=list(V0))
        sent = [0]

        def publish(pub) -> None:
            sent[0] += 1
            msg.header.stamp.sec, msg.header.stamp.nanosec = 1000 + sent[0] // 1000, (sent[0] % 1000) * 10**6
            pub.publish(msg)

        def one_by_one(pub, until) -> None:
            # single samples, each taken before the next, until the node's status says so
            for _ in range(100):
                before = js_taken(p)[0]
                publish(pub)
                assert p.wait(lambda: js_taken(p)[0] > before, 10), js_values(p)
                if until():
                    return
            raise AssertionError(f"not reached: {js_values(p)}")

        assert p.wait(lambda: all(x.get_subscription_count() >= 1 for x in pubs) and js_values(p) is not None, 60), \
            node.stop()[2]
        publish(pubs[0])
        assert p.wait(lambda: js_taken(p)[0] >= 1, 10)
        one_by_one(pubs[1], lambda: js_values(p)["drop_counting"] == "middleware_lost_events")
        r0, d0 = js_settled(p)
        base = sent[0]
        for k in range(10_000):
            publish(pubs[k % 2])
        r1, d1 = js_settled(p)
        flood = sent[0] - base
        print(f"two publishers: sent {flood}, taken {r1 - r0}, counted dropped {d1 - d0}")
        assert js_values(p)["drop_counting"] == "middleware_lost_events"
        assert 0 < r1 - r0 and (r1 - r0) + (d1 - d0) <= flood      # never an over-count

        p.node.destroy_publisher(pubs[1])
        one_by_one(pubs[0], lambda: js_values(p)["drop_counting"] == "sequence_numbers")
        r2, d2 = js_settled(p)
        base = sent[0]
        for _ in range(10_000):
            publish(pubs[0])
        for _ in range(20):      # a slow tail, so a loss at the very end is followed by a sample
            n = sent[0]
            publish(pubs[0])
            p.wait(lambda: sum(js_taken(p)) - r2 - d2 >= n + 1 - base, 1)
        assert p.wait(lambda: sum(js_taken(p)) - r2 - d2 >= sent[0] - base, 30), \
            ({k: v for k, v in js_values(p).items() if "messages" in k}, r2, d2, sent[0] - base)
        r3, d3 = js_settled(p)
        print(f"one publisher again: sent {sent[0] - base}, taken {r3 - r2}, dropped {d3 - d2}")
        assert (r3 - r2) + (d3 - d2) == sent[0] - base
    finally:
        p.close()
        rc, _, err = node.stop(signal.SIGINT)
        assert "Traceback" not in err, err


# --- clock trouble ----------------------------------------------------------------------------
@pytest.mark.timeout(90)
def test_clock_backwards_zero_stamps_and_sim_time_jump(ctx, tmp_path):
    ns = "/clk"
    node = DynNode(namespace=ns, context=ctx, parameter_overrides=[
        Parameter("robot_model", value="panda"), Parameter("use_sim_time", value=True),
        Parameter("diagnostics_period", value=0.1), Parameter("stale_timeout", value=0.5),
        Parameter("record.enabled", value=True), Parameter("record.directory", value=str(tmp_path)),
        Parameter("record.max_bag_duration_s", value=5.0), Parameter("record.topics", value=["joint_states"])])
    p = Probe(ctx, "clk_probe", (node,))
    try:
        clock_pub = p.node.create_publisher(Clock, "/clock", 10)
        js_pub = p.node.create_publisher(JointState, f"{ns}/joint_states", RELIABLE)
        p.sub("inv", JointState, f"{ns}/dyn_node/inverse_dynamics", RELIABLE)
        p.sub("diag", DiagnosticArray, "/diagnostics", 1000)
        assert p.wait(lambda: js_pub.get_subscription_count() >= 1 and clock_pub.get_subscription_count() >= 1, 20)

        def clock(t):
            clock_pub.publish(Clock(clock=t_msg(t)))
            assert p.wait(lambda: abs(node.get_clock().now().nanoseconds * 1e-9 - t) < 1e-6, 5), t

        sim = 100.0
        clock(sim)  # (the node records its own joint_states subscription: no extra subscriber)
        stamps = [200.0, 200.001, 199.5, 0.0, 200.002, 0.0, 150.0]  # backwards, zero, backwards
        for s in stamps:
            js_pub.publish(js(NAMES, Q0, V0, stamp=s))
            sim += 0.001
            clock(sim)
        for jump in (40.0, 30.0):  # /clock jumps back twice
            sim = jump
            clock(sim)
            js_pub.publish(js(NAMES, Q0, V0, stamp=300.0 + jump))
            n = node._counts.received
            assert p.wait(lambda: node._counts.received > n, 5)
        assert p.wait(lambda: len(p.got["inv"]) >= len(stamps) + 2, 10)
        c = node._counts
        assert c.received == len(stamps) + 2 and c.invalid == 0
        # 199.5 < 200.001; both zero stamps (receipt time ~100 s < previous stamps); 330 < 340
        assert c.out_of_order == 4 and c.zero_stamp == 2, (c.out_of_order, c.zero_stamp)
        zero_answers = [m for m in p.got["inv"] if m.header.stamp.sec == 0 and m.header.stamp.nanosec == 0]
        assert not zero_answers  # a zero stamp is answered with the receipt time
        # joint_states stop while sim time runs on: STALE within stale_timeout + one period
        def run_until_stale(start: float, span: float) -> tuple[float | None, int]:
            n0 = len(p.got["diag"])
            t = start
            while t - start < span:
                t = round(t + 0.05, 6)
                clock(t)
                if p.wait(lambda: any(s.name == "dyn_node: joint_states" and s.level == STALE
                                      for a in p.got["diag"][n0:] for s in a.status), 0.2):
                    return t - start, len(p.got["diag"]) - n0
            return None, len(p.got["diag"]) - n0

        stale_at, _ = run_until_stale(sim, 1.1)
        assert stale_at is not None and stale_at <= 0.5 + 0.1 + 1e-9, stale_at
        sim += stale_at
        # One more message, then /clock jumps back 20 s and runs on: STALE within stale_timeout
        # (0.5 s) plus three diagnostics periods (0.1 s) of the new time: the jump is noticed at
        # the first tick after it, staleness counts from there, the next tick publishes STALE,
        # and the test advances /clock in steps.
        js_pub.publish(js(NAMES, Q0, V0, stamp=400.0))
        n = node._counts.received
        assert p.wait(lambda: node._counts.received > n, 5)
        after_jump, n_diag = run_until_stale(sim - 20.0, 1.1)
        assert after_jump is not None and after_jump <= 0.5 + 3 * 0.1 + 1e-9, (after_jump, n_diag)
        print(f"clock: STALE {stale_at:.2f} s (sim) after the last message; after a 20 s jump back: "
              f"STALE after {after_jump} s, {n_diag} /diagnostics arrays in 1.1 s of sim time")
        ok, path = node.recording.stop()
        assert ok
        meta = yaml.safe_load((Path(path) / "metadata.yaml").read_text())
        files = meta["rosbag2_bagfile_information"]["relative_file_paths"]
        assert len(files) == 1, files  # clock jumps back: no spurious split
        rec = meta["dyn_node"]["topics"][f"{ns}/joint_states"]
        assert rec["received"] == rec["written"] == len(stamps) + 3 and rec["dropped"] == 0, rec
        assert node._callback_errors == 0
    finally:
        p.close(node)


@pytest.mark.timeout(60)
def test_stale_within_timeout_wall_clock(ctx):
    ns = "/stale"
    node = DynNode(namespace=ns, context=ctx, parameter_overrides=[
        Parameter("robot_model", value="panda"), Parameter("diagnostics_period", value=0.05),
        Parameter("stale_timeout", value=0.3)])
    p = Probe(ctx, "stale_probe", (node,))
    try:
        js_pub = p.node.create_publisher(JointState, f"{ns}/joint_states", RELIABLE)
        p.sub("inv", JointState, f"{ns}/dyn_node/inverse_dynamics", RELIABLE, stamp_receipt=True)
        p.sub("diag", DiagnosticArray, "/diagnostics", 1000, stamp_receipt=True)
        assert p.wait(lambda: js_pub.get_subscription_count() >= 1, 20)
        js_pub.publish(js(NAMES, Q0, V0, stamp=10.0))
        assert p.wait(lambda: len(p.got["inv"]) >= 1, 10)
        t_last = p.got["inv"][0][0]

        def stale_after_message():  # STALE about *this* message going quiet (not "none yet")
            return [t for t, s in p.statuses("diag", "dyn_node: joint_states", "panda")
                    if t > t_last and s.level == STALE and int(kv(s)["received_messages"]) >= 1]
        assert p.wait(lambda: bool(stale_after_message()), 5)
        t_stale = min(stale_after_message())
        print(f"stale reported {t_stale - t_last:.3f} s after the last answer (stale_timeout 0.3 s, period 0.05 s)")
        # bound: stale_timeout + one diagnostics period + delivery slack on a busy machine
        assert t_stale - t_last <= 0.3 + 0.05 + 0.25
    finally:
        p.close(node)


# --- late join and QoS ------------------------------------------------------------------------
@pytest.mark.timeout(60)
def test_late_join_latched_description_and_both_qos(ctx):
    ns = "/late"
    p = Probe(ctx, "late_probe")
    node = None
    try:
        desc = p.node.create_publisher(String, f"{ns}/robot_description", LATCHED)
        desc.publish(String(data=builtin_urdf("panda")))  # published before the node exists
        node = DynNode(namespace=ns, context=ctx, parameter_overrides=[
            Parameter("locked_joints", value="panda_finger_joint1,panda_finger_joint2"),
            Parameter("diagnostics_period", value=0.1)])
        p.spinner.add_node(node)
        assert p.wait(lambda: node.model is not None, 20), "latched robot_description not received"
        assert node.model.joint_names == PANDA.joint_names
        rel = p.node.create_publisher(JointState, f"{ns}/joint_states", RELIABLE)
        be = p.node.create_publisher(JointState, f"{ns}/joint_states", BEST_EFFORT)
        p.sub("inv", JointState, f"{ns}/dyn_node/inverse_dynamics", RELIABLE)
        assert p.wait(lambda: rel.get_subscription_count() >= 1 and be.get_subscription_count() >= 1, 20)
        # both publishers matched: each one's messages are answered
        for pub, stamp in ((rel, 20.0), (be, 21.0), (rel, 22.0), (be, 23.0)):
            for _ in range(50):  # best effort may lose a sample before discovery settles
                pub.publish(js(NAMES, Q0, V0, stamp=stamp))
                if p.wait(lambda: any(t_s(m.header.stamp) == stamp for m in p.got["inv"]), 0.2):
                    break
            assert any(t_s(m.header.stamp) == stamp for m in p.got["inv"]), stamp
        m = next(m for m in p.got["inv"] if t_s(m.header.stamp) == 23.0)
        np.testing.assert_allclose(m.effort, DYN.rnea(Q0, V0, np.zeros(7)), rtol=0, atol=1e-9)
    finally:
        p.close(*([node] if node else []))


# --- parameters -------------------------------------------------------------------------------
@pytest.mark.timeout(60)
def test_bad_parameters_rejected_with_reason_nothing_half_applied(ctx, tmp_path):
    ns = "/par"
    node = DynNode(namespace=ns, context=ctx, parameter_overrides=[Parameter("robot_model", value="panda")])
    p = Probe(ctx, "par_probe", (node,))
    try:
        client = AsyncParameterClient(p.node, f"{ns}/dyn_node")
        assert p.wait(client.services_are_ready, 20)
        bad_limits = tmp_path / "bad_limits.yaml"
        bad_limits.write_text("joint_limits:\n  no_such_joint:\n    has_effort_limits: true\n    max_effort: 5.0\n")
        good_limits = tmp_path / "good_limits.yaml"
        good_limits.write_text("joint_limits:\n  panda_joint4:\n    has_effort_limits: true\n    max_effort: 50.0\n")

        def call(fut):
            assert p.wait(fut.done, 10), "parameter service timed out"
            return fut.result()

        before = node.settings
        model_before = node.model
        cases = [[Parameter("payload.mass", value=-1.0)], [Parameter("payload.mass", value=float("nan"))],
                 [Parameter("payload.mass", value="heavy")], [Parameter("stale_timeout", value=0.0)],
                 [Parameter("effort_warn_ratio", value=float("inf"))], [Parameter("gravity", value=[0.0, 0.0])],
                 [Parameter("acceleration_source", value="magic")],
                 [Parameter("limits_file", value=str(bad_limits))],
                 [Parameter("limits_file", value=str(tmp_path / "missing.yaml"))]]
        reasons = []
        for params in cases:
            r = call(client.set_parameters(params)).results[0]
            assert not r.successful and r.reason, params
            reasons.append(r.reason)
            assert node.settings == before and node.model is model_before
        assert "no_such_joint" in reasons[7], reasons[7]
        # atomically: a good payload and a bad limits file -> neither applied
        r = call(client.set_parameters_atomically([Parameter("payload.mass", value=2.0),
                                                   Parameter("limits_file", value=str(bad_limits))])).result
        assert not r.successful and r.reason
        assert node.settings == before and node.model is model_before
        got = call(client.get_parameters(["payload.mass", "limits_file"])).values
        assert got[0].double_value == 0.0 and got[1].string_value == ""
        # and the same pair with a good limits file applies both
        r = call(client.set_parameters_atomically([Parameter("payload.mass", value=2.0),
                                                   Parameter("limits_file", value=str(good_limits))])).result
        assert r.successful, r.reason
        assert node.model.payload.mass == 2.0 and node.model.limits.effort[3] == 50.0
        print("rejection reasons:\n  " + "\n  ".join(reasons))
    finally:
        p.close(node)


# --- shutdown races -------------------------------------------------------------------------
SHUTDOWN_REPS = 100 if FULL else 5  # per signal; two processes run side by side


def _run_shutdown_round(ctx, spawn, tmp: Path, rnd: int, pub_node) -> list[tuple[str, float, int, str, Path]]:
    """Start two recording nodes, load them (1 kHz joint_states + a 20,000-point trajectory),
    send SIGINT to one and SIGTERM to the other at a random moment; return their outcomes."""
    procs = []
    for sig_name in ("INT", "TERM"):
        ns = f"/sd{rnd}{sig_name.lower()}"
        bags = tmp / f"{rnd}_{sig_name}"
        cp = spawn(python_cmd("dyn_node.ros.node", "--ros-args", "-r", f"__ns:={ns}", "-p", "robot_model:=panda",
                              "-p", "record.enabled:=true", "-p", f"record.directory:={bags}",
                              "-p", "diagnostics_period:=0.05"))
        procs.append((sig_name, ns, bags, cp))
    pubs = [(pub_node.create_publisher(JointState, f"{ns}/joint_states", RELIABLE),
             pub_node.create_publisher(JointTrajectory, f"{ns}/joint_trajectory", 1)) for _, ns, _, _ in procs]
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not all(j.get_subscription_count() >= 1 and t.get_subscription_count() >= 1
                                                  for j, t in pubs):
        threading.Event().wait(0.02)  # polling the graph: there is no event to wait on
    assert all(j.get_subscription_count() >= 1 for j, _ in pubs), [cp.stop()[2] for *_, cp in procs]
    traj = _long_trajectory_cdr(20_000, Time(sec=0, nanosec=0))
    for _, t in pubs:
        t.publish(traj)
    load_for = random.uniform(0.2, 1.0)
    t0, seq = time.monotonic(), 0
    while time.monotonic() - t0 < load_for:  # ~1 kHz to each node
        seq += 1
        for j, _ in pubs:
            j.publish(js(NAMES, Q0, V0, stamp=100.0 + seq * 1e-3))
        threading.Event().wait(0.001)
    out = []
    for sig_name, ns, bags, cp in procs:
        cp.signal(signal.SIGINT if sig_name == "INT" else signal.SIGTERM)
    for sig_name, ns, bags, cp in procs:
        t_sig = time.monotonic()
        try:
            cp.proc.wait(timeout=10)
        except Exception:
            pass
        took = time.monotonic() - t_sig
        rc, _, err = cp.stop(signal.SIGKILL, timeout=5)
        out.append((sig_name, took, rc, err, bags))
    for j, t in pubs:
        pub_node.destroy_publisher(j)
        pub_node.destroy_publisher(t)
    return out


@pytest.mark.timeout(120 if not FULL else 3600)
def test_shutdown_races_sigint_sigterm_under_load(ctx, spawn, tmp_path):
    from mcap.reader import make_reader

    pub_node = rclpy.create_node("sd_publisher", context=ctx)
    results = []
    try:
        for rnd in range(SHUTDOWN_REPS):
            results += _run_shutdown_round(ctx, spawn, tmp_path, rnd, pub_node)
    finally:
        pub_node.destroy_node()
    worst = max(r[1] for r in results)
    print(f"shutdown: {len(results)} runs, slowest exit {worst:.2f} s")
    for sig_name, took, rc, err, bags in results:
        # rc 0: the process ended by itself within the 10 s this test waits (a hang is killed
        # and gives -9). How fast it ends is a figure, printed above, not a pass criterion: the
        # time includes this busy process's own wait, and a shared machine can stretch it.
        assert rc == 0, (sig_name, rc, took, err)
        assert "Traceback" not in err, err
        bag = next(Path(bags).iterdir())
        meta = yaml.safe_load((bag / "metadata.yaml").read_text())
        assert meta["dyn_node"]["state"] == "closed", meta["dyn_node"]
        for topic, c in meta["dyn_node"]["topics"].items():  # final counts: all received written
            assert c["received"] == c["written"] and c["dropped"] == 0, (topic, c)
        total = meta["rosbag2_bagfile_information"]["message_count"]
        n = 0
        for f in sorted(bag.glob("*.mcap")):
            with open(f, "rb") as fh:
                summary = make_reader(fh).get_summary()
                assert summary is not None and summary.statistics is not None
                n += summary.statistics.message_count
        assert n == total
