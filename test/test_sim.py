"""The MuJoCo simulator core (no ROS): control, saturation, JTC execution semantics, and agreement
of MuJoCo's forward dynamics with Pinocchio's inverse dynamics (two independent engines)."""
from __future__ import annotations

import mujoco
import numpy as np
import pytest

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.errors import TrajectoryError
from dyn_node.core.robot.model import load_model
from dyn_node.sim.scene import SolverSettings
from dyn_node.sim.simulator import SimConfig, Simulator

READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])


@pytest.fixture(scope="module")
def panda():
    return load_model(builtin="panda")


def sim_at(model, q=READY, **kw) -> Simulator:
    return Simulator(model, SimConfig(initial_positions=tuple(q), **kw))


def rest_points(P: list[np.ndarray]) -> tuple[list, list]:
    z = [[0.0] * len(P[0])] * len(P)
    return z, z


def shake(T: float, d2: float, d4: float) -> tuple[list[float], list[np.ndarray]]:
    dl = np.zeros(7)
    dl[1], dl[3] = d2, d4
    P = [READY, READY + dl, READY - dl, READY + dl, READY]
    return [i * T for i in range(len(P))], P


def run_tracking(sim: Simulator, end: float):
    err, ratio = 0.0, 0.0
    states = []
    while sim.time < end - 1e-9:
        st = sim.step()
        states.append(st)
        err = max(err, float(np.abs(st.q - st.q_ref).max()))
        ratio = max(ratio, float((np.abs(st.effort) / sim.effort_limit).max()))
    return err, ratio, states


def test_gravity_hold_with_feedforward_stays_still(panda):
    sim = sim_at(panda)
    st = sim.step(500)
    assert np.abs(st.q - READY).max() < 1e-9
    assert np.abs(st.v).max() < 1e-9
    # Holding still costs exactly the gravity torque, which Pinocchio computes independently.
    np.testing.assert_allclose(st.effort, Dynamics(panda).gravity(READY), atol=1e-9)


def test_without_feedforward_pd_alone_sags(panda):
    sim = sim_at(panda, feedforward=False)
    st = sim.step(500)
    # A PD-only controller needs a position error to produce the gravity torque (joint4: ~22 N·m).
    assert np.abs(st.q - READY).max() > 1e-3


def test_feasible_trajectory_tracked_within_tolerance(panda):
    target = READY + np.array([0.6, 0.35, 0.0, 0.5, 0.0, -0.35, 0.0])
    P = [READY, target, READY]
    v, a = rest_points(P)
    sim = sim_at(panda)
    sim.execute(panda.joint_names, [0.0, 0.8, 1.6], P, v, a)
    err, ratio, _ = run_tracking(sim, 1.8)
    assert err < 0.05
    assert ratio < 1.0
    np.testing.assert_allclose(sim.q, READY, atol=1e-3)


def test_aggressive_trajectory_saturates_and_deviates(panda):
    times, P = shake(0.13, 0.1, -0.07)
    v, a = rest_points(P)
    sim = sim_at(panda)
    sim.execute(panda.joint_names, times, P, v, a)
    err, ratio, states = run_tracking(sim, times[-1] + 0.2)
    assert ratio == pytest.approx(1.0, abs=1e-12)  # measured effort reaches the limit, not beyond
    assert any(st.saturated[1] for st in states)
    assert err > 0.05


def test_measured_effort_is_the_applied_torque(panda):
    times, P = shake(0.13, 0.1, -0.07)
    v, a = rest_points(P)
    sim = sim_at(panda)
    sim.execute(panda.joint_names, times, P, v, a)
    dyn = Dynamics(panda)
    worst = 0.0
    for _ in range(300):
        q0, v0 = sim.q, sim.v
        st = sim.step()
        # MuJoCo's acceleration at the step's starting state under the reported effort (what
        # any integrator starts from) must be what that effort explains: τ = M q̈ + h.
        qacc = sim.forward_acceleration(q0, v0, st.effort)
        worst = max(worst, float(np.abs(dyn.rnea(q0, v0, qacc) - st.effort).max()))
        assert np.all(np.abs(st.effort) <= sim.effort_limit + 1e-12)
    assert worst < 1e-6


