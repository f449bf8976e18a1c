"""dyn_sim's scene: scene files refused or accepted, robot–scene collisions only, a scene that
touches nothing changes nothing, and the contact truth checked against MuJoCo's constraint
forces, Pinocchio's static balance, a frame change done with Pinocchio and the solref/solimp law."""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from dyn_node.core.robot.model import load_model
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.sim.press import PRESS_SCENE, READY, plan_press, static_balance
from dyn_node.sim.scene import SceneError, SolverSettings, load_scene, parse_scene
from dyn_node.sim.simulator import SimConfig, Simulator

REPO = Path(__file__).resolve().parents[1]
TABLE = {"name": "table", "type": "box", "size": [0.4, 0.8, 0.4], "position": [0.5, 0, 0.2],
         "orientation": [0, 0, 0, 1], "friction": 0.8}


@pytest.fixture(scope="module")
def panda():
    return load_model(builtin="panda")


@pytest.fixture(scope="module")
def links(panda):
    return [el.get("name") for el in ET.fromstring(panda.urdf).findall("link")]


@pytest.fixture(scope="module")
def pressed(panda):
    """The Panda held pressing on the table for 4 s (settled), its plan."""
    sim = Simulator(panda, SimConfig(scene=PRESS_SCENE, initial_positions=READY))
    plan = plan_press(sim)
    sim.execute(list(panda.joint_names), *plan.waypoints())
    sim.run(plan.t_press + 4.0)
    return sim


def test_shipped_press_scene_is_the_check_scene(links):
    scene = load_scene(REPO / "config" / "press_scene.yaml", link_names=links)
    assert scene.objects == PRESS_SCENE.objects
    assert scene.collide_links == PRESS_SCENE.collide_links


@pytest.mark.parametrize("change, code, words", [
    ({"colour": "red"}, "bad_keys", "colour"),
    ({"size": [0.4, -0.8, 0.4]}, "bad_size", "positive"),
    ({"size": [0.4, 0.8]}, "bad_value", "needs 3"),
    ({"position": [0.5, float("nan"), 0.2]}, "non_finite", "not finite"),
    ({"orientation": [0, 0, 0, 0]}, "bad_orientation", "zero quaternion"),
    ({"friction": -0.1}, "bad_friction", "≥ 0"),
    ({"type": "cylinder"}, "bad_type", "cylinder"),
    ({"name": "panda_hand"}, "bad_name", "robot link"),
])
def test_bad_objects_are_refused_with_the_object_named(links, change, code, words):
    raw = {"objects": [{**TABLE, **change}]}
    with pytest.raises(SceneError) as e:
        parse_scene(raw, link_names=links)
    assert e.value.code == code and words in str(e.value)
    assert parse_scene({"objects": [TABLE]}, link_names=links).objects[0].size == (0.4, 0.8, 0.4)


def test_bad_scene_level_keys_and_unknown_link(links, tmp_path):
    with pytest.raises(SceneError, match="not links of the robot") as e:
        parse_scene({"objects": [TABLE], "collide_links": ["panda_hand", "gripper"]}, link_names=links)
    assert e.value.code == "unknown_link" and "gripper" in str(e.value)
    with pytest.raises(SceneError, match="unknown keys") as e:
        parse_scene({"objects": [TABLE], "lights": []}, link_names=links)
    with pytest.raises(SceneError, match="duplicate"):
        parse_scene({"objects": [TABLE, TABLE]}, link_names=links)
    bad = tmp_path / "s.yaml"
    bad.write_text("objects: [ {name: a")
    with pytest.raises(SceneError) as e:
        load_scene(bad, link_names=links)
    assert e.value.code == "unreadable"


def test_bad_solver_settings_are_refused():
    for kw, code in (({"solver": "lu"}, "bad_solver"), ({"solref": (0.02, -1.0)}, "bad_solref"),
                     ({"solimp": (0.9, 1.2, 0.001, 0.5, 2)}, "bad_solimp"),
                     ({"iterations": 0}, "bad_iterations"), ({"integrator": "verlet"}, "bad_integrator")):
        with pytest.raises(SceneError) as e:
            SolverSettings(**kw)
        assert e.value.code == code


