"""dyn-audit: replay through the node's core, evidence record, exit codes, re-check, damaged bags.

Bags are written with mcap (test_bag_reader.BagWriter) from rclpy messages. "Node outputs" are
generated here with the same Monitor / check_trajectory the node uses, so the re-check must find
exactly 0.0 difference; a perturbed output must be found. Every evidence.json is validated
against the shipped schema.
"""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Sequence

import jsonschema
import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_bag_reader import T0, BagWriter, joint_state  # noqa: E402

from dyn_node.audit.bag_audit import AuditOptions, main, run_audit  # noqa: E402
from dyn_node.audit.replay.common import MAX_BINS, SeriesBins  # noqa: E402
from dyn_node.bag.reader import BagReader, decode_joint_state  # noqa: E402
from dyn_node.audit.evidence import schema  # noqa: E402
from dyn_node.core.robot.model import load_model  # noqa: E402

MS = 1_000_000
PANDA = load_model(builtin="panda")
PARAMS = "/dyn_node:\n  ros__parameters:\n    robot_model: panda\n    stale_timeout: 0.5\n"


def q_at(i: int) -> tuple[np.ndarray, np.ndarray]:
    t = i * 1e-3
    ph = np.arange(7) * 0.3
    q = np.array([0.0, -0.3, 0.0, -1.8, 0.0, 1.6, 0.7]) + 0.3 * np.sin(2 * np.pi * 0.5 * t + ph)
    v = 0.3 * 2 * np.pi * 0.5 * np.cos(2 * np.pi * 0.5 * t + ph)
    return q, v


def validated(out: Path) -> dict:
    rec = json.loads((out / "evidence.json").read_text())
    jsonschema.Draft202012Validator(schema()).validate(rec)
    return rec


def make_bag(path: Path, n: int = 1500, *, metadata: bool = True, outputs: bool = False,
             effort_spike: tuple[int, int] | None = None, drop: range | None = None,
             invalid: dict[int, str] | None = None, out_of_order: int | None = None,
             trajectories: list | None = None, description_topic: bool = False,
             perturb: int | None = None, single_file: bool = False, measured: bool = False,
             output_burst: int = 1, outputs_from: int = 0,
             later_metadata: dict | None = None) -> Path:
    """A Panda bag: 1 kHz joint_states (+ optional node outputs made with the node's Monitor).

    ``measured``: finite efforts on the model joints (else NaN: not measured); ``output_burst``:
    the outputs are written after every that many inputs (as a recorder that fell behind);
    ``outputs_from``: no outputs for the inputs before that one (as a node without a model yet);
    ``later_metadata``: a second ``dyn_node`` metadata record, written after the messages."""
    from dyn_node.core.live.monitor import Monitor
    from dyn_node.core.robot.settings import settings_from_mapping
    from std_msgs.msg import String

    meta = ({"robot_description": PANDA.urdf, "parameters": PARAMS, "version": "0.1.0"}
            if metadata else None)
    w = BagWriter(path, metadata=meta, single_file=single_file)
    if description_topic:
        w.write("/robot_description", String(data=PANDA.urdf), T0 - MS)
    mon = Monitor(PANDA, settings_from_mapping({"robot_model": "panda"}))
    names = list(PANDA.joint_names) + ["panda_finger_joint1", "panda_finger_joint2"]
    traj_at = {k: tr for k, tr in (trajectories or [])}
    pending: list = []
    for i in range(n):
        if i in traj_at:
            if traj_at[i].points:     # the robot's last state before it: sample i - 1
                start_at_robot(traj_at[i], i - 1)
            w.write("/joint_trajectory", traj_at[i], T0 + i * MS + 500)
            if outputs:
                # the state: sample i - 1 (sample i is written after it)
                _feasibility_output(w, traj_at[i], T0 + i * MS + 900, i - 1, T0 + i * MS + 500)
        if drop is not None and i in drop:
            continue
        q, v = q_at(i)
        e = [float("nan")] * 9
        if measured:
            e = [float(x) for x in 30.0 * np.sin(2 * np.pi * 0.5 * i * 1e-3 + np.arange(7))] + [0.0, 0.0]
        if effort_spike and effort_spike[0] <= i < effort_spike[1]:
            e[1] = 90.0 + (i - effort_spike[0]) * 0.1  # joint2 limit 87 N·m: peak at the last one
        pos = list(q) + [0.01, 0.01]
        stamp = T0 + i * MS
        if out_of_order is not None and i == out_of_order:
            stamp -= 5 * MS
        js_names = names
        if invalid and i in invalid:
            if invalid[i] == "nan":
                pos = pos.copy()
                pos[3] = float("nan")
            elif invalid[i] == "missing":
                js_names, pos, v, e = names[1:], pos[1:], v[1:], e[1:]
        msg = joint_state(js_names, pos, list(v) + ([0.0, 0.0] if len(js_names) == 9 else [0.0, 0.0]),
                          e, stamp_ns=stamp)
        w.write("/joint_states", msg, T0 + i * MS)
        if outputs:
            r = mon.process(msg.name, msg.position, msg.velocity, msg.effort,
                            msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, (T0 + i * MS) * 1e-9)
            if r.accepted and i >= outputs_from:
                g, tau = r.gravity.copy(), r.tau.copy()
                if perturb is not None and i == perturb:
                    tau[2] += 1e-9
                for topic, eff, dt in (("/dyn_node/gravity_torque", g, 200_000),
                                       ("/dyn_node/inverse_dynamics", tau, 250_000)):
                    o = joint_state(PANDA.joint_names, r.q, r.v, eff, stamp_ns=stamp)
                    o.header.frame_id = ""
                    pending.append((topic, o, T0 + i * MS + dt))
            if len(pending) >= 2 * output_burst:
                for args in pending:
                    w.write(*args)
                pending.clear()
    for args in pending:
        w.write(*args)
    if later_metadata is not None:
        w.w.add_metadata("dyn_node", later_metadata)
    return w.close()


def trajectory_msg(stamp_ns: int, scale: float = 1.0, nan: bool = False):
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    m = JointTrajectory()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    m.joint_names = list(PANDA.joint_names)
    q0 = np.array([0.0, -0.3, 0.0, -1.8, 0.0, 1.6, 0.7])
    for k, t in enumerate([0.0, 0.5 * scale, 1.0 * scale]):
        p = JointTrajectoryPoint()
        q = q0 + (0.4 if k == 1 else 0.0) * np.array([1, 1, 1, 0.5, 1, 0.5, 1])
        if nan and k == 1:
            q[2] = float("nan")
        p.positions = [float(x) for x in q]
        p.velocities = [0.0] * 7
        sec, ns = divmod(int(round(t * 1e9)), 1_000_000_000)
        p.time_from_start = Duration(sec=sec, nanosec=ns)
        m.points.append(p)
    return m


def start_at_robot(msg, i: int):
    """``msg`` with its first point (t = 0) where the robot is at sample i, at its velocity: the
    controller steps to a first point due at once, so one elsewhere would be a jump."""
    q, v = q_at(i)
    msg.points[0].positions = [float(x) for x in q]
    msg.points[0].velocities = [float(x) for x in v]
    return msg


