"""The gate's decisions without ROS (dyn_node.gate.decision): what is forwarded, rejected or retimed
in each mode, and the record the bag keeps."""
from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest

from dyn_node.core.check import feasibility
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import load_model
from dyn_node.core.check.trajectory import validate_trajectory
from dyn_node.errors import SettingsError, TrajectoryError
from dyn_node.gate.decision import FORWARDED, REJECTED, RETIMED, GateOptions, decide, rejected

READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])


def quintic(dq: float, duration: float, n: int = 31):
    """Joint 1 moves dq rad rest to rest in ``duration`` s (peak speed 15/8·dq/duration at the middle)."""
    model = load_model(builtin="panda")
    s = np.linspace(0.0, 1.0, n)
    d = np.zeros(7)
    d[0] = dq
    pos = READY + np.outer(10 * s**3 - 15 * s**4 + 6 * s**5, d)
    vel = np.outer((30 * s**2 - 60 * s**3 + 30 * s**4) / duration, d)
    acc = np.outer((60 * s - 180 * s**2 + 120 * s**3) / duration**2, d)
    traj = validate_trajectory(model.joint_names, list(model.joint_names), s * duration, pos, vel, acc)
    return Dynamics(model), traj


@pytest.fixture(scope="module")
def fast():
    return quintic(0.5, 0.15)  # 6.25 rad/s peak on joint 1, limit 2.175 rad/s


@pytest.fixture(scope="module")
def slow():
    return quintic(0.2, 1.5)


def test_modes_validated():
    with pytest.raises(SettingsError, match="gate.mode must be one of reject, retime, check"):
        GateOptions(mode="forward")


def test_feasible_goal_forwarded_unchanged_in_every_mode(slow):
    dyn, traj = slow
    for mode in ("reject", "check"):
        d = decide(dyn, traj, GateOptions(mode=mode), start=None)
        assert (d.decision, d.reason, d.feasible) == (FORWARDED, "", True)
        assert d.trajectory is traj and d.forwards


def test_infeasible_goal_rejected_with_the_verdict_line(fast):
    dyn, traj = fast
    d = decide(dyn, traj, GateOptions(mode="reject"), start=None)
    assert (d.decision, d.reason, d.feasible, d.trajectory) == (REJECTED, "infeasible", False, None)
    # closed form: quintic peak speed 15/8 · 0.5 rad / 0.15 s against the URDF's 2.175 rad/s
    ratio = 15 / 8 * 0.5 / 0.15 / 2.175
    assert d.worst[0:2] == ("panda_joint1", "velocity")
    assert d.worst[2] == pytest.approx(ratio, rel=1e-9)
    assert d.time_scale == pytest.approx(ratio, rel=1e-3)  # speed binds: k = ratio
    assert d.error_string == d.verdict
    assert d.verdict.startswith("infeasible: panda_joint1 velocity 287% of 2.17 rad/s")
    assert d.verdict.endswith("run 2.87× slower: velocity of panda_joint1 binds")


def test_check_mode_forwards_an_infeasible_goal_with_its_verdict(fast):
    dyn, traj = fast
    d = decide(dyn, traj, GateOptions(mode="check"), start=None)
    assert (d.decision, d.reason, d.feasible) == (FORWARDED, "infeasible", False)
    assert d.trajectory is traj and d.verdict.startswith("infeasible: ")


def test_start_state_checked_when_the_first_point_lies_ahead():
    """A goal whose first point is 0.1 s ahead and 0.3 rad away: the controller's move from the
    current state to it is checked too (a quintic from rest: peak 15/8·0.3/0.1 rad/s)."""
    dyn, traj = quintic(0.2, 1.5)
    ahead = type(traj)(times=traj.times + 0.1, positions=traj.positions, velocities=traj.velocities,
                       accelerations=traj.accelerations)
    start = feasibility.StartState(positions=READY - np.array([0.3, 0, 0, 0, 0, 0, 0]),
                                   velocities=np.zeros(7), age_s=0.0)
    d = decide(dyn, ahead, GateOptions(), start=start)
    assert d.decision == REJECTED and "velocity" in d.verdict
    assert decide(dyn, ahead, GateOptions(), start=None).decision == FORWARDED  # no state: not checked