def test_scene_model_settings(panda):
    sim = Simulator(panda, SimConfig(scene=PRESS_SCENE, initial_positions=READY,
                                     solver=SolverSettings(solver="cg", iterations=33, tolerance=1e-7,
                                                           solref=(0.01, 0.8))))
    mj = sim.mj
    g = mj.geom("table").id
    np.testing.assert_array_equal(mj.geom_size[g], [0.2, 0.4, 0.2])  # half extents of the file's full size
    np.testing.assert_array_equal(mj.geom_solref[g], [0.01, 0.8])
    assert (mj.opt.solver, mj.opt.iterations, mj.opt.tolerance) == (int(mujoco.mjtSolver.mjSOL_CG), 33, 1e-7)
    assert not mj.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    # the Panda's STL collision meshes were found (example-robot-data), on the listed links only
    bodies = {mj.body(mj.geom_bodyid[i]).name for i in range(mj.ngeom) if mj.geom_type[i] == mujoco.mjtGeom.mjGEOM_MESH}
    assert bodies == {"panda_link5", "panda_link6", "panda_link7", "panda_hand"}


def test_start_pose_touches_nothing(panda):
    sim = Simulator(panda, SimConfig(scene=PRESS_SCENE, initial_positions=READY))
    sim.run(0.5)
    assert sim.data.ncon == 0 and not sim.contact_truth().active


def test_self_collisions_are_off(panda, links):
    """A folded pose (outside the joint limits, which dyn_sim does not enforce) where the hand
    and forearm overlap the base links: MuJoCo reports those pairs as soon as robot geoms may
    collide with each other, never with the scene's filter (all links listed)."""
    scene = parse_scene({"objects": [{**TABLE, "position": [5.0, 0, 0.2]}]}, link_names=links)
    folded = [0.0, 1.0, 0.0, -3.0, 0.0, 0.5, 0.0]
    sim = Simulator(panda, SimConfig(scene=scene, initial_positions=folded))
    assert sim.data.ncon == 0 and not sim.contact_truth().active
    mj = sim.mj
    mj.geom_conaffinity[mj.geom_bodyid != 0] = 1  # robot geoms accept robot geoms, and their
    mj.body_conaffinity[1:] = 1                   # bodies (MuJoCo's compiled body-level filter)
    mujoco.mj_forward(mj, sim.data)
    pairs = {frozenset((mj.body(mj.geom_bodyid[c.geom1]).name, mj.body(mj.geom_bodyid[c.geom2]).name))
             for c in sim.data.contact[:sim.data.ncon]}
    assert frozenset(("panda_link1", "panda_hand")) in pairs
    assert not sim.contact_truth().active  # robot–robot contacts are never truth


def test_a_scene_without_contact_changes_nothing(panda):
    """A far-away object: the same motion, bit for bit, as with contacts off."""
    far = parse_scene({"objects": [{**TABLE, "position": [5.0, 0, 0.2]}]}, link_names=[])
    runs = []
    for scene in (None, far):
        sim = Simulator(panda, SimConfig(scene=scene, initial_positions=READY))
        plan = plan_press(sim)
        sim.execute(list(panda.joint_names), *plan.waypoints())
        runs.append([(s.q, s.v, s.effort) for s in sim.run(3.0, every=50)])
    for a, b in zip(*runs):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


def test_truth_forces_are_mujocos_constraint_forces(pressed):
    """Σ J_c(contact point)ᵀ·F over the contacts, with MuJoCo's point Jacobian, equals
    MuJoCo's qfrc_constraint (contacts are the only constraints): force sign and frame."""
    sim = pressed
    truth = sim.contact_truth()
    assert len(truth.contacts) >= 2 and truth.normal_force_n > 20.0
    mj, d = sim.mj, sim.data
    tau = np.zeros(mj.nv)
    jp, jr = np.zeros((3, mj.nv)), np.zeros((3, mj.nv))
    for c in truth.contacts:
        mujoco.mj_jac(mj, d, jp, jr, c.position, mj.body(c.body1).id)
        tau += jp.T @ c.force + jr.T @ c.torque
        assert c.body2 == "table" and c.normal @ [0, 0, -1] > 0.99  # hand → table: down
    np.testing.assert_allclose(tau, d.qfrc_constraint, atol=1e-9 * max(1.0, np.abs(tau).max()))


