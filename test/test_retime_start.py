"""The retimer from a moving start state (``retime(..., start=)`` with the first point ahead and
a non-zero velocity) against things we did not write: the closed-form minimum time of one joint
from a given velocity (triangle or trapezoid), TOPP-RA called directly with ``sd_start``, SciPy's
curves for the executed path, and the exact check with the start segment."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.interpolate import BPoly, CubicSpline
from scipy.spatial import cKDTree

from dyn_node.core.check.feasibility import StartState, check_trajectory
from dyn_node.core.check.trajectory import Trajectory, from_current_state
from dyn_node.retime import retime
from test_retime import UR5_WAYPOINTS, _quintic_scipy, one_joint, ur5

V, A = 1.0, 2.0           # test_retime's one joint: URDF velocity 1 rad/s, acceleration 2 rad/s²


def closed_form(v0: float, D: float) -> float:
    """Minimum time from q = 0 moving at v0 ≥ 0 to q = D at rest, |q̇| ≤ V, |q̈| ≤ A, for
    D ≥ v0²/(2A) (no overshoot): accelerate to the peak, (cruise,) brake at A. Triangle when
    the peak √((2AD + v0²)/2) ≤ V, else trapezoid."""
    peak = math.sqrt((2 * A * D + v0**2) / 2)
    if peak <= V:
        return (peak - v0) / A + peak / A
    cruise = D - (V**2 - v0**2) / (2 * A) - V**2 / (2 * A)
    return (V - v0) / A + V / A + cruise / V


def one_joint_case(v0: float, D: float, t0: float, q1: float, v1: float, T: float
                   ) -> tuple[Trajectory, StartState]:
    """Two quintic points ahead (q1 at t0, D at rest at T), the robot at 0 moving at v0."""
    traj = Trajectory(times=np.array([t0, T]), positions=np.array([[q1], [D]]),
                      velocities=np.array([[v1], [0.0]]), accelerations=np.zeros((2, 1)))
    return traj, StartState(positions=np.array([0.0]), velocities=np.array([v0]), age_s=0.0)


def executed(traj: Trajectory, st: StartState) -> BPoly:
    """The controller's curve from the state (SciPy: quintic through the points)."""
    ex = from_current_state(traj, st.positions, st.velocities)
    return BPoly.from_derivatives(ex.times, np.stack([ex.positions, ex.velocities,
                                                      ex.accelerations], axis=1))


CASES = {
    # trapezoid: accelerate from 0.5 to the velocity limit, cruise, brake
    "trapezoid": (0.5, 2.0, 0.5, 2.0 / 3.0, 0.3, 3.0),
    # triangle: peak 0.80 rad/s
    "triangle": (0.3, 0.3, 0.3, 0.1, 0.4, 1.5),
    # 0.9 rad/s, 0.2045 rad to go: brake at once (0.2025 rad at 2 rad/s²); at 0.995 of the limit
    # plus the window's lead there is no timing: retried at the limits themselves
    "brake": (0.9, 0.2045, 0.2, 0.14, 0.5, 0.45),
}


@pytest.mark.parametrize("name", sorted(set(CASES) - {"brake"}))
def test_closed_form_time_from_a_moving_start(name: str) -> None:
    v0, D, t0, q1, v1, T = CASES[name]
    traj, st = one_joint_case(v0, D, t0, q1, v1, T)
    # the closed form holds for any executed path that moves forward only
    qd = executed(traj, st).derivative()(np.linspace(0.0, T, 20001))[:-1, 0]
    assert np.all(qd > 0)
    dyn = one_joint(a=A)
    res = retime(dyn, traj, start=st, grid_points=2000, point_period=0.002,
                 uniform_fallback=False)
    assert res.feasible and res.method == "optimal"
    best = closed_form(v0, D)
    # T*: TOPP-RA from ṡ0 (the robot's speed along the path), to its grid (2000 steps)
    assert res.lower_bound == pytest.approx(best, rel=1e-5)
    # the answer: above the optimum, below it at 0.995 of the limits plus its windows
    assert best * (1 - 1e-9) <= res.duration_out <= best / 0.995 + res.smoothing_s
    out = res.trajectory
    # it starts at the robot's state: q, q̇, and q̈ = 0 as the controller assumes
    assert abs(out.times[0]) == 0.0
    assert abs(out.positions[0, 0]) <= 1e-12
    assert out.velocities[0, 0] == pytest.approx(v0, abs=1e-9)
    assert abs(out.accelerations[0, 0]) <= 1e-9
    # the exact check with the start: as returned, and with its first point ahead (the
    # controller's segment from the state then runs to the second point)
    assert check_trajectory(dyn, out, start=st).feasible
    ahead = Trajectory(times=out.times[1:], positions=out.positions[1:],
                       velocities=out.velocities[1:], accelerations=out.accelerations[1:])
    again = check_trajectory(dyn, ahead, start=st)
    assert again.feasible and again.start_segment == "checked"
    # and between the points (SciPy's quintic through them): the law's switch, which the
    # quintic rounds 1.4 % over at 2 ms points (issue 39), is within the limit
    pp = BPoly.from_derivatives(out.times, np.stack([out.positions, out.velocities,
                                                     out.accelerations], axis=1))
    t = np.linspace(out.times[0], out.times[-1], 200_001)
    assert np.max(np.abs(pp(t, 2))) <= A * (1 + 1e-6)
    assert np.max(np.abs(pp(t, 1))) <= V * (1 + 1e-6)


