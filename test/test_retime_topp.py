"""The retimer's reused TOPP-RA instance (:class:`dyn_node.retime.topp.Reach`) under caps on ṡ²
against TOPP-RA run from scratch with the cap inside its own rows (its LP's x bound)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import toppra.algorithm as algo

from dyn_node.retime import topp
from dyn_node.retime.path import ArcPath, build_path
from test_retime import ur5, ur5_traj


def _constraint(rows: topp.Rows, xmax: np.ndarray, dof: int):
    """TOPP-RA's own linear constraint on our rows (its interpolation discretisation)."""
    from toppra.constraint import DiscretizationType, LinearConstraint
    from toppra.constraint.linear_constraint import canlinear_colloc_to_interpolate

    class _Linear(LinearConstraint):
        def __init__(self) -> None:
            super().__init__()
            self.dof = dof
            self.set_discretization_type(DiscretizationType.Interpolation)
            self.identical = True

        def compute_constraint_params(self, path, gridpoints, *args, **kwargs):
            m = rows.g.shape[0]
            xb = np.column_stack([np.zeros_like(xmax), xmax])
            return canlinear_colloc_to_interpolate(rows.a, rows.b, rows.c, np.eye(m), rows.g,
                                                   None, xb, gridpoints, identical=True)

    return _Linear()


def _toppra_path(path):
    """Our path as TOPP-RA's geometric path."""
    from toppra.interpolator import AbstractGeometricPath

    class _P(AbstractGeometricPath):
        def __call__(self, s, order=0):
            s = np.atleast_1d(np.asarray(s, dtype=float))
            return path.derivatives(s)[order] if order < 3 else path.pp.evaluate(s)[3]

        @property
        def dof(self):
            return path.nv

        @property
        def path_interval(self):
            return np.array([path.pp.breaks[0], path.pp.breaks[-1]])

    return _P()


def _direct(path, grid, rows, cap):
    """TOPP-RA's own controllable sets and forward pass, the cap in the x bound of its LP."""
    cons = _constraint(rows, np.minimum(np.minimum(rows.xmax, cap), 1e12), path.nv)
    inst = algo.TOPPRA([cons], _toppra_path(path), gridpoints=grid,
                       solver_wrapper="seidel", parametrizer="ParametrizeConstAccel")
    _, sd, _ = inst.compute_parameterization(0.0, 0.0)
    return np.asarray(sd) ** 2


def test_caps_on_a_reused_instance_match_toppra_from_scratch() -> None:
    dyn = ur5()
    path = ArcPath(build_path(ur5_traj()))
    grid = np.linspace(0.0, path.length, 401)
    rows = topp.joint_rows(dyn, path, grid, scale=0.995)
    reach = topp.Reach(path, grid, rows)
    x0 = reach.solve()
    assert np.allclose(x0, _direct(path, grid, rows, np.full(len(grid), np.inf)),
                       rtol=1e-9, atol=1e-12)
    cap = np.full(len(grid), np.inf)
    # two successive caps, the second below the first's region: each a partial backward pass
    for lo, hi in ((250, 300), (60, 90)):
        cap[lo:hi] = np.minimum(cap[lo:hi], 0.5 * x0[lo:hi])
        x = reach.solve(cap=cap)
        ref = _direct(path, grid, rows, cap)
        assert np.allclose(x, ref, rtol=1e-9, atol=1e-12)
        assert np.all(x[lo:hi] <= cap[lo:hi] * (1 + 1e-12))
        assert topp.duration(grid, x) > topp.duration(grid, x0)
    # a cap no timing can meet from rest (ṡ² below zero): not controllable
    assert reach.solve(cap=np.full(len(grid), -1.0)) is None


