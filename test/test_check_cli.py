"""dyn-check without ROS: file formats, exit codes and messages, --out evidence and report,
--retime. (The same verdicts and torques as the node: test_services.)"""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from dyn_node.audit import check as check_cli
from dyn_node.audit.check import RETIME_MARGIN, main
from dyn_node.ros.demo import READY
from dyn_node.errors import TrajectoryFileError
from dyn_node.audit.evidence import validate
from dyn_node.audit.trajectory_files import format_trajectory, read_trajectory

EXAMPLES = REPO / "examples" / "trajectories"
REACH = [EXAMPLES / f"panda_reach.{ext}" for ext in ("yaml", "json", "csv")]
SHAKE = EXAMPLES / "panda_shake.yaml"


@pytest.fixture(scope="module")
def checker():
    return check_cli.make_checker(robot_model="panda")


def run(capsys, *args: str) -> tuple[int, str, str]:
    code = main([*map(str, args), "--robot-model", "panda"])
    out, err = capsys.readouterr()
    return code, out, err


def test_the_three_formats_hold_the_same_trajectory_and_verdict(checker):
    files = [read_trajectory(p) for p in REACH]
    assert [f.format for f in files] == ["yaml", "json", "csv"]
    for f in files[1:]:
        assert (f.joint_names, f.times, f.positions, f.velocities, f.accelerations) == (
            files[0].joint_names, files[0].times, files[0].positions, files[0].velocities,
            files[0].accelerations)
    assert files[0].times == [0.0, 1.5, 3.0] and files[0].positions[0] == list(READY)
    verdicts = [check_cli.check_file(checker, str(p)).outcome.result for p in REACH]
    assert all(v.feasible for v in verdicts)
    for v in verdicts[1:]:
        assert v.message == verdicts[0].message and v.time_scale == verdicts[0].time_scale
        np.testing.assert_array_equal(v.waypoint_effort, verdicts[0].waypoint_effort)


def test_exit_0_all_feasible_1_some_infeasible(capsys):
    code, out, _ = run(capsys, *REACH)
    assert code == 0 and out.count(": FEASIBLE (") == 3
    code, out, _ = run(capsys, REACH[0], SHAKE)
    assert code == 1
    k = shake_velocity_time_scale()
    assert f"{SHAKE}: INFEASIBLE (ERROR), time_scale {k:.4g}: " in out and "panda_joint2 effort" in out
    assert f"run {k:.2f}× slower: velocity of panda_joint2 binds" in out


def shake_velocity_time_scale() -> float:
    """panda_shake's k from its file alone: each segment is a quintic with zero velocity and
    acceleration at both ends, peak |q̇| = 15/8·|Δq|/T at mid-segment; k = the largest peak over
    the joint's URDF velocity limit (read by Pinocchio). Its effort (166 % at most, k ≤ √1.66)
    binds less."""
    import pinocchio as pin
    import yaml

    doc = yaml.safe_load(SHAKE.read_text())
    t = np.array([p["time_from_start"]["sec"] + p["time_from_start"]["nanosec"] * 1e-9
                  for p in doc["points"]])
    q = np.array([p["positions"] for p in doc["points"]])
    peak = 15 / 8 * np.abs(np.diff(q, axis=0)) / np.diff(t)[:, None]
    model = check_cli.make_checker(robot_model="panda").model.base_model
    vmax = np.array([model.velocityLimit[model.joints[model.getJointId(n)].idx_v]
                     for n in doc["joint_names"]])
    return float(np.max(peak / vmax))


def test_shake_time_scale_is_its_velocity_peak_over_the_limit(checker):
    k = shake_velocity_time_scale()
    assert k == pytest.approx(1.875 * 0.2 / 0.13 / 2.175, rel=1e-12)   # joint2, 0.2 rad in 0.13 s
    r = check_cli.check_file(checker, str(SHAKE)).outcome.result
    assert r.time_scale == pytest.approx(k, rel=1e-9)
    assert (r.binding_joint, r.binding_constraint) == ("panda_joint2", "velocity")


