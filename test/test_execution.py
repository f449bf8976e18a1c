"""The execution model (dyn_node.core.check.execution) against joint_trajectory_controller's rules,
and the issue's findings through dyn-check, the services' core and the gate's decision.

Line numbers cite ros2_controllers, branch jazzy at ed360c9 (2026-08-16):
T = joint_trajectory_controller/src/trajectory.cpp, C = .../src/joint_trajectory_controller.cpp,
D = .../doc/trajectory.rst. Independent references: scipy's Hermite polynomials.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pytest
from scipy.interpolate import BPoly, CubicHermiteSpline

from dyn_node.audit.check import main as dyn_check
from dyn_node.audit.trajectory_files import format_trajectory, TrajectoryFile
from dyn_node.core.check import on_demand
from dyn_node.core.check.execution import (CUBIC, HOLD, HOLD_S, LINEAR, QUINTIC, START_AT_STAMP,
                                           START_ON_RECEIPT, ExecutionOptions, Timing, execute)
from dyn_node.core.check.start_segment import StartState
from dyn_node.core.check.trajectory import Trajectory, validate_trajectory
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import load_model
from dyn_node.core.robot.settings import Settings
from dyn_node.gate.decision import FORWARDED, REJECTED, GateOptions, decide

READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
T0 = np.array([0.0, 1.0, 2.0, 3.0])
P = np.array([[0.0, 0.0], [0.5, -0.2], [0.7, 0.1], [0.6, 0.1]])
V = np.array([[0.0, 0.0], [0.4, 0.1], [0.1, 0.2], [0.0, 0.0]])
A = np.array([[0.0, 0.0], [-0.3, 0.2], [0.5, -0.1], [0.0, 0.0]])
REST = StartState(P[0].copy(), np.zeros(2), 0.004)


def tr(times=T0, positions=P, velocities=None, accelerations=None, fields=None) -> Trajectory:
    return Trajectory(times=np.asarray(times, dtype=float), positions=np.asarray(positions, dtype=float),
                      velocities=velocities, accelerations=accelerations, fields=fields)


# ---------------------------------------------------------------------------------------------
# start time (T sample 125-134; C validate_trajectory_msg 1734-1750)

def test_zero_stamp_starts_on_receipt():
    """T 128-131: a zero stamp is replaced by the first update's time: no offset."""
    ex = execute(tr(velocities=V), REST, Timing(0.0, 1234.5))
    assert ex.start_rule == START_ON_RECEIPT and ex.offset_s == 0.0
    np.testing.assert_array_equal(ex.knots.times, T0)


def test_past_stamp_starts_inside_the_trajectory_at_its_interpolated_state():
    """T 101-107 and 171-206: a stamp 1.3 s before receipt puts the first update 1.3 s into the
    trajectory; its state there is the cubic's (scipy's Hermite spline through the points)."""
    ex = execute(tr(velocities=V), REST, Timing(100.0, 101.3))
    assert ex.start_rule == START_AT_STAMP and ex.offset_s == pytest.approx(1.3)
    ref = CubicHermiteSpline(T0, P, V)
    np.testing.assert_allclose(ex.knots.times, [0.0, 0.7, 1.7], atol=1e-12)
    np.testing.assert_allclose(ex.knots.positions[0], ref(1.3), atol=1e-12)
    np.testing.assert_allclose(ex.knots.velocities[0], ref(1.3, 1), atol=1e-12)
    t = np.linspace(0.0, 1.7, 41)
    q, v, a, _ = ex.pp.evaluate(t)
    np.testing.assert_allclose(q, ref(t + 1.3), atol=1e-12)
    np.testing.assert_allclose(a, ref(t + 1.3, 2), atol=1e-9)
    assert list(ex.point_knots) == [-1, -1, 1, 2] and not ex.start_segment
    # the command steps from the robot (at the first point) to that state: a jump
    np.testing.assert_allclose(ex.jump.position, ref(1.3) - P[0], atol=1e-12)
    assert ex.jump.exceeds_position