def test_brake_at_the_limits_is_never_answered_over_them() -> None:
    """0.9 rad/s with 0.2045 rad to go needs all the braking there is (0.2025 rad at 2 rad/s²):
    the search at the limits themselves rounds its corners with quintics that go 1–2 % over
    between the points (issue 39: the check sampled them only at the points), so whatever is
    answered must hold between them: SciPy's quintic through the points, densely sampled."""
    v0, D, t0, q1, v1, T = CASES["brake"]
    traj, st = one_joint_case(v0, D, t0, q1, v1, T)
    dyn = one_joint(a=A)
    res = retime(dyn, traj, start=st, grid_points=2000, point_period=0.002)
    assert res.feasible and check_trajectory(dyn, res.trajectory, start=st).feasible
    out = res.trajectory
    cols = [out.positions, out.velocities] + ([out.accelerations]
                                              if out.accelerations is not None else [])
    pp = BPoly.from_derivatives(out.times, np.stack(cols, axis=1))
    t = np.linspace(out.times[0], out.times[-1], 200_001)
    assert np.max(np.abs(pp(t, 2))) <= A * (1 + 1e-6)
    assert np.max(np.abs(pp(t, 1))) <= 1.0 * (1 + 1e-6)


def test_toppra_called_directly_with_sd_start() -> None:
    """TOPP-RA (toppra 0.6.10, its own spline and velocity and acceleration constraints) on the
    straight line 0 → D (one joint: every forward path is it), from sd_start = v0 to rest:
    the closed form, and our T* on the executed path."""
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as tc

    for name in ("trapezoid", "triangle"):
        v0, D, t0, q1, v1, T = CASES[name]
        line = ta.SplineInterpolator([0.0, D], [[0.0], [D]], bc_type="natural")
        cons = [tc.JointVelocityConstraint(np.array([[-V, V]])),
                tc.JointAccelerationConstraint(
                    np.array([[-A, A]]),
                    discretization_scheme=tc.DiscretizationType.Interpolation)]
        inst = algo.TOPPRA(cons, line, gridpoints=np.linspace(0.0, D, 2001),
                           solver_wrapper="seidel", parametrizer="ParametrizeConstAccel")
        direct = inst.compute_trajectory(v0, 0.0).duration
        traj, st = one_joint_case(v0, D, t0, q1, v1, T)
        res = retime(one_joint(a=A), traj, start=st, grid_points=2000, point_period=0.002,
                     uniform_fallback=False)
        assert direct == pytest.approx(closed_form(v0, D), rel=1e-5)
        assert res.lower_bound == pytest.approx(direct, rel=1e-5)


def test_no_braking_within_the_path_falls_back() -> None:
    """0.9 rad/s with 0.203 rad to go: braking takes 0.2025 rad, and the window's lead at ṡ0
    (1.8 mm) more: no timing along the executed path from that state (the note says so); the
    uniform stretch (whose start segment swings further) is the answer, checked with its
    start segment."""
    traj, st = one_joint_case(0.9, 0.203, 0.2, 0.14, 0.5, 0.45)
    dyn = one_joint(a=A)
    res = retime(dyn, traj, start=st, grid_points=2000, point_period=0.002)
    assert res.feasible and res.method == "uniform"
    assert "outside TOPP-RA's controllable set" in res.message
    assert res.check.start_segment == "checked" and res.check.feasible
    assert check_trajectory(dyn, res.trajectory, start=st).feasible
    assert res.lower_bound == pytest.approx(closed_form(0.9, 0.203), rel=2e-5)