def test_rejected_input_and_record(fast):
    d = rejected(TrajectoryError("joints not in the model: elbow", code="unknown_joints"))
    assert (d.decision, d.reason, d.error_string) == (REJECTED, "unknown_joints",
                                                      "rejected: joints not in the model: elbow")
    dyn, traj = fast
    rec = decide(dyn, traj, GateOptions(), start=None).to_dict(goal_id="g1", mode="reject",
                                                                joint_names=list(dyn.model.joint_names))
    back = json.loads(json.dumps(rec, allow_nan=False))
    assert (back["goal_id"], back["decision"], back["forwarded"], back["duration_out"]) == ("g1", "rejected", None, None)
    assert back["error_string"] == back["verdict"]
    fwd = decide(*quintic(0.2, 1.5), GateOptions(), start=None)
    rec = json.loads(json.dumps(fwd.to_dict(goal_id="g2", mode="reject", joint_names=["a"] * 7), allow_nan=False))
    np.testing.assert_array_equal(rec["forwarded"]["positions"], fwd.trajectory.positions)
    assert rec["forwarded"]["times"] == fwd.trajectory.times.tolist()


def test_retime_mode_without_the_retimer_rejects_with_the_reason(fast, slow, monkeypatch):
    monkeypatch.setitem(sys.modules, "dyn_node.retime", None)  # as where it is not installed
    dyn, traj = fast
    d = decide(dyn, traj, GateOptions(mode="retime"), start=None)
    assert (d.decision, d.reason) == (REJECTED, "retime_failed")
    assert "gate.mode retime needs dyn_node.retime" in d.error_string
    assert d.error_string.startswith(d.verdict)
    # a feasible goal that retime_all could not retime still goes as it came
    d = decide(*slow, GateOptions(mode="retime", retime_all=True), start=None)
    assert (d.decision, d.reason, d.trajectory is slow[1]) == (FORWARDED, "retime_failed", True)


def test_retime_mode_forwards_a_retimed_trajectory_that_passes_the_check(fast):
    dyn, traj = fast
    d = decide(dyn, traj, GateOptions(mode="retime"), start=None)
    assert d.decision == RETIMED and d.trajectory is not None
    again = feasibility.check_trajectory(dyn, d.trajectory)  # what is forwarded passes the check
    assert again.feasible
    np.testing.assert_allclose(d.trajectory.positions[[0, -1]], traj.positions[[0, -1]], atol=1e-9)
    assert traj.duration < d.duration_out <= d.duration_uniform * (1 + 1e-9)
    assert math.isclose(d.duration_in, traj.duration)


def test_retime_mode_uses_the_nodes_limit_margin(fast):
    """decide_goal passes the node's retime.limit_margin to the retimer: a lower share of each
    limit gives a longer forwarded trajectory (joint 1's speed binds), still passing the check."""
    from dyn_node.core.robot.settings import settings_from_mapping
    from dyn_node.gate.decision import decide_goal

    dyn, traj = fast
    names = list(dyn.model.joint_names)
    args = (names, traj.times.tolist(), traj.positions.tolist(), traj.velocities.tolist(),
            traj.accelerations.tolist())
    # a fresh state at the goal's first point, at rest (retime mode refuses a goal without one)
    at_rest = feasibility.StartState(traj.positions[0].copy(), np.zeros(7), 0.0)
    got = {m: decide_goal(dyn, settings_from_mapping({"retime.limit_margin": m}), GateOptions(mode="retime"),
                          *args, start=at_rest) for m in (0.995, 0.85)}
    assert all(d.decision == RETIMED for d in got.values())
    assert got[0.85].duration_out > got[0.995].duration_out * 1.05
    for d in got.values():
        assert feasibility.check_trajectory(dyn, d.trajectory).feasible


