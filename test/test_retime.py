"""The retimer against things we did not write: closed-form bang-bang and S-curve times, MuJoCo's
mj_inverse, SciPy's splines and finite differences, TOPP-RA called directly."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.interpolate import BPoly, CubicSpline
from scipy.spatial import cKDTree

from benchmarks.mujoco_ref import MujocoInverse
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
from dyn_node.core.robot.model import load_model
from dyn_node.core.check.trajectory import Trajectory
from dyn_node.errors import TrajectoryError
from dyn_node.retime import RetimeResult, retime

# one joint about the vertical axis: gravity exerts no torque on it
ONE_JOINT = """<robot name="one"><link name="base"/>
  <link name="arm"><inertial><origin xyz="0.3 0 0"/><mass value="2.0"/>
    <inertia ixx="0.01" iyy="0.01" izz="0.02" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="j" type="revolute"><parent link="base"/><child link="arm"/><axis xyz="0 0 1"/>
    <limit lower="-10" upper="10" effort="0" velocity="1"/></joint></robot>"""


def one_joint(**limits: float) -> Dynamics:
    entry = {"has_acceleration_limits": True, "max_acceleration": limits["a"]}
    if "j" in limits:
        entry.update(has_jerk_limits=True, max_jerk=limits["j"])
    return Dynamics(load_model(urdf=ONE_JOINT).with_limits({"joint_limits": {"j": entry}}))


def ur5(effort_share: float = 0.4) -> Dynamics:
    m = load_model(builtin="ur5")
    lim = {n: {"has_acceleration_limits": True, "max_acceleration": 8.0,
               "has_effort_limits": True, "max_effort": effort_share * float(e),
               "has_jerk_limits": True, "max_jerk": 4000.0, "max_effort_rate": 1000.0}
           for n, e in zip(m.limits.names, m.limits.effort)}
    return Dynamics(m.with_limits({"joint_limits": lim}))


UR5_WAYPOINTS = np.array([[0.0, -1.2, 1.0, -1.0, -1.4, 0.0],
                          [1.2, -1.6, 1.6, -1.6, -1.0, 0.8],
                          [0.2, -1.0, 0.6, -0.6, -1.8, -0.6],
                          [-0.9, -1.5, 1.3, -1.2, -1.2, 0.4]])


def ur5_traj() -> Trajectory:
    return Trajectory(times=np.array([0.0, 0.6, 1.2, 1.8]), positions=UR5_WAYPOINTS.copy())


@pytest.fixture(scope="module")
def ur5_result() -> tuple[Dynamics, Trajectory, RetimeResult]:
    dyn = ur5()
    traj = ur5_traj()
    return dyn, traj, retime(dyn, traj)


# 0 → 2 rad along a straight line (cubic points with the mean speed at both ends: q linear in
# s); the optimal search answers rest to rest, which the closed forms are (the uniform stretch,
# left out, keeps the 0.4 rad/s end speeds)
LINE = Trajectory(times=np.array([0.0, 5.0]), positions=np.array([[0.0], [2.0]]),
                  velocities=np.array([[0.4], [0.4]]))


def test_bang_bang_time_one_joint() -> None:
    """Velocity 1 rad/s, acceleration 2 rad/s², 2 rad rest to rest: D/v + v/a = 2.5 s."""
    dyn = one_joint(a=2.0)
    res = retime(dyn, LINE, grid_points=2000, point_period=0.002, uniform_fallback=False)
    assert res.feasible and res.method == "optimal"
    # T*: the bang-bang time (to 1e-6 here: the grid's error vanishes on a straight line)
    assert res.lower_bound == pytest.approx(2.5, rel=1e-6)
    # the output: the bound, the 0.5 % limit margin, and the 2-point smoothing window (4 ms)
    assert 2.5 * (1 - 1e-6) <= res.duration_out <= 2.5 / 0.995 + 0.004 + 1e-6
    assert res.check.feasible and res.trajectory.jtc_interpolation == "quintic"


def test_s_curve_time_one_joint() -> None:
    """Jerk 20 rad/s³ too: the S-curve time D/v + v/a + a/j = 2.6 s, to 1 %."""
    dyn = one_joint(a=2.0, j=20.0)
    res = retime(dyn, LINE, grid_points=2000, point_period=0.002, uniform_fallback=False)
    assert res.feasible and res.method == "optimal"
    assert res.duration_out == pytest.approx(2.6, rel=0.01)
    assert res.duration_out >= 2.6 * (1 - 1e-3)    # faster would break a limit


def toppra_joint_constraints(model, coulomb: np.ndarray) -> list:
    """toppra's own velocity, acceleration and torque constraints for ``model``'s limits (torque:
    Pinocchio's rnea plus ``coulomb``·sign(q̇), toppra's friction), interpolation discretisation."""
    import pinocchio as pin
    import toppra.constraint as tc

    pm, lim = model.pin_model, model.limits
    data = pm.createData()
    interp = tc.DiscretizationType.Interpolation
    return [tc.JointVelocityConstraint(np.column_stack([-lim.velocity, lim.velocity])),
            tc.JointAccelerationConstraint(np.column_stack([-lim.acceleration, lim.acceleration]),
                                           discretization_scheme=interp),
            tc.JointTorqueConstraint(lambda q, v, a: pin.rnea(pm, data, q, v, a),
                                     np.column_stack([-lim.effort, lim.effort]),
                                     coulomb, discretization_scheme=interp)]


def test_lower_bound_is_toppra_directly() -> None:
    """TOPP-RA's grid optimum equals TOPP-RA with its own joint velocity, acceleration and
    torque constraints (torque from Pinocchio's RNEA) on the same curve and grid: a cubic from moving to moving
    (both ends at ṡ = 0, as TOPP-RA's default), which SciPy's spline with those end slopes is."""
    import pinocchio as pin
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as tc

    dyn = ur5()
    v0, v1 = np.full(6, 0.2), np.full(6, -0.1)
    traj = Trajectory(times=np.array([0.0, 3.0]), positions=UR5_WAYPOINTS[:2].copy(),
                      velocities=np.stack([v0, v1]))
    res = retime(dyn, traj)
    path = ta.SplineInterpolator(traj.times, traj.positions, bc_type=((1, v0), (1, v1)))
    cons = toppra_joint_constraints(dyn.model, np.zeros(dyn.model.nv))
    grid = np.linspace(0.0, traj.duration, 1001)
    inst = algo.TOPPRA(cons, path, gridpoints=grid, solver_wrapper="seidel",
                       parametrizer="ParametrizeConstAccel")
    direct = inst.compute_trajectory(0, 0)
    # TOPP-RA's optimum on the grid (T* before issue 39 item 4) is TOPP-RA's; T*, certified
    # against the grid, below it (test_retime_bound measures how far)
    assert res.grid_optimum == pytest.approx(direct.duration, rel=1e-6)
    assert 0.98 * direct.duration <= res.lower_bound <= direct.duration
    assert res.feasible and res.duration_out >= res.lower_bound * (1 - 1e-3)


def test_output_rechecked_with_controller_interpolation(ur5_result) -> None:
    dyn, traj, res = ur5_result
    assert res.feasible and res.method == "optimal"
    out = res.trajectory
    assert out.jtc_interpolation == "quintic"
    again = check_trajectory(dyn, out, FeasibilityOptions())
    assert again.feasible and again.interpolation == "quintic"
    assert again.time_scale == pytest.approx(res.check.time_scale, rel=1e-12)
    # the input is too fast (0.6 s per waypoint); the output beats its uniform stretch
    assert not res.input_check.feasible
    assert res.duration_out < res.duration_uniform


def _quintic_scipy(out: Trajectory) -> BPoly:
    """joint_trajectory_controller's quintic through the points, built by SciPy."""
    y = np.stack([out.positions, out.velocities, out.accelerations], axis=1)   # N×3×nv
    return BPoly.from_derivatives(out.times, y)


def test_path_kept(ur5_result) -> None:
    """Every sample of the output's quintic lies within 1e-4 rad of the input curve (SciPy's
    clamped cubic spline, the check's curve for positions-only points)."""
    _, traj, res = ur5_result
    curve = CubicSpline(traj.times, traj.positions, bc_type="clamped")
    s_dense = np.linspace(0.0, traj.duration, 100_001)
    tree = cKDTree(curve(s_dense))
    q_out = _quintic_scipy(res.trajectory)(np.linspace(0, res.duration_out, 3001))
    _, near = tree.query(q_out, p=np.inf)
    worst = 0.0
    for q, i in zip(q_out, near):      # refine between the nearest sample's neighbours
        fine = np.linspace(s_dense[max(i - 1, 0)], s_dense[min(i + 1, len(s_dense) - 1)], 201)
        worst = max(worst, float(np.min(np.max(np.abs(curve(fine) - q), axis=1))))
    assert worst <= 1e-4
    # and the curve is traversed whole: same ends
    np.testing.assert_allclose(res.trajectory.positions[[0, -1]], traj.positions[[0, -1]],
                               atol=1e-12)


def test_torques_against_mujoco(ur5_result) -> None:
    """The check's torques at the output's points equal MuJoCo's mj_inverse, and MuJoCo's
    torques at dense samples of the output stay within the effort limits; their finite
    differences within the effort-rate limit, and the quintic's jerk within the jerk limit."""
    dyn, _, res = ur5_result
    out = res.trajectory
    mj = MujocoInverse(dyn.model)
    tau_mj = np.array([mj.rnea(q, v, a) for q, v, a in
                       zip(out.positions, out.velocities, out.accelerations)])
    np.testing.assert_allclose(res.check.waypoint_effort, tau_mj, atol=1e-6)
    lim = dyn.model.limits
    pp = _quintic_scipy(out)
    h = 2e-4
    t = np.arange(0.0, out.duration, h)
    Q, V, A = pp(t), pp(t, 1), pp(t, 2)
    tau = np.array([mj.rnea(q, v, a) for q, v, a in zip(Q, V, A)])
    assert np.max(np.abs(tau) / lim.effort) <= 1.0 + 1e-6
    rate = np.diff(tau, axis=0) / h
    assert np.max(np.abs(rate) / lim.effort_rate) <= 1.0 + 0.01
    jerk = np.diff(A, axis=0) / h
    assert np.max(np.abs(jerk) / lim.jerk) <= 1.0 + 0.01
    assert np.max(np.abs(V) / lim.velocity) <= 1.0 + 1e-6
    assert np.max(np.abs(A) / lim.acceleration) <= 1.0 + 1e-6


def test_untimed_waypoints() -> None:
    """All times zero: the clamped C² spline over the chord length (∞-norm of each step)."""
    dyn = ur5()
    traj = Trajectory(times=np.zeros(4), positions=UR5_WAYPOINTS.copy())
    res = retime(dyn, traj)
    assert res.feasible and res.duration_in == 0.0
    chord = np.concatenate(([0.0], np.cumsum(np.max(np.abs(np.diff(UR5_WAYPOINTS, axis=0)),
                                                    axis=1))))
    curve = CubicSpline(chord, UR5_WAYPOINTS, bc_type="clamped")
    # the output's points lie on that curve: each at the nearest of a dense sampling
    dist, _ = cKDTree(curve(np.linspace(0, chord[-1], 400_001))).query(
        res.trajectory.positions, p=np.inf)
    assert np.max(dist) < 1e-4


def test_bad_inputs() -> None:
    dyn = ur5()
    bad = UR5_WAYPOINTS.copy()
    bad[1, 2] = math.nan
    with pytest.raises(TrajectoryError) as e:
        retime(dyn, Trajectory(times=np.arange(4.0), positions=bad))
    assert e.value.code == "non_finite"
    with pytest.raises(TrajectoryError) as e:
        retime(dyn, Trajectory(times=np.zeros(1), positions=UR5_WAYPOINTS[:1]))
    assert e.value.code == "too_few_points"
    still = Trajectory(times=np.arange(3.0), positions=np.repeat(UR5_WAYPOINTS[:1], 3, axis=0))
    res = retime(dyn, still)
    assert res.feasible and res.trajectory is still and "nothing to move" in res.message


def test_position_limit_on_the_path_is_blocked() -> None:
    dyn = ur5()
    m = dyn.model
    j = 1
    P = UR5_WAYPOINTS.copy()
    P[1, j] = m.limits.position_upper[j] + 0.05
    res = retime(dyn, Trajectory(times=np.arange(4.0) * 2, positions=P))
    assert not res.feasible and res.trajectory is None
    assert "position" in res.blocked and "no slowdown helps" in res.blocked


def test_gravity_above_the_limit_is_blocked() -> None:
    """Torque limits at 10 %: holding the arm out needs more than that; no slowdown helps."""
    dyn = ur5(effort_share=0.1)
    res = retime(dyn, ur5_traj())
    assert not res.feasible and res.trajectory is None
    assert "gravity" in res.blocked and math.isnan(res.duration_uniform)


def test_stops_and_reversals_are_retimed_by_pieces() -> None:
    """Quintic points at rest (v = a = 0) that turn back: the path is cut at each stop, each
    piece retimed by arc length, and the answer stops there too, on the input's curve (SciPy's
    quintic Hermite through the points)."""
    dyn = ur5()
    P = np.array([UR5_WAYPOINTS[0], UR5_WAYPOINTS[1], UR5_WAYPOINTS[0], UR5_WAYPOINTS[2]])
    z = np.zeros_like(P)
    traj = Trajectory(times=np.array([0.0, 0.5, 1.0, 1.5]), positions=P, velocities=z,
                      accelerations=z)
    res = retime(dyn, traj)
    assert res.feasible and res.method == "optimal"
    out = res.trajectory
    assert check_trajectory(dyn, out).feasible
    assert res.lower_bound * (1 - 1e-3) <= res.duration_out < res.duration_uniform
    # every waypoint is passed at rest (v = a = 0 there, as the input stops)
    for q in P[1:-1]:
        i = int(np.argmin(np.max(np.abs(out.positions - q), axis=1)))
        assert np.max(np.abs(out.positions[i] - q)) < 1e-9
        assert np.max(np.abs(out.velocities[i])) < 1e-9
    curve = BPoly.from_derivatives(traj.times, np.stack([P, z, z], axis=1))
    dense = curve(np.linspace(0.0, traj.duration, 300_001))
    samples = _quintic_scipy(out)(np.linspace(0.0, res.duration_out, 4001))
    dist, _ = cKDTree(dense).query(samples, p=np.inf)
    assert np.max(dist) <= 1e-4


def test_start_state_at_rest_and_moving() -> None:
    """First point 0.5 s ahead: from a state at rest the answer starts at the robot's position;
    from a moving state too, with its velocity (the optimal search on the executed path;
    test_retime_start has the closed forms), shorter than the uniform stretch."""
    from dyn_node.core.check.feasibility import StartState

    dyn = ur5()
    traj = Trajectory(times=np.array([0.5, 1.1, 1.7, 2.3]), positions=UR5_WAYPOINTS.copy())
    q0 = UR5_WAYPOINTS[0] + np.array([0.1, -0.05, 0.05, 0.0, 0.1, -0.1])
    rest = StartState(positions=q0, velocities=np.zeros(6), age_s=0.0)
    res = retime(dyn, traj, start=rest)
    assert res.feasible and res.method == "optimal"
    np.testing.assert_allclose(res.trajectory.positions[0], q0, atol=1e-12)
    np.testing.assert_allclose(res.trajectory.velocities[0], 0.0, atol=1e-12)
    assert check_trajectory(dyn, res.trajectory, start=rest).feasible
    moving = StartState(positions=q0, velocities=np.full(6, 0.05), age_s=0.0)
    res = retime(dyn, traj, start=moving)
    assert res.feasible and res.method == "optimal"
    np.testing.assert_allclose(res.trajectory.positions[0], q0, atol=1e-12)
    np.testing.assert_allclose(res.trajectory.velocities[0], 0.05, atol=1e-9)
    assert check_trajectory(dyn, res.trajectory, start=moving).feasible
    assert res.duration_out < res.duration_uniform


def test_input_check_given_or_made_without_the_payload_margin(ur5_result) -> None:
    """The input's check: made here without the payload margin (NaN: not computed), its time
    scale the full check's; or the caller's own (dyn-check, the gate), then not made again and
    the answer the same; a check of another trajectory is refused."""
    dyn, traj, res = ur5_result
    full = check_trajectory(dyn, traj)
    assert math.isnan(res.input_check.payload_margin_kg) and math.isfinite(full.payload_margin_kg)
    assert res.input_check.time_scale == full.time_scale
    # positions only, as the controller runs them (linear): velocity steps no slowdown removes;
    # the uniform stretch is the retimer's path's, the C² spline through the points
    assert full.time_scale == math.inf and full.to_dict()["velocity_steps"] == 3
    from dyn_node.core.check.trajectory import clamped_spline_velocities
    path = check_trajectory(dyn, Trajectory(times=traj.times, positions=traj.positions,
                                            velocities=clamped_spline_velocities(traj.times, traj.positions)))
    assert res.duration_uniform == pytest.approx(traj.duration * path.time_scale, rel=1e-12)
    again = retime(dyn, traj, input_check=full)
    assert again.input_check is full
    assert again.duration_out == res.duration_out and again.lower_bound == res.lower_bound
    other = check_trajectory(dyn, Trajectory(times=traj.times * 2, positions=traj.positions))
    with pytest.raises(TrajectoryError) as err:
        retime(dyn, traj, input_check=other)
    assert err.value.code == "bad_options"


def test_point_screen_finds_the_runs_over_the_share() -> None:
    """The screen before the exact check: one entry per joint and run of points whose |q̈|
    exceeds the share of the limit (2 rad/s², share 0.9975: 1.995), with the run's first and
    peak times and its length; nothing where no point is over."""
    from dyn_node.retime.retimer import _screen

    dyn = one_joint(a=2.0)
    acc = np.array([0.5, 1.99, -2.5, 2.6, 0.1, 2.2, 1.995])
    t = np.arange(7) * 0.004
    pts = Trajectory(times=t, positions=np.zeros((7, 1)), velocities=np.zeros((7, 1)),
                     accelerations=acc[:, None])
    hits = _screen(dyn, pts, 0.9975)
    assert [(h.kind, h.first_time_s, h.peak_time_s, h.duration_s) for h in hits] == [
        ("acceleration", t[2], t[3], t[3] - t[2]), ("acceleration", t[5], t[5], 0.0)]
    assert hits[0].peak_value / hits[0].limit == pytest.approx(2.6 / 2.0 / 0.9975, rel=1e-12)
    calm = Trajectory(times=t, positions=np.zeros((7, 1)), velocities=np.zeros((7, 1)),
                      accelerations=np.clip(acc, -1.99, 1.99)[:, None])
    assert _screen(dyn, calm, 0.9975) == []
