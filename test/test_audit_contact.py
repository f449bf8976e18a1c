"""dyn-audit replays contact from a bag: a real DynNode records the simulator's joint_states
(MuJoCo, pushed at the flange with 30 N for 0.3 s, with a pause longer than stale_timeout), and
the audit re-derives ~/external_torque, ~/external_wrench and ~/observer_events with exactly 0.0
difference, finds the one contact episode at the push's time (the simulator's, an independent
clock of truth) and the resets where the node made them; a damaged copy is still audited."""
from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_audit import validated  # noqa: E402
from test_bag_reader import joint_state  # noqa: E402

from dyn_node.audit.bag_audit import AuditOptions, run_audit  # noqa: E402
from dyn_node.core.robot.model import load_model  # noqa: E402
from dyn_node.sim.simulator import SimConfig, Simulator  # noqa: E402

PANDA = load_model(builtin="panda")
READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
MS = 1_000_000
N = 1400                 # simulator samples (1 kHz stamps)
PUSH_AT, PUSH_STEPS = 500, 300   # the push starts on step 500 and lasts 0.3 s
FORCE = np.array([0.0, 30.0, 0.0])  # N, in panda_link8's axes
GAP_AT = 1100            # the publisher pauses before this sample ...
GAP_S = 0.7              # ... for longer than stale_timeout (0.5 s): the node resets
OUTPUTS = ("/dyn_node/external_torque", "/dyn_node/external_wrench", "/dyn_node/observer_events")


def simulated() -> list:
    """The pushed simulator's states, one per 1 ms step, during a comfortable motion."""
    sim = Simulator(PANDA, SimConfig(initial_positions=tuple(READY)))
    move = np.array([0.3, 0.2, 0.0, 0.3, 0.0, -0.2, 0.0])
    zero = np.zeros((3, 7))
    sim.execute(PANDA.joint_names, [0.1, 0.8, 1.4], np.vstack([READY, READY + move, READY]), zero, zero)
    states = []
    for k in range(N):
        if k == PUSH_AT:
            sim.apply_wrench("panda_link8", FORCE, (0.0, 0.0, 0.0), hold_s=PUSH_STEPS * 1e-3)
        states.append(sim.step(1))
    return states


def record_pushed(ctx, tmp: Path, *, gap_at: int | None = GAP_AT, at: dict | None = None) -> tuple[str, int]:
    """(bag path, t0): a DynNode recording its inputs and outputs while the simulated states
    are published, stamped t0 + (k + 1) ms (the simulator's clock); a pause of GAP_S before
    sample ``gap_at``; ``at[k](node)`` runs before sample k is published."""
    import time

    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState

    from conftest import Stepper
    from dyn_node.ros.node import DynNode

    node = DynNode(context=ctx, parameter_overrides=[
        Parameter("robot_model", value="panda"), Parameter("record.enabled", value=True),
        Parameter("record.directory", value=str(tmp / "bags"))])
    bridge = node.recording
    pub_node = Node(f"audit_contact_publisher_{len(list(tmp.iterdir()))}", context=ctx)
    js_pub = pub_node.create_publisher(JointState, "joint_states", 1000)
    steps = Stepper(ctx, (node, pub_node))
    rec_topics = lambda: bridge.recorder.stats().topics if bridge.recorder else {}  # noqa: E731
    names = list(PANDA.joint_names) + ["panda_finger_joint1", "panda_finger_joint2"]
    t0 = time.time_ns() // MS * MS
    try:
        assert steps.until(lambda: js_pub.get_subscription_count() >= 1, 30.0)
        for k, st in enumerate(simulated()):
            if k == gap_at:
                steps.until(lambda: False, GAP_S)
            if at and k in at:
                at[k](node)
            js_pub.publish(joint_state(names, list(st.q) + [0.01, 0.01], list(st.v) + [0.0, 0.0],
                                       list(st.effort) + [0.0, 0.0], stamp_ns=t0 + (k + 1) * MS))
            steps.until(lambda: False, 0.002)
        steps.until(lambda: False, 1.2)  # a diagnostics period closes after the last input

        def done():
            t = rec_topics()
            return all(k in t and t[k].received >= N for k in
                       ("/joint_states", "/dyn_node/inverse_dynamics", "/dyn_node/external_torque"))
        assert steps.until(done, 30.0), {k: v.received for k, v in rec_topics().items()}
        ok, path = bridge.stop()
        assert ok, path
    finally:
        bridge.close()
        steps.close()
    return path, t0


@pytest.fixture(scope="module")
def recorded(module_ros_context, tmp_path_factory):
    """(bag path, t0, tmp dir) of the pushed run with a gap."""
    tmp = tmp_path_factory.mktemp("contact")
    return (*record_pushed(module_ros_context, tmp), tmp)


