"""dyn_sim's external push: the link's wrench as MuJoCo's xfrc_applied, checked against Pinocchio's
frame Jacobian and MuJoCo's own mj_applyFT; merged links, hold, replacement, zero and bad input."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pinocchio as pin
import pytest
from robots import fast_panda_points

from dyn_node.errors import InputError
from dyn_node.core.robot.model import load_model
from dyn_node.sim.mujoco_model import mujoco_urdf
from dyn_node.sim.scene import INTEGRATORS, SolverSettings
from dyn_node.sim.simulator import SimConfig, Simulator, body_wrench, link_mount

READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])


@pytest.fixture(scope="module")
def panda():
    return load_model(builtin="panda")


def generalized_force(mj, data, body_id, xfrc) -> np.ndarray:
    """qfrc of a world wrench at a body's centre of mass, by MuJoCo's mj_applyFT."""
    qfrc = np.zeros(mj.nv)
    mujoco.mj_applyFT(mj, data, xfrc[:3].copy(), xfrc[3:].copy(), data.xipos[body_id].copy(), body_id, qfrc)
    return qfrc


def pinocchio_torque(model, q, link, wrench) -> np.ndarray:
    """J_localᵀ·wrench at the link's frame: the joint torque of a wrench at its origin, in its axes."""
    pm = model.pin_model
    data = pm.createData()
    J = pin.computeFrameJacobian(pm, data, q, pm.getFrameId(link), pin.ReferenceFrame.LOCAL)
    return J.T @ wrench


@pytest.mark.parametrize("integrator", ["euler", "rk4"])  # rk4: no step1/step2 split, own path
@pytest.mark.parametrize("link", ["panda_link8", "panda_hand", "panda_link4", "panda_leftfinger"])
def test_applied_xfrc_is_the_transformed_wrench(panda, link, integrator):
    """After one pushed step, the body's xfrc_applied is R·f and R·m + (p_o − p_com) × R·f with R,
    p_o the link's pose from Pinocchio's kinematics, and its generalized force (MuJoCo's
    mj_applyFT at the body's centre of mass) equals Pinocchio's J_localᵀ·wrench, to 1e-9."""
    sim = Simulator(panda, SimConfig(initial_positions=tuple(READY), solver=SolverSettings(integrator=integrator)))
    assert sim.mj.opt.integrator == int(INTEGRATORS[integrator])
    rng = np.random.default_rng(sum(map(ord, link)))  # a fixed seed per link
    sim.reset(READY + rng.uniform(-0.3, 0.3, 7), rng.uniform(-1.0, 1.0, 7))  # moving
    w = np.concatenate([rng.uniform(-30, 30, 3), rng.uniform(-3, 3, 3)])
    push = sim.apply_wrench(link, w[:3], w[3:], hold_s=0.5)
    assert push.mount.body == link and push.mount.body_id == sim.mj.body(link).id
    sim.step(20)
    q = sim.q  # the state the next step starts from, where MuJoCo applies the push
    sim.step(1)
    b = push.mount.body_id
    xfrc = sim.data.xfrc_applied[b].copy()
    pm = panda.pin_model
    data = pm.createData()
    pin.framesForwardKinematics(pm, data, q)
    oMf = data.oMf[pm.getFrameId(link)]
    F = oMf.rotation @ w[:3]
    np.testing.assert_allclose(xfrc[:3], F, atol=1e-9)
    at_q = mujoco.MjData(sim.mj)  # MuJoCo's kinematics at q (RK4 leaves sim.data at a later stage)
    sim.robot.set_state(at_q, q)
    mujoco.mj_forward(sim.mj, at_q)
    np.testing.assert_allclose(xfrc[3:], oMf.rotation @ w[3:] + np.cross(oMf.translation - at_q.xipos[b], F),
                               atol=1e-9)
    qfrc = generalized_force(sim.mj, at_q, b, xfrc)[sim.robot.dof_ids]
    np.testing.assert_allclose(qfrc, pinocchio_torque(panda, q, link, w), atol=1e-9)


def _fused(panda) -> tuple[mujoco.MjModel, ET.Element]:
    """The Panda compiled with MuJoCo's fusestatic on: every link hanging from panda_link7 by
    fixed joints (link8, hand, tcp, fingers) is merged into panda_link7's body."""
    text = mujoco_urdf(panda)[0]
    spec = mujoco.MjSpec.from_string(text)
    spec.compiler.fusestatic = True
    spec.compiler.discardvisual = True
    return spec.compile(), ET.fromstring(text)