def test_open_loop_torque_is_applied_unchanged(panda):
    sim = sim_at(panda)
    tau = Dynamics(panda).gravity(READY) + np.array([1.0, -2.0, 0.5, 3.0, 0.1, -0.2, 0.05])
    sim.set_open_loop_torque(tau)
    st = sim.step()
    np.testing.assert_array_equal(st.effort, tau)


@pytest.mark.parametrize("seed", range(5))
def test_mujoco_forward_matches_pinocchio_inverse(panda, seed):
    rng = np.random.default_rng(seed)
    lo, hi = panda.limits.position_lower, panda.limits.position_upper
    q = rng.uniform(lo, hi)
    v = rng.uniform(-2.0, 2.0, panda.nv)
    a_des = rng.uniform(-5.0, 5.0, panda.nv)
    tau = Dynamics(panda).rnea(q, v, a_des)  # Pinocchio, damping included
    sim = sim_at(panda, solver=SolverSettings(integrator="euler"))
    sim.reset(q, v)
    sim.set_open_loop_torque(tau)
    np.testing.assert_allclose(sim.forward_acceleration(q, v, tau), a_des, atol=1e-6)
    # The same through the simulator's own step: Euler's mj_step leaves the qacc of the state
    # it started from (RK4 leaves a later stage's: test_default_step_is_classical_rk4).
    sim.step()
    np.testing.assert_allclose(sim.data.qacc[sim.robot.dof_ids], a_des, atol=1e-6)


