"""#18 in the audit's consumers: the evidence record's per_frame and task_limits, the re-check of
per-place statuses, the recorded limits file rebuilding the same task limits, dyn-check's place
rows and the report's task plot."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from dyn_node.audit.bag_audit import task_limits_differences  # noqa: E402
from dyn_node.audit.check import place_lines  # noqa: E402
from dyn_node.audit.evidence import (EvidenceError, per_frame_curves, per_frame_section,  # noqa: E402
                                     task_limits_section, validate)
from dyn_node.audit.replay.common import worst_status_difference  # noqa: E402
from dyn_node.audit.report import render_html, task_plot, task_rows  # noqa: E402
from dyn_node.core.robot.model import load_model  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEMO_LIMITS = REPO / "config" / "demo_task_limits.yaml"
STATUS = "dyn_node: trajectory feasibility"

LIMITS = """\
joint_limits:
  panda_joint1: {has_velocity_limits: true, max_velocity: 2.175}
frame_limits:
  panda_link8:
    point: [0.0, 0.0, 0.1]
    max_linear_speed: 0.25
    max_transferred_energy: 2.0
robot_limits: {max_kinetic_energy: 5.0}
base_limits: {max_force: 400.0, max_moment: 150.0, base_mass: 20.0, base_com: [0, 0, 0.1],
              support_polygon: [[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]]}