@pytest.mark.parametrize("name,text,where", [
    ("bad.yaml", "joint_names: [a, b\npoints: []\n", "bad.yaml:2: not valid YAML"),
    ("bad.json", '{"joint_names": ["a"],\n "points": [}\n', "bad.json:2: not valid JSON"),
    ("nonames.yaml", "header: {frame_id: x}\npoints: []\n", "nonames.yaml:1: joint_names: missing"),
    ("nonames.json", '{\n "points": []\n}\n', "nonames.json:1: joint_names: missing"),
    ("word.yaml", "joint_names: [a]\npoints:\n- positions: [1.0]\n  time_from_start: {sec: 0}\n"
                  "- positions: [two]\n  time_from_start: {sec: 1}\n",
     "word.yaml:5: points[1].positions[0]: not a number ('two')"),
    ("notime.yaml", "joint_names: [a]\npoints:\n- positions: [1.0]\n",
     "notime.yaml:3: points[0].time_from_start: missing"),
    ("notime.csv", "t,panda_joint1\n0,1\n", "notime.csv:1: time: missing column"),
    ("novel.csv", "time,a,b,a.vel\n0,1,2,3\n", "novel.csv:1: b.vel: missing column"),
    ("cell.csv", "time,a\n0,1\n1,x\n", "cell.csv:3: a: not a number ('x')"),
    ("short.csv", "time,a,b\n0,1,2\n1,2\n", "short.csv:3: 2 cells for 3 columns"),
])
def test_unreadable_files_exit_2_naming_file_line_and_field(capsys, tmp_path, name, text, where):
    p = tmp_path / name
    p.write_text(text)
    code, out, err = run(capsys, REACH[0], p)
    assert code == 2
    assert err.strip() == f"{p}: UNREADABLE: {tmp_path}/{where}" or err.strip().startswith(
        f"{p}: UNREADABLE: {tmp_path}/{where}"), err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert out.count(": FEASIBLE (") == 1  # the readable file is still checked


def test_no_model_exits_2_with_one_line(capsys):
    code = main([str(REACH[0])])
    _, err = capsys.readouterr()
    assert code == 2 and err.startswith("dyn-check: error: no robot model") and err.count("\n") == 1


def test_a_params_file_with_a_huge_integer_exits_2_with_one_line(capsys, tmp_path):
    """Issue 40: a 4,301-digit integer in --params-file was a traceback (exit 0 after it)."""
    params = tmp_path / "params.yaml"
    params.write_text("dyn_node:\n  ros__parameters:\n    sample_period: " + "9" * 4301 + "\n")
    code = main([str(REACH[0]), "--robot-model", "panda", "--params-file", str(params)])
    _, err = capsys.readouterr()
    assert code == 2 and err.count("\n") == 1, err
    assert str(params) in err and "4301 digits" in err, err


def _edit_csv(tmp_path: Path, name: str, row: int, col: int, value: str) -> Path:
    lines = REACH[2].read_text().splitlines()
    cells = lines[row].split(",")
    cells[col] = value
    lines[row] = ",".join(cells)
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p


def test_rejected_trajectories_exit_1_with_the_nodes_reason(capsys, tmp_path):
    nan = _edit_csv(tmp_path, "nan.csv", 2, 4, "nan")
    backwards = _edit_csv(tmp_path, "backwards.csv", 3, 0, "1.0")
    lines = REACH[2].read_text().splitlines()
    (tmp_path / "unknown.csv").write_text("\n".join([lines[0].replace("panda_joint7", "elbow_x"),
                                                     *lines[1:]]) + "\n")
    for p, reason in ((nan, "point 1: positions of panda_joint4 is nan"),
                      (backwards, "time_from_start not strictly increasing at point 2 (1.5 s then 1 s)"),
                      (tmp_path / "unknown.csv", "joints not in the model: elbow_x; model joints missing "
                                                  "from the trajectory: panda_joint7")):
        code, out, _ = run(capsys, p)
        assert code == 1
        assert out.strip() == f"{p}: REJECTED: {reason}"


def test_out_writes_a_valid_evidence_record_and_report_per_file(tmp_path, capsys):
    code, out, _ = run(capsys, SHAKE, REACH[2], "--out", tmp_path)
    assert code == 1
    for stem, result in (("panda_shake", "violations"), ("panda_reach", "feasible")):
        rec = json.loads((tmp_path / stem / "evidence.json").read_text())
        validate(rec)
        assert rec["kind"] == "check" and rec["tool"]["name"] == "dyn-check"
        assert rec["verdict"]["result"] == result
        (traj,) = rec["outputs"]["trajectories"]
        assert traj["feasible"] == (result == "feasible")
        html = (tmp_path / stem / "report.html").read_text()
        assert "dyn-check report" in html and traj["message"] in html
    shake = json.loads((tmp_path / "panda_shake" / "evidence.json").read_text())
    assert shake["failure_labels"] == ["planning error"]
    assert "panda_joint2" in {v["joint"] for v in shake["outputs"]["trajectories"][0]["violations"]}