@pytest.mark.parametrize("link", ["panda_link8", "panda_hand_tcp", "panda_rightfinger"])
def test_a_link_merged_into_its_parent_body(panda, link):
    """With fusestatic the link is no MuJoCo body: link_mount finds panda_link7 and the link's
    pose in it (the product of the fixed joints' origins, equal to Pinocchio's relative frame
    placement), and the wrench moved onto the merged body has the same generalized force as on
    the unmerged model, where the link is a body of its own (mj_applyFT at the link's origin)."""
    fused, urdf = _fused(panda)
    assert mujoco.mj_name2id(fused, mujoco.mjtObj.mjOBJ_BODY, link) == -1
    mount = link_mount(fused, urdf, link)
    assert mount.body == "panda_link7"
    q = READY + np.array([0.2, -0.1, 0.3, 0.2, -0.4, 0.1, 0.5])
    pm = panda.pin_model
    pdata = pm.createData()
    pin.framesForwardKinematics(pm, pdata, q)
    rel = pdata.oMf[pm.getFrameId("panda_link7")].inverse() * pdata.oMf[pm.getFrameId(link)]
    np.testing.assert_allclose(mount.rotation, rel.rotation, atol=1e-12)
    np.testing.assert_allclose(mount.translation, rel.translation, atol=1e-12)

    w = np.array([12.0, -7.0, 25.0, 0.4, -1.1, 0.8])
    fd = mujoco.MjData(fused)
    fd.qpos[[fused.joint(n).qposadr[0] for n in panda.joint_names]] = q
    mujoco.mj_forward(fused, fd)
    b = mount.body_id
    xfrc = body_wrench(mount, fd.xmat[b].reshape(3, 3), fd.xpos[b], fd.xipos[b], w)
    dofs = [fused.joint(n).dofadr[0] for n in panda.joint_names]
    merged = generalized_force(fused, fd, b, xfrc)[dofs]

    sim = Simulator(panda)
    sim.reset(q)
    ub = sim.mj.body(link).id
    R, p = sim.data.xmat[ub].reshape(3, 3), sim.data.xpos[ub].copy()
    qfrc = np.zeros(sim.mj.nv)
    mujoco.mj_applyFT(sim.mj, sim.data, R @ w[:3], R @ w[3:], p, ub, qfrc)
    np.testing.assert_allclose(merged, qfrc[sim.robot.dof_ids], atol=1e-9)
    np.testing.assert_allclose(merged, pinocchio_torque(panda, q, link, w), atol=1e-9)


# fixed joints whose rotations and offsets do not commute, so their order matters
CHAIN_URDF = """<robot name="chain">
  <link name="base"/>
  <link name="l1"><inertial><origin xyz="0.1 0 0"/><mass value="1.0"/>
    <inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="a"><inertial><origin xyz="0 0.05 0"/><mass value="0.5"/>
    <inertia ixx="0.002" iyy="0.002" izz="0.002" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="b"><inertial><origin xyz="0 0 0.04"/><mass value="0.3"/>
    <inertia ixx="0.001" iyy="0.001" izz="0.001" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="c"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.2" rpy="0.2 0 0"/><axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="50" velocity="3"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="a"/>
    <origin xyz="0.3 0 0"/><axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="50" velocity="3"/></joint>
  <joint name="fa" type="fixed"><parent link="a"/><child link="b"/>
    <origin xyz="0.1 0.2 0.3" rpy="0.3 0.5 -0.2"/></joint>
  <joint name="fb" type="fixed"><parent link="b"/><child link="c"/>
    <origin xyz="-0.1 0.05 0.2" rpy="-0.4 0.2 0.7"/></joint>
</robot>"""


def test_merged_chain_of_non_commuting_fixed_joints():
    """Two fixed joints with general rotations and offsets under one body: the link's pose in it
    is the product in the right order, equal to Pinocchio's relative frame placement."""
    model = load_model(urdf=CHAIN_URDF)
    fused, urdf = _fused(model)
    mount = link_mount(fused, urdf, "c")
    assert mount.body == "a"
    pm = model.pin_model
    data = pm.createData()
    pin.framesForwardKinematics(pm, data, np.array([0.3, -0.5]))
    rel = data.oMf[pm.getFrameId("a")].inverse() * data.oMf[pm.getFrameId("c")]
    np.testing.assert_allclose(mount.rotation, rel.rotation, atol=1e-12)
    np.testing.assert_allclose(mount.translation, rel.translation, atol=1e-12)


def test_hold_replace_and_zero(panda):
    sim = Simulator(panda, SimConfig(initial_positions=tuple(READY)))
    b8 = sim.mj.body("panda_link8").id
    sim.step(3)
    sim.apply_wrench("panda_link8", (0.0, 0.0, 10.0), (0.0, 0.0, 0.0), hold_s=0.0104)  # → 10 steps
    pushed = []
    for _ in range(12):
        sim.step(1)
        pushed.append(bool(np.any(sim.data.xfrc_applied[b8])))
    # the 10 steps after the call are pushed (the xfrc row is cleared before step 11 runs)
    assert pushed == [True] * 10 + [False] * 2 and sim.wrench is None
    # a newer push replaces the one before, on another body: the old body's row is cleared
    sim.apply_wrench("panda_link8", (5.0, 0.0, 0.0), (0.0, 0.0, 0.0), hold_s=1.0)
    sim.step(1)
    sim.apply_wrench("panda_link4", (0.0, 5.0, 0.0), (0.0, 0.0, 0.0), hold_s=1.0)
    sim.step(1)
    assert not np.any(sim.data.xfrc_applied[b8])
    assert np.any(sim.data.xfrc_applied[sim.mj.body("panda_link4").id])
    # a zero wrench ends the push, whatever its frame
    assert sim.apply_wrench("", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), hold_s=1.0) is None
    sim.step(1)
    assert sim.wrench is None and not np.any(sim.data.xfrc_applied)