def test_future_stamp_lengthens_the_start_segment():
    """T 147-169: before stamp + time_from_start of the first point, the controller interpolates
    from the state at the first update to the first point, so a stamp 0.4 s ahead adds 0.4 s."""
    late = tr(times=T0 + 0.5, velocities=V)
    ex = execute(late, REST, Timing(50.4, 50.0))
    assert ex.start_segment and ex.offset_s == pytest.approx(-0.4)
    np.testing.assert_allclose(ex.knots.times, [0.0, 0.9, 1.9, 2.9, 3.9], atol=1e-12)


def test_stamped_end_in_the_past_is_refused_and_judged_as_if_stamped_zero():
    """C 1734-1750: a non-zero stamp whose end is already past is rejected; a zero stamp never is."""
    ex = execute(tr(velocities=V), REST, Timing(10.0, 13.5))
    assert [c for c, _ in ex.refusals] == ["ends_in_past"]
    assert ex.offset_s == 0.0 and ex.start_rule == START_ON_RECEIPT
    assert execute(tr(velocities=V), REST, Timing(0.0, 13.5)).refusals == ()
    assert execute(tr(velocities=V), REST, Timing(10.0, 12.9)).refusals == ()


# ---------------------------------------------------------------------------------------------
# the start (T sample 143-169, set_point_before_trajectory_msg 58-70; C update 292-313; D 94-97)

def test_first_point_reached_at_once_has_no_start_segment_and_jumps():
    """T 147-148 (and D 96-97): a first point at t = 0 is due at the first update: no segment
    from the state; the command steps there."""
    robot = StartState(P[0] + [0.15, 0.0], np.array([1.6, 0.0]), 0.01)
    ex = execute(tr(velocities=V), robot)
    assert not ex.start_segment and ex.knots.times[0] == 0.0
    np.testing.assert_allclose(ex.jump.position, [-0.15, 0.0], atol=1e-15)
    np.testing.assert_allclose(ex.jump.velocity, [-1.6, 0.0], atol=1e-15)
    assert ex.jump.size == pytest.approx(0.15) and ex.jump.joint == 0
    small = execute(tr(velocities=V), StartState(P[0] + [0.005, 0.0], np.zeros(2), 0.0))
    assert not small.jump.exceeds_position and not small.jump.exceeds_velocity   # start_tolerance 0.01


def test_first_point_ahead_is_reached_by_a_segment_from_the_state():
    """T 162-164: interpolated from the state (measured q, q̇; q̈ zero-filled by T 66-70 since the
    points have accelerations) to the first point: the quintic of scipy's Hermite basis."""
    late = tr(times=T0 + 0.5, velocities=V, accelerations=A)
    robot = StartState(np.array([-0.2, 0.1]), np.array([0.3, -0.1]), 0.02)
    ex = execute(late, robot)
    assert ex.start_segment and ex.modes == (QUINTIC,) * 4 and ex.jump is None
    assert ex.start_age_s == 0.02 and ex.fixed_start
    ref = BPoly.from_derivatives([0.0, 0.5], [np.stack([robot.positions, robot.velocities, np.zeros(2)]),
                                              np.stack([P[0], V[0], A[0]])])
    t = np.linspace(0.0, 0.5, 21)
    np.testing.assert_allclose(ex.pp.evaluate(t)[0], ref(t), atol=1e-12)
    np.testing.assert_allclose(ex.pp.evaluate(t)[2], ref(t, 2), atol=1e-9)
    # stretched by k: the robot's own velocity stays, the points' scale (start_segment.py's search)
    s = ex.stretched(2.0)
    np.testing.assert_array_equal(s.knots.velocities[0], robot.velocities)
    np.testing.assert_allclose(s.knots.velocities[1:], ex.knots.velocities[1:] / 2.0)


def test_desired_state_keeps_its_accelerations():
    """C 300-307: with interpolate_from_desired_state the state is the last command, whose
    accelerations the start segment begins from (quintic when the first point has them)."""
    late = tr(times=T0 + 0.5, velocities=V, accelerations=A)
    desired = StartState(P[0], np.zeros(2), 0.0, accelerations=np.array([2.0, -1.0]))
    ex = execute(late, desired, options=ExecutionOptions(interpolate_from_desired_state=True))
    np.testing.assert_allclose(ex.pp.evaluate(np.array([0.0]))[2][0], [2.0, -1.0], atol=1e-12)
    measured = execute(late, desired)
    np.testing.assert_allclose(measured.pp.evaluate(np.array([0.0]))[2][0], [0.0, 0.0], atol=1e-12)