def _toppra_line(velocity: float, acceleration: float) -> float:
    """TOPP-RA's own duration on test_retime's LINE (its cubic, 2000 steps) with one joint's
    velocity and acceleration limits."""
    import toppra as ta
    import toppra.constraint as tc

    from test_retime import LINE

    path = ta.SplineInterpolator(LINE.times, LINE.positions,
                                 bc_type=((1, LINE.velocities[0]), (1, LINE.velocities[1])))
    cons = [tc.JointVelocityConstraint(np.array([[-velocity, velocity]])),
            tc.JointAccelerationConstraint(np.array([[-acceleration, acceleration]]),
                                           discretization_scheme=tc.DiscretizationType.Interpolation)]
    inst = algo.TOPPRA(cons, path, gridpoints=np.linspace(0.0, LINE.duration, 2001),
                       solver_wrapper="seidel", parametrizer="ParametrizeConstAccel")
    return inst.compute_trajectory(0, 0).duration


# one prismatic joint along x: the link translates, so any point's acceleration is q̈·x̂
SLIDE = """<robot name="slide"><link name="base"/>
  <link name="arm"><inertial><origin xyz="0 0 0"/><mass value="2.0"/>
    <inertia ixx="0.01" iyy="0.01" izz="0.02" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="j" type="prismatic"><parent link="base"/><child link="arm"/><axis xyz="1 0 0"/>
    <limit lower="-10" upper="10" effort="0" velocity="1"/></joint></robot>"""


# (urdf, limits, T*, the joint velocity and acceleration limits TOPP-RA gets for the same
# bound, the answer's largest duration ÷ T*, the check's place)
# - a point 0.5 m from the one joint's axis limited to 0.25 m/s is a 0.5 rad/s joint speed
#   limit: T* = D/v + v/a = 2/0.5 + 0.5/2 = 4.25 s (2.5 s without); within 2 % (a 0.3 %
#   acceleration overshoot at the last switch may cost a capped round)
# - a point on the sliding link limited to 2 m/s² (gravity excluded), velocity 1 m/s:
#   T* = 2/1 + 1/2 = 2.5 s (2 s without); the retiming keeps inside the disc (limit × 0.995
#   × cos(π/24)) and the window: within 3 %
# - the mounting's force on the sliding 2 kg link limited to 20 N: (m·q̈, 0, m·g), so
#   |q̈| ≤ √((20/2)² − 9.81²) = 1.9401 m/s², T* = 2/1 + 1/1.9401 = 2.5154 s; the retiming's
#   share of the force (× 0.995) leaves √(9.95² − 9.81²)·cos(π/24) = 1.649 m/s² (gravity
#   takes most of the force): 2 + 1/1.649 = 2.606 s and the window, within 4.5 %
BASE_ACC = math.sqrt((20.0 / 2.0) ** 2 - 9.81**2)
# - the mounting's moment on test_retime's one joint (2 kg at 0.3 m from the vertical axis,
#   I = 0.02 + 2·0.3² = 0.2 kg·m²) limited to 6 N·m: gravity's 0.3·2·9.81 = 5.886 N·m about a
#   horizontal axis and I·q̈ about the vertical one (the centripetal force passes through the
#   axis), so |q̈| ≤ √(6² − 5.886²)/0.2 = 5.819 rad/s², T* = 2/1 + 1/5.819 s
MOMENT_ACC = math.sqrt(6.0**2 - (0.3 * 2.0 * 9.81) ** 2) / 0.2
# - a 1 kg payload held on the sliding link, the grip's normal axis vertical, μ·grip·faces =
#   0.5·2·2 = 2 N: the grasp supplies (q̈, 0, 9.81) N, its part across the normal axis is q̈,
#   so |q̈| ≤ 2 m/s² and T* = 2/1 + 1/2 = 2.5 s
GRIP = {"frame": "arm", "normal_axis": [0.0, 0.0, 1.0], "friction_coefficient": 0.5,
        "grip_force": 2.0, "faces": 2}