def test_link_wrench_is_the_sum_moved_to_the_link_origin(panda, pressed):
    """The link wrench against Pinocchio: each contact force as a pin.Force at its point,
    moved by the link's placement from Pinocchio's forward kinematics."""
    truth = pressed.contact_truth()
    q = pressed.q
    pm = panda.pin_model
    data = pm.createData()
    pin.framesForwardKinematics(pm, data, q)
    assert {w.link for w in truth.link_wrenches} == {c.body1 for c in truth.contacts}
    for w in truth.link_wrenches:
        oMl = data.oMf[pm.getFrameId(w.link)]
        total = pin.Force.Zero()
        for c in (c for c in truth.contacts if c.body1 == w.link):
            at_point = pin.Force(c.force, c.torque)  # world axes, at the contact point
            # to world axes at the world origin, then into the link's frame at its origin
            total += oMl.actInv(pin.SE3(np.eye(3), c.position).act(at_point))
        np.testing.assert_allclose(w.force, total.linear, atol=1e-9)
        np.testing.assert_allclose(w.torque, total.angular, atol=1e-9)


def test_held_press_is_statically_balanced(panda, pressed):
    """At rest: Σ over contacts of J_pointᵀ·F (Pinocchio's world-aligned Jacobian of the contact
    point on its link) + τ_actuators = g(q) (dyn_node's gravity), the base carrying the rest;
    static_balance (link wrenches and LOCAL Jacobians) gives the same torques."""
    sim = pressed
    assert np.abs(sim.v).max() < 1e-4
    truth = sim.contact_truth()
    pm = panda.pin_model
    data = pm.createData()
    q = sim.q
    pin.computeJointJacobians(pm, data, q)
    pin.framesForwardKinematics(pm, data, q)
    tau_ext = np.zeros(panda.nv)
    for c in truth.contacts:
        fid = pm.getFrameId(c.body1)
        J = pin.getFrameJacobian(pm, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        lever = c.position - data.oMf[fid].translation
        J_point = J[:3] - np.cross(lever, J[3:].T).T  # v_p = v_o + ω × (p − o)
        tau_ext += J_point.T @ c.force
    g = Dynamics(panda).gravity(q)
    tau = sim.state().effort
    scale = np.abs(g).max()
    np.testing.assert_allclose(tau_ext + tau, g, atol=1e-4 * scale)
    assert np.abs(tau_ext).max() > 0.05 * scale  # the contact carries a real share
    bal = static_balance(panda, q, tau, truth)
    np.testing.assert_allclose(bal.contact_torque, tau_ext, atol=1e-9 * scale)
    assert bal.residual_rel < 1e-4


def test_penetration_is_what_solref_and_solimp_imply(pressed):
    """MuJoCo's soft contact, written here from its documentation: each row's reference
    acceleration is aref = −B·v − K·I·dist = −B·v + K·I·r with K = 1/(d_width²·τ²·ζ²) and B = 2/(d_width·τ) from
    solref (τ, ζ) and I = d(r) the solimp sigmoid at the depth r; a row that pushes satisfies
    f·R = aref − a. So at rest (v = 0, after the no-slip pass stopped all motion) the depth is
    r = (f·R + a)/(K·I) on every pushing row; re-solved without the no-slip pass so f is the
    main solver's. Checked against the measured depth (−dist) of every contact."""
    sim = pressed
    assert np.abs(sim.v).max() < 1e-6
    mj, d = sim.mj, sim.data
    mj.opt.noslip_iterations = 0
    try:
        _check_depths(mj, d)
    finally:
        mj.opt.noslip_iterations = SolverSettings().noslip_iterations
        mujoco.mj_forward(mj, d)


def _check_depths(mj, d) -> None:
    mujoco.mj_forward(mj, d)
    (tc, zeta), (d0, dw, width, mid, power) = SolverSettings().solref, SolverSettings().solimp
    K, B = 1.0 / (dw * dw * tc * tc * zeta * zeta), 2.0 / (dw * tc)
    acc = np.zeros(d.nefc)
    mujoco.mj_mulJacVec(mj, d, acc, d.qacc)  # a = J·q̈ (J̇·q̇ = 0 at rest)
    checked = 0
    for i in range(d.ncon):
        c = d.contact[i]
        r = -c.dist
        x = min(r / width, 1.0)
        y = x ** power / mid ** (power - 1) if x <= mid else 1 - (1 - x) ** power / (1 - mid) ** (power - 1)
        imp = d0 + y * (dw - d0)
        assert 0 < r < 5e-3
        for j in range(c.efc_address, c.efc_address + 4):  # the pyramid's 4 edges
            np.testing.assert_allclose(d.efc_KBIP[j, :3], [K, B, imp], rtol=1e-9)
            np.testing.assert_allclose(d.efc_aref[j], -B * d.efc_vel[j] + K * imp * r, rtol=1e-9)
            if d.efc_force[j] > 0:
                np.testing.assert_allclose((d.efc_force[j] * d.efc_R[j] + acc[j]) / (K * imp), r, rtol=1e-6)
                checked += 1
    assert checked >= 2




def test_truth_is_empty_without_a_scene(panda):
    sim = Simulator(panda, SimConfig(initial_positions=READY))
    sim.run(0.1)
    assert not sim.contact_truth().active and sim.contact_truth().max_penetration_m == 0.0


@pytest.mark.parametrize("obj, size", [
    ({"name": "floor", "type": "plane", "size": [0, 0], "position": [0.0, 0.0, 0.40]}, [0.0, 0.0, 1.0]),
    ({"name": "ball", "type": "sphere", "size": [0.05], "position": [0.5, 0.0, 0.35],
      "orientation": [0.0, 0.0, 0.3826834, 0.9238795]}, [0.05, 0.0, 0.0]),
])
def test_plane_and_sphere_take_the_press(panda, links, obj, size):
    """The other two object types: MuJoCo's sizes (an infinite plane, the radius), and the same
    press touches them from above (normal down, force up on the fingers)."""
    scene = parse_scene({"objects": [{**obj, "friction": 0.8}], "collide_links": list(PRESS_SCENE.collide_links)},
                        link_names=links)
    sim = Simulator(panda, SimConfig(scene=scene, initial_positions=READY))
    np.testing.assert_array_equal(sim.mj.geom_size[sim.mj.geom(obj["name"]).id], size)
    assert sim.data.ncon == 0
    sim.execute(list(panda.joint_names), *plan_press(sim).waypoints())
    sim.run(4.0)
    truth = sim.contact_truth()
    assert truth.active and {c.body2 for c in truth.contacts} == {obj["name"]}
    assert all(c.normal @ [0, 0, -1] > 0.7 and c.force[2] > 0 for c in truth.contacts)
    assert 0 < truth.max_penetration_m < 5e-3 and truth.normal_force_n > 20.0


# --- hostile scene files (issue 37): the bounded, strict reader; one line each ------------------
def _box(**change) -> str:
    o = {"name": "t", "type": "box", "size": "[0.1, 0.1, 0.1]", "position": "[0.5, 0, 0.2]", **change}
    return "objects:\n  - " + "\n    ".join(f"{k}: {v}" for k, v in o.items()) + "\n"


HOSTILE = {
    "integer beyond float range": (_box(size="[1" + "0" * 400 + ", 0.1, 0.1]"), "beyond float range"),
    "invalid UTF-8": (b"objects: []\n# \xff\xfe\n", "not UTF-8"),
    "deep nesting": ("objects: " + "[" * 200 + "]" * 200 + "\n", "nested more than"),
    "alias bomb inside size": ("a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n" + "".join(
        f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
        for p, c in zip("abcdefgh", "bcdefghi")) + _box(size="*i"), "aliases expand"),
    "duplicate keys": (_box() + "    size: [0.2, 0.2, 0.2]\n", "duplicate key"),
    "overflowing quaternion": (_box(orientation="[1e308, 1e308, 0, 0]"), "norm overflows"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_scene_files_are_refused_in_one_line(case, links, tmp_path):
    text, words = HOSTILE[case]
    path = tmp_path / "scene.yaml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(SceneError) as e:
        load_scene(path, link_names=links)
    assert words in str(e.value) and "\n" not in str(e.value) and len(str(e.value)) < 300


@pytest.mark.parametrize("kind", ["/dev/zero", "fifo"])
def test_devices_and_fifos_are_refused_without_reading(kind, links, tmp_path):
    """/dev/zero never ends and a FIFO without a writer would block: neither is a regular file."""
    import os

    path = Path(kind) if kind.startswith("/") else tmp_path / "scene.fifo"
    if kind == "fifo":
        os.mkfifo(path)
    with pytest.raises(SceneError, match="not a regular file") as e:
        load_scene(path, link_names=links)
    assert e.value.code == "unreadable"