def _feasibility_output(w: BagWriter, msg, log_ns: int, state_i: int | None = None,
                        receipt: int = 0) -> None:
    """What the node publishes on ~/feasibility for ``msg`` (computed with the same core), the
    robot in joint_states sample ``state_i`` (received at T0 + state_i ms), the trajectory
    received at ``receipt`` (ns)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
    from dyn_node.errors import TrajectoryError
    from dyn_node.core.check.feasibility import (NO_CURRENT_STATE, FeasibilityOptions, Timing,
                                                 check_trajectory, current_state, rejected_statuses)
    from dyn_node.core.check.trajectory import validate_trajectory

    pts = msg.points
    times = [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts]
    try:
        traj = validate_trajectory(PANDA.joint_names, list(msg.joint_names), times,
                                   [p.positions for p in pts], [p.velocities for p in pts],
                                   [p.accelerations for p in pts])
        start = timing = None
        if state_i is not None:
            q, v = q_at(state_i)
            start = current_state((T0 + state_i * MS, q, v), receipt, 0.1)
            timing = Timing(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, receipt * 1e-9)
        statuses = check_trajectory(Dynamics(PANDA, DynamicsOptions(include_friction=True)), traj,
                                    FeasibilityOptions(), start=start, timing=timing,
                                    start_unknown=NO_CURRENT_STATE).statuses(PANDA.name)
    except TrajectoryError as exc:
        statuses = rejected_statuses(exc, PANDA.name, len(times), float(times[-1]) if all(
            np.isfinite(times)) else 0.0)
    arr = DiagnosticArray()
    arr.header.stamp = msg.header.stamp
    for s in statuses:
        arr.status.append(DiagnosticStatus(level=bytes([s.level]), name=s.name, message=s.message,
                                           hardware_id=s.hardware_id,
                                           values=[KeyValue(key=k, value=v) for k, v in s.key_values()]))
    w.write("/dyn_node/feasibility", arr, log_ns)


# --- tests -----------------------------------------------------------------------------------
def test_clean_bag_is_feasible_and_matches_the_monitor(tmp_path, capsys):
    bag = make_bag(tmp_path / "bag")
    assert main([str(bag), "--out", str(tmp_path / "out")]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("FEASIBLE") and err == ""  # no progress bar when not a terminal
    rec = validated(tmp_path / "out")
    assert rec["verdict"]["result"] == "feasible" and rec["verdict"]["exit_code"] == 0
    assert rec["inputs"]["message_counts"] == {"/joint_states": 1500}
    assert rec["inputs"]["time_span"]["duration_s"] == pytest.approx(1.499, abs=1e-12)
    assert rec["configuration"]["model"]["urdf_sha256"] == PANDA.urdf_hash
    assert rec["configuration"]["model"]["source"] == "bag:parameters"
    assert rec["configuration"]["parameters"]["robot_model"] == "panda"
    assert rec["outputs"]["monitor_counts"]["accepted"] == 1500
    assert rec["outputs"]["monitor_counts"]["ignored_joint_values"] == 3000  # locked fingers
    # the per-joint peak is what a direct Monitor replay gives (independent loop here)
    from dyn_node.core.live.monitor import Monitor
    from dyn_node.core.robot.settings import Settings

    mon = Monitor(PANDA, Settings())
    util = []
    for i in range(1500):
        q, v = q_at(i)
        sec, nsec = divmod(T0 + i * MS, 1_000_000_000)
        r = mon.process(PANDA.joint_names, q, v, None, sec + nsec * 1e-9, (T0 + i * MS) * 1e-9)
        util.append(r.utilisation)
    util = np.array(util)
    for j, pj in enumerate(rec["outputs"]["effort"]["per_joint"]):
        k = int(np.argmax(util[:, j]))
        assert pj["peak_utilisation"] == util[k, j]
        assert pj["peak_time_s"] == pytest.approx(k * 1e-3, abs=1e-9)
    assert rec["outputs"]["violations"] == [] and rec["input_quality"]["gaps"] == []
    assert rec["outputs"]["controller_states"]["states_seen"] == ["idle"]
    assert (tmp_path / "out" / "report.html").is_file()


def test_effort_violation_found_with_exact_times(tmp_path):
    bag = make_bag(tmp_path / "bag", effort_spike=(1000, 1100))
    res = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out"), report=False))
    assert res.exit_code == 1
    rec = validated(tmp_path / "out")
    v = [x for x in rec["outputs"]["violations"] if x["kind"] == "effort"]
    assert len(v) == 1
    v = v[0]
    assert v["joint"] == "panda_joint2" and v["messages"] == 100
    assert v["start_s"] == pytest.approx(1.0, abs=1e-9) and v["end_s"] == pytest.approx(1.099, abs=1e-9)
    assert v["peak_time_s"] == pytest.approx(1.099, abs=1e-9)
    assert v["peak_value"] == pytest.approx(90.0 + 99 * 0.1, rel=1e-12) and v["limit"] == 87.0
    assert v["peak_ratio"] == pytest.approx(99.9 / 87.0, rel=1e-12)
    # the per-joint peak says it came from the measured effort, and gives both torques then
    pj = {r["joint"]: r for r in rec["outputs"]["effort"]["per_joint"]}["panda_joint2"]
    assert pj["peak_source"] == "measured" and pj["peak_measured_effort"] == pytest.approx(99.9, rel=1e-12)
    assert pj["peak_utilisation"] == pytest.approx(99.9 / 87.0, rel=1e-12)
    assert abs(pj["peak_effort"]) < 87.0 and pj["unit"] == "N·m" and v["unit"] == "N·m"
    j1 = {r["joint"]: r for r in rec["outputs"]["effort"]["per_joint"]}["panda_joint1"]
    assert j1["peak_source"] == "model" and j1["peak_measured_effort"] is None  # NaN efforts elsewhere
    assert "control error" in rec["failure_labels"] and rec["verdict"]["result"] == "violations"
    assert rec["outputs"]["controller_states"]["states_seen"] == ["idle", "saturated"]


def test_a_gap_ends_a_violation_episode(tmp_path):
    """Over the limit before and after 200 ms without joint_states: two episodes, neither
    counting the gap as time over the limit."""
    bag = make_bag(tmp_path / "bag", effort_spike=(1000, 1500), drop=range(1100, 1300))
    run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out"), report=False))
    v = [x for x in validated(tmp_path / "out")["outputs"]["violations"] if x["kind"] == "effort"]
    assert [(x["messages"], round(x["start_s"], 6), round(x["end_s"], 6)) for x in v] == \
        [(100, 1.0, 1.099), (200, 1.3, 1.499)]
    assert v[0]["duration_s"] == pytest.approx(0.099, abs=1e-9)


def test_input_quality_gaps_stale_invalid_out_of_order(tmp_path):
    bag = make_bag(tmp_path / "bag", n=2500, drop=range(300, 400),
                   invalid={50: "nan", 60: "missing", 61: "missing"}, out_of_order=900)
    res = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out"), report=False))
    rec = validated(tmp_path / "out")
    iq = rec["input_quality"]
    assert [(g["start_s"], g["end_s"]) for g in iq["gaps"]] == [
        pytest.approx((0.299, 0.400), abs=1e-9)]
    assert iq["stale_periods"] == []  # 0.101 s < stale_timeout 0.5 s
    assert iq["invalid_messages"]["count"] == 3
    assert iq["invalid_messages"]["by_reason"] == {"non_finite": 1, "missing_joints": 2}
    assert [e["time_s"] for e in iq["invalid_messages"]["examples"]] == pytest.approx([0.05, 0.06, 0.061])
    # message 900's stamp is 5 ms older than 899's; 901 is newer than 900 again
    assert iq["out_of_order"]["count"] == 1
    assert iq["out_of_order"]["examples"][0]["time_s"] == pytest.approx(0.9)
    # bad inputs are findings (state error), not violations: nothing over a limit, nothing lost
    assert res.exit_code == 0 and rec["verdict"]["result"] == "feasible"
    assert rec["failure_labels"] == ["state error"]


def test_stale_period_reported(tmp_path):
    bag = make_bag(tmp_path / "bag", n=2000, drop=range(500, 1200))
    run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out"), report=False))
    rec = validated(tmp_path / "out")
    st = rec["input_quality"]["stale_periods"]
    assert len(st) == 1 and st[0]["start_s"] == pytest.approx(0.499) and st[0]["end_s"] == pytest.approx(1.2)
    cs = rec["outputs"]["controller_states"]
    assert [c["state"] for c in cs["replayed_transitions"]] == ["idle", "stale", "idle"]
    assert cs["replayed_transitions"][1]["time_s"] == pytest.approx(0.999, abs=1e-5)
    assert cs["replayed_time_in_state_s"]["stale"] == pytest.approx(0.201, abs=1e-5)
    assert "state error" in rec["failure_labels"]


def test_recheck_of_node_outputs_is_exactly_zero_and_a_perturbation_is_found(tmp_path):
    trajs = [(200, trajectory_msg(T0 + 200 * MS)), (400, trajectory_msg(T0 + 400 * MS, scale=0.05)),
             (600, trajectory_msg(T0 + 600 * MS, nan=True))]
    bag = make_bag(tmp_path / "bag", n=1000, outputs=True, trajectories=trajs)
    res = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out"), report=False))
    rec = validated(tmp_path / "out")
    rc = rec["outputs"]["recheck"]
    for topic in ("/dyn_node/gravity_torque", "/dyn_node/inverse_dynamics"):
        assert rc[topic]["matched"] == 1000 and rc[topic]["unmatched"] == 0
        assert rc[topic]["max_abs_difference"] == 0.0 and rc[topic]["identical"] is True
    assert rc["/dyn_node/feasibility"]["matched"] == 3
    assert rc["/dyn_node/feasibility"]["max_abs_difference"] == 0.0
    assert rc["/dyn_node/feasibility"]["identical"] is True
    lat = rec["outputs"]["latency"]["stamp_to_output_s"]
    assert lat["count"] == 1000 and lat["min"] == pytest.approx(2e-4) and lat["max"] == pytest.approx(2e-4)
    assert rec["outputs"]["latency"]["receipt_to_output_s"]["p50"] == pytest.approx(2e-4, rel=0.01)
    # trajectories: feasible, infeasible (20× too fast, k ≈ 20-ish), rejected
    t = rec["outputs"]["trajectories"]
    assert [x["feasible"] for x in t] == [True, False, False]
    assert [x["accepted"] for x in t] == [True, True, False]
    assert t[0]["time_scale"] <= 1.0 < t[1]["time_scale"]
    assert t[2]["error_code"] == "non_finite" and t[2]["failure_label"] == "planning error"
    assert t[0]["time_s"] == pytest.approx(0.2 + 500e-9, abs=1e-9)
    # the payload margin by its definition: feasible with that much more payload, not beyond it
    _assert_payload_margin(trajs[0][1], t[0]["payload_margin_kg"])
    assert res.exit_code == 1 and "planning error" in rec["failure_labels"]
    # each plan starts where the robot is (a first point elsewhere would be a jump) and runs from
    # its receipt (stamp + 500 ns, the execution model's start), so it is tracked from the next
    # sample (0.201 s), then the recorded motion, which does not follow the plans, leaves it
    # (0.294 s); the sample stamped 0.4 s is still the first plan's (the second arrives 500 ns
    # later), the second (50 ms long) is tracked from 0.401 s, left after 5 ms and has ended by
    # the sample at 0.451 s; the rejected third is never tracked
    cs = rec["outputs"]["controller_states"]
    assert [(c["state"], c["time_s"]) for c in cs["replayed_transitions"]] == [
        ("idle", 0.0), ("tracking", pytest.approx(0.201, abs=1e-9)), ("deviating", pytest.approx(0.294, abs=1e-9)),
        ("tracking", pytest.approx(0.401, abs=1e-9)), ("deviating", pytest.approx(0.406, abs=1e-9)),
        ("idle", pytest.approx(0.451, abs=1e-9))]

    bag2 = make_bag(tmp_path / "bag2", n=300, outputs=True, perturb=123)
    run_audit(AuditOptions(bag=str(bag2), out=str(tmp_path / "out2"), report=False))
    rc2 = validated(tmp_path / "out2")["outputs"]["recheck"]
    assert rc2["/dyn_node/gravity_torque"]["max_abs_difference"] == 0.0
    d = rc2["/dyn_node/inverse_dynamics"]
    assert d["identical"] is False and d["max_abs_difference"] == pytest.approx(1e-9, rel=1e-3)
    assert d["worst"]["time_s"] == pytest.approx(0.123 + 250e-6, abs=1e-9)

    # inputs the node never answered (no model yet) are "unanswered", not a discrepancy
    bag3 = make_bag(tmp_path / "bag3", n=300, outputs=True, outputs_from=40)
    run_audit(AuditOptions(bag=str(bag3), out=str(tmp_path / "out3"), report=False))
    rc3 = validated(tmp_path / "out3")["outputs"]["recheck"]
    for topic in ("/dyn_node/gravity_torque", "/dyn_node/inverse_dynamics"):
        assert (rc3[topic]["matched"], rc3[topic]["unmatched"], rc3[topic]["unanswered"]) == (260, 0, 40)
        assert rc3[topic]["identical"] is True


def _assert_payload_margin(msg, margin: float) -> None:
    from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
    from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
    from dyn_node.core.robot.model import Payload
    from dyn_node.core.check.trajectory import validate_trajectory

    pts = msg.points
    traj = validate_trajectory(PANDA.joint_names, list(msg.joint_names),
                               [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts],
                               [p.positions for p in pts], [p.velocities for p in pts],
                               [p.accelerations for p in pts])
    assert margin > 0.1

    def feasible(extra: float) -> bool:
        model = load_model(builtin="panda", payload=Payload(extra))
        dyn = Dynamics(model, DynamicsOptions(include_friction=True))
        return bool(check_trajectory(dyn, traj, FeasibilityOptions()).feasible)

    assert feasible(margin * 0.999) and not feasible(margin * 1.001)


def test_bag_recorded_elsewhere_needs_a_model(tmp_path, capsys):
    bag = make_bag(tmp_path / "bag", n=200, metadata=False)
    assert main([str(bag), "--out", str(tmp_path / "o1")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--robot-model" in err and "Traceback" not in err
    assert main([str(bag), "--robot-model", "panda", "--out", str(tmp_path / "o2")]) == 0
    rec = validated(tmp_path / "o2")
    assert rec["configuration"]["overrides"] == {"robot_model": "panda"}
    assert rec["configuration"]["parameters"] == {}
    # the /robot_description topic is enough (single .mcap file, no metadata.yaml)
    f = make_bag(tmp_path / "single", n=200, metadata=False, description_topic=True, single_file=True)
    assert main([str(f), "--out", str(tmp_path / "o3")]) == 0
    rec = validated(tmp_path / "o3")
    assert rec["configuration"]["model"]["source"] == "bag:topic"
    assert rec["configuration"]["model"]["joint_names"][0] == "panda_joint1"
    # --robot-description FILE overrides; --limits with a tighter effort limit finds violations
    urdf = tmp_path / "p.urdf"
    urdf.write_text(PANDA.urdf)
    lim = tmp_path / "lim.yaml"
    lim.write_text("joint_limits:\n  panda_joint2:\n    has_effort_limits: true\n    max_effort: 1.0\n")
    capsys.readouterr()
    code = main([str(bag), "--robot-description", str(urdf), "--limits", str(lim), "--out", str(tmp_path / "o4")])
    rec = validated(tmp_path / "o4")
    assert rec["configuration"]["limits"]["effort"][1] == 1.0
    assert code == 1 and any(v["joint"] == "panda_joint2" and v["kind"] == "effort"
                             for v in rec["outputs"]["violations"])


def test_live_deceleration_limit_is_audited_as_the_monitor_checks_it(tmp_path):
    """max_deceleration is checked on the live acceleration estimate where q̇·q̈̂ < 0, by the
    node's monitor and by the audit's replay alike. q_at's panda_joint5 (phase 1.2 rad) slows
    down for its first 118 ms (q̇ > 0, q̈ ≈ −2.8 rad/s²), then speeds up the other way."""
    from dyn_node.core.live.monitor import LIMITS, Monitor
    from dyn_node.core.robot.settings import Settings

    bag = make_bag(tmp_path / "bag", n=200)
    lim = tmp_path / "lim.yaml"
    lim.write_text("joint_limits:\n  panda_joint5:\n    has_deceleration_limits: true\n"
                   "    max_deceleration: 1.0\n")
    assert main([str(bag), "--limits", str(lim), "--out", str(tmp_path / "o"), "--no-report"]) == 1
    rec = validated(tmp_path / "o")
    assert rec["configuration"]["limits"]["deceleration"][4] == 1.0
    (v,) = [v for v in rec["outputs"]["violations"] if v["kind"] == "deceleration"]
    assert v["joint"] == "panda_joint5" and v["limit"] == 1.0
    # |q̈| = 0.3·π²·sin(πt + 1.2) grows to its maximum 0.3·π² as q̇ reaches 0 at t = 0.118 s
    assert v["peak_value"] == pytest.approx(0.3 * np.pi ** 2, rel=1e-3)
    assert v["peak_ratio"] == v["peak_value"] and v["peak_time_s"] == pytest.approx(0.118, abs=2e-3)
    assert v["duration_s"] == pytest.approx(0.118, abs=3e-3)
    # the node, on the same messages and stamps (s since the epoch, as the header carries them)
    mon = Monitor(PANDA.with_limits(lim), Settings())
    for i in range(200):
        q, qd = q_at(i)
        sec, nsec = divmod(T0 + i * MS, 1_000_000_000)
        mon.process(list(PANDA.joint_names), q, qd, [], sec + nsec * 1e-9, (T0 + i * MS) * 1e-9)
    st = {s.name: s for s in mon.statuses(2.0, "t")}[LIMITS]
    assert st.values["deceleration_violations"] == 1
    assert st.values["panda_joint5_deceleration_rad_s2"] == pytest.approx(-v["peak_value"], rel=1e-12)


@pytest.mark.parametrize("args, words", [
    (["/nonexistent/bag"], "does not exist"),
    (["{junk}"], "unreadable"),
    (["{bag}", "--robot-model", "nosuchrobot"], "model"),
    (["{bag}", "--limits", "/nonexistent.yaml"], "limits file"),
])
def test_unusable_input_exit_2_one_line(tmp_path, capsys, args, words):
    bag = make_bag(tmp_path / "bag", n=20)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x00" * 100)
    argv = [a.format(bag=bag, junk=junk) for a in args] + ["--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("dyn-audit: error:") and err.count("\n") == 1 and words in err


def test_damaged_bags_partial_audit_or_clear_error(tmp_path, capsys):
    from mcap.reader import make_reader

    bag = make_bag(tmp_path / "bag", n=1500, outputs=True)
    f = bag / "bag_0.mcap"
    full = f.read_bytes()
    # cut after the header: nothing usable (2); every later cut: a partial audit, which must not
    # exit 0 (3: partial, no violations in what was read)
    f.write_bytes(full[: int(len(full) * 0.0005)])
    assert main([str(bag), "--out", str(tmp_path / "o0"), "--no-report"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dyn-audit: error:") and err.count("\n") == 1 and "Traceback" not in err
    for frac in (0.2, 0.5, 0.8, 0.95):
        f.write_bytes(full[: int(len(full) * frac)])
        out = tmp_path / f"o{frac}"
        code = main([str(bag), "--out", str(out), "--no-report"])
        assert "Traceback" not in capsys.readouterr().err
        rec = validated(out)
        ur = rec["input_quality"]["unreadable_ranges"]
        assert 0 < rec["inputs"]["message_counts"]["/joint_states"] < 1500
        assert code == 3 and rec["verdict"]["exit_code"] == 3 and rec["verdict"]["result"] == "feasible"
        assert ur and rec["verdict"]["partial"] is True and "PARTIAL" in rec["verdict"]["summary"]
        # the lost range starts where the readable messages stop and ends at the bag's end
        n_read = rec["inputs"]["message_counts"]["/joint_states"]
        assert ur[-1]["start_s"] <= n_read * 1e-3 + 1e-9
        assert ur[-1]["end_s"] == pytest.approx(1.499 + 250e-6, abs=1e-9)
    # one flipped byte inside a chunk: exactly that chunk's time range is reported
    with open(tmp_path / "ref.mcap", "wb") as fh:
        fh.write(full)
    with open(tmp_path / "ref.mcap", "rb") as fh:
        chunk = list(make_reader(fh).get_summary().chunk_indexes)[2]
    data = bytearray(full)
    data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0x01
    f.write_bytes(bytes(data))
    code = main([str(bag), "--out", str(tmp_path / "oc"), "--no-report"])
    rec = validated(tmp_path / "oc")
    ur = rec["input_quality"]["unreadable_ranges"]
    t0 = rec["inputs"]["time_span"]["start_ns"]
    assert [(u["start_s"], u["end_s"]) for u in ur] == [
        pytest.approx(((chunk.message_start_time - t0) * 1e-9, (chunk.message_end_time - t0) * 1e-9),
                      abs=1e-12)]
    assert "damaged chunk" in ur[0]["reason"] and rec["verdict"]["partial"] is True
    assert code == 3 and "Traceback" not in capsys.readouterr().err


def test_series_bins_stay_bounded_and_keep_extremes():
    rng = np.random.default_rng(1)
    n = 50_000
    tau = rng.normal(size=(n, 2))
    util = np.abs(tau) / 3.0
    s = SeriesBins(2, 0, width_ns=MS)
    for i in range(n):
        s.add(i * MS, tau[i], util[i], np.array([3.0, 3.0]))
    assert s.n <= MAX_BINS and s.width == MS * 64
    per = s.width // MS
    for b in (0, 17, s.n - 1):
        sl = slice(b * per, min((b + 1) * per, n))
        np.testing.assert_array_equal(s.tau_max[b], tau[sl].max(axis=0))
        np.testing.assert_array_equal(s.tau_min[b], tau[sl].min(axis=0))
        np.testing.assert_array_equal(s.util[b], util[sl].max(axis=0))
    assert s.count[: s.n].sum() == n
    # the batched path used by the audit gives the same bins (including a batch that goes back)
    b = SeriesBins(2, 0, width_ns=MS)
    t = np.arange(n, dtype=np.int64) * MS
    t[30_000:30_010] = t[30_000:30_010][::-1]
    s2 = SeriesBins(2, 0, width_ns=MS)
    meas = np.where(rng.random((n, 2)) < 0.5, np.nan, tau)
    for i in range(n):
        s2.add(int(t[i]), tau[i], util[i], np.array([3.0, 3.0]), meas[i])
    for k in range(0, n, 1024):
        sl = slice(k, k + 1024)
        b.add_batch(t[sl], tau[sl], util[sl], np.full((len(t[sl]), 2), 3.0), meas[sl])
    for name in ("tau_min", "tau_max", "util", "limit", "meas_min", "meas_max", "count"):
        np.testing.assert_array_equal(getattr(b, name), getattr(s2, name))
    assert (b.n, b.width) == (s2.n, s2.width)
    # the measured effort keeps its sign (the report plots it beside the signed model torque)
    per = s2.width // MS
    for k in (0, 17):
        sl = slice(k * per, (k + 1) * per)
        np.testing.assert_array_equal(s2.meas_min[k], np.nanmin(meas[sl], axis=0))
        np.testing.assert_array_equal(s2.meas_max[k], np.nanmax(meas[sl], axis=0))
        assert (s2.meas_min[k] < 0).all() and (s2.meas_max[k] > 0).all()


@pytest.mark.timeout(60)
def test_cli_module_runs_and_reports_progress_only_on_a_tty(tmp_path):
    import os

    bag = make_bag(tmp_path / "bag", n=100)
    cmd = [sys.executable, "-m", "dyn_node.audit.bag_audit", str(bag), "--out", str(tmp_path / "o"), "--no-report"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and p.stderr == "" and "evidence:" in p.stdout
    validated(tmp_path / "o")
    # stderr on a terminal: a \r-updated progress line ending at 100 %
    master, slave = os.openpty()
    try:
        p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=slave, timeout=60)
        os.close(slave)
        chunks = []
        while True:
            try:
                b = os.read(master, 4096)
            except OSError:
                break
            if not b:
                break
            chunks.append(b)
    finally:
        os.close(master)
    err = b"".join(chunks).decode()
    assert p.returncode == 0 and err.startswith("\rdyn-audit [") and "100.0%" in err
    assert "100 msgs" in err and "Traceback" not in err


def record_node_run(ros_context, tmp_path: Path, n: int, *, trajectories_at: Sequence[int] = (150,),
                    at: dict | None = None, params: Sequence = ()) -> str:
    """A real DynNode recording its inputs and outputs (record.enabled): n joint_states at
    ~300 Hz, a trajectory at each of ``trajectories_at``; ``at[i](node)`` runs before input i;
    ``params``: more parameter overrides. Returns the bag path once every output is recorded."""
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory

    from conftest import Stepper
    from dyn_node.ros.node import DynNode

    node = DynNode(context=ros_context, parameter_overrides=[
        Parameter("robot_model", value="panda"), Parameter("record.enabled", value=True),
        Parameter("record.directory", value=str(tmp_path / "bags")), *params])
    bridge = node.recording
    pub_node = Node("audit_test_publisher", context=ros_context)
    js_pub = pub_node.create_publisher(JointState, "joint_states", 1000)
    traj_pub = pub_node.create_publisher(JointTrajectory, "joint_trajectory", 10)
    steps = Stepper(ros_context, (node, pub_node))
    spin_until = steps.until
    rec_topics = lambda: bridge.recorder.stats().topics if bridge.recorder else {}  # noqa: E731
    try:
        # the node records what it takes and publishes itself: no extra subscriptions to wait for
        assert spin_until(lambda: js_pub.get_subscription_count() >= 1
                          and traj_pub.get_subscription_count() >= 1, 30.0)
        names = list(PANDA.joint_names) + ["panda_finger_joint1", "panda_finger_joint2"]
        for i in range(n):
            if at and i in at:
                at[i](node)
            q, v = q_at(i)
            js_pub.publish(joint_state(names, list(q) + [0.01, 0.01], list(v) + [0.0, 0.0], [],
                                       stamp_ns=T0 + i * 5 * MS))
            if i in trajectories_at:
                traj_pub.publish(start_at_robot(trajectory_msg(T0 + i * 5 * MS), i))
            spin_until(lambda: False, 0.002)  # ~ 300 Hz, the node keeps up without drops

        def done():
            t = rec_topics()
            return all(k in t and t[k].received >= n for k in
                       ("/joint_states", "/dyn_node/gravity_torque", "/dyn_node/inverse_dynamics")) \
                and all(k in t and t[k].received >= len(trajectories_at)
                        for k in ("/dyn_node/feasibility", "/dyn_node/trajectory_effort"))
        assert spin_until(done, 30.0), {k: v.received for k, v in rec_topics().items()}
        ok, path = bridge.stop()
        assert ok, path
    finally:
        bridge.close()
        steps.close()
    return path


@pytest.mark.timeout(120)
def test_recorded_node_run_audits_with_zero_difference(ros_context, tmp_path):
    """The audit of a real node's recording recomputes every output with exactly 0.0 difference."""
    n = 300
    path = record_node_run(ros_context, tmp_path, n)
    res = run_audit(AuditOptions(bag=path, out=str(tmp_path / "out"), report=False))
    rec = validated(tmp_path / "out")
    assert rec["configuration"]["model"]["urdf_sha256"] == PANDA.urdf_hash
    assert rec["configuration"]["parameters"]["robot_model"] == "panda"
    assert rec["configuration"]["changes"] == []
    rc = rec["outputs"]["recheck"]
    for topic in ("/dyn_node/gravity_torque", "/dyn_node/inverse_dynamics"):
        assert rc[topic]["matched"] == n, rc[topic]
        assert rc[topic]["max_abs_difference"] == 0.0 and rc[topic]["identical"] is True
    for topic in ("/dyn_node/feasibility", "/dyn_node/trajectory_effort"):
        assert rc[topic]["matched"] == 1, rc[topic]
        assert rc[topic]["max_abs_difference"] == 0.0 and rc[topic]["identical"] is True, rc[topic]
    assert rec["outputs"]["latency"]["stamp_to_output_s"]["count"] == n
    assert res.exit_code == 0