FRAME_CASES = {
    "frame_speed": ("ONE_JOINT", {"joint_limits": {"j": {"has_acceleration_limits": True,
                                                         "max_acceleration": 2.0}},
                                  "frame_limits": {"arm": {"point": [0.5, 0.0, 0.0],
                                                           "max_linear_speed": 0.25}}},
                    4.25, 0.5, 2.0, 1.02, "arm"),
    "frame_acceleration": ("SLIDE", {"joint_limits": {"j": {}},
                                     "frame_limits": {"arm": {
                                         "point": [0.1, 0.2, 0.0],
                                         "max_linear_acceleration": 2.0}}},
                           2.5, 1.0, 2.0, 1.03, "arm"),
    "base_force": ("SLIDE", {"joint_limits": {"j": {}}, "base_limits": {"max_force": 20.0}},
                   2.0 + 1.0 / BASE_ACC, 1.0, BASE_ACC, 1.045, "base_limits"),
    "base_moment": ("ONE_JOINT", {"joint_limits": {"j": {}}, "base_limits": {"max_moment": 6.0}},
                    2.0 + 1.0 / MOMENT_ACC, 1.0, MOMENT_ACC, 1.03, "base_limits"),
    "grasp_slip": ("SLIDE+1kg", {"joint_limits": {"j": {}}, "grasp": GRIP},
                   2.5, 1.0, 2.0, 1.03, "grasp"),
}


@pytest.mark.parametrize("kind", sorted(FRAME_CASES))
def test_frame_limit_bounds_the_lower_bound(kind: str) -> None:
    """A frame or mounting limit on one joint that amounts to a joint limit: T* is the closed-form
    bang-bang time and equals TOPP-RA run directly with that joint limit on the same line; the
    answer passes the check's kind near its limit (97–100 %)."""
    from dyn_node.core.check.feasibility import check_trajectory
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.robot.model import load_model
    from dyn_node.retime import retime
    import test_retime

    from dyn_node.core.robot.model import Payload

    name, limits, t_star, velocity, acceleration, slack, place = FRAME_CASES[kind]
    urdf = test_retime.ONE_JOINT if name == "ONE_JOINT" else SLIDE
    extra = {"payload": Payload(1.0, (0.0, 0.0, 0.0), "arm")} if name.endswith("+1kg") else {}
    dyn = Dynamics(load_model(urdf=urdf, **extra).with_limits(limits))
    res = retime(dyn, test_retime.LINE, grid_points=2000, point_period=0.002,
                 uniform_fallback=False)
    assert res.lower_bound == pytest.approx(t_star, rel=1e-6)
    # TOPP-RA's optimum on the grid (T* before issue 39 item 4) is TOPP-RA's, T* below it
    assert res.grid_optimum == pytest.approx(_toppra_line(velocity, acceleration), rel=1e-6)
    assert res.lower_bound <= res.grid_optimum
    assert res.feasible and res.method == "optimal"
    assert t_star * (1 - 1e-6) <= res.duration_out <= t_star * slack
    check = check_trajectory(dyn, res.trajectory)
    assert check.feasible
    assert 0.97 <= check.per_frame[place][kind]["ratio"] <= 1.0


def test_kinetic_energy_bounds_the_lower_bound() -> None:
    """Robot kinetic energy ≤ 0.025 J on the one joint (I = izz + m·r² = 0.02 + 2·0.3² =
    0.2 kg·m² about its axis): q̇ ≤ √(2E/I) = 0.5 rad/s, so T* is again 4.25 s."""
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.check.feasibility import check_trajectory
    from dyn_node.core.robot.model import load_model
    from dyn_node.retime import retime
    from test_retime import LINE, ONE_JOINT

    limits = {"joint_limits": {"j": {"has_acceleration_limits": True, "max_acceleration": 2.0}},
              "robot_limits": {"max_kinetic_energy": 0.025}}
    dyn = Dynamics(load_model(urdf=ONE_JOINT).with_limits(limits))
    res = retime(dyn, LINE, grid_points=2000, point_period=0.002, uniform_fallback=False)
    assert res.lower_bound == pytest.approx(4.25, rel=1e-6)
    assert res.feasible and 4.25 * (1 - 1e-6) <= res.duration_out <= 4.25 * 1.02
    check = check_trajectory(dyn, res.trajectory)
    assert check.feasible
    assert 0.95 <= check.per_frame["robot_limits"]["kinetic_energy"]["ratio"] <= 1.0