# ---------------------------------------------------------------------------------------------
# per-segment interpolation (T interpolate_between_points 279-406; D 29-48)

@pytest.mark.parametrize("fields,mode", [((False, False), LINEAR), ((True, False), CUBIC),
                                         ((True, True), QUINTIC)])
def test_fields_choose_linear_cubic_quintic(fields, mode):
    """T 315-333 linear, 334-364 cubic, 365-406 quintic; each against scipy's polynomial with
    the same end conditions."""
    traj = tr(velocities=V if fields[0] else None, accelerations=A if fields[1] else None)
    ex = execute(traj)
    assert ex.modes == (mode,) * 3 and ex.interpolation == mode
    t = np.linspace(0.0, 3.0, 301)
    if mode == LINEAR:
        ref = np.column_stack([np.interp(t, T0, P[:, j]) for j in range(2)])
    elif mode == CUBIC:
        ref = CubicHermiteSpline(T0, P, V)(t)
    else:
        ref = BPoly.from_derivatives(T0, np.stack([P, V, A], axis=1))(t)
    np.testing.assert_allclose(ex.pp.evaluate(t)[0], ref, atol=1e-12)


def test_mixed_fields_pick_each_segments_mode_from_both_ends():
    """T 279-280: a field counts for a segment only when both its ends carry it (validation
    allows each point's field empty: C validate_trajectory_point_field)."""
    names = ["a", "b"]
    rows = lambda m, given: [list(r) if g else [] for r, g in zip(m, given)]  # noqa: E731
    traj = validate_trajectory(names, names, T0, P, rows(V, [True, True, False, True]),
                               rows(A, [True, True, False, True]))
    ex = execute(traj)
    assert ex.modes == (QUINTIC, LINEAR, LINEAR) and ex.interpolation == "mixed"
    assert ex.linear_segments == (1, 2) and ex.mode_counts() == {QUINTIC: 1, LINEAR: 2}
    traj = validate_trajectory(names, names, T0, P, rows(V, [True, True, True, True]),
                               rows(A, [True, True, False, True]))
    assert execute(traj).modes == (QUINTIC, CUBIC, CUBIC)


def test_accelerations_without_velocities_match_no_branch():
    """T 315, 334, 365: has_accel without has_velocity takes none of the three branches: refused
    (validation says so at the boundary; the model lists it for a trajectory built by hand)."""
    with pytest.raises(Exception, match="point 2: accelerations given without velocities"):
        validate_trajectory(["a", "b"], ["a", "b"], T0, P, [list(V[0]), list(V[1]), [], list(V[3])],
                            [list(r) for r in A])
    fields = np.array([[True, True], [True, True], [False, True], [False, True]])
    ex = execute(tr(velocities=V, accelerations=A, fields=fields))
    assert "accelerations_without_velocities" in [c for c, _ in ex.refusals]


def test_nonzero_end_velocity_is_refused_unless_allowed():
    """C 1716-1732: |v| > float epsilon at the last point is rejected unless
    allow_nonzero_velocity_at_trajectory_end."""
    Vend = V.copy()
    Vend[-1, 1] = 0.3
    assert [c for c, _ in execute(tr(velocities=Vend)).refusals] == ["nonzero_end_velocity"]
    allowed = ExecutionOptions(allow_nonzero_velocity_at_trajectory_end=True)
    assert execute(tr(velocities=Vend), options=allowed).refusals == ()
    Vend[-1, 1] = 1e-8          # below float epsilon (1.19e-7): the controller takes it as zero
    assert execute(tr(velocities=Vend)).refusals == ()