@pytest.fixture(scope="module")
def audited(recorded):
    path, t0, tmp = recorded
    res = run_audit(AuditOptions(bag=path, out=str(tmp / "out")))
    return validated(tmp / "out"), res, t0


@pytest.mark.timeout(180)
def test_replayed_contact_outputs_are_identical(audited):
    rec, res, _ = audited
    rc = rec["outputs"]["recheck"]
    for topic in OUTPUTS:
        d = rc[topic]
        assert d["identical"] is True and d["max_abs_difference"] == 0.0, (topic, d)
        assert (d["unmatched"], d["unanswered"]) == (0, 0), (topic, d)
    assert rc["/dyn_node/external_torque"]["matched"] == N
    assert rc["/dyn_node/external_wrench"]["matched"] == N  # the flange is never singular here
    c = rec["outputs"]["contact"]
    assert (c["samples"], c["estimated"]) == (N, N)
    # every observer event was replayed: the two resets and each diagnostics period
    assert rc["/dyn_node/observer_events"]["matched"] == c["resets_total"] + c["power_balance_periods"]
    assert c["power_balance_periods"] >= 2
    assert res.exit_code == 0


def test_the_push_is_one_episode_at_its_time(audited):
    """The simulator pushed from its sample PUSH_AT + 1 (the first state the push moved) for
    0.3 s: the one episode starts (at the first sample over the contact threshold) within the
    observer's rise after it (< 1/K = 20 ms for a push of many times the threshold), ends after
    the push did, and its peak force at the flange is the applied 30 N within 10 % + 1 N."""
    rec, res, t0 = audited
    c = rec["outputs"]["contact"]
    start_ns = rec["inputs"]["time_span"]["start_ns"]
    (ep,) = c["episodes"]
    first_pushed = (t0 + (PUSH_AT + 1) * MS - start_ns) * 1e-9
    # (1e-6: episode times are float seconds of the stamps, ~2e-7 s apart at today's epoch)
    assert first_pushed - 1e-6 <= ep["start_s"] <= first_pushed + 0.02, (ep, first_pushed)
    assert ep["end_s"] > first_pushed + PUSH_STEPS * 1e-3
    assert ep["level"] in ("contact", "collision") and ep["frame"] == "panda_link8"
    assert abs(ep["peak_force_n"] - 30.0) <= 0.01 * 30.0, ep  # the lag settles within the push
    assert ep["failure_label"] == "control error" and ep["joints"]
    findings = rec["verdict"]["findings"]
    assert any(f.startswith(f"{ep['level']} from {ep['start_s']:.3f} s") for f in findings), findings
    out = res.out_dir
    assert (out / "contact.png").stat().st_size > 10_000
    assert "Contact and collision (replayed)" in (out / "report.html").read_text()


def test_the_gap_resets_the_replay_where_the_node_reset(audited):
    """The pause before GAP_AT is longer than stale_timeout: the node restarted its observer
    on the next sample, and so did the replay (its event, with the sample's stamp, matched)."""
    rec, _, t0 = audited
    c = rec["outputs"]["contact"]
    start_ns = rec["inputs"]["time_span"]["start_ns"]
    assert [r["code"] for r in c["resets"]] == ["recording_start", "gap"]
    assert c["resets"][1]["time_s"] == pytest.approx((t0 + (GAP_AT + 1) * MS - start_ns) * 1e-9, abs=1e-6)
    assert c["resets"][0]["time_s"] == pytest.approx((t0 + MS - start_ns) * 1e-9, abs=1e-6)


def test_batched_and_per_message_replays_agree(recorded, audited, monkeypatch):
    import dyn_node.audit.replay.inputs as ba  # the batch threshold lives with the replay

    path, _, tmp = recorded
    monkeypatch.setattr(ba, "MIN_BATCH", 10**9)  # every message on its own
    run_audit(AuditOptions(bag=path, out=str(tmp / "one"), report=False))
    one = validated(tmp / "one")
    assert one["outputs"]["contact"] == audited[0]["outputs"]["contact"]
    assert {t: one["outputs"]["recheck"][t] for t in OUTPUTS} == {
        t: audited[0]["outputs"]["recheck"][t] for t in OUTPUTS}


