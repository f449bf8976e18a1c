"""dyn-check --retime (optimal, the default): the written file, its re-check, the line, the exit
codes, the plot in --out."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dyn_node.audit import check as check_cli
from dyn_node.audit.check import main
from dyn_node.audit.trajectory_files import format_trajectory, read_trajectory

REPO = Path(__file__).resolve().parents[1]
REACH_CSV = REPO / "examples" / "trajectories" / "panda_reach.csv"
REACH_YAML = REPO / "examples" / "trajectories" / "panda_reach.yaml"
SHAKE = REPO / "examples" / "trajectories" / "panda_shake.yaml"


def run(capsys, *args) -> tuple[int, str, str]:
    code = main([*map(str, args), "--robot-model", "panda"])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def checker():
    return check_cli.make_checker(robot_model="panda")


def test_optimal_retime_written_in_the_input_format_and_rechecked(tmp_path, capsys, checker):
    out = tmp_path / "fast.csv"
    code, text, _ = run(capsys, REACH_CSV, "--retime", out, "--out", tmp_path / "ev")
    assert code == 0
    line = next(x for x in text.splitlines() if x.startswith("  retime: "))
    assert "optimal: 3 s → " in line and "T* " in line and "gap " in line
    assert "re-check: FEASIBLE" in line and line.endswith(f"→ {out}")
    tf = read_trajectory(out)
    assert tf.format == "csv" and tf.velocities is not None and tf.accelerations is not None
    again = check_cli.check_file(checker, str(out)).outcome.result
    assert again.feasible and again.interpolation == "quintic"
    # faster than the input (3 s) and than the uniform stretch the line names
    summary = json.loads((tmp_path / "ev" / "panda_reach" / "retime.json").read_text())
    assert summary["method"] == "optimal"
    assert tf.times[-1] == pytest.approx(summary["duration_out_s"], abs=1e-9)
    assert tf.times[-1] < summary["duration_uniform_s"] < 3.0
    assert summary["lower_bound_s"] <= tf.times[-1]
    png = tmp_path / "ev" / "panda_reach" / "retime.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_untimed_waypoints_are_retimed(tmp_path, capsys, checker):
    src = read_trajectory(REACH_YAML)
    from dataclasses import replace
    untimed = tmp_path / "untimed.yaml"
    untimed.write_text(format_trajectory(replace(src, times=[0.0] * len(src.times),
                                                 velocities=None, accelerations=None)))
    out = tmp_path / "timed.yaml"
    code, text, _ = run(capsys, untimed, "--retime", out)
    assert code == 0, text
    assert "REJECTED" in text           # the node's validation rejects all-zero times
    tf = read_trajectory(out)
    assert tf.times[0] == 0.0 and np.all(np.diff(tf.times) > 0)
    assert check_cli.check_file(checker, str(out)).outcome.result.feasible
    np.testing.assert_allclose(tf.positions[-1], src.positions[-1], atol=1e-12)


def test_no_retiming_exits_1_and_writes_nothing(tmp_path, capsys):
    limits = tmp_path / "weak.yaml"  # joint2 cannot even hold the arm up at the ready pose
    limits.write_text("joint_limits:\n  panda_joint2:\n    has_effort_limits: true\n    max_effort: 1.0\n")
    code, text, _ = run(capsys, REACH_CSV, SHAKE, "--retime", tmp_path / "rt", "--limits", limits)
    assert code == 1
    assert list((tmp_path / "rt").glob("*")) == []     # nothing written (glob of no dir: [])
    assert text.count("  retime: not written: gravity") == 2


def test_unreadable_input_exits_2(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("joint_names: [a\n")
    code, _, err = run(capsys, bad, REACH_CSV, "--retime", tmp_path / "rt")
    assert code == 2 and "UNREADABLE" in err
    assert (tmp_path / "rt" / "panda_reach.csv").is_file()


def test_exit_codes_with_and_without_retime(tmp_path, capsys):
    """docs/dyn-check.md's table, row by row: an infeasible input exits 1 when only checked and
    0 when its retiming is written (the code is the retiming's with --retime); a file no
    retiming fixes exits 1 (test_no_retiming_exits_1_and_writes_nothing), an input printed
    REJECTED whose retiming is written 0 (test_untimed_waypoints_are_retimed), an unreadable
    one 2 (test_unreadable_input_exits_2)."""
    code, text, _ = run(capsys, SHAKE)
    assert code == 1 and "INFEASIBLE" in text
    out = tmp_path / "shake.yaml"
    code, text, _ = run(capsys, SHAKE, "--retime", out)
    assert code == 0 and "INFEASIBLE" in text and out.is_file()
    code, text, _ = run(capsys, REACH_CSV)
    assert code == 0 and "FEASIBLE" in text and "INFEASIBLE" not in text
