"""dyn_sim's controller (dyn_node.sim.control, issue 37): the closed loop against its closed form
on a coupled pose, the gain rule against the timestep, the divergence status, and the panel —
every example-robot-data arm the loader takes × 5 seeded poses, a gentle goal from each."""
from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.sim_bench import ARMS, SPEED_SLACK, TRACK_TOL, load_arm, panel_case, poses
from dyn_node.core.robot.model import load_model
from dyn_node.sim.control import MAX_OMEGA_DT, choose_integrator, gain_warning, sampled_loop_radius
from dyn_node.sim.physics_status import ERROR
from dyn_node.sim.simulator import SimConfig, Simulator

PANEL_GOAL_S = 1.0  # the bench runs 3 s goals; 1 s keeps the panel well under 2 minutes


@pytest.fixture(scope="module")
def panda():
    return load_model(builtin="panda")


def test_every_mode_decays_as_the_closed_form_at_pandas_q2_zero(panda):
    """Computed torque: released 10–30 mrad off a held pose where j1 and j3 couple (q2 = 0, the
    default), every joint's error follows e(t) = e0·(1 + ωt)·e^(−ωt) (ζ = 1), the textbook
    critically damped response, within 3 % of e0 (the sampled loop at ω·dt = 0.04)."""
    sim = Simulator(panda)
    q0 = sim.q
    assert abs(q0[1]) < 1e-12
    e0 = np.array([0.02, -0.01, 0.03, 0.02, -0.02, 0.01, 0.03])
    sim.reset(q0 + e0)
    sim.hold(q0)
    w = sim.config.natural_frequency
    worst = 0.0
    for _ in range(300):
        st = sim.step()
        closed = (1 + w * st.t) * math.exp(-w * st.t) * e0
        worst = max(worst, float(np.abs((st.q - q0) - closed).max()))
    assert worst < 0.03 * np.abs(e0).max()


def test_sampled_loop_radius_closed_forms():
    """Scalar plant, ζ = 1: ω·dt = 1 puts an eigenvalue of the RK4 (exact ZOH) loop at −1
    (A = [[1/2, 0], [−1, −1]]); semi-implicit Euler's loop is [[1 − x², 1 − 2x], [−x², 1 − 2x]]
    (x = ω·dt), whose eigenvalues at x = 0.5 are 0.75 and 0 — radius 0.75."""
    one = np.eye(1)
    assert sampled_loop_radius(one, np.array([1e6]), np.array([2e3]), 1e-3) == pytest.approx(1.0, abs=1e-12)
    assert sampled_loop_radius(one, np.array([0.25]), np.array([1.0]), 1.0, rk4=False) == pytest.approx(0.75, abs=1e-12)


def test_the_old_diagonal_gains_cannot_be_integrated_at_pandas_q2_zero(panda):
    """The cause issue 37 found: kp = M_ii·ω², kd = 2·M_ii·ω (ω = 40) as user gains at Panda's
    default pose grow ×5 per step (the j1 − j3 mode), so dyn_sim warns; computed torque with the
    same ω does not, and ω·dt beyond the rule does."""
    sim = Simulator(panda)
    mii = np.diag(sim._inertia(sim.q))
    user = Simulator(panda, SimConfig(kp=tuple(mii * 1600.0), kd=tuple(mii * 80.0)))
    assert user.gain_warning.startswith("kp/kd cannot be integrated at timestep 0.001 s")
    assert sampled_loop_radius(sim._inertia(sim.q), mii * 1600.0, mii * 80.0, 1e-3) > 5.0
    assert sim.gain_warning == ""
    fast = gain_warning(np.eye(7), np.zeros(7), np.zeros(7), 1e-3, rk4=True, automatic=True,
                        omega=1.01 * MAX_OMEGA_DT / 1e-3)
    assert "lower one of them" in fast and "unstable" not in fast


def test_stiff_urdf_damping_switches_to_implicitfast():
    """xArm7's joint7: 2 N·m·s/rad on 1.4e-4 kg·m² decays 14× per 1 ms step, past RK4's
    stability (2.79): implicitfast is used, and said; a heavy arm keeps RK4."""
    xarm = load_arm("xarm7")
    sim = Simulator(xarm)
    assert sim.integrator == "implicitfast" and "λ_max(M⁻¹D)·dt" in sim.integrator_note
    assert choose_integrator("rk4", np.eye(2), np.array([1.0, 0.5]), 1e-3) == ("rk4", "")


def test_a_huge_user_gain_is_a_fault_held_until_reset(panda):
    """kp = 1e9: the first steps diverge; the simulator stops at the last good state, the physics
    status is ERROR naming joint, quantity and step, and a reset clears it."""
    sim = Simulator(panda, SimConfig(kp=(1e9,) * 7, kd=(0.0,) * 7, saturate=False, energy=True))
    assert sim.gain_warning.startswith("kp/kd cannot be integrated")
    q0 = sim.q
    sim.execute(panda.joint_names, [0.5], [q0 + 0.1])
    states = sim.run(0.2, every=1)
    assert sim.fault is not None and sim.fault.step < 50
    assert all(np.all(np.abs(s.v) < 1e3) and np.all(np.isfinite(s.q)) for s in states)
    held = states[-1].q
    np.testing.assert_array_equal(sim.step(10).q, held)
    st = sim.physics.report(sim.data)
    assert st.level == ERROR and st.failure_label == "evaluation error"
    assert f"at step {sim.fault.step}" in st.message and f"joint {sim.fault.joint}" in st.message
    assert st.values["fault"] == st.message and sim.active is None
    sim.reset(held)
    assert sim.fault is None and sim.physics.report(sim.data).level != ERROR


@pytest.mark.parametrize("arm", [a[0] for a in ARMS])
def test_panel(arm):
    """5 seeded poses (the first the default: Panda's q2 = 0) × a 0.2 rad goal on every joint:
    SUCCEEDED within the duration + 0.5 s, |q − q_ref| ≤ 0.01 rad at every step, no joint faster
    than 2 × the reference's peak + 0.05 rad/s, nothing non-finite, no fault."""
    model = load_arm(arm)
    ps = poses(model, 5)
    lo, hi = model.limits.position_lower, model.limits.position_upper
    assert np.all((ps >= lo) & (ps <= hi))
    for i, q0 in enumerate(ps):
        r = panel_case(model, arm, i, q0, duration=PANEL_GOAL_S)
        assert not math.isnan(r.succeeded_s), r
        assert r.max_error_rad <= TRACK_TOL and r.finite and not r.fault, r
        assert r.max_speed_rad_s <= 2 * 1.875 * 0.2 / PANEL_GOAL_S + SPEED_SLACK, r


@pytest.mark.parametrize("steps_before", [0, 5])
def test_mujocos_own_reset_is_a_fault_even_on_the_first_step(panda, steps_before, tmp_path, monkeypatch):
    """A velocity beyond MuJoCo's mjMAXVAL: MuJoCo warns and resets the data (clock included);
    the guard names MuJoCo's warning and puts the last good state back, on the very first step
    too (where MuJoCo's restarted clock looks like an ordinary step)."""
    monkeypatch.chdir(tmp_path)  # MuJoCo writes MUJOCO_LOG.TXT in the cwd
    sim = Simulator(panda)
    sim.step(steps_before)  # 0: none
    good = sim.q
    sim.data.qvel[sim.robot.dof_ids[2]] = 1e11
    sim.step()
    assert sim.fault is not None and sim.fault.step == steps_before + 1
    assert "MuJoCo's badqvel warning" in sim.fault.text and sim.fault.quantity == "velocity"
    np.testing.assert_array_equal(sim.q, good)
