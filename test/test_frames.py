"""The batched frame kernels against Pinocchio state by state, MuJoCo and finite differences."""
from __future__ import annotations

import mujoco
import numpy as np
import pinocchio as pin
import pytest
from robots import BRANCHED_URDF

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.errors import InputError, ModelError
from dyn_node.core.check.frames import FrameKinematics, FramePoint, root_link
from dyn_node.core.robot.model import Payload, load_model
from dyn_node.sim.mujoco_model import mujoco_from_model, mujoco_urdf

TOL = 1e-9
WRENCH = (3.0, -2.0, 20.0, 0.4, -0.3, 0.2)

# MuJoCo refuses two of the tree's inertias that sit exactly on the triangle inequality
# (A + B = C) once rotated and rounded; moved inside it for the MuJoCo comparisons
MUJOCO_TREE = (BRANCHED_URDF
               .replace('ixx="0.02" iyy="0.03" izz="0.01"', 'ixx="0.02" iyy="0.025" izz="0.01"')
               .replace('ixx="0.001" iyy="0.002" izz="0.001"',
                        'ixx="0.001" iyy="0.0015" izz="0.001"'))


# a massless mounting flange fixed to the tree's root, off its origin and turned
MOUNT = ('<link name="mount"/><joint name="mount_joint" type="fixed"><parent link="base"/>'
         '<child link="mount"/><origin xyz="0.3 -0.2 0.1" rpy="0.2 0.1 -0.4"/></joint></robot>')
BASES = [("panda", None), ("ur5", None), ("ur5", "base"), ("planar_2link", None), ("tree", None),
         ("tree", "mount")]


def _armature(model):
    return {"joint_limits": {n: {"armature": 0.01 + 0.02 * i}
                             for i, n in enumerate(model.joint_names)}}


def robot(name: str, urdf: str = BRANCHED_URDF):
    """(model, frame points): each model with a payload, tilted gravity and armature where it
    has them; points on moving links with offsets, fixed-joint links, a link after a prismatic
    joint and the root link (never moves)."""
    if name == "tree":
        model = load_model(urdf=urdf.replace("</robot>", MOUNT),
                           payload=Payload(1.5, (0.02, -0.03, 0.05), "f"),
                           gravity=(1.1, -2.3, -9.5))
        points = [FramePoint("c_tool", (0.05, -0.02, 0.1), WRENCH), FramePoint("f", (0.1, 0, 0)),
                  FramePoint("e", wrench=WRENCH), FramePoint("base", (0.1, 0.2, 0.3), WRENCH)]
    elif name == "panda":
        model = load_model(builtin="panda", payload=Payload(1.2, (0.01, -0.02, 0.05)),
                           gravity=(2.0, -1.0, -9.5))
        points = [FramePoint("panda_link8", (0.0, 0.0, 0.1), WRENCH),
                  FramePoint("panda_hand", (0.02, 0.0, 0.05)), FramePoint("panda_link3")]
    elif name == "ur5":
        model = load_model(builtin="ur5", payload=Payload(0.8, (0.0, 0.05, 0.02)))
        points = [FramePoint("tool0", (0.0, 0.0, 0.05), WRENCH), FramePoint("upper_arm_link"),
                  FramePoint("base_link", (0.1, 0.0, 0.0), WRENCH)]
    else:
        model = load_model(builtin="planar_2link", gravity=(0.0, -9.81, -1.0))
        points = [FramePoint("tool", (0.05, 0.02, 0.0), WRENCH),
                  FramePoint("link1", (0.1, 0.05, 0.0))]
    if name != "planar_2link":
        model = model.with_limits(_armature(model))
    return model, points


