"""dyn-audit: replay through the node's core, evidence record, exit codes, re-check, damaged bags.

Bags are written with mcap (test_bag_reader.BagWriter) from rclpy messages. "Node outputs" are
generated here with the same Monitor / check_trajectory the node uses, so the re-check must find
exactly 0.0 difference; a perturbed output must be found. Every evidence.json is validated
against the shipped schema.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jsonschema
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_bag_reader import T0, BagWriter, joint_state  # noqa: E402

from dyn_node.audit import AuditOptions, SeriesBins, main, run_audit, MAX_BINS  # noqa: E402
from dyn_node.evidence import schema  # noqa: E402
from dyn_node.model import load_model  # noqa: E402

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
             output_burst: int = 1, outputs_from: int = 0) -> Path:
    """A Panda bag: 1 kHz joint_states (+ optional node outputs made with the node's Monitor).

    ``measured``: finite efforts on the model joints (else NaN: not measured); ``output_burst``:
    the outputs are written after every that many inputs (as a recorder that fell behind);
    ``outputs_from``: no outputs for the inputs before that one (as a node without a model yet)."""
    from dyn_node.monitor import Monitor
    from dyn_node.settings import settings_from_mapping
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
            w.write("/joint_trajectory", traj_at[i], T0 + i * MS + 500)
            if outputs:
                _feasibility_output(w, traj_at[i], T0 + i * MS + 900)
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


def _feasibility_output(w: BagWriter, msg, log_ns: int) -> None:
    """What the node publishes on ~/feasibility for ``msg`` (computed with the same core)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from dyn_node.dynamics import Dynamics, DynamicsOptions
    from dyn_node.errors import TrajectoryError
    from dyn_node.feasibility import FeasibilityOptions, check_trajectory, rejected_statuses
    from dyn_node.trajectory import validate_trajectory

    pts = msg.points
    times = [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts]
    try:
        traj = validate_trajectory(PANDA.joint_names, list(msg.joint_names), times,
                                   [p.positions for p in pts], [p.velocities for p in pts],
                                   [p.accelerations for p in pts])
        statuses = check_trajectory(Dynamics(PANDA, DynamicsOptions(include_friction=True)), traj,
                                    FeasibilityOptions()).statuses(PANDA.name)
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
    from dyn_node.monitor import Monitor
    from dyn_node.settings import Settings

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
    assert pj["peak_source"] == "measured" and pj["peak_measured_nm"] == pytest.approx(99.9, rel=1e-12)
    assert pj["peak_utilisation"] == pytest.approx(99.9 / 87.0, rel=1e-12)
    assert abs(pj["peak_torque_nm"]) < 87.0
    j1 = {r["joint"]: r for r in rec["outputs"]["effort"]["per_joint"]}["panda_joint1"]
    assert j1["peak_source"] == "model" and j1["peak_measured_nm"] is None  # NaN efforts elsewhere
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
    assert res.exit_code in (0, 1)


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
    assert isinstance(t[0]["payload_margin_kg"], float)
    assert res.exit_code == 1 and "planning error" in rec["failure_labels"]
    states = rec["outputs"]["controller_states"]["states_seen"]
    assert "tracking" in states or "deviating" in states

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
    for frac in (0.0005, 0.2, 0.5, 0.8, 0.95):
        f.write_bytes(full[: int(len(full) * frac)])
        out = tmp_path / f"o{frac}"
        code = main([str(bag), "--out", str(out), "--no-report"])
        err = capsys.readouterr().err
        assert "Traceback" not in err
        if code == 2:
            assert err.startswith("dyn-audit: error:") and err.count("\n") == 1
            continue
        rec = validated(out)
        ur = rec["input_quality"]["unreadable_ranges"]
        if rec["inputs"]["message_counts"].get("/joint_states") == 1500:
            assert ur == []
            continue
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
    assert code in (0, 1) and "Traceback" not in capsys.readouterr().err


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
    for name in ("tau_min", "tau_max", "util", "limit", "measured", "count"):
        np.testing.assert_array_equal(getattr(b, name), getattr(s2, name))
    assert (b.n, b.width) == (s2.n, s2.width)


@pytest.mark.timeout(60)
def test_cli_module_runs_and_reports_progress_only_on_a_tty(tmp_path):
    import os

    bag = make_bag(tmp_path / "bag", n=100)
    cmd = [sys.executable, "-m", "dyn_node.audit", str(bag), "--out", str(tmp_path / "o"), "--no-report"]
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


@pytest.mark.timeout(120)
def test_recorded_node_run_audits_with_zero_difference(ros_context, tmp_path):
    """A real DynNode recording its inputs and outputs (record.enabled): the audit of that bag
    recomputes every output with exactly 0.0 difference."""
    import time

    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory

    from dyn_node.node import DynNode

    node = DynNode(context=ros_context, parameter_overrides=[
        Parameter("robot_model", value="panda"), Parameter("record.enabled", value=True),
        Parameter("record.directory", value=str(tmp_path / "bags"))])
    bridge = node.recording
    pub_node = Node("audit_test_publisher", context=ros_context)
    js_pub = pub_node.create_publisher(JointState, "joint_states", 1000)
    traj_pub = pub_node.create_publisher(JointTrajectory, "joint_trajectory", 10)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    ex.add_node(pub_node)

    def spin_until(cond, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not cond():
            ex.spin_once(timeout_sec=0.01)
        return cond()

    rec_topics = lambda: bridge.recorder.stats().topics if bridge.recorder else {}  # noqa: E731
    try:
        # the node records what it takes and publishes itself: no extra subscriptions to wait for
        assert spin_until(lambda: js_pub.get_subscription_count() >= 1
                          and traj_pub.get_subscription_count() >= 1, 30.0)
        n = 300
        names = list(PANDA.joint_names) + ["panda_finger_joint1", "panda_finger_joint2"]
        for i in range(n):
            q, v = q_at(i)
            js_pub.publish(joint_state(names, list(q) + [0.01, 0.01], list(v) + [0.0, 0.0], [],
                                       stamp_ns=T0 + i * 5 * MS))
            if i == 150:
                traj_pub.publish(trajectory_msg(T0 + i * 5 * MS))
            spin_until(lambda: False, 0.002)  # ~ 300 Hz, the node keeps up without drops

        def done():
            t = rec_topics()
            return all(k in t and t[k].received >= n for k in
                       ("/joint_states", "/dyn_node/gravity_torque", "/dyn_node/inverse_dynamics")) \
                and "/dyn_node/feasibility" in t and t["/dyn_node/feasibility"].received >= 1
        assert spin_until(done, 30.0), {k: v.received for k, v in rec_topics().items()}
        ok, path = bridge.stop()
        assert ok, path
    finally:
        bridge.close()
        ex.shutdown()
        node.destroy_node()
        pub_node.destroy_node()
    res = run_audit(AuditOptions(bag=path, out=str(tmp_path / "out"), report=False))
    rec = validated(tmp_path / "out")
    assert rec["configuration"]["model"]["urdf_sha256"] == PANDA.urdf_hash
    assert rec["configuration"]["parameters"]["robot_model"] == "panda"
    rc = rec["outputs"]["recheck"]
    for topic in ("/dyn_node/gravity_torque", "/dyn_node/inverse_dynamics"):
        assert rc[topic]["matched"] == n, rc[topic]
        assert rc[topic]["max_abs_difference"] == 0.0 and rc[topic]["identical"] is True
    assert rc["/dyn_node/feasibility"]["matched"] == 1
    assert rc["/dyn_node/feasibility"]["max_abs_difference"] == 0.0
    assert rc["/dyn_node/feasibility"]["identical"] is True, rc["/dyn_node/feasibility"]
    if "/dyn_node/trajectory_effort" in rc:  # recorded when the bridge discovered it in time
        assert rc["/dyn_node/trajectory_effort"]["max_abs_difference"] == 0.0
    assert rec["outputs"]["latency"]["stamp_to_output_s"]["count"] == n
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
    from dyn_node.audit import Episodes, LiveStats

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
    live = LiveStats(nv, lo, hi, vel)
    ref = Episodes()
    for r in range(n):
        live.add(int(T[r]), U[r] * 10.0, U[r], L[r], Q[r], V[r], None)
        for j in range(nv):
            u, lim, q, av = float(U[r, j]), float(L[r, j]), float(Q[r, j]), abs(float(V[r, j]))
            ref.update(j, "effort", u > 1.0, int(T[r]), u * lim, lim, u)
            below = q < lo[j]
            ref.update(j, "position", bool(q < lo[j] or q > hi[j]), int(T[r]), q,
                       float(lo[j] if below else hi[j]), float(lo[j] - q if below else q - hi[j]))
            ref.update(j, "velocity", av > vel[j], int(T[r]), av, float(vel[j]), av / float(vel[j]))
        if r == 2500:
            live.flush()  # an early, partial batch
    live.flush()
    assert list(live.episodes.open) == list(ref.open)
    assert live.episodes.open == ref.open
    live.finish()
    ref.finish()
    assert live.episodes.total == ref.total > 100
    assert live.episodes.closed == ref.closed


@pytest.mark.parametrize("kind", ["measured", "quality", "trajectories", "outputs_in_bursts"])
def test_batched_replay_gives_exactly_the_per_message_evidence(tmp_path, monkeypatch, kind):
    """Runs of regular joint_states are replayed in batches (Monitor.process_batch); the evidence
    must be exactly what message-by-message replay gives (MIN_BATCH raised past every run), with
    gaps, invalid and out-of-order messages, trajectories being tracked and outputs re-checked."""
    import dyn_node.audit as audit_mod
    from dyn_node.monitor import Monitor

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
