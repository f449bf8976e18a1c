"""Trajectory files as dyn-check reads them: every unknown key named (with the closest
spelling), files over the size or point cap refused before they are parsed, and an integer of
4,301 digits a one-line exit-2 error naming the field (never a traceback)."""
from __future__ import annotations

import json

import pytest

from conftest import REPO
from dyn_node.audit.check import main
from dyn_node.audit.trajectory_files import MAX_POINTS, MAX_TRAJECTORY_BYTES, parse_trajectory, read_trajectory
from dyn_node.errors import TrajectoryFileError

REACH = REPO / "examples" / "trajectories" / "panda_reach.yaml"
NAMES = [f"panda_joint{i}" for i in range(1, 8)]
READY = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]


def _doc(n: int = 2, **point_extra) -> dict:
    pts = [{"positions": READY, "time_from_start": {"sec": i, "nanosec": 0}} for i in range(n)]
    pts[-1].update(point_extra)
    return {"joint_names": NAMES, "points": pts}


def test_a_nanosecs_typo_is_an_error_not_a_second_lost():
    doc = _doc()
    doc["points"][1]["time_from_start"] = {"sec": 1, "nanosecs": 900_000_000}
    with pytest.raises(TrajectoryFileError) as e:
        parse_trajectory(json.dumps(doc, indent=1), "json", "t.json")
    assert e.value.field == "points[1].time_from_start.nanosecs"
    assert e.value.problem == "unknown key (did you mean 'nanosec'?)"
    # with the right key the same point is at 1.9 s
    doc["points"][1]["time_from_start"] = {"sec": 1, "nanosec": 900_000_000}
    assert parse_trajectory(json.dumps(doc), "json").times == [0.0, 1.9]


def test_every_unknown_key_is_named_with_its_line():
    text = ("joint_names: [a]\nheadr: {}\npoints:\n- positions: [0]\n  time_from_start: {sec: 0}\n"
            "- positions: [1]\n  velocity: [0]\n  time_from_start: {sec: 1, nsec: 5}\n")
    with pytest.raises(TrajectoryFileError) as e:
        parse_trajectory(text, "yaml", "t.yaml")
    assert e.value.line == 2 and e.value.field == ""
    assert e.value.problem == ("3 unknown keys: headr (did you mean 'header'?); points[1].velocity "
                               "(did you mean 'velocities'?); points[1].time_from_start.nsec (did you mean 'sec'?)")
    with pytest.raises(TrajectoryFileError) as e:
        parse_trajectory(json.dumps({"joint_names": ["a"], "header": {"stamp": {"secs": 1}},
                                     "points": [{"positions": [0], "time_from_start": 0}]}), "json")
    assert (e.value.field, e.value.problem) == ("header.stamp.secs", "unknown key (did you mean 'sec'?)")


def test_the_known_keys_all_read():
    doc = _doc(2, velocities=[0.0] * 7, accelerations=[0.0] * 7, effort=[])
    doc["header"] = {"stamp": {"sec": 3, "nanosec": 4}, "frame_id": "w"}
    tf = parse_trajectory(json.dumps(doc), "json")
    assert (tf.stamp, tf.frame_id, tf.velocities[1], tf.times) == ((3, 4), "w", [0.0] * 7, [0.0, 1.0])


def test_files_over_the_point_cap_are_refused_before_parsing(tmp_path):
    assert (MAX_POINTS, MAX_TRAJECTORY_BYTES) == (100_000, 16_000_000)
    p = tmp_path / "t.json"
    p.write_text(json.dumps(_doc(11)))
    with pytest.raises(TrajectoryFileError) as e:
        read_trajectory(p, max_points=10)
    assert e.value.problem == ("11 time_from_start entries, more than the 10 points read at most "
                               "(dyn-check --max-points raises it)")
    assert len(read_trajectory(p, max_points=11).times) == 11
    # not parsed: text that is not even JSON is refused for its count alone
    with pytest.raises(TrajectoryFileError, match="11 time_from_start entries"):
        parse_trajectory("{" + "time_from_start " * 11, "json", max_points=10)
    csv = tmp_path / "t.csv"
    csv.write_text("time,a\n" + "".join(f"{i},0\n" for i in range(11)))
    with pytest.raises(TrajectoryFileError, match="11 rows after the header, more than the 10 points"):
        read_trajectory(csv, max_points=10)
    # YAML aliases repeat points without writing them: counted once parsed
    text = "joint_names: [a]\npoints:\n- &p {positions: [0], time_from_start: 0}\n" + "- *p\n" * 10
    with pytest.raises(TrajectoryFileError, match="^<text>: points: 11 points, more than the 10"):
        parse_trajectory(text, "yaml", max_points=10)


def test_dyn_check_refuses_a_large_file_in_one_line_unless_raised(tmp_path, capsys):
    p = tmp_path / "big.json"
    p.write_text(json.dumps(_doc(3)) + " " * 1_100_000)
    code = main([str(p), "--robot-model", "panda", "--max-file-mb", "1"])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert err == (f"{p}: UNREADABLE: {p}: is {p.stat().st_size} bytes, more than the 1000000 read at "
                   "most (dyn-check --max-file-mb raises it)\n")
    code = main([str(p), "--robot-model", "panda", "--max-file-mb", "1.2"])
    assert code == 0 and capsys.readouterr().out.startswith(f"{p}: FEASIBLE")
    code = main([str(p), "--robot-model", "panda", "--max-points", "2"])
    assert code == 2 and "3 time_from_start entries, more than the 2 points" in capsys.readouterr().err


@pytest.mark.parametrize("fmt", ["json", "yaml"])
@pytest.mark.parametrize("where", ["sec", "position", "stamp"])
def test_a_4301_digit_integer_is_one_line_naming_the_field(tmp_path, capsys, fmt, where):
    huge = "9" * 4301
    doc = _doc()
    text = json.dumps(doc).replace('"sec": 1', f'"sec": {huge}') if where == "sec" else \
        json.dumps(doc).replace("0.785]", f"{huge}]", 1) if where == "position" else \
        json.dumps({**doc, "header": {"stamp": {"sec": 0, "nanosec": 1}}}).replace('"nanosec": 1}', f'"nanosec": {huge}}}')
    field = {"sec": "points[1].time_from_start.sec", "position": "points[0].positions[6]",
             "stamp": "header.stamp.nanosec"}[where]
    p = tmp_path / f"t.{fmt}"
    p.write_text(text)   # JSON is YAML: the same text read by either parser
    code = main([str(p), "--robot-model", "panda"])
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and err.count("\n") == 1
    assert f": {field}: too large for a number (an integer of 4301 digits; at most 4300)" in err and "Traceback" not in err


def test_a_4301_digit_limit_is_one_line_naming_the_field(tmp_path, capsys):
    lim = tmp_path / "limits.yaml"
    lim.write_text(f"joint_limits:\n  panda_joint3:\n    max_effort: {'9' * 4301}\n")
    code = main([str(REACH), "--robot-model", "panda", "--limits", str(lim)])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert err == (f"dyn-check: error: robot model unusable: {lim}: line 3: "
                   "joint_limits.panda_joint3.max_effort: too large for a number (an integer of 4301 digits; at most 4300)\n")