def test_retimed_answer_is_forwarded_only_when_its_check_passes(fast):
    """The retimer's own check of its answer decides (no second check of the same trajectory);
    a retimer that brings none gets its answer checked here. Either way, an answer that fails
    is never forwarded."""
    from dataclasses import replace

    from dyn_node.retime import retime

    dyn, traj = fast
    bad_check = feasibility.check_trajectory(dyn, traj)  # the fast goal's: infeasible
    assert not bad_check.feasible

    def claims_a_failed_check(*a, **k):
        return replace(retime(*a, **k), check=bad_check)

    def brings_the_input_unchecked(*a, **k):  # "retimed" to the infeasible input itself
        return replace(retime(*a, **k), trajectory=traj, check=None)

    for fn in (claims_a_failed_check, brings_the_input_unchecked):
        d = decide(dyn, traj, GateOptions(mode="retime"), start=None, retimer=fn)
        assert (d.decision, d.reason) == (REJECTED, "retime_failed"), fn.__name__
        assert "the retimed trajectory failed the re-check" in d.error_string, fn.__name__
    # the retimer's passing check is taken as it is: forwarded, and it passes when checked again
    d = decide(dyn, traj, GateOptions(mode="retime"), start=None, retimer=retime)
    assert d.decision == RETIMED and feasibility.check_trajectory(dyn, d.trajectory).feasible
    assert "T* not certified" in d.retime_message   # the gate does not wait for the bound


def _args(traj, names):
    return (names, traj.times.tolist(), traj.positions.tolist(), traj.velocities.tolist(),
            traj.accelerations.tolist())


def test_reject_and_retime_fail_closed_without_a_fresh_state(slow):
    """No state, or one older than max_state_age: refused (stale_state, state error) in reject and
    retime; check forwards it but says it was not judged from the state."""
    from dyn_node.core.robot.settings import Settings
    from dyn_node.gate.decision import STALE_STATE, decide_goal

    dyn, traj = slow
    args = _args(traj, list(dyn.model.joint_names))
    at = lambda age: feasibility.StartState(traj.positions[0].copy(), np.zeros(7), age)  # noqa: E731
    for mode in ("reject", "retime"):
        for start, why in ((None, "no joint_states"), (at(0.25), "joint_states 250 ms old")):
            d = decide_goal(dyn, Settings(), GateOptions(mode=mode, max_state_age=0.1), *args, start=start)
            assert (d.decision, d.reason, d.failure_label, d.forwards) == (REJECTED, STALE_STATE, "state error", False)
            assert d.error_string.startswith(f"rejected: stale_state: {why}"), d.error_string
            assert d.line == d.error_string  # "rejected: " once
    fresh = decide_goal(dyn, Settings(), GateOptions(mode="reject", max_state_age=0.1), *args, start=at(0.05))
    assert (fresh.decision, fresh.reason, fresh.failure_label) == (FORWARDED, "", "planning error")
    seen = decide_goal(dyn, Settings(), GateOptions(mode="check"), *args, start=None)
    assert (seen.decision, seen.reason, seen.trajectory is not None) == (FORWARDED, STALE_STATE, True)


def test_retime_plans_from_the_extrapolated_state_and_rechecks_from_a_fresh_one(fast):
    """The retimer starts from q + q̇·lead (the robot moves on while it works); its answer is
    checked from the state fresh() gives when it is ready, and refused without one."""
    from dyn_node.gate.decision import RetimePlan, extrapolate

    dyn, traj = fast
    q0 = traj.positions[0].copy()
    v = np.zeros(7)
    v[1] = 1e-3
    moving = feasibility.StartState(q0, v, 0.01)
    ahead = extrapolate(moving, 0.2)
    np.testing.assert_array_equal(ahead.positions, q0 + 0.2 * v)
    assert (ahead.age_s, extrapolate(moving, 0.0)) == (pytest.approx(0.21), moving)
    rest = feasibility.StartState(q0, np.zeros(7), 0.02)
    plan = RetimePlan(0.2, lambda: rest)
    d = decide(dyn, traj, GateOptions(mode="retime"), start=moving, plan=plan)
    assert d.decision == RETIMED and d.result is not None and d.result.feasible
    np.testing.assert_array_equal(plan.planned_from.positions, ahead.positions)
    assert plan.rechecked_from is rest
    gone = RetimePlan(0.2, lambda: None)
    d = decide(dyn, traj, GateOptions(mode="retime"), start=moving, plan=gone)
    assert (d.decision, d.reason) == (REJECTED, "retime_failed")
    assert "re-check: stale_state: no joint_states" in d.error_string