@pytest.mark.timeout(120)
def test_a_parameter_change_mid_recording_is_replayed_from_when_it_took_effect(ros_context, tmp_path):
    """payload.mass set on the running node halfway through (as `ros2 param set` does): the
    recorder writes the new configuration with the log time it took effect, and the audit
    replays each configuration from that moment: every output identical, before and after."""
    from mcap.reader import make_reader
    from rclpy.parameter import Parameter

    n = 300
    path = record_node_run(ros_context, tmp_path, n, trajectories_at=(100, 200), at={
        150: lambda node: node.set_parameters([Parameter("payload.mass", value=3.0)])})
    # every file's dyn_node records: the start configuration, then the change with its time
    metas = []
    for f in sorted(Path(path).glob("*.mcap")):
        with open(f, "rb") as fh:
            metas += [r.metadata for r in make_reader(fh).iter_metadata() if r.name == "dyn_node"]
    params = [yaml.safe_load(m["parameters"])["/dyn_node"]["ros__parameters"]["payload"]["mass"]
              for m in metas]
    assert params[0] == 0.0 and params[-1] == 3.0
    since = [int(m["effective_log_time_ns"]) for m in metas]
    assert since == sorted(since) and since[-1] > since[0]
    res = run_audit(AuditOptions(bag=path, out=str(tmp_path / "out"), report=False))
    rec = validated(tmp_path / "out")
    ch = rec["configuration"]["changes"]
    assert [(c["parameters"], c["payload_mass_kg"], c["effective_log_time_ns"]) for c in ch] == [
        ({"payload.mass": 3.0}, 3.0, since[-1])]
    rc = rec["outputs"]["recheck"]
    for topic in ("/dyn_node/gravity_torque", "/dyn_node/inverse_dynamics"):
        assert (rc[topic]["matched"], rc[topic]["unmatched"]) == (n, 0), rc[topic]
        assert rc[topic]["max_abs_difference"] == 0.0 and rc[topic]["identical"] is True, rc[topic]
    for topic in ("/dyn_node/feasibility", "/dyn_node/trajectory_effort"):
        assert rc[topic]["matched"] == 2 and rc[topic]["identical"] is True, rc[topic]
    # the change mattered: the recorded gravity torque of the last input is not the one the
    # first configuration gives (so an audit that kept it could not be identical)
    from dyn_node.core.robot.dynamics import Dynamics

    last = None
    for m in BagReader(path).messages():
        if m.topic == "/dyn_node/gravity_torque":
            last = decode_joint_state(m.data)
    g0 = Dynamics(PANDA).gravity(last.position)
    assert float(np.max(np.abs(last.effort - g0))) > 1.0
    assert res.exit_code == 0