@pytest.mark.parametrize("fmt", ["yaml", "json", "csv"])
def test_retime_writes_a_trajectory_that_rechecks_feasible(tmp_path, capsys, checker, fmt):
    src = read_trajectory(SHAKE)
    inp = tmp_path / f"shake.{fmt}"
    inp.write_text(format_trajectory(src, fmt))
    out = tmp_path / f"retimed.{fmt}"
    code, text, _ = run(capsys, inp, "--retime", out, "--retime-method", "uniform")
    assert code == 0  # with --retime: every file written with a feasible timing
    assert "INFEASIBLE" in text   # the input's own verdict is still printed
    before = check_cli.check_file(checker, str(inp)).outcome.result
    after = check_cli.check_file(checker, str(out)).outcome.result
    assert read_trajectory(out).format == fmt
    assert after.feasible
    # stretched by k(1 + m): the retimed one could run about 1/(1 + m) faster (the sample grid
    # moves with the stretch, so not to the digit), and not more than the margin
    assert 1 - RETIME_MARGIN <= after.time_scale <= 1.0
    np.testing.assert_allclose(read_trajectory(out).times, np.array(src.times) * before.time_scale
                               * (1 + RETIME_MARGIN), rtol=0, atol=1e-9)
    assert f"re-checked: time_scale now {after.time_scale:.6g}" in text


def test_retime_copies_feasible_and_skips_what_no_slowdown_fixes(tmp_path, capsys):
    limits = tmp_path / "weak.yaml"  # joint2 cannot even hold the arm up at the ready pose
    limits.write_text("joint_limits:\n  panda_joint2:\n    has_effort_limits: true\n    max_effort: 1.0\n")
    code, text, _ = run(capsys, REACH[2], SHAKE, "--retime", tmp_path / "rt", "--limits", limits,
                        "--retime-method", "uniform")
    assert code == 1
    assert not (tmp_path / "rt" / "panda_reach.csv").exists()
    assert not (tmp_path / "rt" / "panda_shake.yaml").exists()
    assert text.count("not written: no slowdown makes it feasible") == 2
    code, text, _ = run(capsys, REACH[2], "--retime", tmp_path / "rt2", "--retime-method", "uniform")
    assert code == 0
    assert (tmp_path / "rt2").is_dir() is False  # one input: OUT is the file itself
    assert (tmp_path / "rt2").read_bytes() == REACH[2].read_bytes()