def test_task_wrench_torque_in_the_effort_rows() -> None:
    """A 0.5 N·m task torque about the one joint's axis with a 1 N·m effort limit (I = 0.2
    kg·m²): |q̈| ≤ (1 ∓ 0.5)/0.2 = 2.5 one way and 7.5 the other, so rest to rest over 2 rad
    at 1 rad/s takes D/v + v/(2·2.5) + v/(2·7.5) = 2.2667 s whichever way the torque points
    (without it 2 + 2·1/(2·5) = 2.2 s)."""
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.check.feasibility import check_trajectory
    from dyn_node.core.robot.model import load_model
    from dyn_node.retime import retime
    from test_retime import LINE, ONE_JOINT

    limits = {"joint_limits": {"j": {"has_effort_limits": True, "max_effort": 1.0}},
              "task_wrench": {"frame": "arm", "force": [0.0, 0.0, 0.0],
                              "torque": [0.0, 0.0, 0.5]}}
    dyn = Dynamics(load_model(urdf=ONE_JOINT).with_limits(limits))
    res = retime(dyn, LINE, grid_points=2000, point_period=0.002, uniform_fallback=False)
    assert res.lower_bound == pytest.approx(2.0 + 1 / 5 + 1 / 15, rel=1e-5)
    assert res.feasible and res.duration_out >= res.lower_bound * (1 - 1e-6)
    assert check_trajectory(dyn, res.trajectory).feasible


@pytest.mark.parametrize("lower_bound", [False, True])
def test_compiled_passes_match_toppra_on_seven_joints(lower_bound: bool) -> None:
    """The compiled passes (:mod:`dyn_node.retime.reach`) on the Panda's rows (acceleration and
    torque, 28 per stage) along a 10-waypoint path by arc length, 1000 steps: TOPP-RA's own
    controllable sets to its solver's feasibility tolerance (1e-10 on a row, so 1e-8 on ṡ²
    here), its forward pass to rounding."""
    from benchmarks.retime_bench import panel, robot

    dyn = robot("panda")
    path = ArcPath(build_path(panel(dyn, 1, seed=99, n_waypoints=10)[0]))
    grid = np.linspace(0.0, path.length, 1001)
    rows = topp.joint_rows(dyn, path, grid, scale=1.0 if lower_bound else 0.995,
                           lower_bound=lower_bound)
    ours = topp.Reach(path, grid, rows)
    x = ours.solve()
    cons = _constraint(rows, np.minimum(rows.xmax, 1e12), path.nv)
    inst = algo.TOPPRA([cons], _toppra_path(path), gridpoints=grid, solver_wrapper="seidel",
                       parametrizer="ParametrizeConstAccel")
    _, sd, _, K = inst.compute_parameterization(0.0, 0.0, return_data=True)
    assert np.all(np.isfinite(K)) and K[:, 1].max() > 1.0     # a real, bounded problem
    assert np.allclose(ours.controllable(0.0), K, rtol=1e-9, atol=1e-8)
    assert np.allclose(x, np.asarray(sd) ** 2, rtol=1e-9, atol=1e-12)


def test_arc_length_path_agrees_with_its_own_differences() -> None:
    """The points' q(s(ℓ)) and the q_ℓ, q_ℓℓ they carry are one curve: central differences
    of the positions (step 1e-4: truncation ~1e-9) give the derivatives, at 400 places 0.05
    rad or more from the ends (worst here 8e-7 and 1.1e-3; a linear inverse of ℓ(s), as
    before, misses by 5e-5 and 2.5: the controller's quintic through such points swung 1 %
    over their acceleration)."""
    path = ArcPath(build_path(ur5_traj()))
    L, h = path.length, 1e-4
    ell = np.random.default_rng(3).uniform(0.05, L - 0.05, 400)
    _, d1, d2 = path.derivatives(ell)
    qp, q0, qm = (path.positions(ell + d) for d in (h, 0.0, -h))
    assert np.max(np.abs((qp - qm) / (2 * h) - d1)) < 5e-6
    assert np.max(np.abs((qp - 2 * q0 + qm) / h**2 - d2)) < 1e-2
    assert np.allclose(np.linalg.norm(d1, axis=1), 1.0, atol=1e-12)