def test_bag_written_by_the_rosbags_library(tmp_path, capsys):
    """A rosbag2 MCAP bag from an independent writer (rosbags), no dyn_node metadata at all."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    JS = ts.types["sensor_msgs/msg/JointState"]
    H, T = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    bag = tmp_path / "rosbags_bag"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/robot1/joint_states", JS.__msgtype__, typestore=ts)
        for i in range(400):
            t = T0 + i * MS
            q, v = q_at(i)
            m = JS(header=H(stamp=T(sec=t // 10**9, nanosec=t % 10**9), frame_id=""),
                   name=list(PANDA.joint_names), position=q, velocity=v, effort=np.array([], float))
            w.write(c, t, ts.serialize_cdr(m, JS.__msgtype__))
    assert main([str(bag), "--out", str(tmp_path / "o")]) == 2
    assert "--robot-model" in capsys.readouterr().err
    assert main([str(bag), "--robot-model", "panda", "--out", str(tmp_path / "o"), "--no-report"]) == 0
    rec = validated(tmp_path / "o")
    assert rec["outputs"]["monitor_counts"]["accepted"] == 400
    assert rec["inputs"]["topics"] == [{"name": "/robot1/joint_states", "type": "sensor_msgs/msg/JointState",
                                        "count": 400, "role": "joint_states"}]
    assert rec["input_quality"]["unreadable_ranges"] == []


def test_batched_live_episodes_equal_a_message_by_message_update():
    """LiveStats finds violation episodes run by run over a batch; the oracle is Episodes.update
    called per message, per joint, per kind (same episodes, peaks, close order and total)."""
    from dyn_node.audit.replay.stats import Episodes, LiveStats

    rng = np.random.default_rng(5)
    nv, n = 3, 5000
    lo, hi, vel = np.array([-1.0, -2.0, -np.inf]), np.array([1.0, 2.0, np.inf]), np.array([1.0, 2.0, 3.0])
    # piecewise-constant regimes so episodes span batches, start at a batch's first row, etc.
    regime = np.repeat(rng.random((n // 50 + 1, nv)) < 0.4, 50, axis=0)[:n]
    Q = np.where(regime, rng.uniform(-2.5, 2.5, (n, nv)), rng.uniform(-0.5, 0.5, (n, nv)))
    V = rng.normal(0, 1.5, (n, nv))
    U = np.where(rng.random((n, nv)) < 0.3, rng.uniform(0.5, 1.5, (n, nv)), 0.2)
    U[rng.random((n, nv)) < 0.01] = np.nan
    L = np.full((n, nv), 10.0)
    T = np.arange(n, dtype=np.int64) * MS
    A = rng.normal(0, 4.0, (n, nv))   # acceleration estimates: decelerating where V·A < 0
    dec = np.array([5.0, np.inf, 3.0])
    live = LiveStats(nv, lo, hi, vel, dec)
    ref = Episodes()
    for r in range(n):
        live.add(int(T[r]), U[r] * 10.0, U[r], L[r], Q[r], V[r], None, A[r])
        for j in range(nv):
            u, lim, q, av = float(U[r, j]), float(L[r, j]), float(Q[r, j]), abs(float(V[r, j]))
            ref.update(j, "effort", u > 1.0, int(T[r]), u * lim, lim, u)
            below = q < lo[j]
            ref.update(j, "position", bool(q < lo[j] or q > hi[j]), int(T[r]), q,
                       float(lo[j] if below else hi[j]), float(lo[j] - q if below else q - hi[j]))
            ref.update(j, "velocity", av > vel[j], int(T[r]), av, float(vel[j]), av / float(vel[j]))
            d = abs(float(A[r, j])) if float(V[r, j]) * float(A[r, j]) < 0 else 0.0
            ref.update(j, "deceleration", d > dec[j], int(T[r]), d, float(dec[j]), d - float(dec[j]))
        if r == 2500:
            live.flush()  # an early, partial batch
    live.flush()
    assert list(live.episodes.open) == list(ref.open)
    assert live.episodes.open == ref.open
    live.finish()
    ref.finish()
    assert live.episodes.total == ref.total > 100
    assert live.episodes.closed == ref.closed
    assert {e["kind"] for e in ref.closed} == {"effort", "position", "velocity", "deceleration"}


@pytest.mark.parametrize("kind", ["measured", "quality", "trajectories", "outputs_in_bursts"])
def test_batched_replay_gives_exactly_the_per_message_evidence(tmp_path, monkeypatch, kind):
    """Runs of regular joint_states are replayed in batches (Monitor.process_batch); the evidence
    must be exactly what message-by-message replay gives (MIN_BATCH raised past every run), with
    gaps, invalid and out-of-order messages, trajectories being tracked and outputs re-checked."""
    import dyn_node.audit.replay.inputs as audit_mod  # the batch threshold lives with the replay
    from dyn_node.core.live.monitor import Monitor

    trajs = [(300, trajectory_msg(T0 + 300 * MS)), (1200, trajectory_msg(T0 + 1200 * MS, scale=0.3))]
    bag = make_bag(tmp_path / "bag", **{
        "measured": dict(n=2500, measured=True, effort_spike=(700, 760)),
        "quality": dict(n=2500, measured=True, drop=range(900, 1500), out_of_order=2000,
                        invalid={300: "nan", 301: "missing", 1800: "nan"}),
        "trajectories": dict(n=2500, trajectories=trajs),
        "outputs_in_bursts": dict(n=800, outputs=True, output_burst=100, trajectories=trajs[:1]),
    }[kind])
    used = []
    batch = Monitor.process_batch

    def spy(self, *args):
        out = batch(self, *args)
        used.append(out is not None)
        return out

    monkeypatch.setattr(Monitor, "process_batch", spy)
    fast = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "fast"), report=False)).record
    assert any(used)
    monkeypatch.setattr(audit_mod, "MIN_BATCH", 10 ** 9)
    used.clear()
    slow = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "slow"), report=False)).record
    assert not used
    validated(tmp_path / "fast")
    for rec in (fast, slow):
        rec.pop("timestamps")
    assert json.dumps(fast, sort_keys=True) == json.dumps(slow, sort_keys=True)
    if kind == "outputs_in_bursts":
        for topic in ("/dyn_node/gravity_torque", "/dyn_node/inverse_dynamics"):
            assert fast["outputs"]["recheck"][topic]["identical"] is True
            assert fast["outputs"]["recheck"][topic]["matched"] == 800


# --- issue 16: the audit -------------------------------------------------------------------------
def huge_trajectory_msg(stamp_ns: int):
    """Finite but so large that the interpolated torques overflow: the check raises non_finite
    (TrajectoryError) after validation, and the node publishes a rejected verdict."""
    m = trajectory_msg(stamp_ns)
    m.points[1].positions = [1e150] * 7
    return m


def test_a_trajectory_the_check_rejects_is_a_finding_and_the_rest_is_audited(tmp_path, capsys):
    trajs = [(200, huge_trajectory_msg(T0 + 200 * MS)), (400, trajectory_msg(T0 + 400 * MS))]
    bag = make_bag(tmp_path / "bag", n=600, outputs=True, trajectories=trajs)
    code = main([str(bag), "--out", str(tmp_path / "o"), "--no-report"])
    assert "Traceback" not in capsys.readouterr().err
    rec = validated(tmp_path / "o")
    t = rec["outputs"]["trajectories"]
    assert [(x["accepted"], x["feasible"], x["error_code"]) for x in t] == [
        (False, False, "non_finite"), (True, True, None)]
    assert t[0]["message"].startswith("rejected: the interpolated motion or its torque is not finite")
    assert t[0]["failure_label"] == "planning error" and t[0]["n_points"] == 3
    assert t[0]["duration_s"] == 1.0
    # the rest of the bag was audited, and the node's rejected verdict is reproduced exactly
    assert rec["outputs"]["monitor_counts"]["accepted"] == 600
    fe = rec["outputs"]["recheck"]["/dyn_node/feasibility"]
    assert (fe["matched"], fe["unmatched"], fe["identical"]) == (2, 0, True)
    assert code == 1 and rec["verdict"]["result"] == "violations"
    assert rec["verdict"]["summary"].startswith("1 of 2 executed trajectories infeasible or rejected")


@pytest.mark.parametrize("burst", [1, 40])  # 1: message by message; 40: runs replayed as batches
def test_outputs_of_zero_stamped_inputs_match_by_the_stamp_the_node_gave_them(tmp_path, burst):
    """The node answers a zero-stamped joint_states with the receipt time as the outputs' stamp
    (ros_convert.s_to_stamp, the node's own conversion, is the oracle here)."""
    from dyn_node.core.live.monitor import Monitor
    from dyn_node.ros.convert import s_to_stamp
    from dyn_node.core.robot.settings import settings_from_mapping

    w = BagWriter(tmp_path / "bag", metadata={"robot_description": PANDA.urdf, "parameters": PARAMS,
                                              "version": "0.1.0"})
    mon = Monitor(PANDA, settings_from_mapping({"robot_model": "panda"}))
    names = list(PANDA.joint_names) + ["panda_finger_joint1", "panda_finger_joint2"]
    pending, n, zeros = [], 200, 0
    for i in range(n):
        q, v = q_at(i)
        # receipt times with sub-µs parts, so a float round trip that loses them would show
        log_ns = T0 + i * MS + 123_457
        stamp = 0 if i % 10 == 3 else T0 + i * MS
        zeros += stamp == 0
        msg = joint_state(names, list(q) + [0.01, 0.01], list(v) + [0.0, 0.0], [], stamp_ns=stamp)
        w.write("/joint_states", msg, log_ns)
        st = msg.header.stamp  # the node's stamp arithmetic (node._handle_joint_state)
        r = mon.process(msg.name, msg.position, msg.velocity, msg.effort, st.sec + st.nanosec * 1e-9,
                        log_ns * 1e-9)
        assert r.accepted and r.zero_stamp == (stamp == 0)
        st = s_to_stamp(r.stamp_s) if r.zero_stamp else msg.header.stamp
        out_ns = st.sec * 1_000_000_000 + st.nanosec
        assert out_ns != 0
        for topic, eff, dt in (("/dyn_node/gravity_torque", r.gravity, 200_000),
                               ("/dyn_node/inverse_dynamics", r.tau, 250_000)):
            pending.append((topic, joint_state(PANDA.joint_names, r.q, r.v, eff, stamp_ns=out_ns),
                            log_ns + dt))
        if len(pending) >= 2 * burst:
            for args in pending:
                w.write(*args)
            pending.clear()
    for args in pending:
        w.write(*args)
    bag = w.close()
    assert zeros == 20
    run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "o"), report=False))
    rec = validated(tmp_path / "o")
    assert rec["input_quality"]["zero_stamp_messages"] == 20
    for topic in ("/dyn_node/gravity_torque", "/dyn_node/inverse_dynamics"):
        d = rec["outputs"]["recheck"][topic]
        assert (d["matched"], d["unmatched"], d["unanswered"]) == (n, 0, 0), d
        assert d["identical"] is True and d["max_abs_difference"] == 0.0