def test_faster_than_the_velocity_limit_is_blocked() -> None:
    """1.2 rad/s against a 1 rad/s limit: no timing at all; nothing returned, the check's
    own reason in ``blocked``."""
    traj, st = one_joint_case(1.2, 1.0, 0.5, 0.5, 0.5, 2.0)
    dyn = one_joint(a=A)
    res = retime(dyn, traj, start=st)
    assert not res.feasible and res.trajectory is None
    check = check_trajectory(dyn, traj, start=st)
    assert math.isinf(check.time_scale)
    assert res.blocked and res.blocked == check.message.partition("; ")[2]
    assert "outside TOPP-RA's controllable set" in res.message


def test_ur5_moving_start_keeps_the_executed_path() -> None:
    """Six joints with effort, jerk and effort-rate limits, the robot in the middle of a quintic
    through test_retime's waypoints (SciPy's clamped spline, 0.6 s apart) when the rest of it
    arrives again as a new goal (0.3 s in: its state, the waypoints ahead): the answer starts at
    that state, passes the check with the start, stays within 1e-4 rad of the executed curve
    (SciPy), and is shorter than the uniform stretch."""
    dyn = ur5()
    t = np.arange(4) * 0.6
    spline = CubicSpline(t, UR5_WAYPOINTS, bc_type="clamped")
    now = 0.3
    traj = Trajectory(times=t[1:] - now, positions=UR5_WAYPOINTS[1:].copy(),
                      velocities=spline(t[1:], 1), accelerations=spline(t[1:], 2))
    q0, v0 = spline(now), spline(now, 1)
    st = StartState(positions=q0, velocities=v0, age_s=0.0)
    res = retime(dyn, traj, start=st)
    assert res.feasible and res.method == "optimal"
    out = res.trajectory
    np.testing.assert_allclose(out.positions[0], q0, atol=1e-12)
    np.testing.assert_allclose(out.velocities[0], v0, atol=1e-9)
    assert check_trajectory(dyn, out, start=st).feasible
    assert res.lower_bound * (1 - 1e-3) <= res.duration_out < res.duration_uniform
    ex = from_current_state(traj, q0, v0)
    curve = BPoly.from_derivatives(ex.times, np.stack([ex.positions, ex.velocities,
                                                      ex.accelerations], axis=1))
    tree = cKDTree(curve(np.linspace(0.0, ex.duration, 200_001)))
    dist, _ = tree.query(_quintic_scipy(out)(np.linspace(0.0, res.duration_out, 4001)),
                         p=np.inf)
    assert np.max(dist) <= 1e-4


def test_law_led_in_at_the_robots_speed() -> None:
    """The windows' average of a law led in at ṡ0 (constant before t = 0), by hand: for
    t ≤ 0 every window sees s = ṡ0·τ only, so s̄ = ṡ0·(t − (w + w2)/2), ṡ̄ = ṡ0, s̈̄ = 0; and
    over a law that holds ṡ0 on, the same line continues (no trace of t = 0)."""
    from dyn_node.retime import timing

    sd0, w, w2 = 0.8, 0.05, 0.008
    grid = np.linspace(0.0, 2.0, 201)
    lw = timing.law(grid, np.full(201, sd0**2), lead=sd0)
    t = np.array([-0.3, -0.01, 0.0, 0.02, 0.5, 1.0])
    s, sd, sdd = timing.smoothed(lw, w, t, w2)
    np.testing.assert_allclose(s, sd0 * (t - (w + w2) / 2), atol=1e-12)
    np.testing.assert_allclose(sd, sd0, atol=1e-12)
    np.testing.assert_allclose(sdd, 0.0, atol=1e-9)
    # at rest before t = 0 (lead 0, as before): the average starts from s = 0
    s0 = timing.smoothed(timing.law(grid, np.full(201, sd0**2)), w, np.array([0.0]), w2)[0]
    assert s0[0] == 0.0