def test_module_and_help_run_without_ros():
    # python -m dyn_node.audit.check works, and the command never imports rclpy
    code = ("import sys, runpy; sys.argv = ['dyn-check', '--help']\n"
            "try:\n    runpy.run_module('dyn_node.audit.check', run_name='__main__')\n"
            "except SystemExit as e:\n    assert e.code == 0\n"
            "from dyn_node.audit import check as check_cli\n"
            f"assert check_cli.main([{str(REACH[0])!r}, '--robot-model', 'panda']) == 0\n"
            "assert 'rclpy' not in sys.modules, 'rclpy imported'\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(REPO),
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert "usage: dyn-check" in r.stdout and "exit codes: 0 everything feasible" in r.stdout


def test_parse_errors_carry_file_line_and_field(tmp_path):
    p = tmp_path / "t.yaml"
    p.write_text("joint_names: [a]\npoints:\n- positions: [1.0]\n  velocities: 3\n  time_from_start: 0.5\n")
    with pytest.raises(TrajectoryFileError) as e:
        read_trajectory(p)
    assert (e.value.line, e.value.field) == (4, "points[0].velocities")
    p.write_text("joint_names: [a]\npoints:\n- positions: [.nan]\n  time_from_start: 0.5\n")
    assert math.isnan(read_trajectory(p).positions[0][0])  # parses: the check rejects it


def test_console_scripts_are_on_the_venvs_path():
    # `source .venv/bin/activate` must put every command of setup.py on PATH (make links them)
    if sys.prefix == sys.base_prefix:
        pytest.skip("not running in a virtual environment")
    import re

    names = re.findall(r'"([\w-]+) = dyn_node\.', (REPO / "setup.py").read_text())
    assert {"dyn-check", "dyn-audit", "dyn-bag-recover", "dyn_node", "dyn_sim"} <= set(names)
    bin_dir = Path(sys.prefix) / "bin"
    assert [n for n in names if not (bin_dir / n).is_file()] == []
    r = subprocess.run([str(bin_dir / "dyn-check"), "--help"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.startswith("usage: dyn-check")


def test_task_limits_give_a_row_per_place_evidence_and_a_retime_that_passes(tmp_path, capsys):
    """The demo's TCP limit (250 mm/s at panda_hand's TCP) on the reach example: the place row
    carries the core's numbers, the record its per_frame and task_limits, and --retime fixes it."""
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.check.feasibility import check_trajectory
    from dyn_node.core.robot.model import load_model
    from dyn_node.core.check.trajectory import validate_trajectory

    limits = REPO / "config" / "demo_task_limits.yaml"
    tf = read_trajectory(REACH[0])
    model = load_model(builtin="panda", limits_yaml=str(limits))
    res = check_trajectory(Dynamics(model), validate_trajectory(
        model.joint_names, tf.joint_names, tf.times, tf.positions, tf.velocities, tf.accelerations))
    e = res.per_frame["panda_hand"]["frame_speed"]
    assert e["ratio"] > 1 and res.worst_joint == "panda_hand"
    out_file = tmp_path / "slow.yaml"
    code, out, _ = run(capsys, REACH[0], "--limits", limits, "--out", tmp_path, "--retime", out_file,
                       "--retime-method", "uniform")
    assert code == 0 and "INFEASIBLE" in out
    lines = out.splitlines()
    assert lines[1] == (f"  panda_hand: frame_speed {e['value']:.4g} of 0.25 m/s "
                        f"({e['ratio'] * 100:.0f}%) at t = {e['time_s']:.2f} s")
    rec = json.loads((tmp_path / "panda_reach" / "evidence.json").read_text())
    validate(rec)
    assert rec["configuration"]["task_limits"]["frame_limits"]["panda_hand"]["max_linear_speed"] == 0.25
    pf = rec["outputs"]["trajectories"][0]["per_frame"]["panda_hand"]["frame_speed"]
    assert pf == {"unit": "m/s", "ratio": e["ratio"], "time_s": e["time_s"], "value": e["value"],
                  "limit": 0.25}
    assert (tmp_path / "panda_reach" / "task_limits.png").is_file()
    assert "id='task-limits'" in (tmp_path / "panda_reach" / "report.html").read_text()
    code, out, _ = run(capsys, out_file, "--limits", limits)
    assert code == 0
    # speed ÷ k: the retimed peak is the limit ÷ (1 + margin), up to the moved sample grid
    again = read_trajectory(out_file)
    res2 = check_trajectory(Dynamics(model), validate_trajectory(
        model.joint_names, again.joint_names, again.times, again.positions, again.velocities,
        again.accelerations))
    assert res2.per_frame["panda_hand"]["frame_speed"]["ratio"] == pytest.approx(
        1 / (1 + RETIME_MARGIN), rel=1e-5)


def test_a_positions_only_file_is_infeasible_with_velocity_steps_not_unreadable(capsys, tmp_path):
    """Issue 36: positions only, the controller interpolates linearly (trajectory.cpp 315-333,
    jazzy ed360c9): the velocity steps at the inner point and at the end. Judged (exit 1, the
    words say why), never unreadable (exit 2); the same points with their velocities pass."""
    text = REACH[0].read_text()
    only = "\n".join(line for line in text.splitlines()
                     if not line.lstrip().startswith(("velocities:", "accelerations:")))
    path = tmp_path / "reach_positions_only.yaml"
    path.write_text(only + "\n")
    code, out, _ = run(capsys, path)
    assert code == 1, out
    assert "INFEASIBLE (ERROR)" in out
    assert ("positions only: velocity steps at 2 points as the controller interpolates them; no slowdown "
            "removes a velocity step: send velocities (cubic) or velocities and accelerations (quintic)") in out
    code, out, _ = run(capsys, REACH[0])
    assert code == 0 and "FEASIBLE (OK" in out, out