def test_exit_code_mapping_unusable_violations_partial_ok():
    from dyn_node.audit.exit_codes import EXIT_OK, EXIT_PARTIAL, EXIT_UNUSABLE, EXIT_VIOLATIONS, exit_code

    assert (EXIT_OK, EXIT_VIOLATIONS, EXIT_UNUSABLE, EXIT_PARTIAL) == (0, 1, 2, 3)
    assert exit_code(violations=False, partial=False) == 0
    assert exit_code(violations=False, partial=True) == 3
    assert exit_code(violations=True, partial=True) == 1   # violations win; evidence says partial
    assert exit_code(violations=True, partial=False) == 1
    assert exit_code(violations=True, partial=True, unusable=True) == 2
    assert schema()["properties"]["verdict"]["properties"]["exit_code"]["enum"] == [0, 1, 2, 3]


def test_a_partial_audit_with_violations_exits_1_and_still_says_partial(tmp_path):
    from mcap.reader import make_reader

    bag = make_bag(tmp_path / "bag", n=1500, effort_spike=(100, 120), measured=True)
    f = bag / "bag_0.mcap"
    full = f.read_bytes()
    with open(f, "rb") as fh:
        chunk = list(make_reader(fh).get_summary().chunk_indexes)[-2]  # far from the spike
    data = bytearray(full)
    data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0x01
    f.write_bytes(bytes(data))
    assert main([str(bag), "--out", str(tmp_path / "o"), "--no-report"]) == 1
    rec = validated(tmp_path / "o")
    assert rec["verdict"]["exit_code"] == 1 and rec["verdict"]["partial"] is True
    assert rec["outputs"]["violation_episodes_total"] >= 1
    assert len(rec["input_quality"]["unreadable_ranges"]) == 1