def test_single_point_goals_are_interpolated_to_then_held():
    """T 147-169 then 208-253: one point ahead is reached by the segment from the state and
    held; one due at once is a step to it, held."""
    one = tr(times=[0.8], positions=P[1:2], velocities=np.zeros((1, 2)))
    ex = execute(one, REST)
    assert ex.start_segment and ex.modes == (CUBIC,)
    np.testing.assert_allclose(ex.knots.times, [0.0, 0.8])
    np.testing.assert_allclose(ex.pp.evaluate(np.array([0.8, 5.0]))[0], [P[1], P[1]], atol=1e-12)
    now = execute(tr(times=[0.0], positions=P[1:2]), REST)
    assert now.modes == (HOLD,) and now.knots.times[-1] == HOLD_S
    np.testing.assert_allclose(now.jump.position, P[1] - P[0])


def test_linear_segments_step_the_velocity_at_each_point_and_the_end():
    """T 330-331: a linear segment's velocity is its slope; after the end the last point is held
    with zero velocity (T 240-244). Steps = slope differences."""
    ex = execute(tr())
    slopes = np.diff(P, axis=0) / np.diff(T0)[:, None]
    steps = ex.velocity_steps
    assert [s.point for s in steps] == [1, 2, 3]
    np.testing.assert_allclose(steps[0].step, slopes[1] - slopes[0], atol=1e-12)
    np.testing.assert_allclose(steps[-1].step, -slopes[-1], atol=1e-12)
    # from a state, a linear start segment also steps from the robot's velocity to its slope
    moving = execute(tr(times=T0 + 1.0), StartState(P[0] - 0.1, np.array([0.5, 0.0]), 0.0))
    first = moving.velocity_steps[0]
    assert first.point == -1 and first.time_s == 0.0
    np.testing.assert_allclose(first.step, [0.1 - 0.5, 0.1], atol=1e-12)
    assert execute(tr(velocities=V)).velocity_steps == ()


# ---------------------------------------------------------------------------------------------
# the issue's findings: dyn-check, the services' core (on_demand.check), the gate's decision

@lru_cache(maxsize=None)
def panda():
    model = load_model(builtin="panda")
    return model, Dynamics(model)


def reach(n: int = 5, duration: float = 4.0, velocities: bool = True, t0: float = 0.0):
    """READY → joint1 +0.3 rad, joint2 +0.2 rad → READY, gentle: (times, positions, velocities)."""
    s = np.linspace(0.0, 1.0, n)
    d = np.array([0.3, 0.2, 0, 0, 0, 0, 0])
    shape = np.sin(np.pi * s) ** 2
    dshape = 2 * np.pi * np.sin(np.pi * s) * np.cos(np.pi * s) / duration
    P_ = READY + np.outer(shape, d)
    V_ = np.outer(dshape, d) if velocities else None
    return t0 + s * duration, P_, V_


def ask(times, positions, velocities=None, start=None, timing=None):
    model, dyn = panda()
    names = list(model.joint_names)
    rows = None if velocities is None else [list(r) for r in velocities]
    return on_demand.check(dyn, Settings(), names, list(times), [list(r) for r in positions], rows,
                           start=start, timing=timing)


def gate(times, positions, velocities=None, start=None, timing=None):
    model, dyn = panda()
    names = list(model.joint_names)
    traj = validate_trajectory(names, names, times, positions, velocities)
    return decide(dyn, traj, GateOptions(mode="reject"), start=start, timing=timing)


def test_a_first_point_015_rad_from_the_robot_is_a_jump():
    times, Pr, Vr = reach()
    robot = StartState(READY + [0, 0.15, 0, 0, 0, 0, 0], np.zeros(7), 0.005)
    assert ask(times, Pr, Vr).feasible            # from its own first point: gentle
    out = ask(times, Pr, Vr, start=robot)
    assert out.result is not None and not out.feasible
    want = ("infeasible: the first point is 0.15 rad from the robot (panda_joint2): the controller "
            "steps to it at once")
    assert out.result.message.startswith(want), out.result.message
    assert out.result.time_scale == math.inf
    d = out.result.to_dict()
    assert d["start_jump"] == pytest.approx(0.15) and d["start_jump_joint"] == "panda_joint2"
    assert d["start_state"]["age_s"] == 0.005
    g = gate(times, Pr, Vr, start=robot)
    assert g.decision == REJECTED and g.verdict.startswith(want)
    assert g.judged["start_jump_joint"] == "panda_joint2"


