"""The 'dyn_sim: physics' status core: the energy budget against work recomputed from the
simulator's own states, its closing on a press with a push, and a diverging step as an ERROR."""
from __future__ import annotations


from dyn_node.core.robot.model import load_model
from dyn_node.sim.physics_status import ERROR, OK
from dyn_node.sim.press import PRESS_SCENE, READY, plan_press
from dyn_node.sim.simulator import SimConfig, Simulator


def test_actuator_work_is_tau_dot_v():
    """A moving arm without scene: the actuators' work over a period equals Σ τ_k·(v_k + v_k+1)/2·h
    from the states the simulator returns (its applied efforts and velocities), and ΔE matches."""
    arm = load_model(builtin="planar_2link")
    sim = Simulator(arm, SimConfig(initial_positions=(0.0, 0.0), energy=True))
    sim.execute(list(arm.joint_names), [0.6], [[0.8, -0.5]])
    states = [sim.state()]
    for _ in range(800):
        states.append(sim.step())
    sim.physics.report(sim.data)  # closes the period (its last step's work is pending)
    states2 = [states[-1]]
    for _ in range(400):
        states2.append(sim.step())
    period = sim.physics.period  # the numbers behind the status's texts
    st = sim.physics.report(sim.data)
    h = sim.config.timestep
    # step k goes from states2[k] to states2[k+1] under states2[k+1].effort; the period
    # accounts the steps up to the one before its last (whose work is still pending)
    seq = [states[-2], *states2]  # the step into states2[0] is the period's first
    w = sum(float(b.effort @ (a.v + b.v)) * 0.5 * h for a, b in zip(seq[:-2], seq[1:-1]))
    assert abs(period.work["actuators"] - w) < 1e-9 * abs(w)
    assert st.values["work_actuators_j"] == f"{period.work['actuators']:.9g}"
    assert abs(w) > 1e-3  # it moved under torque
    assert st.level == OK and float(st.values["energy_error_rel"]) < 1e-2


def test_press_with_a_push_closes_the_budget():
    panda = load_model(builtin="panda")
    sim = Simulator(panda, SimConfig(scene=PRESS_SCENE, initial_positions=READY, energy=True))
    sim.execute(list(panda.joint_names), *plan_press(sim).waypoints())
    sim.run(3.0)
    sim.physics.report(sim.data)
    e0 = _mujoco_energy(sim)
    sim.apply_wrench("panda_link4", [30.0, 0.0, 0.0], [0.0, 0.0, 0.0], hold_s=0.3)
    sim.run(1.0)
    period = sim.physics.period
    st = sim.physics.report(sim.data)
    v = {k: float(x) for k, x in st.values.items() if k not in ("warnings",)}
    assert abs(v["work_push_j"]) > 1e-3 and abs(v["work_constraints_j"]) > 1e-4
    assert 0 < v["max_penetration_m"] < 5e-3 and v["solver_iterations_max"] > 0
    # the work of every source against the energy change MuJoCo computes for the two states
    # (not the status's own ΔE, of which energy_error is the remainder by construction)
    work = sum(period.work.values())
    assert abs((_mujoco_energy(sim) - e0) - work) < 1e-2 * sum(abs(w) for w in period.work.values())
    assert st.level == OK and v["energy_error_rel"] < 1e-2


def _mujoco_energy(sim) -> float:
    """Potential + kinetic energy of the simulation's state, by MuJoCo on a fresh MjData."""
    import mujoco

    d = mujoco.MjData(sim.physics.mj)
    d.qpos[:], d.qvel[:], d.time = sim.data.qpos, sim.data.qvel, sim.data.time
    mujoco.mj_forward(sim.physics.mj, d)
    return float(d.energy.sum())


def test_rk4_budget_closes_through_the_contact_onset():
    """Under RK4 (the default) damping and contact forces change within a step; the budget takes
    their power at each step's start state (trapezoid). Half-second periods over the whole press
    (approach, first touch, hold) stay below 1 % (measured ≤ 0.79 % at the touch, ≤ 4.4e-4
    elsewhere); the Euler accounting applied to RK4's steps reached 3.7 % at the touch."""
    panda = load_model(builtin="panda")
    sim = Simulator(panda, SimConfig(scene=PRESS_SCENE, initial_positions=READY, energy=True))
    assert sim.config.solver.integrator == "rk4"
    sim.execute(list(panda.joint_names), *plan_press(sim).waypoints())
    rel, constraint_work = [], 0.0
    for _ in range(10):
        sim.run(0.5)
        st = sim.physics.report(sim.data)
        assert st.level == OK, st.message
        rel.append(float(st.values["energy_error_rel"]))
        constraint_work += abs(float(st.values["work_constraints_j"]))
    assert max(rel) < 1e-2 and constraint_work > 1e-3  # the table did work: the contact was accounted


def test_a_diverging_step_is_an_error(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo writes its warning to MUJOCO_LOG.TXT in the cwd
    arm = load_model(builtin="planar_2link")
    sim = Simulator(arm, SimConfig(initial_positions=(0.3, -0.2), energy=True))
    sim.run(0.1)
    sim.physics.report(sim.data)
    sim.data.qvel[0] = 1e11  # beyond MuJoCo's mjMAXVAL: it warns (bad qvel) and resets the state
    sim.step()
    st = sim.physics.report(sim.data)
    assert st.level == ERROR and st.failure_label == "evaluation error"
    assert "badqvel" in st.message and "badqvel ×1" in st.values["warnings"]
    # issue 37: the simulator holds its last good state and the status stays ERROR (the warning
    # counted once, in its own period) until the simulator is reset; then it is OK again
    q_good = sim.q
    held = []
    for _ in range(2):
        sim.run(0.1)
        held.append(sim.physics.report(sim.data))
    assert all(s.level == ERROR and s.values["warnings"] == "none" for s in held)
    assert "velocity of joint joint1" in held[-1].message and "step 101" in held[-1].message
    assert sim.q.tolist() == q_good.tolist() and abs(sim.q[0] - 0.3) < 1e-6  # not MuJoCo's reset (0)
    sim.reset(sim.q)
    sim.run(0.1)
    assert sim.physics.report(sim.data).level == OK