@pytest.mark.parametrize("seed", range(3))
def test_default_step_is_classical_rk4(panda, seed):
    """dyn_sim's default integrator: one step equals the textbook RK4 tableau (1/6, 1/3, 1/3,
    1/6) over MuJoCo's forward accelerations with the applied torque held, hinge joints only."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(panda.limits.position_lower, panda.limits.position_upper)
    v = rng.uniform(-2.0, 2.0, panda.nv)
    tau = Dynamics(panda).rnea(q, v, rng.uniform(-5.0, 5.0, panda.nv))
    sim = sim_at(panda)
    assert sim.mj.opt.integrator == int(mujoco.mjtIntegrator.mjINT_RK4)
    sim.reset(q, v)
    sim.set_open_loop_torque(tau)
    h = sim.config.timestep
    v1, a1 = v, sim.forward_acceleration(q, v, tau)
    v2 = v + h / 2 * a1
    a2 = sim.forward_acceleration(q + h / 2 * v1, v2, tau)
    v3 = v + h / 2 * a2
    a3 = sim.forward_acceleration(q + h / 2 * v2, v3, tau)
    v4 = v + h * a3
    a4 = sim.forward_acceleration(q + h * v3, v4, tau)
    mj_data = mujoco.MjData(sim.mj)  # MuJoCo's own mj_step from the same state: the same step
    sim.robot.set_state(mj_data, q, v)
    mj_data.qfrc_applied[sim.robot.dof_ids] = tau
    mujoco.mj_step(sim.mj, mj_data)
    st = sim.step()
    np.testing.assert_array_equal(sim.data.qpos, mj_data.qpos)
    np.testing.assert_array_equal(sim.data.qvel, mj_data.qvel)
    np.testing.assert_allclose(st.q, q + h / 6 * (v1 + 2 * v2 + 2 * v3 + v4), rtol=0, atol=1e-12)
    np.testing.assert_allclose(st.v, v + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4), rtol=0, atol=1e-12)
    # the 1e-12 above tells the integrators apart: Euler's step (still selectable) lands > 1e-5 away
    euler = sim_at(panda, solver=SolverSettings(integrator="euler"))
    euler.reset(q, v)
    euler.set_open_loop_torque(tau)
    assert np.abs(euler.step().v - st.v).max() > 1e-5


def test_first_segment_from_current_state_when_first_time_positive(panda):
    sim = sim_at(panda)
    sim.step(100)  # t = 0.1 s
    target = READY + np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    act = sim.execute(panda.joint_names, [0.5, 1.0], [target, target + 0.01])
    assert act.mode == "linear"
    assert act.received_time == pytest.approx(0.1)
    assert act.start_time == pytest.approx(0.1)  # zero stamp: on receipt
    q, _, _ = sim.reference([0.1, 0.35, 0.6])
    np.testing.assert_allclose(q[0], READY, atol=1e-12)            # starts where the robot is
    np.testing.assert_allclose(q[1], 0.5 * (READY + target), atol=1e-12)  # linear halfway
    np.testing.assert_allclose(q[2], target, atol=1e-12)           # reaches the first point


def test_start_at_header_stamp_and_hold_last_point(panda):
    sim = sim_at(panda)
    target = READY + np.array([0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
    P = [READY, target]
    v, a = rest_points(P)
    act = sim.execute(panda.joint_names, [0.0, 0.4], P, v, a, start_time=0.3)
    assert act.mode == "quintic"
    assert act.start_time == pytest.approx(0.3) and act.end_time == pytest.approx(0.7)
    q, _, _ = sim.reference([0.0, 0.3, 0.5, 0.7, 5.0])
    np.testing.assert_allclose(q[0], READY, atol=1e-12)
    np.testing.assert_allclose(q[1], READY, atol=1e-12)
    np.testing.assert_allclose(q[2], 0.5 * (READY + target), atol=1e-12)  # quintic midpoint
    np.testing.assert_allclose(q[3], target, atol=1e-12)
    np.testing.assert_allclose(q[4], target, atol=1e-12)                  # held afterwards
    sim.step(1200)
    assert not sim.executing
    np.testing.assert_allclose(sim.q, target, atol=1e-4)


def test_cubic_when_velocities_only(panda):
    sim = sim_at(panda)
    P = [READY, READY + 0.05]
    act = sim.execute(panda.joint_names, [0.0, 0.5], P, [[0.0] * 7] * 2)
    assert act.mode == "cubic"


def test_bad_trajectory_rejected_and_state_unchanged(panda):
    sim = sim_at(panda)
    with pytest.raises(TrajectoryError) as exc:
        sim.execute(panda.joint_names, [0.0, 0.5, 0.4], [READY] * 3)
    assert exc.value.code == "bad_times"
    with pytest.raises(TrajectoryError) as exc:
        sim.execute(["nope"], [0.0], [[0.0]])
    assert exc.value.code == "unknown_joints"
    assert sim.active is None


def test_deterministic(panda):
    times, P = shake(0.13, 0.1, -0.07)
    runs = []
    for _ in range(2):
        sim = sim_at(panda)
        sim.execute(panda.joint_names, times, P)
        runs.append(sim.step(400))
    np.testing.assert_array_equal(runs[0].q, runs[1].q)
    np.testing.assert_array_equal(runs[0].effort, runs[1].effort)


def test_locked_joints_may_be_named_and_are_ignored(panda):
    sim = sim_at(panda)
    names = list(panda.joint_names) + ["panda_finger_joint1"]
    target = READY + 0.05
    act = sim.execute(names, [0.5], [list(target) + [0.04]])
    np.testing.assert_allclose(act.trajectory.positions[0], target)


def test_mid_range_start_of_continuous_joints_is_zero_without_a_warning():
    """Issue 37: Kinova's continuous joints (±inf limits) start at 0, bounded ones mid-range,
    and no RuntimeWarning (inf − inf) is raised on the way."""
    import warnings

    from dyn_node.core.robot.model import example_robot_data_dir, model_from_source
    from dyn_node.sim.simulator import default_initial_positions

    kinova = model_from_source("", str(example_robot_data_dir() / "kinova_description/robots/kinova.urdf"), "")
    lo, hi = kinova.limits.position_lower, kinova.limits.position_upper
    assert np.any(~np.isfinite(lo))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        q0 = default_initial_positions(kinova)
    bounded = np.isfinite(lo) & np.isfinite(hi)
    np.testing.assert_array_equal(q0[~bounded], 0.0)
    np.testing.assert_allclose(q0[bounded], 0.5 * (lo[bounded] + hi[bounded]), rtol=0, atol=1e-15)
