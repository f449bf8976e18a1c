"""dyn-check --out: report.html shows the checked trajectory (its curves against the limits, the
violations, the time scale), not a bag report. The plotted curves are checked against the file
(waypoints), finite differences of the plotted positions, and Pinocchio's RNEA."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from dyn_node.audit import check as check_cli
from dyn_node.audit.check_report import _over, sample_curves

REPO = Path(__file__).resolve().parents[1]
SHAKE = REPO / "examples" / "trajectories" / "panda_shake.yaml"
REACH = REPO / "examples" / "trajectories" / "panda_reach.csv"
BAG_WORDS = ("joint_states", "chunks", "CRC", "bag's first message", "No accepted", "Re-check",
             "Input quality", "controller")


@pytest.fixture(scope="module")
def checker():
    return check_cli.make_checker(robot_model="panda")


@pytest.mark.parametrize("path, word", [(SHAKE, "INFEASIBLE"), (REACH, "FEASIBLE")])
def test_report_is_about_the_trajectory_not_a_bag(tmp_path, capsys, path, word):
    code = check_cli.main([str(path), "--robot-model", "panda", "--out", str(tmp_path)])
    capsys.readouterr()
    page = (tmp_path / path.stem / "report.html").read_text()
    assert f">{word}<small>" in page and (tmp_path / path.stem / "trajectory.png").is_file()
    assert page.count("data:image/png;base64,") >= 1
    text = re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "", page)  # words, not image bytes
    for w in BAG_WORDS:
        assert w not in text, w
    assert "Times are seconds from the trajectory's first point" in page
    rec_k = re.search(r"time_scale ([0-9.]+)", page).group(1)
    assert f"<td>Time scale k</td><td>{float(rec_k):.4g}" in page
    assert code == (1 if word == "INFEASIBLE" else 0)


def test_violations_are_listed_and_the_peaks_tabled(tmp_path, capsys, checker):
    check_cli.main([str(SHAKE), "--robot-model", "panda", "--out", str(tmp_path)])
    capsys.readouterr()
    page = (tmp_path / "panda_shake" / "report.html").read_text()
    v = check_cli.check_file(checker, str(SHAKE))
    assert len(v.outcome.result.violations) == 3
    for x in v.outcome.result.violations:  # every violation has its row: place, kind, peak time
        assert f"<td>{x.joint}</td><td>{x.kind}</td>" in page and f"{x.peak_time_s:.4f}" in page
    ratio = v.outcome.result.per_joint["panda_joint2"]["effort"]["ratio"]
    assert f"<b style='color:#b3261e'>{ratio * 100:.1f}%</b>" in page


def test_plotted_curves_are_the_trajectory_and_its_torque(checker):
    v = check_cli.check_file(checker, str(SHAKE))
    traj, r = v.outcome.trajectory, v.outcome.result
    c = sample_curves(traj, r, checker.dynamics)
    # through every waypoint of the file, in model order
    idx = np.searchsorted(c.t, traj.times)
    np.testing.assert_allclose(c.t[idx], traj.times, atol=0)
    np.testing.assert_allclose(c.values["position"][idx], traj.positions, atol=1e-12)
    # velocity and acceleration are the derivatives of the plotted positions
    for lo, hi in (("position", "velocity"), ("velocity", "acceleration")):
        fd = np.gradient(c.values[lo], c.t, axis=0)
        scale = np.abs(c.values[hi]).max()
        assert np.abs(fd[5:-5] - c.values[hi][5:-5]).max() < 0.02 * scale
    # the torque is Pinocchio's RNEA plus the model's friction at each plotted state
    pm = checker.dynamics.pin_model
    data = pm.createData()
    damping, coulomb = checker.dynamics.friction_coefficients
    for i in range(0, len(c.t), 97):
        q, qd, qdd = (c.values[k][i] for k in ("position", "velocity", "acceleration"))
        want = pin.rnea(pm, data, q, qd, qdd) + damping * qd + coulomb * np.sign(qd)
        np.testing.assert_allclose(c.values["torque"][i], want, rtol=1e-9, atol=1e-9)
    # and its peak is the check's (sampled at 1 ms, the plot at about 0.5 ms)
    peak = np.abs(c.values["torque"][:, 1]).max()
    assert peak == pytest.approx(r.per_joint["panda_joint2"]["effort"]["value"], rel=2e-3)


def test_over_the_limit_intervals():
    t = np.linspace(0.0, 1.0, 11)
    y = np.array([0, 2, 3, 0, 0, -5, 0, 0, 0, 4, 4.0])
    assert _over(t, y, (-1.0, 1.0)) == [(0.1, 0.2), (0.5, 0.5), (0.9, 1.0)]
    assert _over(t, y, None) == []


def test_sections_hook_adds_a_section(tmp_path, checker):
    from dyn_node.audit.check_report import write_check_report

    v = check_cli.check_file(checker, str(REACH))
    rec = check_cli.evidence_record(checker, v, "2026-01-01T00:00:00Z")
    files = write_check_report(rec, v, checker, tmp_path, sections=[
        lambda verdict, ch: (["<h2 id='retime'>Retimed</h2>"], {"retime.png": b"\x89PNG"})])
    page = (tmp_path / "report.html").read_text()
    assert page.index("id='retime'") > page.index("id='trajectory'")
    assert (tmp_path / "retime.png") in files and (tmp_path / "retime.png").read_bytes() == b"\x89PNG"


@pytest.mark.parametrize("mutate, word, banner, want_code", [
    (lambda ls: [ls[0], ls[1], ls[2].replace("-0.435", "nan", 1), *ls[3:]], "REJECTED", "REJECTED", 1),
    (lambda ls: [ls[0].replace("panda_joint7", "panda_joint8", 1), *ls[1:]], "UNREADABLE", "NOT CHECKED", 2)])
def test_a_file_that_cannot_be_checked_gets_a_report_with_nothing_to_plot(tmp_path, capsys, mutate, word,
                                                                          banner, want_code):
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(mutate(REACH.read_text().splitlines())) + "\n")
    code = check_cli.main([str(bad), "--robot-model", "panda", "--out", str(tmp_path / "o")])
    io = capsys.readouterr()
    assert f"bad.csv: {word}" in io.out + io.err
    page = (tmp_path / "o" / "bad" / "report.html").read_text()
    assert f">{banner}<small>" in page and "could not be checked" in page
    assert "data:image/png" not in page and not (tmp_path / "o" / "bad" / "trajectory.png").exists()
    assert code == want_code