def test_disc_rows_hold_and_are_held_by_the_disc() -> None:
    """The polygon rows against the disc |a·u + b·x + c| ≤ r itself, on random (a, b, c) and
    (u, x): the outer rows pass every point of the disc, the inner rows pass none outside it
    (also where a = 0, a ∥ b, c = 0)."""
    rng = np.random.default_rng(7)
    a, b = rng.normal(size=(200, 3)), rng.normal(size=(200, 3))
    c = rng.normal(size=(200, 3)) * 0.8
    a[:20] = 0.0                                 # no s̈ term at some points
    a[20:30] = 2 * b[20:30]                      # a and b parallel
    c[30:60] = 0.0
    c[60:70] *= 5.0                              # |c| over the limit: no (u, x) at all
    ux = rng.normal(size=(200, 2)) * 3
    norm = np.linalg.norm(a * ux[:, :1] + b * ux[:, 1:] + c, axis=1)
    for outer in (True, False):
        A, B, C, G = topp._disc_rows(a, b, c, 2.0, outer=outer)
        ok = np.all(A * ux[:, :1] + B * ux[:, 1:] + C <= G, axis=1)
        if outer:
            assert np.all(ok[norm <= 2.0]) and not np.all(ok)
        else:
            assert not np.any(ok[norm > 2.0]) and np.any(ok)


# the sliding 2 kg link 0.5 m above the floor on a base whose support reaches 0.1 m behind the
# start and 3 m ahead: the floor's centre of pressure is q − 0.5·q̈/9.81 (the mounting carries
# (m·q̈, 0, m·g) at the link's centre (q, 0, 0.5)), so accelerating is bounded by
# q̈ ≤ 9.81·(q + 0.1)/0.5, growing with q: no closed form, TOPP-RA with that law as its own
# second-order constraint is the reference
RAISED = SLIDE.replace('<axis xyz="1 0 0"/>', '<origin xyz="0 0 0.5"/><axis xyz="1 0 0"/>')


def test_tipping_bounds_the_lower_bound() -> None:
    """T* with a support polygon equals TOPP-RA run directly with the centre of pressure's
    closed form as its constraint (toppra's SecondOrderConstraint: w = q − h·q̈/g within
    [−0.1, 3]), on the same line and grid, to 1e-6; without the polygon T* is 2 s (velocity
    only); the answer passes the check's tipping kind with its gauge near 1."""
    import toppra as ta
    import toppra.constraint as tc

    from dyn_node.core.check.feasibility import check_trajectory
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.robot.model import load_model
    from dyn_node.retime import retime
    from test_retime import LINE

    polygon = [[-0.1, -1.0], [3.0, -1.0], [3.0, 1.0], [-0.1, 1.0]]
    limits = {"joint_limits": {"j": {}}, "base_limits": {"support_polygon": polygon}}
    dyn = Dynamics(load_model(urdf=RAISED).with_limits(limits))
    res = retime(dyn, LINE, grid_points=2000, point_period=0.002, uniform_fallback=False)
    path = ta.SplineInterpolator(LINE.times, LINE.positions,
                                 bc_type=((1, LINE.velocities[0]), (1, LINE.velocities[1])))
    interp = tc.DiscretizationType.Interpolation
    cop = tc.SecondOrderConstraint(lambda q, v, a: np.atleast_1d(q - 0.5 * a / 9.81),
                                   lambda q: np.array([[1.0], [-1.0]]),
                                   lambda q: np.array([3.0, 0.1]), dof=1,
                                   discretization_scheme=interp)
    cons = [tc.JointVelocityConstraint(np.array([[-1.0, 1.0]])), cop]
    inst = algo.TOPPRA(cons, path, gridpoints=np.linspace(0.0, LINE.duration, 2001),
                       solver_wrapper="seidel", parametrizer="ParametrizeConstAccel")
    direct = inst.compute_trajectory(0, 0).duration
    assert direct > 2.2                          # the polygon binds (velocity alone: 2 s)
    # TOPP-RA's optimum on the grid is TOPP-RA's; T*, certified, within 0.1 % below it
    assert res.grid_optimum == pytest.approx(direct, rel=1e-6)
    assert direct * 0.999 <= res.lower_bound <= direct
    assert res.feasible and res.duration_out >= res.lower_bound
    check = check_trajectory(dyn, res.trajectory)
    assert check.feasible
    assert 0.97 <= check.per_frame["base_limits"]["tipping"]["ratio"] <= 1.0
