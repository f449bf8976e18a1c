"""What binds the time scale, named beside the largest ratio (issue 27): a minimum-jerk move
whose velocity needs k = 3 while its acceleration's larger ratio (6) needs only √6.

The oracle is the closed form of the quintic through zero velocity and acceleration at both
ends: peak |q̇| = 15/8·Δ/T at mid-segment, peak |q̈| = 10/√3·Δ/T² (and velocity scales with 1/k,
acceleration with 1/k²)."""
from __future__ import annotations

import math

import pytest

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.feasibility import STATUS_NAME, check_trajectory
from dyn_node.core.robot.model import load_model
from dyn_node.core.check.trajectory import validate_trajectory

DELTA, T = 1.0, 1.0
V_PEAK, A_PEAK = 15 / 8 * DELTA / T, 10 / math.sqrt(3) * DELTA / T ** 2
V_RATIO, A_RATIO = 3.0, 6.0      # velocity needs k = 3, acceleration √6 ≈ 2.45


@pytest.fixture(scope="module")
def verdict():
    limits = ("joint_limits:\n"
              f"  joint1: {{max_velocity: {V_PEAK / V_RATIO!r}, max_acceleration: {A_PEAK / A_RATIO!r},"
              " has_effort_limits: false}\n"
              "  joint2: {has_effort_limits: false, has_velocity_limits: false}\n")
    model = load_model(builtin="planar_2link", limits_yaml=limits)
    names = list(model.joint_names)
    zero = [0.0, 0.0]
    traj = validate_trajectory(names, names, [0.0, T], [[0.0, 0.0], [DELTA, 0.0]],
                               [zero, zero], [zero, zero])
    return check_trajectory(Dynamics(model), traj), names


def test_binding_names_the_kind_whose_slowdown_sets_k(verdict):
    r, names = verdict
    assert not r.feasible
    # the largest ratio is acceleration's (6 against velocity's 3) ...
    assert (r.worst_joint, r.worst_constraint) == (names[0], "acceleration")
    assert r.worst_ratio == pytest.approx(A_RATIO, rel=1e-4)
    # ... but velocity sets k = 3 (acceleration alone would need √6)
    assert r.time_scale == pytest.approx(V_RATIO, rel=1e-9)
    assert (r.binding_joint, r.binding_constraint) == (names[0], "velocity")
    assert r.time_scale_by_kind["acceleration"] == pytest.approx(math.sqrt(A_RATIO), rel=1e-4)
    assert r.message.endswith(f"run 3.00× slower: velocity of {names[0]} binds (2 violations)"), \
        r.message


def test_binding_keys_in_the_summary_status_and_the_dict(verdict):
    r, names = verdict
    summary = r.statuses("robot")[0]
    assert summary.name == STATUS_NAME
    assert summary.values["binding_joint"] == names[0]
    assert summary.values["binding_constraint"] == "velocity"
    assert summary.values["worst_constraint"] == "acceleration"   # unchanged beside it
    d = r.to_dict()
    assert (d["binding_joint"], d["binding_constraint"]) == (names[0], "velocity")
    # the older keys stay, with the same values
    assert (d["time_scale_joint"], d["time_scale_constraint"]) == (names[0], "velocity")


def test_client_verdict_parses_binding(verdict):
    pytest.importorskip("rclpy")
    from builtin_interfaces.msg import Time

    from dyn_node.ros.client import Verdict
    from dyn_node.ros.convert import diagnostic_array

    r, names = verdict
    v = Verdict.from_msg(diagnostic_array(r.statuses("robot"), Time(sec=1, nanosec=2)))
    assert (v.binding_joint, v.binding_constraint) == (names[0], "velocity")
    assert (v.worst_joint, v.worst_constraint) == (names[0], "acceleration")
    assert v.time_scale == pytest.approx(V_RATIO, rel=1e-6)


def test_rejected_status_has_empty_binding_keys():
    from dyn_node.core.check.feasibility import rejected_statuses
    from dyn_node.errors import TrajectoryError

    s = rejected_statuses(TrajectoryError("x", code="bad_times"))[0]
    assert s.values["binding_joint"] == "" and s.values["binding_constraint"] == ""


def test_evidence_entry_of_dyn_check_carries_binding():
    """dyn-check's evidence entry and line name what binds (panda_shake: effort is the largest
    ratio, velocity sets k)."""
    from conftest import REPO
    from dyn_node.audit import check as check_cli

    checker = check_cli.make_checker(robot_model="panda")
    v = check_cli.check_file(checker, str(REPO / "examples" / "trajectories" / "panda_shake.yaml"))
    rec = check_cli.evidence_record(checker, v, "2026-01-01T00:00:00Z")
    entry = rec["outputs"]["trajectories"][0]
    assert (entry["binding_joint"], entry["binding_constraint"]) == ("panda_joint2", "velocity")
    assert (entry["worst_joint"], entry["worst_constraint"]) == ("panda_joint2", "effort")
    assert "run 1.33× slower: velocity of panda_joint2 binds" in check_cli.verdict_line(v)
    from dyn_node.audit.evidence import validate
    validate(rec)