def test_a_moving_robot_preempted_by_a_plan_at_rest_is_a_velocity_step():
    times, Pr, Vr = reach()
    robot = StartState(READY.copy(), np.array([1.6, 0, 0, 0, 0, 0, 0]), 0.002)
    out = ask(times, Pr, Vr, start=robot)
    assert not out.feasible and out.result.time_scale == math.inf
    assert out.result.message.startswith(
        "infeasible: the robot moves at 1.6 rad/s (panda_joint1) and the controller steps its "
        "command to 0 rad/s at once"), out.result.message
    assert gate(times, Pr, Vr, start=robot).decision == REJECTED


def test_a_goal_stamped_03_s_ago_is_judged_from_03_s_into_it():
    times, Pr, Vr = reach()
    robot = StartState(READY.copy(), np.zeros(7), 0.001)
    assert ask(times, Pr, Vr, start=robot).feasible        # from its start: at the robot, at rest
    timing = Timing(stamp_s=1000.0, receipt_s=1000.3)
    out = ask(times, Pr, Vr, start=robot, timing=timing)
    ref = CubicHermiteSpline(times, Pr, Vr)(0.3)           # where the controller starts
    d = out.result.to_dict()
    assert not out.feasible and d["start_offset_s"] == pytest.approx(0.3)
    assert d["start_time"] == START_AT_STAMP
    # the first point was passed before the start: its torque on the message's own motion
    # (scipy's cubic there), one row per message point all the same
    model, dyn = panda()
    spline = CubicHermiteSpline(times, Pr, Vr)
    assert out.result.waypoint_effort.shape == (len(times), 7)
    np.testing.assert_allclose(out.result.waypoint_effort[0],
                               dyn.rnea(spline(0.0), spline(0.0, 1), spline(0.0, 2)), rtol=0, atol=1e-9)
    assert d["start_jump"] == pytest.approx(np.abs(ref - READY).max(), rel=1e-9)
    assert out.result.message.startswith("infeasible: started 0.3 s into it (past stamp), the "
                                         "trajectory is "), out.result.message
    assert gate(times, Pr, Vr, start=robot, timing=timing).decision == REJECTED
    # a robot already where the trajectory is at 0.3 s (as if it had been executing it): feasible
    there = StartState(ref, CubicHermiteSpline(times, Pr, Vr)(0.3, 1), 0.001)
    assert ask(times, Pr, Vr, start=there, timing=timing).feasible


def test_positions_only_is_infeasible_with_velocity_steps_and_with_velocities_feasible(tmp_path, capsys):
    times, Pr, Vr = reach()
    only = ask(times, Pr)
    assert not only.feasible and only.result is not None       # judged (accepted), not rejected
    # sin² through 5 points: equal slopes on each side of points 1 and 3; steps at 2 and the end
    want = "infeasible: positions only: velocity steps at 2 points as the controller interpolates them"
    assert only.result.message.startswith(want), only.result.message
    assert only.result.to_dict()["velocity_step_points"] == "2, 4"
    assert gate(times, Pr).decision == REJECTED
    cubic = ask(times, Pr, Vr)
    assert cubic.feasible and cubic.result.interpolation == CUBIC, cubic.result.message
    assert gate(times, Pr, Vr).decision == FORWARDED
    # dyn-check: exit 1 (infeasible) for positions only, 0 with velocities, never 2 (unreadable)
    model, _ = panda()
    names = list(model.joint_names)
    files = {}
    for name, vel in (("only", None), ("cubic", Vr)):
        tf = TrajectoryFile(f"{name}.yaml", "yaml", names, [float(t) for t in times],
                            [list(map(float, r)) for r in Pr],
                            None if vel is None else [list(map(float, r)) for r in vel])
        files[name] = tmp_path / f"{name}.yaml"
        files[name].write_text(format_trajectory(tf))
    assert dyn_check([str(files["only"]), "--robot-model", "panda"]) == 1
    assert want in capsys.readouterr().out
    assert dyn_check([str(files["cubic"]), "--robot-model", "panda"]) == 0