def test_a_goal_whose_first_point_is_away_from_the_robot_is_rejected_as_a_jump(slow):
    """Issue 36: a first point due at once (t = 0) 0.15 rad from the robot: the controller steps
    there (trajectory.cpp sample 147-169, jazzy ed360c9): rejected, the jump named, and the record
    says what was judged."""
    dyn, traj = slow
    robot = feasibility.StartState(READY + np.array([0, 0.15, 0, 0, 0, 0, 0]), np.zeros(7), 0.004)
    d = decide(dyn, traj, GateOptions(mode="reject"), start=robot)
    assert (d.decision, d.reason, d.feasible) == (REJECTED, "infeasible", False)
    assert d.verdict.startswith("infeasible: the first point is 0.15 rad from the robot (panda_joint2): "
                                "the controller steps to it at once"), d.verdict
    rec = d.to_dict(goal_id="g", mode="reject", joint_names=list(dyn.model.joint_names))
    assert rec["judged"]["start_jump_joint"] == "panda_joint2"
    assert rec["judged"]["start_jump"] == pytest.approx(0.15)
    assert rec["judged"]["interpolation_segments"] == "quintic 30"
    at_rest = decide(dyn, traj, GateOptions(mode="reject"), start=feasibility.StartState(READY, np.zeros(7), 0.004))
    assert at_rest.decision == FORWARDED


def test_a_goal_stamped_in_the_past_is_judged_from_inside_it(slow):
    """Issue 36: stamped 0.3 s before receipt, the controller starts 0.3 s into it (trajectory.cpp
    update 101-107, sample 171-206): from a robot resting at its first point that is a jump."""
    dyn, traj = slow
    robot = feasibility.StartState(READY.copy(), np.zeros(7), 0.002)
    timing = feasibility.Timing(stamp_s=500.0, receipt_s=500.3)
    d = decide(dyn, traj, GateOptions(mode="reject"), start=robot, timing=timing)
    assert d.decision == REJECTED and d.judged["start_offset_s"] == pytest.approx(0.3)
    assert d.judged["start_time"] == "at header.stamp"
    assert d.verdict.startswith("infeasible: started 0.3 s into it (past stamp), the trajectory is "), d.verdict
    assert decide(dyn, traj, GateOptions(mode="reject"), start=robot).decision == FORWARDED


def test_retime_mode_plans_a_junction_from_the_state_for_a_start_jump(slow):
    """Issue 38: a first point due at once 0.15 rad from the robot is refused in reject, and in
    retime answered by a plan that starts at the measured state (the junction) and passes the
    controller's own check from it (verified by SciPy's quintic through the answer's points)."""
    from scipy.interpolate import BPoly

    dyn, traj = slow
    robot = feasibility.StartState(READY + np.array([0, 0.15, 0, 0, 0, 0, 0]), np.zeros(7), 0.004)
    assert decide(dyn, traj, GateOptions(mode="reject"), start=robot).decision == REJECTED
    d = decide(dyn, traj, GateOptions(mode="retime"), start=robot)
    assert d.decision == RETIMED, d.error_string
    out = d.trajectory
    np.testing.assert_allclose(out.positions[0], robot.positions, atol=1e-9)   # starts at the robot
    np.testing.assert_allclose(out.positions[-1], traj.positions[-1], atol=1e-9)  # ends where asked
    again = feasibility.check_trajectory(dyn, out, start=robot)
    assert again.feasible and (again.summary_values().get("start_jump") or 0.0) < 0.01
    curve = BPoly.from_derivatives(out.times, np.stack([out.positions, out.velocities, out.accelerations], axis=1))
    t = np.linspace(out.times[0], out.times[-1], 20001)
    speed = np.abs(curve.derivative()(t)) / dyn.model.limits.velocity
    assert speed.max() <= 1.0 + 1e-6