def states(nv: int, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return (rng.uniform(-2.5, 2.5, (n, nv)), rng.uniform(-2, 2, (n, nv)),
            rng.uniform(-5, 5, (n, nv)))


def point_frames(pm: pin.Model, points) -> list[int]:
    """A Pinocchio frame at every point (offset included), for Pinocchio's own answers."""
    ids = []
    for n, p in enumerate(points):
        fid = pm.getFrameId(p.frame)
        f = pm.frames[fid]
        placement = f.placement * pin.SE3(np.eye(3), np.array(p.point, dtype=float))
        ids.append(pm.addFrame(pin.Frame(f"point{n}", f.parentJoint, fid, placement,
                                         pin.OP_FRAME)))
    return ids


NAMES = ["panda", "ur5", "planar_2link", "tree"]


@pytest.mark.parametrize("name", NAMES)
def test_frame_terms_match_pinocchio(name):
    """Position, velocity, classical acceleration, angular velocity and acceleration of every
    point (getFrameVelocity / getFrameClassicalAcceleration, LOCAL_WORLD_ALIGNED, at a frame
    added at the offset), J_localᵀW (getFrameJacobian LOCAL), M (crba), ½q̇ᵀMq̇
    (computeKineticEnergy) and m_u from Pinocchio's LOCAL_WORLD_ALIGNED Jacobian and a dense
    solve."""
    model, points = robot(name)
    Q, V, A = states(model.nv, 60, 1)
    out = FrameKinematics(model, points).compute(Q, V, A, mass_matrix=True)
    rigid_ke = FrameKinematics(model, points, include_armature=False).compute(
        Q, V, A).inertia.kinetic_energy
    pm = model.pin_model.copy()
    ids = point_frames(pm, points)
    data = pm.createData()
    rigid = pm.copy()
    rigid.armature = np.zeros(pm.nv)
    rigid_data = rigid.createData()
    worst = {}

    def diff(key, got, ref):
        worst[key] = max(worst.get(key, 0.0), float(np.abs(got - ref).max()))

    for k in range(len(Q)):
        pin.forwardKinematics(pm, data, Q[k], V[k], A[k])
        pin.updateFramePlacements(pm, data)
        pin.computeJointJacobians(pm, data, Q[k])
        M = pin.crba(pm, data, Q[k])
        diff("M", out.inertia.mass_matrix[k], M)
        diff("g(q)", out.inertia.gravity_torque[k],
             pin.computeGeneralizedGravity(pm, data, Q[k]))
        # Pinocchio 4.1's computeKineticEnergy leaves out the armature of RevoluteUnaligned
        # joints (its crba has it): the energy with armature against ½q̇ᵀMq̇ of its crba, the
        # rigid-body energy against computeKineticEnergy (and both against MuJoCo below)
        diff("ke", out.inertia.kinetic_energy[k], 0.5 * V[k] @ M @ V[k])
        diff("rigid ke", rigid_ke[k], pin.computeKineticEnergy(rigid, rigid_data, Q[k], V[k]))
        for fid, p, f in zip(ids, points, out.frames):
            vel = pin.getFrameVelocity(pm, data, fid, pin.LOCAL_WORLD_ALIGNED)
            acc = pin.getFrameClassicalAcceleration(pm, data, fid, pin.LOCAL_WORLD_ALIGNED)
            diff("position", f.position[k], data.oMf[fid].translation)
            worst["rotation"] = max(worst.get("rotation", 0.0), float(np.abs(
                f.rotation[k] - data.oMf[fid].rotation).max()))
            diff("velocity", f.linear_velocity[k], vel.linear)
            diff("angular velocity", f.angular_velocity[k], vel.angular)
            diff("acceleration", f.linear_acceleration[k], acc.linear)
            diff("angular acceleration", f.angular_acceleration[k], acc.angular)
            J = pin.getFrameJacobian(pm, data, pm.getFrameId(p.frame), pin.LOCAL)
            diff("task torque", f.task_torque[k], J.T @ np.array(p.wrench))
            Jv = pin.getFrameJacobian(pm, data, fid, pin.LOCAL_WORLD_ALIGNED)[:3]
            speed = np.linalg.norm(vel.linear)
            if speed > 0:
                u = vel.linear / speed
                m_u = 1.0 / (u @ Jv @ np.linalg.solve(M, Jv.T @ u))
                worst["m_u rel"] = max(worst.get("m_u rel", 0.0),
                                       abs(f.effective_mass[k] - m_u) / m_u)
            else:
                assert f.effective_mass[k] == 0.0
    assert max(worst.values()) < TOL, worst
    assert worst["rotation"] < 1e-12, worst
    assert set(worst) >= {"m_u rel", "M", "task torque", "g(q)"}
    assert np.abs(out.inertia.gravity_torque).max() > 1.0
    # the states move the points and load the wrench: the comparisons are not of zeros
    moving = [n for n, p in enumerate(points) if p.frame not in ("base", "base_link")]
    assert min(np.abs(out.frames[n].linear_acceleration).max() for n in moving) > 0.1
    assert min(np.abs(out.frames[n].task_torque).max() for n in moving
               if any(points[n].wrench)) > 0.1


def everything_com(pm: pin.Model, data: pin.Data, q: np.ndarray) -> np.ndarray:
    """Centre of mass of every body, the ones fixed to the world (joint 0: the root link's,
    UR5's base_link) included; Pinocchio's centerOfMass leaves those out."""
    c = pin.centerOfMass(pm, data, q)
    Y0 = pm.inertias[0]
    return (data.mass[0] * c + Y0.mass * Y0.lever) / (data.mass[0] + Y0.mass)


@pytest.mark.parametrize("name,frame", BASES)
def test_base_wrench_matches_rnea_joint_forces(name, frame):
    """The mounting's wrench against Pinocchio's RNEA joint forces: data.f of the root's child
    joints (in the world, moved to the root link's origin and axes) plus the weight of the
    bodies fixed to the root (joint 0); static = the same at q̇ = q̈ = 0; at time scale k the
    RNEA of (q, q̇/k, q̈/k²) is static + dynamic/k²; mass and centre of mass as Pinocchio's."""
    model, points = robot(name)
    pm = model.pin_model
    Q, V, A = states(model.nv, 40, 2)
    fk = FrameKinematics(model, points, base_frame=frame)
    base = fk.compute(Q, V, A, inertia=False).base
    assert base.frame == (frame or root_link(model.urdf))
    root = pm.frames[pm.getFrameId(base.frame)].placement    # its joint is the world
    assert (frame is None) == (root == pin.SE3.Identity())
    data = pm.createData()
    Y0 = pm.inertias[0]
    g = pm.gravity.linear
    fixed = pin.Force(-Y0.mass * g, -np.cross(Y0.mass * Y0.lever, g))

    def mounting(q, v, a):
        pin.rnea(pm, data, q, v, a)
        pin.forwardKinematics(pm, data, q)     # rnea leaves data.oMi alone
        w = fixed
        for i in range(1, pm.njoints):
            if pm.parents[i] == 0:
                w = w + data.oMi[i].act(data.f[i])
        return root.actInv(w).vector

    k = 1.7
    worst = 0.0
    for n in range(len(Q)):
        q, v, a = Q[n], V[n], A[n]
        worst = max(worst, np.abs(base.static[n] - mounting(q, 0 * v, 0 * a)).max(),
                    np.abs(base.at(1.0)[n] - mounting(q, v, a)).max(),
                    np.abs(base.at(k)[n] - mounting(q, v / k, a / k**2)).max())
        com = root.actInv(everything_com(pm, data, q))
        worst = max(worst, np.abs(base.com[n] - com).max())
    assert worst < TOL
    assert base.mass == pytest.approx(model.total_mass, abs=1e-12)
    assert np.abs(base.dynamic).max() > 1.0


@pytest.mark.parametrize("name,frame", BASES)
def test_base_wrench_is_the_momentum_rate_less_gravity(name, frame):
    """dynamic = dh/dt (Pinocchio's centroidal momentum rate moved to the root link) and
    static = −(weight) at the centre of mass: the whole robot's Newton–Euler balance."""
    model, points = robot(name)
    pm = model.pin_model
    data = pm.createData()
    Q, V, A = states(model.nv, 30, 3)
    base = FrameKinematics(model, points, base_frame=frame).compute(Q, V, A, inertia=False).base
    root = pm.frames[pm.getFrameId(base.frame)].placement
    g = pm.gravity.linear
    for n in range(len(Q)):
        dhg = pin.computeCentroidalMomentumTimeVariation(pm, data, Q[n], V[n], A[n])
        c = data.com[0]     # of the moving bodies: their momentum is about it
        rate = pin.Force(dhg.linear, dhg.angular + np.cross(c, dhg.linear))
        np.testing.assert_allclose(base.dynamic[n], root.actInv(rate).vector, rtol=0, atol=TOL)
        c = everything_com(pm, data, Q[n])
        weight = pin.Force(base.mass * g, np.cross(c, base.mass * g))
        np.testing.assert_allclose(base.static[n], -root.actInv(weight).vector, rtol=0,
                                   atol=TOL)


def _mujoco_sites(model, points) -> tuple[mujoco.MjModel, list[int]]:
    """model's URDF as MuJoCo compiles it (mujoco_urdf: same adaptations) with a site at each
    point; fixed-joint links stay bodies (fusestatic off)."""
    text, _ = mujoco_urdf(model)
    spec = mujoco.MjSpec.from_string(text)
    spec.compiler.fusestatic = False
    spec.compiler.balanceinertia = False
    spec.option.gravity = np.asarray(model.gravity, dtype=float)
    for n, p in enumerate(points):
        spec.body(p.frame).add_site(name=f"point{n}", pos=list(p.point))
    mj = spec.compile()
    return mj, [mj.site(f"point{n}").id for n in range(len(points))]


def _mujoco_model(name):
    return robot(name, MUJOCO_TREE) if name == "tree" else robot(name)


@pytest.mark.parametrize("name", NAMES)
def test_point_motion_matches_mujoco(name):
    """Point velocities (mj_objectVelocity) and classical accelerations
    (mj_objectAcceleration after mj_inverse and mj_rnePostConstraint, gravity taken out: MuJoCo
    accelerates the world by −g) at MuJoCo sites placed at the points."""
    model, points = _mujoco_model(name)
    mj, sites = _mujoco_sites(model, points)
    joints = [mj.joint(n) for n in model.joint_names]
    Q, V, A = states(model.nv, 40, 4)
    out = FrameKinematics(model, points).compute(Q, V, A, inertia=False, base=False)
    d = mujoco.MjData(mj)
    res = np.zeros(6)
    g = np.asarray(model.gravity, dtype=float)
    worst = 0.0
    for n in range(len(Q)):
        for j, J in enumerate(joints):
            d.qpos[J.qposadr[0]] = Q[n, j]
            d.qvel[J.dofadr[0]], d.qacc[J.dofadr[0]] = V[n, j], A[n, j]
        mujoco.mj_inverse(mj, d)
        mujoco.mj_rnePostConstraint(mj, d)
        for s, f in zip(sites, out.frames):
            worst = max(worst, np.abs(d.site_xpos[s] - f.position[n]).max())
            mujoco.mj_objectVelocity(mj, d, mujoco.mjtObj.mjOBJ_SITE, s, res, 0)
            worst = max(worst, np.abs(res[3:] - f.linear_velocity[n]).max(),
                        np.abs(res[:3] - f.angular_velocity[n]).max())
            mujoco.mj_objectAcceleration(mj, d, mujoco.mjtObj.mjOBJ_SITE, s, res, 0)
            worst = max(worst, np.abs(res[3:] + g - f.linear_acceleration[n]).max(),
                        np.abs(res[:3] - f.angular_acceleration[n]).max())
    assert worst < TOL


def _mounting_body(mj: mujoco.MjModel) -> int:
    """The one body hanging from MuJoCo's world: the subtree the mounting carries."""
    top = [b for b in range(1, mj.nbody) if mj.body_parentid[b] == 0]
    assert len(top) == 1
    return top[0]


@pytest.mark.parametrize("name,frame", BASES)
def test_energy_and_base_wrench_match_mujoco(name, frame):
    """½q̇ᵀMq̇ against MuJoCo's energy[1] (mjENBL_ENERGY, armature included in both) and the
    base wrench against cfrc_int of the body hanging from the world after mj_inverse and
    mj_rnePostConstraint, moved from the subtree's centre of mass to the root link's origin
    and axes (MuJoCo's own pose of the root link; its world when the URDF root is `world`)."""
    model, points = _mujoco_model(name)
    robot_ = mujoco_from_model(model)
    mj = robot_.model
    mj.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    d = robot_.make_data()
    top = _mounting_body(mj)
    at = frame or root_link(model.urdf)
    rid = mj.body(at).id if at != "world" else 0
    Q, V, A = states(model.nv, 40, 5)
    out = FrameKinematics(model, points, base_frame=frame).compute(Q, V, A)
    for n in range(len(Q)):
        robot_.set_state(d, Q[n], V[n])
        mujoco.mj_forward(mj, d)
        assert abs(d.energy[1] - out.inertia.kinetic_energy[n]) < TOL
        d.qacc[:] = 0.0
        d.qacc[robot_.dof_ids] = A[n]
        mujoco.mj_inverse(mj, d)
        mujoco.mj_rnePostConstraint(mj, d)
        torque, force = d.cfrc_int[top, :3], d.cfrc_int[top, 3:]
        c, r, R = d.subtree_com[mj.body_rootid[top]], d.xpos[rid], d.xmat[rid].reshape(3, 3)
        moment = torque + np.cross(c - r, force)
        np.testing.assert_allclose(out.base.at(1.0)[n], np.concatenate([R.T @ force, R.T @ moment]),
                                   rtol=0, atol=TOL)
        np.testing.assert_allclose(out.base.com[n], R.T @ (d.subtree_com[0] - r), rtol=0,
                                   atol=TOL)
    assert out.base.mass == pytest.approx(float(mj.body_subtreemass[0]), abs=1e-12)
    assert np.abs(out.inertia.kinetic_energy).max() > 1.0


@pytest.mark.parametrize("name", NAMES)
def test_task_torque_holds_the_motion_against_mujoco_xfrc_applied(name):
    """MuJoCo pushes every frame with −W (the environment's reaction, xfrc_applied at the body's
    centre of mass, W rotated by MuJoCo's pose of the body) while the joints apply
    RNEA(q, q̇, q̈) + Σ J_localᵀW: its forward dynamics then gives back q̈. mj_applyFT gives
    J_localᵀW itself."""
    model, points = _mujoco_model(name)
    robot_ = mujoco_from_model(model)
    mj = robot_.model
    d = robot_.make_data()
    Q, V, A = states(model.nv, 30, 6)
    out = FrameKinematics(model, points).compute(Q, V, A, inertia=False, base=False)
    dyn = Dynamics(model)
    bodies = [mj.body(p.frame).id for p in points]
    qfrc = np.zeros(mj.nv)
    worst_acc = worst_ft = 0.0
    for n in range(len(Q)):
        robot_.set_state(d, Q[n], V[n])
        mujoco.mj_kinematics(mj, d)
        mujoco.mj_comPos(mj, d)
        d.xfrc_applied[:] = 0.0
        task = np.zeros(model.nv)
        for b, p, f in zip(bodies, points, out.frames):
            R, o = d.xmat[b].reshape(3, 3), d.xpos[b]
            force, torque = R @ np.array(p.wrench[:3]), R @ np.array(p.wrench[3:])
            d.xfrc_applied[b, :3] -= force
            d.xfrc_applied[b, 3:] -= torque + np.cross(o - d.xipos[b], force)
            qfrc[:] = 0.0
            mujoco.mj_applyFT(mj, d, force, torque, o, b, qfrc)
            worst_ft = max(worst_ft, np.abs(qfrc[robot_.dof_ids] - f.task_torque[n]).max())
            task += f.task_torque[n]
        robot_.apply_torque(d, dyn.rnea(Q[n], V[n], A[n]) + task)
        mujoco.mj_forward(mj, d)
        worst_acc = max(worst_acc, np.abs(robot_.get_qacc(d) - A[n]).max())
    assert worst_ft < TOL and worst_acc < TOL


@pytest.mark.parametrize("name", ["panda", "tree"])
def test_motion_is_the_time_derivative_of_the_pose(name):
    """Along q(t) = q + q̇t + q̈t²/2: the point's velocity and acceleration are the 4th-order
    central differences of its position, the angular velocity that of the frame's rotation
    (Pinocchio's forward kinematics), the angular acceleration that of the angular velocity."""
    model, points = robot(name)
    Q, V, A = states(model.nv, 10, 7)
    fk = FrameKinematics(model, points)
    pm = model.pin_model
    data = pm.createData()
    fids = [pm.getFrameId(p.frame) for p in points]
    h = 1e-3
    steps = np.array([-2, -1, 0, 1, 2])
    d1 = np.array([1, -8, 0, 8, -1]) / (12 * h)
    d2 = np.array([-1, 16, -30, 16, -1]) / (12 * h * h)
    for q, v, a in zip(Q, V, A):
        t = steps * h
        Qt = q + np.outer(t, v) + 0.5 * np.outer(t * t, a)
        Vt = v + np.outer(t, a)
        path = fk.compute(Qt, Vt, np.tile(a, (5, 1)), inertia=False, base=False)
        for fid, f in zip(fids, path.frames):
            np.testing.assert_allclose(d1 @ f.position, f.linear_velocity[2], rtol=0, atol=1e-8)
            np.testing.assert_allclose(d2 @ f.position, f.linear_acceleration[2], rtol=0,
                                       atol=1e-6)
            np.testing.assert_allclose(d1 @ f.angular_velocity, f.angular_acceleration[2],
                                       rtol=0, atol=1e-8)
            Rs = []
            for qt in Qt:
                pin.framesForwardKinematics(pm, data, qt)
                Rs.append(data.oMf[fid].rotation.copy())
            Rdot = np.tensordot(d1, np.array(Rs), axes=1)
            W = Rdot @ Rs[2].T
            np.testing.assert_allclose([W[2, 1], W[0, 2], W[1, 0]], f.angular_velocity[2],
                                       rtol=0, atol=1e-8)


def test_still_points_root_frames_and_time_scaling():
    """A still state: every motion 0, m_u = 0 and the transferred energy 0 (no NaN); the root
    link never moves and its task torque is 0; stretched by k, speeds go as 1/k,
    accelerations, kinetic and transferred energy as 1/k² with m_u unchanged."""
    model, points = robot("panda")
    points = points + [FramePoint("panda_link0", (0.1, 0.0, 0.2), WRENCH)]
    fk = FrameKinematics(model, points)
    Q, V, A = states(model.nv, 20, 8)
    V[0] = 0.0
    A[0] = 0.0
    out = fk.compute(Q, V, A)
    for f in out.frames:
        assert np.all(np.isfinite(f.effective_mass))
        assert f.effective_mass[0] == 0.0 and f.transferred_energy[0] == 0.0
        assert not f.linear_velocity[0].any() and not f.linear_acceleration[0].any()
    root = out.frame("panda_link0")
    assert not root.linear_velocity.any() and not root.task_torque.any()
    assert not root.effective_mass.any()
    np.testing.assert_allclose(root.position, np.tile([0.1, 0.0, 0.2], (20, 1)), atol=1e-15)
    k = 2.5
    slow = fk.compute(Q, V / k, A / k**2)
    for f, s in zip(out.frames[:-1], slow.frames[:-1]):
        np.testing.assert_allclose(s.speed, f.speed / k, rtol=1e-12)
        np.testing.assert_allclose(s.linear_acceleration, f.linear_acceleration / k**2,
                                   rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(s.effective_mass, f.effective_mass, rtol=1e-12)
        np.testing.assert_allclose(s.transferred_energy, f.transferred_energy / k**2,
                                   rtol=1e-12, atol=1e-16)
    np.testing.assert_allclose(slow.inertia.kinetic_energy, out.inertia.kinetic_energy / k**2,
                               rtol=1e-12)
    assert out.frames[0].transferred_energy[1:].min() > 0


def test_armature_is_optional_and_parts_can_be_switched_off():
    model, points = robot("panda")
    Q, V, A = states(model.nv, 5, 9)
    with_arm = FrameKinematics(model, points).compute(Q, V, A, mass_matrix=True)
    rigid = FrameKinematics(model, points, include_armature=False).compute(Q, V, A,
                                                                           mass_matrix=True)
    np.testing.assert_allclose(with_arm.inertia.mass_matrix - rigid.inertia.mass_matrix,
                               np.tile(np.diag(model.limits.armature), (5, 1, 1)), atol=1e-14)
    bare = FrameKinematics(model, points).compute(Q, V, A, inertia=False, base=False)
    assert bare.inertia is None and bare.base is None and bare.frames[0].effective_mass is None
    assert with_arm.frames[0].effective_mass is not None
    assert FrameKinematics(model, points).compute(Q, V, A).inertia.mass_matrix is None
    np.testing.assert_array_equal(bare.frames[0].linear_acceleration,
                                  with_arm.frames[0].linear_acceleration)
    with pytest.raises(ValueError, match="needs inertia=True"):
        FrameKinematics(model, points).compute(Q, V, A, inertia=False, mass_matrix=True)
    empty = FrameKinematics(model, points).compute(Q[:0], V[:0], A[:0])
    assert empty.frames[0].position.shape == (0, 3) and empty.base.static.shape == (0, 6)


def test_bad_frames_and_states_are_rejected_naming_what():
    model = load_model(builtin="panda")
    with pytest.raises(ModelError, match="frame 'panda_link88' .*did you mean 'panda_link8'"):
        FrameKinematics(model, [FramePoint("panda_link88")])
    with pytest.raises(ModelError, match="point of frame 'panda_hand' must be 3 finite"):
        FrameKinematics(model, [FramePoint("panda_hand", (0.0, float("nan"), 0.0))])
    with pytest.raises(ModelError, match="wrench at frame 'panda_hand' must be 6 finite"):
        FrameKinematics(model, [FramePoint("panda_hand", wrench=(1.0, 2.0, 3.0))])
    fk = FrameKinematics(model, [FramePoint("panda_hand")])
    Q, V, A = states(7, 4, 10)
    with pytest.raises(InputError, match="q must be N×7"):
        fk.compute(Q[:, :6], V, A)
    with pytest.raises(InputError, match="different numbers of states"):
        fk.compute(Q, V[:3], A)
    V[2, 3] = np.inf
    with pytest.raises(InputError, match="v is not finite in state 2"):
        fk.compute(Q, V, A)


def test_layouts_and_threads_give_the_same_numbers():
    """Column-major and strided states give the row-major result to the bit, and compute()
    calls running in several threads at once (the kernel releases the GIL) do not disturb each
    other."""
    import threading

    model, points = robot("tree")
    fk = FrameKinematics(model, points)
    Q, V, A = states(model.nv, 300, 11)
    ref = fk.compute(Q, V, A)
    wide = np.zeros((300, 2 * model.nv))
    wide[:, ::2] = V
    other = fk.compute(np.asfortranarray(Q), wide[:, ::2], np.asfortranarray(A))
    results = [None] * 4

    def run(i):
        results[i] = fk.compute(Q, V, A)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for got in [other] + results:
        for f, g in zip(ref.frames, got.frames):
            np.testing.assert_array_equal(f.linear_acceleration, g.linear_acceleration)
            np.testing.assert_array_equal(f.effective_mass, g.effective_mass)
        np.testing.assert_array_equal(ref.base.dynamic, got.base.dynamic)
        np.testing.assert_array_equal(ref.inertia.kinetic_energy, got.inertia.kinetic_energy)


@pytest.mark.parametrize("name", ["panda", "tree"])
def test_couple_point_gives_the_effective_mass_with_more_payload(name):
    """J_c·M⁻¹ products at the payload point: m_u with Δm more payload by Woodbury's identity
    equals m_u of the model re-loaded with that payload (its own CRBA and factor), for added
    and removed mass; Λ = J_cM⁻¹J_cᵀ against Pinocchio's Jacobian and a dense solve."""
    model, points = robot(name)
    p = model.payload
    pts = [*points, FramePoint(model.payload_frame, p.com)]
    Q, V, A = states(model.nv, 50, 8)
    out = FrameKinematics(model, pts, couple_point=len(points)).compute(Q, V, A)
    pm = model.pin_model.copy()
    ids = point_frames(pm, pts)
    data = pm.createData()
    for n in range(0, len(Q), 7):
        pin.computeJointJacobians(pm, data, Q[n])
        pin.updateFramePlacements(pm, data)
        Jc = pin.getFrameJacobian(pm, data, ids[-1], pin.LOCAL_WORLD_ALIGNED)[:3]
        M = pin.crba(pm, data, Q[n])
        M = np.triu(M) + np.triu(M, 1).T
        np.testing.assert_allclose(out.inertia.couple_inertia[n], Jc @ np.linalg.solve(M, Jc.T),
                                   rtol=1e-9, atol=1e-12)
    for dm in (2.5, -0.5 * p.mass):
        heavy = model.with_payload(Payload(p.mass + dm, p.com, p.frame))
        ref = FrameKinematics(heavy, pts).compute(Q, V, A)
        checked = 0
        for f, r in zip(out.frames[:-1], ref.frames[:-1]):
            got = f.effective_mass_with(dm, out.inertia.couple_inertia)
            moving = r.effective_mass > 0
            checked += int(moving.sum())
            np.testing.assert_allclose(got[moving], r.effective_mass[moving], rtol=1e-9)
            assert np.all(got[~moving] == 0.0)
            # the added mass matters: the comparison is not of equal numbers
            assert not moving.any() or np.abs(got[moving] / f.effective_mass[moving] - 1).max() > 1e-3
        assert checked > 80
    with pytest.raises(ValueError):
        FrameKinematics(model, pts, couple_point=len(pts))