def test_a_damaged_bag_is_still_audited_in_part(recorded):
    """One flipped byte in a chunk in the middle: that range is lost, the rest is replayed
    (exit 3, partial), the contact section is there and the outputs before it are identical."""
    from mcap.reader import make_reader

    path, _, tmp = recorded
    (src,) = sorted(Path(path).glob("*.mcap")) if Path(path).is_dir() else [Path(path)]
    bad = tmp / "damaged"
    bad.mkdir()
    data = bytearray(src.read_bytes())
    with open(src, "rb") as fh:
        chunks = sorted(make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.message_start_time)
    chunk = chunks[len(chunks) // 2]
    data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0x01
    (bad / src.name).write_bytes(bytes(data))
    res = run_audit(AuditOptions(bag=str(bad / src.name), out=str(tmp / "dmg")))
    rec = validated(tmp / "dmg")
    assert res.exit_code == 3 and rec["verdict"]["partial"] is True
    c = rec["outputs"]["contact"]
    assert 0 < c["samples"] < N
    d = rec["outputs"]["recheck"]["/dyn_node/external_torque"]
    assert 0 < d["matched"] < N
    shutil.rmtree(bad)


@pytest.mark.timeout(180)
def test_a_parameter_change_resets_the_replay_from_when_it_took_effect(module_ros_context, tmp_path):
    """observer_gain set on the running node during the push (as `ros2 param set` does): the
    node builds a new monitor and resets it (parameter_change, on the next sample); the audit
    replays the new configuration from its effective_log_time_ns and reproduces every contact
    output and event exactly, the new gain included."""
    from rclpy.parameter import Parameter

    change = PUSH_AT + 100
    path, t0 = record_pushed(module_ros_context, tmp_path, gap_at=None, at={
        change: lambda node: node.set_parameters([Parameter("observer_gain", value=[30.0])])})
    run_audit(AuditOptions(bag=path, out=str(tmp_path / "out"), report=False))
    rec = validated(tmp_path / "out")
    assert [c["parameters"] for c in rec["configuration"]["changes"]] == [{"observer_gain": [30.0]}]
    rc = rec["outputs"]["recheck"]
    for topic in OUTPUTS:
        assert rc[topic]["identical"] is True and (rc[topic]["unmatched"], rc[topic]["unanswered"]) == (0, 0), rc
    assert rc["/dyn_node/external_torque"]["matched"] == N
    c = rec["outputs"]["contact"]
    start_ns = rec["inputs"]["time_span"]["start_ns"]
    assert [r["code"] for r in c["resets"]] == ["recording_start", "parameter_change"]
    assert c["resets"][1]["time_s"] == pytest.approx((t0 + (change + 1) * MS - start_ns) * 1e-9, abs=1e-6)
    assert c["observer_gain_per_s"] == [30.0] * 7
    # the restart mid-push ends the first episode (its estimate drops to 0) and a second one
    # starts once the new observer has risen again
    assert len(c["episodes"]) == 2, c["episodes"]


def test_a_replay_off_by_a_hair_is_found(recorded, monkeypatch):
    """The re-check can fail: the same bag replayed with observer_gain 50 + 1e-6 /s gives
    external torques and wrenches that differ from the recorded ones (by less than 1e-3), not identical."""
    from dataclasses import replace

    import dyn_node.audit.replay.contact as cr
    from dyn_node.core.contacts.contact_monitor import ContactMonitor, contact_settings

    path, _, tmp = recorded
    monkeypatch.setattr(cr, "monitor_for", lambda cfg, dyn: ContactMonitor(dyn, replace(
        contact_settings(cfg.settings), observer_gain=(50.0 + 1e-6,))))
    run_audit(AuditOptions(bag=path, out=str(tmp / "off"), report=False))
    rc = validated(tmp / "off")["outputs"]["recheck"]
    for topic in OUTPUTS[:2]:
        assert rc[topic]["matched"] == N and rc[topic]["identical"] is False, rc[topic]
        assert 0.0 < rc[topic]["max_abs_difference"] < 1e-3, rc[topic]


def test_one_thread_audits_the_same_without_a_thread_of_its_own(recorded, audited, monkeypatch):
    """threads=1 (a fleet worker's audit): no pool is ever made, the contact pass runs in turn,
    the plots are drawn in turn, and the evidence and every plot are the same as with two."""
    import dyn_node.audit.replay.inputs as inputs
    import dyn_node.audit.report as report

    def no_pool(*_a, **_k):
        raise AssertionError("a thread pool was made with threads=1")

    monkeypatch.setattr(inputs, "ThreadPoolExecutor", no_pool)
    monkeypatch.setattr(report, "ThreadPoolExecutor", no_pool)
    path, _, tmp = recorded
    run_audit(AuditOptions(bag=path, out=str(tmp / "single"), threads=1))
    single = validated(tmp / "single")
    assert single["outputs"]["contact"] == audited[0]["outputs"]["contact"]
    assert single["outputs"]["recheck"] == audited[0]["outputs"]["recheck"]
    pngs = sorted(p.name for p in (tmp / "out").glob("*.png"))
    assert "contact.png" in pngs
    for name in pngs:
        assert (tmp / "single" / name).read_bytes() == (tmp / "out" / name).read_bytes(), name