def test_no_push_steps_as_before(panda):
    """A push that ended leaves the plant as if it never was: the same steps from the same state
    give bit-identical states with or without the (expired) push having existed."""
    a = Simulator(panda, SimConfig(initial_positions=tuple(READY)))
    b = Simulator(panda, SimConfig(initial_positions=tuple(READY)))
    b.apply_wrench("panda_link8", (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), hold_s=0.001)
    b.clear_wrench()
    for s in (a, b):
        s.step(200)
    np.testing.assert_array_equal(a.data.qpos, b.data.qpos)
    np.testing.assert_array_equal(a.data.qvel, b.data.qvel)


def test_bad_push_is_refused_and_the_current_one_continues(panda):
    sim = Simulator(panda, SimConfig(initial_positions=tuple(READY)))
    sim.apply_wrench("panda_link8", (0.0, 0.0, 10.0), (0.0, 0.0, 0.0), hold_s=1.0)
    before = sim.wrench
    with pytest.raises(InputError, match="'panda_link9' is not a link of the robot") as info:
        sim.apply_wrench("panda_link9", (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), hold_s=1.0)
    assert info.value.code == "unknown_frame" and info.value.failure_label == "state error"
    with pytest.raises(InputError, match="not finite") as info:
        sim.apply_wrench("panda_link8", (float("nan"), 0.0, 0.0), (0.0, 0.0, 0.0), hold_s=1.0)
    assert info.value.code == "non_finite"
    with pytest.raises(InputError) as info:
        sim.apply_wrench("panda_link8", (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), hold_s=0.0)
    assert info.value.code == "bad_hold"
    assert sim.wrench is before
    sim.step(1)
    assert np.any(sim.data.xfrc_applied[sim.mj.body("panda_link8").id])


def test_no_false_contact_through_the_contact_monitor_over_a_fast_trajectory(panda):
    """No push, the Panda at 90 % of its speed limits (quintic, 0.6 s segments) and the same
    points interpolated linearly (velocity steps, torques saturating): the node's own
    ContactMonitor (default thresholds) never leaves ``none`` and records no episode, while
    estimating at every sample."""
    from dyn_node.core.contacts.contact_monitor import ContactMonitor, ContactSettings
    from dyn_node.core.robot.dynamics import Dynamics

    times, pos = fast_panda_points(panda.limits, READY)
    for mode in ("quintic", "linear"):
        sim = Simulator(panda, SimConfig(initial_positions=tuple(READY)))
        if mode == "quintic":
            zero = np.zeros_like(pos)
            sim.execute(panda.joint_names, times, pos, zero, zero)
        else:
            sim.execute(panda.joint_names, times, pos)
        mon = ContactMonitor(Dynamics(panda), ContactSettings())
        states, speed, saturated = set(), 0.0, 0
        for k, st in enumerate(sim.run(times[-1] + 0.3)):
            t_ns = (k + 1) * 1_000_000
            states.add(mon.update(t_ns, t_ns, st.q, st.v, st.effort).state)
            speed = max(speed, float((np.abs(st.v) / panda.limits.velocity).max()))
            saturated += int(st.saturated.any())
        assert states == {"none"} and mon.episodes == [] and mon.estimates == k + 1, (mode, states)
        assert speed > 0.85 if mode == "quintic" else saturated > 0


@pytest.mark.parametrize("force", [(0.0, 30.0, 0.0), (30.0, 0.0, 0.0), (0.0, 0.0, -30.0)])
def test_detection_latency_is_the_minimum_duration_after_the_first_order_crossing(panda, force):
    """benchmarks.contact_bench's latency for a push from standstill against the closed form:
    τ̂ rises as Jᵀ·F·(1 − e^(−K t)) (a constant torque at rest), so joint i crosses its
    threshold c_i at t_i = −ln(1 − c_i/|τ_i|)/K; the state turns ``contact`` once the earliest
    crossing has held contact_min_duration (0.02 s). The measured latency is that, rounded up
    to the 1 ms sample, plus at most one sample (the observer starts on the first pushed one)."""
    import math

    from benchmarks.contact_bench import FRAME, one_push

    force = np.array(force)
    lat_ns = one_push(panda, force, 0.0)  # the motion starts 0.05 s later: ~at rest until then
    J = pin.computeFrameJacobian(panda.pin_model, panda.pin_model.createData(), READY,
                                 panda.pin_model.getFrameId(FRAME), pin.ReferenceFrame.LOCAL)
    tau = np.abs(J.T @ np.concatenate([force, np.zeros(3)]))
    c = 0.05 * panda.limits.effort
    t_cross = min(-math.log(1 - ci / ti) / 50.0 for ci, ti in zip(c, tau) if ti > ci)
    assert 0.0 < lat_ns * 1e-9 - (t_cross + 0.02) <= 0.002, (lat_ns, t_cross)