grasp: {frame: panda_hand, normal_axis: [0, 1, 0], friction_coefficient: 0.5, grip_force: 40.0, faces: 2}
"""


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("limits")
    (d / "a.yaml").write_text(LIMITS)
    (d / "b.yaml").write_text(LIMITS.replace("max_linear_speed: 0.25", "max_linear_speed: 0.3"))
    return {"a": load_model(builtin="panda", limits_yaml=str(d / "a.yaml")),
            "a2": load_model(builtin="panda", limits_yaml=str(d / "a.yaml")),
            "b": load_model(builtin="panda", limits_yaml=str(d / "b.yaml")),
            "none": load_model(builtin="panda")}


def _entry(per_frame: dict, *, index: int = 0, time_s: float = 0.0, feasible: bool = False) -> dict:
    return {"index": index, "request": "execute", "topic": "/joint_trajectory", "time_s": time_s, "stamp_ns": 0,
            "accepted": True, "feasible": feasible, "failure_label": None, "per_frame": per_frame}


PER_FRAME = {
    "panda_link8": {"frame_speed": {"ratio": 1.5, "time_s": 0.42, "value": 0.375, "limit": 0.25},
                    "transferred_energy": {"ratio": 0.1, "time_s": 0.4, "value": 0.2, "limit": 2.0}},
    "base_limits": {"tipping": {"ratio": math.inf, "time_s": 0.3, "value": math.inf, "limit": 1.0}},
    "grasp": {"grasp_slip": {"ratio": 1.2125, "time_s": 0.42, "value": 48.5, "limit": 40.0}},
}


def _record(trajectories: list[dict], task_limits: dict | None) -> dict:
    from test_evidence import minimal_record

    rec = minimal_record()
    if task_limits is not None:
        rec.configuration["task_limits"] = task_limits
    rec.outputs["trajectories"] = trajectories
    return rec.to_dict()


def test_task_limits_section_is_the_models_task_limits_and_none_without(models):
    d = task_limits_section(models["a"])
    assert d["frame_limits"] == {"panda_link8": {
        "point": [0.0, 0.0, 0.1], "max_linear_speed": 0.25, "max_angular_speed": None,
        "max_linear_acceleration": None, "max_transferred_energy": 2.0}}
    assert d["grasp"]["friction_coefficient"] * d["grasp"]["grip_force"] * d["grasp"]["faces"] == 40.0
    assert d["base_limits"]["support_polygon"] == [[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]]
    assert task_limits_section(models["none"]) is None


def test_record_with_per_frame_and_task_limits_validates_and_keeps_inf_rules(models):
    pf = per_frame_section({"per_frame": PER_FRAME})
    assert pf["grasp"]["grasp_slip"]["unit"] == "N" and pf["base_limits"]["tipping"]["unit"] == ""
    rec = _record([_entry(pf)], task_limits_section(models["a"]))
    json.dumps(rec, allow_nan=False)
    tip = rec["outputs"]["trajectories"][0]["per_frame"]["base_limits"]["tipping"]
    assert tip["ratio"] == "inf" and tip["value"] == "inf"   # lift-off: no finite gauge
    assert rec["configuration"]["task_limits"]["robot_limits"] == {"max_kinetic_energy": 5.0}


@pytest.mark.parametrize("mutate", [
    lambda r: r["outputs"]["trajectories"][0]["per_frame"]["grasp"].update(grasp_sleep={
        "ratio": 1.0, "time_s": 0.0, "value": 1.0, "limit": 1.0}),                 # unknown kind
    lambda r: r["outputs"]["trajectories"][0]["per_frame"]["grasp"]["grasp_slip"].update(unit="lbf"),
    lambda r: r["outputs"]["trajectories"][0]["per_frame"]["grasp"]["grasp_slip"].pop("limit"),
    lambda r: r["configuration"]["task_limits"].update(frame_limit={}),            # misspelt section
    lambda r: r["configuration"]["task_limits"]["grasp"].update(faces=0),
    lambda r: r["configuration"]["task_limits"]["frame_limits"]["panda_link8"].update(max_linear_speed=-1),
    lambda r: r["configuration"]["task_limits"]["base_limits"].update(support_polygon=[[0, 0], [1, 0]]),
])
def test_schema_rejects_bad_task_sections(models, mutate):
    rec = _record([_entry(per_frame_section({"per_frame": PER_FRAME}))], task_limits_section(models["a"]))
    bad = json.loads(json.dumps(rec))
    mutate(bad)
    with pytest.raises(EvidenceError):
        validate(bad)


def test_the_same_limits_file_rebuilds_the_same_task_limits_and_another_differs(models):
    assert task_limits_differences(models["a"], models["a2"]) == []
    assert task_limits_differences(models["a"], models["b"]) == ["task limits: frame_limits"]
    assert task_limits_differences(models["none"], models["a"]) == [
        "task limits: base_limits, frame_limits, grasp, robot_limits"]


def _status(name: str, values: dict[str, str]):
    return SimpleNamespace(name=name, values=[SimpleNamespace(key=k, value=v) for k, v in values.items()])


def test_recheck_compares_place_statuses_like_joint_ones_and_counts_a_missing_one():
    mine = {STATUS: {"time_scale": "1.5"},
            f"{STATUS}/panda_joint1": {"velocity_ratio": "0.5"},
            f"{STATUS}/panda_link8": {"frame_speed_ratio": "1.5", "frame_speed_peak": "0.375"},
            f"{STATUS}/grasp": {"grasp_slip_ratio": "1.2125"}}
    same = [_status(n, v) for n, v in mine.items()]
    assert worst_status_difference(same, mine) == (0.0, None, 0)
    off = [_status(n, dict(v, frame_speed_peak="0.376") if n.endswith("panda_link8") else v)
           for n, v in mine.items()]
    worst, where, mismatched = worst_status_difference(off, mine)
    assert worst == pytest.approx(0.001, abs=1e-15) and mismatched == 0
    assert where["status"] == f"{STATUS}/panda_link8" and where["key"] == "frame_speed_peak"
    # the node said nothing about the grasp: a place only one side has is a mismatch
    assert worst_status_difference(same[:-1], mine)[2] == 1
    assert worst_status_difference(same + [_status(f"{STATUS}/base_limits", {})], mine)[2] == 1


# every configured kind of LIMITS by place, with its unit (the kinds' documented units)
PLACE_UNITS = {"panda_link8": {"frame_speed": "m/s", "transferred_energy": "J"},
               "robot_limits": {"kinetic_energy": "J"},
               "base_limits": {"base_force": "N", "base_moment": "N·m", "tipping": ""},
               "grasp": {"grasp_slip": "N"}}


def test_place_statuses_carry_each_configured_kinds_unit(models):
    """``<kind>_unit`` beside ``<kind>_peak``/``<kind>_limit``: the kind class's unit, for every
    configured kind of every place, and none for a kind the place does not configure."""
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.check.feasibility import Trajectory, check_trajectory
    from dyn_node.core.check.kinds import KIND_CLASS

    t = np.linspace(0.0, 1.0, 9)
    home = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8])
    step = np.array([0.8, 0.4, -0.3, 0.5, 0.2, -0.3, 0.5])
    res = check_trajectory(Dynamics(models["a"]), Trajectory(
        times=t, positions=home + np.outer((1 - np.cos(np.pi * t)) / 2, step)))
    sts = {s.name: s for s in res.statuses()}
    for place, units in PLACE_UNITS.items():
        st = sts[f"{STATUS}/{place}"]
        assert {k[:-len("_unit")]: v for k, v in st.values.items() if k.endswith("_unit")} == units
        for kind, unit in units.items():
            assert KIND_CLASS[kind].unit == unit == res.per_frame[place][kind]["unit"]
            assert dict(st.key_values())[f"{kind}_unit"] == unit


def test_dyn_check_prints_one_row_per_place():
    result = SimpleNamespace(per_frame=PER_FRAME)
    v = SimpleNamespace(outcome=SimpleNamespace(result=result))
    rows = place_lines(v)
    assert rows == [
        "  panda_link8: frame_speed 0.375 of 0.25 m/s (150%) at t = 0.42 s; "
        "transferred_energy 0.2 of 2 J (10%) at t = 0.40 s",
        "  base_limits: tipping inf of 1 (inf%) at t = 0.30 s",
        "  grasp: grasp_slip 48.5 of 40 N (121%) at t = 0.42 s"]
    assert place_lines(SimpleNamespace(outcome=SimpleNamespace(result=SimpleNamespace(per_frame={})))) == []


def test_curves_keep_each_bins_peak():
    t = np.linspace(0.0, 1.0, 10_001)
    v = np.sin(np.pi * t) ** 2
    v[7_777] = 5.0
    res = SimpleNamespace(task_curves={"panda_link8": {"frame_speed": (t, v)}})
    c = per_frame_curves(res, max_points=400)["panda_link8"]["frame_speed"]
    assert len(c["t_s"]) == 400 == len(c["value"])
    assert max(c["value"]) == 5.0 and c["t_s"][int(np.argmax(c["value"]))] == t[7_777]
    short = per_frame_curves(SimpleNamespace(task_curves={"g": {"grasp_slip": (t[:5], v[:5])}}))
    np.testing.assert_array_equal(short["g"]["grasp_slip"]["value"], v[:5])
    assert per_frame_curves(SimpleNamespace()) is None


def _pixels(png: bytes) -> np.ndarray:
    import io

    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def test_report_draws_a_row_per_place_and_kind_with_its_limit(models):
    pf = per_frame_section({"per_frame": PER_FRAME})
    ok = json.loads(json.dumps(pf))
    ok["panda_link8"]["frame_speed"].update(ratio=0.8, value=0.2)
    rec = _record([_entry(pf, index=0, time_s=1.0), _entry(ok, index=1, time_s=3.0, feasible=True)],
                  task_limits_section(models["a"]))
    trajs = rec["outputs"]["trajectories"]
    assert task_rows(trajs) == [("panda_link8", "frame_speed"), ("panda_link8", "transferred_energy"),
                                ("base_limits", "tipping"), ("grasp", "grasp_slip")]
    img = _pixels(task_plot(trajs))
    assert img.shape == (40 + 4 * 130 + 40, 1100, 3)
    # first row: the infeasible peak (red bar) above the feasible one (green bar)
    row = img[40:40 + 114]
    red = np.all(np.abs(row.astype(int) - (0xb3, 0x26, 0x1e)) < 40, axis=2)
    green = np.all(np.abs(row.astype(int) - (0x1e, 0x7d, 0x3a)) < 40, axis=2)
    assert red.any() and green.any()
    top_red = np.flatnonzero(red[:, 150:1084].any(axis=1))[0]
    top_green = np.flatnonzero(green.any(axis=1))[0]
    assert top_red < top_green
    html = render_html(rec, {"task_limits.png": task_plot(trajs)})
    assert "id='task-limits'" in html and "advisory, not a certification" in html
    assert "<td>grasp_slip</td><td class=\"num\">48.5</td><td class=\"num\">40</td><td>N</td>" in html
    assert "Task limits" not in render_html(_record([], None), {})


# --- a bag whose node ran with task limits: the audit re-checks the place statuses --------------
MS = 1_000_000


def _transfer(stamp_ns: int, seg: float):
    """ready → joint1 +1 rad → ready (the demo's transfer), ``seg`` s per segment, at rest."""
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from dyn_node.ros.demo import task_transfer

    m = JointTrajectory()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    tr = task_transfer()
    m.joint_names = [f"panda_joint{i}" for i in range(1, 8)]
    for t, p in zip(tr.times, tr.positions):
        sec, ns = divmod(int(round(t * seg * 1e9)), 1_000_000_000)
        m.points.append(JointTrajectoryPoint(positions=list(p), velocities=[0.0] * 7,
                                             accelerations=[0.0] * 7,
                                             time_from_start=Duration(sec=sec, nanosec=ns)))
    return m


def _verdict(model, msg, drop: str = "", receipt_ns: int = 0):
    """The node's ~/feasibility array for ``msg`` (same core), without the ``drop`` status,
    judged as received at ``receipt_ns`` (its stamp 500 ns before: the execution starts there)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
    from dyn_node.core.check.feasibility import FeasibilityOptions, Timing, check_trajectory
    from dyn_node.core.check.trajectory import validate_trajectory

    pts = msg.points
    traj = validate_trajectory(model.joint_names, list(msg.joint_names),
                               [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts],
                               [p.positions for p in pts], [p.velocities for p in pts],
                               [p.accelerations for p in pts])
    timing = Timing(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, receipt_ns * 1e-9)
    res = check_trajectory(Dynamics(model, DynamicsOptions(include_friction=True)), traj,
                           FeasibilityOptions(), timing=timing)
    arr = DiagnosticArray()
    arr.header.stamp = msg.header.stamp
    for s in res.statuses(model.name):
        if drop and s.name.endswith("/" + drop):
            continue
        arr.status.append(DiagnosticStatus(level=bytes([s.level]), name=s.name, message=s.message,
                                           hardware_id=s.hardware_id,
                                           values=[KeyValue(key=k, value=v) for k, v in s.key_values()]))
    return arr, res


def _task_bag(path: Path, limits: Path, *, drop: str = "") -> tuple[Path, list]:
    from test_bag_reader import T0, BagWriter

    model = load_model(builtin="panda", limits_yaml=str(limits))
    params = ("/dyn_node:\n  ros__parameters:\n    robot_model: panda\n"
              f"    limits_file: {limits}\n")
    w = BagWriter(path, metadata={"robot_description": model.urdf, "parameters": params,
                                  "version": "0.1.0"})
    results = []
    for i, seg in enumerate((1.0, 2.7)):
        msg = _transfer(T0 + i * 1000 * MS, seg)
        w.write("/joint_trajectory", msg, T0 + i * 1000 * MS + 500)
        arr, res = _verdict(model, msg, drop if i == 0 else "", T0 + i * 1000 * MS + 500)
        w.write("/dyn_node/feasibility", arr, T0 + i * 1000 * MS + 900)
        results.append(res)
    w.close()
    return path, results


def test_audit_rechecks_place_statuses_from_the_bags_limits_file(tmp_path):
    from dyn_node.audit.bag_audit import AuditOptions, run_audit

    limits = tmp_path / "limits.yaml"
    limits.write_text(DEMO_LIMITS.read_text())
    bag, results = _task_bag(tmp_path / "bag", limits)
    assert not results[0].feasible and results[1].feasible   # 256 % of 0.25 m/s, then 95 %
    run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out")))
    rec = json.loads((tmp_path / "out" / "evidence.json").read_text())
    validate(rec)
    feas = rec["outputs"]["recheck"]["/dyn_node/feasibility"]
    assert (feas["matched"], feas["max_abs_difference"], feas["identical"]) == (2, 0.0, True)
    assert rec["configuration"]["task_limits"] == json.loads(json.dumps(
        task_limits_section(load_model(builtin="panda", limits_yaml=str(limits)))))
    for entry, res in zip(rec["outputs"]["trajectories"], results):
        e = res.per_frame["panda_hand"]["frame_speed"]
        assert entry["per_frame"]["panda_hand"]["frame_speed"]["value"] == e["value"]
        assert entry["per_frame"]["panda_hand"]["frame_speed"]["ratio"] == e["ratio"]
    assert rec["outputs"]["trajectories"][0]["worst_joint"] == "panda_hand"
    assert (tmp_path / "out" / "task_limits.png").is_file()


def test_audit_finds_a_missing_place_status_and_a_different_limits_file(tmp_path):
    from dyn_node.audit.bag_audit import AuditOptions, run_audit

    limits = tmp_path / "limits.yaml"
    limits.write_text(DEMO_LIMITS.read_text())
    bag, _ = _task_bag(tmp_path / "bag", limits, drop="panda_hand")
    run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out")))
    feas = json.loads((tmp_path / "out" / "evidence.json").read_text())["outputs"]["recheck"][
        "/dyn_node/feasibility"]
    assert feas["identical"] is False and feas["mismatched_non_numeric_values"] == 1
    other = tmp_path / "other.yaml"
    other.write_text(DEMO_LIMITS.read_text().replace("max_linear_speed: 0.25", "max_linear_speed: 0.3"))
    run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "out2"), limits=str(other)))
    feas = json.loads((tmp_path / "out2" / "evidence.json").read_text())["outputs"]["recheck"][
        "/dyn_node/feasibility"]
    assert feas["comparable"] is False and "task limits: frame_limits" in feas["not_comparable"]


def test_report_curves_follow_the_trajectorys_own_time():
    """With per_frame_curves, a triangle peaking at t = 0.3 s is drawn with its top there."""
    t = np.linspace(0.0, 1.0, 101)
    v = np.minimum(t / 0.3, (1.0 - t) / 0.7) * 0.4
    pf = {"panda_hand": {"frame_speed": {"ratio": 1.6, "time_s": 0.3, "value": 0.4, "limit": 0.25,
                                         "unit": "m/s"}}}
    entry = _entry(pf)
    entry["per_frame_curves"] = {"panda_hand": {"frame_speed": {"t_s": t.tolist(), "value": v.tolist()}}}
    img = _pixels(task_plot([entry])).astype(int)
    R, G, B = img[..., 0], img[..., 1], img[..., 2]
    orange = (R > 200) & (G > 100) & (R - B > 80)   # the curve, anti-aliased over white
    rows, cols = np.nonzero(orange[40:40 + 114, 150:1084])
    x_top = cols[rows == rows.min()].mean() + 150
    # axes: 150 … 1084 px over [−0.03, 1.03] s (3 % padding)
    assert x_top == pytest.approx(150 + (0.3 + 0.03) / 1.06 * 934, abs=3)
    # the limit (dashed red) lies at 0.25 of the 0 … 1.15·0.4 range
    red = (R > 150) & (G < 110) & (B < 110)
    red_rows = np.flatnonzero(red[40:154, 160:1080].sum(axis=1) > 100)
    y_limit = 40 + red_rows.mean()
    assert y_limit == pytest.approx(40 + 114 - 0.25 / (1.15 * 0.4) * 114, abs=3)