_REAL_KEY = re.compile(r"(_s|_ns|_kg|_nm|_m_s2|ratio|difference|utilisation|time_scale|^p\d\d"
                       r"|^min|^max|^mean|^limit|^peak_value)$")


def _numeric_paths(node, path=()):
    """Paths of every real-valued field of a record: floats, "inf"/"-inf", and nulls under a
    key that names a real quantity (a null trajectory time, difference, measured torque...)."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _numeric_paths(v, path + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _numeric_paths(v, path + (i,))
    elif isinstance(node, float) or node in ("inf", "-inf") or (
            node is None and isinstance(path[-1], str) and _REAL_KEY.search(path[-1])):
        yield path


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")])
def test_every_number_a_record_holds_validates_when_not_finite(tmp_path, value):
    """A record with trajectories, violations, a re-check, latencies, gaps and unreadable ranges:
    each real-valued field in turn set to ±inf / NaN (jsonable writes "inf", "-inf", null, as
    the README says), and the whole record validates against the shipped schema."""
    import copy

    from dyn_node.audit.evidence import jsonable, validate

    trajs = [(200, trajectory_msg(T0 + 200 * MS)), (400, trajectory_msg(T0 + 400 * MS, scale=0.05)),
             (600, trajectory_msg(T0 + 600 * MS, nan=True))]
    bag = make_bag(tmp_path / "bag", n=1200, outputs=True, trajectories=trajs, drop=range(700, 800),
                   effort_spike=(900, 920), measured=True, invalid={50: "nan"}, out_of_order=1000)
    f = bag / "bag_0.mcap"
    f.write_bytes(f.read_bytes()[: int(f.stat().st_size * 0.9)])
    run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "o"), report=False))
    rec = validated(tmp_path / "o")
    paths = [p for p in _numeric_paths(rec)
             if p[0] != "metric_definitions" and p[:2] != ("configuration", "limits")]
    assert len(paths) > 200
    sections = {p[0] for p in paths}
    assert {"outputs", "input_quality", "inputs", "configuration", "timestamps"} <= sections
    if value < 0:  # durations are never negative: the schema keeps their minimum 0
        paths = [p for p in paths if p[-1] != "duration_s"]
    r = copy.deepcopy(rec)
    for p in paths:
        node = r
        for k in p[:-1]:
            node = node[k]
        node[p[-1]] = value
    r = jsonable(r)
    # every error, not just the first: each field is judged on its own
    errors = ["/".join(map(str, e.absolute_path)) + ": " + e.message
              for e in jsonschema.Draft202012Validator(schema()).iter_errors(r)]
    assert errors == []
    validate(r)


def test_an_override_that_differs_from_the_recorded_model_is_not_comparable(tmp_path, capsys):
    """The documented override on a bag recorded with robot_model:=panda: the URDF file (fingers
    not locked) is another model, so the re-check says so instead of an infinite difference."""
    from dyn_node.core.robot.model import builtin_urdf

    bag = make_bag(tmp_path / "bag", n=400, outputs=True,
                   trajectories=[(100, trajectory_msg(T0 + 100 * MS))])
    urdf = tmp_path / "panda.urdf"
    urdf.write_text(builtin_urdf("panda"))
    code = main([str(bag), "--robot-description", str(urdf), "--out", str(tmp_path / "o"), "--no-report"])
    out = capsys.readouterr()
    assert "Traceback" not in out.err and "evidence record invalid" not in out.err
    rec = validated(tmp_path / "o")
    assert len(rec["configuration"]["model"]["joint_names"]) == 9
    rc = rec["outputs"]["recheck"]
    assert set(rc) == {"/dyn_node/gravity_torque", "/dyn_node/inverse_dynamics", "/dyn_node/feasibility"}
    for d in rc.values():
        assert d["comparable"] is False and d["identical"] is False and d["max_abs_difference"] is None
        assert d["not_comparable"] == (
            "not comparable: joints: 7 recorded, 9 here (here only: panda_finger_joint1, "
            "panda_finger_joint2); locked joints: recorded panda_finger_joint1, panda_finger_joint2; "
            "here none")
    assert "evaluation error" not in rec["failure_labels"]
    assert "re-check not comparable: joints: 7 recorded, 9 here" in " ".join(rec["verdict"]["findings"])
    # under that model the 7-joint trajectory lacks the finger joints: rejected, as the node would
    assert rec["outputs"]["trajectories"][0]["error_code"] == "missing_joints" and code == 1
    # a tighter --limits file is another configuration too; the same model by name is not
    lim = tmp_path / "lim.yaml"
    lim.write_text("joint_limits:\n  panda_joint1:\n    has_velocity_limits: true\n    max_velocity: 2.0\n")
    main([str(bag), "--limits", str(lim), "--out", str(tmp_path / "o2"), "--no-report"])
    rc2 = validated(tmp_path / "o2")["outputs"]["recheck"]
    assert rc2["/dyn_node/gravity_torque"]["not_comparable"] == "not comparable: limits: velocity"
    assert main([str(bag), "--robot-model", "panda", "--out", str(tmp_path / "o3"), "--no-report"]) == 0
    rc3 = validated(tmp_path / "o3")["outputs"]["recheck"]
    for d in rc3.values():
        assert "comparable" not in d and d["identical"] is True and d["max_abs_difference"] == 0.0


def test_undecodable_joint_states_replayed_as_the_node_counts_them(tmp_path):
    """Bytes that are no JointState: the audit's monitor counts them received and invalid
    (received = accepted + invalid, as the node's joint_states status) and its controller
    tracker sees the fault the node reported."""
    w = BagWriter(tmp_path / "bag", metadata={"robot_description": PANDA.urdf, "parameters": PARAMS,
                                               "version": "0.1.0"})
    names = list(PANDA.joint_names)
    for i in range(3):
        q, v = q_at(i)
        w.write("/joint_states", joint_state(names, list(q), list(v), stamp_ns=T0 + i * MS), T0 + i * MS)
    cid, _ = w.channels["/joint_states"]
    w.w.add_message(cid, log_time=T0 + 3 * MS, data=b"\x00\x01\x00\x00" + b"\xff" * 12,
                    publish_time=T0 + 3 * MS, sequence=3)
    q, v = q_at(4)
    w.write("/joint_states", joint_state(names, list(q), list(v), stamp_ns=T0 + 4 * MS), T0 + 4 * MS)
    bag = w.close()
    run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out"), report=False))
    rec = validated(tmp_path / "out")
    counts = rec["outputs"]["monitor_counts"]
    assert (counts["received"], counts["accepted"], counts["invalid"]) == (5, 4, 1)
    assert rec["input_quality"]["invalid_messages"]["count"] == 1
    assert rec["input_quality"]["invalid_messages"]["by_reason"] == {"undecodable": 1}
    assert "fault" in rec["outputs"]["controller_states"]["states_seen"]


def test_a_configuration_change_without_its_time_is_not_replayed_and_says_so(tmp_path):
    """Bags from recorders before effective_log_time_ns: a second, different dyn_node record
    cannot be placed in time, so the re-check is not comparable (not a false difference)."""
    bag = make_bag(tmp_path / "bag", n=200, outputs=True, later_metadata={
        "robot_description": PANDA.urdf, "version": "0.1.0",
        "parameters": PARAMS + "    payload:\n      mass: 3.0\n"})
    run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "o"), report=False))
    rec = validated(tmp_path / "o")
    assert rec["configuration"]["changes"] == []
    d = rec["outputs"]["recheck"]["/dyn_node/gravity_torque"]
    assert d["not_comparable"] == ("not comparable: 1 configuration change(s) recorded without the "
                                   "time they took effect (older recorder): not replayed")
    assert d["matched"] == 200 and d["max_abs_difference"] is None
    assert "evaluation error" not in rec["failure_labels"]


def test_per_joint_effort_entries_carry_each_joints_own_unit(tmp_path):
    """A model with prismatic joints (j2, j5): their per-joint effort entries and violations
    are in N (as the feasibility verdicts and live statuses say), the revolute ones in N·m; the
    keys are the same for every joint, so a reader never parses a unit out of a key name."""
    from robots import BRANCHED_URDF
    from sensor_msgs.msg import JointState  # noqa: F401 - joint_state builds one

    model = load_model(urdf=BRANCHED_URDF)
    w = BagWriter(tmp_path / "bag", metadata={"robot_description": BRANCHED_URDF,
                                              "parameters": "", "version": "0.1.0"})
    names = list(model.joint_names)
    for i in range(200):
        q = [0.1 * np.sin(1e-2 * i + k) for k in range(len(names))]
        v = [0.1 * np.cos(1e-2 * i + k) for k in range(len(names))]
        w.write("/joint_states", joint_state(names, q, v, [1e3] * len(names), stamp_ns=T0 + i * MS),
                T0 + i * MS)
    bag = w.close()
    res = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out"), report=False))
    rec = validated(tmp_path / "out")
    units = {r["joint"]: r["unit"] for r in rec["outputs"]["effort"]["per_joint"]}
    assert units == {"j1": "N·m", "j2": "N", "j3": "N·m", "j4": "N·m", "j5": "N", "j6": "N·m"}
    assert all(set(r) == {"joint", "unit", "peak_utilisation", "peak_time_s", "peak_effort",
                          "peak_measured_effort", "peak_source", "effort_limit"}
               for r in rec["outputs"]["effort"]["per_joint"])
    effort = {v["joint"]: v["unit"] for v in rec["outputs"]["violations"] if v["kind"] == "effort"}
    assert res.exit_code == 1 and effort == units  # 1000 N(·m) measured: over every limit
