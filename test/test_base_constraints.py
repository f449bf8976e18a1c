"""The base and grasp kinds (dyn_node.core.check.base_constraints): their per-sample quantities against
MuJoCo and closed forms, and the kinds through check_trajectory against brute force.

The mounting's wrench with a task wrench against MuJoCo's cfrc_int of the body hanging from the
world (the environment's −W through xfrc_applied); the grasp force against a point mass under
pure translation worked by hand and against MuJoCo's cfrc_int of the payload welded at its
frame; the centre of pressure against the still robot's centre of mass and against MuJoCo with
the base's mass as a body of its own. Then, per kind, the time scale by re-checking the
stretched trajectory, the blocked verdicts, and the payload margin by bisection over the mass
with the check itself.
"""
from __future__ import annotations

import json
import math
from dataclasses import replace
from types import SimpleNamespace

import mujoco
import numpy as np
import pinocchio as pin
import pytest
from test_frames import _armature, _mounting_body, _mujoco_model, everything_com, states

from dyn_node.core.check import base_constraints as B
from dyn_node.core.check import constraints as C
from dyn_node.core.check import feasibility as F
from dyn_node.core.check import force_laws as laws
from dyn_node.core.check import task_motion
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.feasibility import FeasibilityOptions, StartState, check_trajectory
from dyn_node.core.check.frames import root_link
from dyn_node.core.robot.model import Payload, load_model
from dyn_node.core.check.start_segment import stretched
from dyn_node.core.check.trajectory import validate_trajectory
from dyn_node.sim.mujoco_model import mujoco_from_model

TOL = 1e-9
FORCE, TORQUE = [3.0, -2.0, 20.0], [0.4, -0.3, 0.2]
WRENCH_FRAME = {"panda": "panda_link8", "ur5": "tool0", "tree": "c_tool"}
SQUARE = [[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]]


def configured(model, **sections):
    """``model`` with its armature and the given task sections."""
    return model.with_limits({**_armature(model), **sections})


def task_of(model, Q, V, A):
    return task_motion.build(Dynamics(model), Q, V, A)


def motion_of(model, Q, V, A) -> SimpleNamespace:
    """What a kind reads of a Motion, for states that are not a trajectory (every sample
    covered by the per-sample laws)."""
    n = len(Q)
    return SimpleNamespace(task=task_of(model, Q, V, A), rows=slice(0, None), r0=0, Q=Q,
                           smp=SimpleNamespace(t=np.arange(n) * 0.01, weight=np.full(n, 0.01)))


def mujoco_states(robot_, d, q, v, a):
    robot_.set_state(d, q, v)
    d.qacc[:] = 0.0
    d.qacc[robot_.dof_ids] = a


def push_back(mj, d, body: int, force_local, torque_local) -> None:
    """The environment's −W on ``body`` (W in its axes at its origin) as xfrc_applied, which
    MuJoCo takes at the body's centre of mass in world axes."""
    mujoco.mj_kinematics(mj, d)
    mujoco.mj_comPos(mj, d)
    R, o = d.xmat[body].reshape(3, 3), d.xpos[body]
    f, t = R @ np.asarray(force_local), R @ np.asarray(torque_local)
    d.xfrc_applied[:] = 0.0
    d.xfrc_applied[body, :3] = -f
    d.xfrc_applied[body, 3:] = -(t + np.cross(o - d.xipos[body], f))


def mujoco_mounting(model, Q, V, A, *, wrench: bool) -> np.ndarray:
    """M×6 [force; moment] the world exerts on the robot, at the URDF root's origin in its axes,
    from cfrc_int of the body hanging from the world after mj_inverse and mj_rnePostConstraint."""
    robot_ = mujoco_from_model(model)
    mj = robot_.model
    d = robot_.make_data()
    top = _mounting_body(mj)
    root = root_link(model.urdf)
    rid = mj.body(root).id if root != "world" else 0
    w = model.task_limits.task_wrench
    out = np.empty((len(Q), 6))
    for n in range(len(Q)):
        mujoco_states(robot_, d, Q[n], V[n], A[n])
        if wrench:
            push_back(mj, d, mj.body(w.frame).id, w.force, w.torque)
        mujoco.mj_inverse(mj, d)
        mujoco.mj_rnePostConstraint(mj, d)
        torque, force = d.cfrc_int[top, :3], d.cfrc_int[top, 3:]
        c, r, R = d.subtree_com[mj.body_rootid[top]], d.xpos[rid], d.xmat[rid].reshape(3, 3)
        out[n] = np.concatenate([R.T @ force, R.T @ (torque + np.cross(c - r, force))])
    return out


# --- (a) the mounting's wrench ------------------------------------------------------------------

@pytest.mark.parametrize("name", ["panda", "ur5", "tree"])
def test_mounting_wrench_with_a_task_wrench_matches_mujoco(name):
    """static + dynamic (k = 1) and static alone (the still states) against MuJoCo with −W on
    the tool; and the base kinds' values are the norms of those parts."""
    model, _ = _mujoco_model(name)
    model = configured(model, task_wrench={"frame": WRENCH_FRAME[name], "force": FORCE,
                                           "torque": TORQUE},
                       base_limits={"max_force": 1e4, "max_moment": 1e4})
    Q, V, A = states(model.nv, 30, 21)
    task = task_of(model, Q, V, A)
    ref = mujoco_mounting(model, Q, V, A, wrench=True)
    np.testing.assert_allclose(task.base.at(1.0), ref, rtol=0, atol=TOL)
    still = mujoco_mounting(model, Q, 0 * V, 0 * A, wrench=True)
    np.testing.assert_allclose(task.base.static, still, rtol=0, atol=TOL)
    # the task wrench changes the comparison (it is not W-free on both sides)
    assert np.abs(still - mujoco_mounting(model, Q, 0 * V, 0 * A, wrench=False)).max() > 1.0
    motion = motion_of(model, Q, V, A)
    for cls, cols in ((B.BaseForce, slice(0, 3)), (B.BaseMoment, slice(3, 6))):
        c = cls(motion)
        np.testing.assert_allclose(c.values()[:, 0], np.linalg.norm(ref[:, cols], axis=1),
                                   rtol=0, atol=TOL)
        np.testing.assert_allclose(c.law.static_value, np.linalg.norm(still[:, cols], axis=1),
                                   rtol=0, atol=TOL)


# --- (b) the grasp force ------------------------------------------------------------------------

SLIDER_URDF = """<robot name="slider">
  <link name="base"/>
  <link name="carriage"><inertial><mass value="2.0"/>
    <inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="hand"><inertial><origin xyz="0 0.02 0.03"/><mass value="0.5"/>
    <inertia ixx="0.001" iyy="0.001" izz="0.001" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="tcp"/>
  <joint name="x" type="prismatic"><parent link="base"/><child link="carriage"/>
    <origin xyz="0.1 0 0.5" rpy="0.3 0 0"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="100" velocity="1"/></joint>
  <joint name="z" type="prismatic"><parent link="carriage"/><child link="hand"/>
    <origin xyz="0 0.2 0" rpy="0 0.4 0.2"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="100" velocity="1"/></joint>
  <joint name="tcp_joint" type="fixed"><parent link="hand"/><child link="tcp"/>
    <origin xyz="0 0 0.1" rpy="0.1 -0.2 0.7"/></joint>
</robot>"""


def rpy(r: float, p: float, y: float) -> np.ndarray:
    """URDF's rpy: Rz(y)·Ry(p)·Rx(r)."""
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), \
        math.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


GRASP = {"frame": "tcp", "normal_axis": [0.0, 0.6, 0.8], "friction_coefficient": 0.5,
         "grip_force": 40.0, "faces": 2}


def test_grasp_force_of_a_point_mass_under_pure_translation():
    """Two prismatic joints only translate the tool: a_c = e1·q̈1 + e2·q̈2 with the axes e from
    the joint origins' rpy, whatever q̇; the grasp supplies m·(a_c − g), seen in the tool's axes
    (its rotation worked out the same way); its part across the normal axis is checked."""
    mass, g = 1.5, np.array([0.5, -1.0, -9.7])
    model = load_model(urdf=SLIDER_URDF, payload=Payload(mass, (0.02, -0.01, 0.05), "tcp"),
                       gravity=g).with_limits({"joint_limits": {}, "grasp": GRASP})
    Q, V, A = states(model.nv, 40, 22)
    R0 = rpy(0.3, 0, 0)
    R1 = R0 @ rpy(0, 0.4, 0.2)
    R_tcp = R1 @ rpy(0.1, -0.2, 0.7)
    a_c = np.outer(A[:, 0], R0[:, 0]) + np.outer(A[:, 1], R1[:, 2])
    static, dynamic = -mass * (R_tcp.T @ g), mass * a_c @ R_tcp
    n = np.array(GRASP["normal_axis"])
    across = np.linalg.norm(np.cross(static + dynamic, n), axis=1)   # |f − (f·n)n| = |f × n|
    motion = motion_of(model, Q, V, A)
    task = motion.task
    np.testing.assert_allclose(task.rotation[task.roles["grasp"]], np.tile(R_tcp, (40, 1, 1)),
                               rtol=0, atol=1e-12)
    f = B.grasp_force(task.frame("payload"), task.rotation[task.roles["grasp"]], g, mass)
    np.testing.assert_allclose(f.static, np.tile(static, (40, 1)), rtol=0, atol=TOL)
    np.testing.assert_allclose(f.dynamic, dynamic, rtol=0, atol=TOL)
    c = B.GraspSlip(motion)
    np.testing.assert_allclose(c.values()[:, 0], across, rtol=0, atol=TOL)
    assert c.law.limit == 0.5 * 40.0 * 2
    assert np.ptp(across) > 1.0       # the accelerations move the comparison


@pytest.mark.parametrize("name,grasp_frame", [("panda", "panda_hand"), ("tree", "f")])
def test_grasp_force_matches_mujoco_welded_payload(name, grasp_frame):
    """The payload as its own body welded at its frame (mujoco_from_model's payload body):
    cfrc_int of that body is the force its parent (the grasp) exerts on it, world axes, seen in
    the grasp frame's axes by MuJoCo's pose of that body."""
    model, _ = _mujoco_model(name)
    model = configured(model, grasp={**GRASP, "frame": grasp_frame})
    Q, V, A = states(model.nv, 30, 23)
    task = task_of(model, Q, V, A)
    f = B.grasp_force(task.frame("payload"), task.rotation[task.roles["grasp"]], task.gravity,
                      model.payload.mass)
    robot_ = mujoco_from_model(model)
    mj = robot_.model
    d = robot_.make_data()
    body, grip = mj.body("dyn_node_payload").id, mj.body(grasp_frame).id
    for n in range(len(Q)):
        mujoco_states(robot_, d, Q[n], V[n], A[n])
        mujoco.mj_inverse(mj, d)
        mujoco.mj_rnePostConstraint(mj, d)
        ref = d.xmat[grip].reshape(3, 3).T @ d.cfrc_int[body, 3:]
        np.testing.assert_allclose(f.static[n] + f.dynamic[n], ref, rtol=0, atol=TOL)
    assert np.abs(f.dynamic).max() > 1.0


# --- (c) tipping --------------------------------------------------------------------------------

BASE_MASS, BASE_COM = 20.0, [0.05, -0.02, 0.1]
TIPPING = {"support_polygon": SQUARE, "base_mass": BASE_MASS, "base_com": BASE_COM}


def upright(name: str):
    model, _ = _mujoco_model(name)
    return model.with_gravity([0.0, 0.0, -9.81])


@pytest.mark.parametrize("name", ["panda", "tree"])
def test_still_centre_of_pressure_is_the_centre_of_mass_below(name):
    """Still robot on a still base: the floor's centre of pressure is the horizontal position
    of the common centre of mass of robot (every body, payload included) and base."""
    model = configured(upright(name), base_limits=TIPPING)
    Q, V, A = states(model.nv, 20, 24)
    c = B.Tipping(motion_of(model, Q, 0 * V, 0 * A))
    pm = model.pin_model
    data = pm.createData()
    mass = model.total_mass
    for n, q in enumerate(Q):
        com = (mass * everything_com(pm, data, q) + BASE_MASS * np.array(BASE_COM)) / (
            mass + BASE_MASS)
        np.testing.assert_allclose(c.law.centre_of_pressure[n], com[:2], rtol=0, atol=TOL)
    # still: any timing inside the polygon, none outside (the law's k per sample)
    gauge = model.task_limits.base_limits.support_polygon.gauge(c.law.centre_of_pressure)
    np.testing.assert_array_equal(c.law.time_scale, np.where(gauge <= 1, 0.0, np.inf))


CART = ('<link name="cart"><inertial><origin xyz="{x} {y} {z}"/><mass value="{m}"/>'
        '<inertia ixx="1e-3" iyy="1e-3" izz="1e-3" ixy="0" ixz="0" iyz="0"/></inertial></link>'
        '<joint name="cart_joint" type="fixed"><parent link="{root}"/><child link="cart"/>'
        '</joint></robot>')


def test_centre_of_pressure_matches_mujoco_with_the_base_as_a_body():
    """The base's mass as a body fixed to the root in MuJoCo (the robot configured with
    base_mass instead): the floor's wrench is MuJoCo's mounting wrench of that robot, and the
    centre of pressure the point of the floor about which its horizontal moment vanishes
    (M − p × F)_xy = 0, with the task wrench pushed back through xfrc_applied."""
    model = configured(upright("panda"), base_limits=TIPPING,
                       task_wrench={"frame": "panda_link8", "force": FORCE, "torque": TORQUE})
    root = root_link(model.urdf)
    with_cart = load_model(urdf=model.urdf.replace("</robot>", CART.format(
        x=BASE_COM[0], y=BASE_COM[1], z=BASE_COM[2], m=BASE_MASS, root=root)),
        locked_joints=model.locked_joints, payload=model.payload, gravity=model.gravity)
    with_cart = configured(with_cart, task_wrench={"frame": "panda_link8", "force": FORCE,
                                                   "torque": TORQUE})
    Q, V, A = states(model.nv, 30, 25)
    V, A = 0.3 * V, 0.2 * A      # the robot stays on its feet
    c = B.Tipping(motion_of(model, Q, V, A))
    floor = mujoco_mounting(with_cart, Q, V, A, wrench=True)
    F, M = floor[:, :3], floor[:, 3:]
    cop = np.empty((len(Q), 2))
    for n in range(len(Q)):
        # (M − p × F)_x = M_x − p_y·F_z, (M − p × F)_y = M_y + p_x·F_z for p = (p_x, p_y, 0)
        cop[n] = np.linalg.solve(np.array([[0.0, F[n, 2]], [-F[n, 2], 0.0]]), M[n, :2])
    np.testing.assert_allclose(c.law.centre_of_pressure, cop, rtol=0, atol=TOL)
    np.testing.assert_allclose(c.law.normal_force, F[:, 2], rtol=0, atol=TOL)
    poly = model.task_limits.base_limits.support_polygon
    np.testing.assert_allclose(c.values()[:, 0], poly.gauge(cop), rtol=0, atol=1e-9)


# --- the kinds through check_trajectory ---------------------------------------------------------

PANDA = load_model(builtin="panda", payload=Payload(2.0, (0.0, 0.0, 0.05), "panda_hand"))
NAMES = list(PANDA.joint_names)
Q0 = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8])
DQ = np.array([1.5, 0.8, -0.6, 0.9, 0.7, -0.8, 1.0])
TRAJ = validate_trajectory(NAMES, NAMES, [0.0, 0.7], [Q0, Q0 + DQ], np.zeros((2, 7)),
                           np.zeros((2, 7)))
PERIOD = 0.004
OPTS = FeasibilityOptions(sample_period=PERIOD, compute_payload_margin=False)
GRIP = {"frame": "panda_hand", "normal_axis": [0.0, 1.0, 0.0], "friction_coefficient": 0.5,
        "faces": 2}
PLACE = {"base_force": "base_limits", "base_moment": "base_limits", "tipping": "base_limits",
         "grasp_slip": "grasp"}
KIND = {cls.kind: cls for cls in B.BASE_KINDS}


def only(**sections):
    """PANDA with the given task sections and no joint limit at all (so the kind under test is
    the only one that can bind)."""
    model = PANDA.with_limits({"joint_limits": {}, **sections})
    inf = np.full(model.nv, np.inf)
    free = replace(model.limits, velocity=inf, acceleration=inf, deceleration=inf, jerk=inf,
                   effort=inf, effort_rate=inf, power=inf, rms_effort=inf,
                   effort_speed_curve=(None,) * model.nv, position_lower=-inf,
                   position_upper=inf, soft_lower=-inf, soft_upper=inf)
    return replace(model, limits=free)


def sections(kind: str, x: float) -> dict:
    """The one section that configures ``kind`` with its limit (tipping: the square's half
    width, m; grasp: the friction cone's radius μ·grip_force·faces, N) at ``x``."""
    if kind == "tipping":
        square = [[-x, -x], [x, -x], [x, x], [-x, x]]
        return {"base_limits": {"support_polygon": square, "base_mass": BASE_MASS,
                                "base_com": BASE_COM}}
    if kind == "grasp_slip":
        return {"grasp": {**GRIP, "grip_force": x / (0.5 * 2)}}
    return {"base_limits": {"max_" + kind.split("_")[1]: x}}


def built(kind: str, model, traj=TRAJ, period: float = PERIOD):
    """The kind built on the sampled Motion the check uses."""
    motion, _ = F._motion(Dynamics(model), traj, replace(OPTS, sample_period=period), False, [])
    (c,) = C.build(motion, (KIND[kind],))
    return c, motion


def tuned(kind: str, where: float = 0.5):
    """The kind's limit ``where`` of the way from its still peak to its peak at k = 1 (tipping:
    the square scaled so that the gauge does the same), so that slowing down helps."""
    c, _ = built(kind, only(**sections(kind, 0.3 if kind == "tipping" else 1e5)))
    still, moving = float(np.max(c.law.static_value)), float(np.max(c.law.value))
    assert moving > 1.1 * still
    mid = still + where * (moving - still)
    return only(**sections(kind, 0.3 * mid if kind == "tipping" else mid))


def check(model, k: float = 1.0, **opts):
    """The check of TRAJ stretched by k, sampled at the same phases."""
    return check_trajectory(Dynamics(model), stretched(TRAJ, k),
                            replace(OPTS, sample_period=PERIOD * k, **opts))


@pytest.mark.parametrize("kind", list(PLACE))
def test_time_scale_contract(kind):
    """k from the per-sample laws: the trajectory stretched by 1.001·k (and far beyond) is
    feasible, some stretch in [0.97·k, k) is not; the kind and place are named, with its peak
    in per_frame, and the message is the kind's own text."""
    model = tuned(kind)
    r = check(model)
    k = r.time_scale
    assert not r.feasible and 1.0 < k < 10.0
    assert (r.time_scale_constraint, r.time_scale_joint) == (kind, PLACE[kind])
    assert r.worst_constraint == kind and r.worst_joint == PLACE[kind]
    entry = r.per_frame[PLACE[kind]][kind]
    assert entry["ratio"] > 1.0 and entry["unit"] == KIND[kind].unit
    (v,) = r.violations
    assert r.message.startswith("infeasible: " + KIND[kind].describe(v) + "; run ")
    (status,) = [s for s in r.statuses() if s.name.endswith("/" + PLACE[kind])]
    assert status.values[f"{kind}_ratio"] == entry["ratio"] and KIND[kind].describe(v) in \
        status.message
    for x in (1.001, 1.01, 1.5, 10.0):
        assert check(model, x * k).feasible, x
    assert not all(check(model, x * k).feasible for x in (0.97, 0.99, 0.999, 1 - 1e-5))
    # the laws are exact per sample, and the stretches keep the samples' phases: just below k
    # the binding sample is over
    assert not check(model, (1 - 1e-4) * k).feasible


def test_messages_name_the_grasp_frame_and_the_centre_of_pressure():
    r = check(tuned("grasp_slip"))
    e = r.per_frame["grasp"]["grasp_slip"]
    assert r.message.startswith(
        f"infeasible: grasp at panda_hand slips (tangential {e['value']:.1f} N of "
        f"{e['limit']:.1f} N) at t = {e['time_s']:.2f} s; run {r.time_scale:.2f}× slower")
    model = tuned("tipping")
    c, motion = built("tipping", model)
    n = c.law.peak_index
    x, y = c.law.centre_of_pressure[n]
    r = check(model)
    assert r.message.startswith(
        f"infeasible: tipping: centre of pressure ({x:.3f}, {y:.3f}) m outside the support "
        f"polygon (gauge {c.law.value[n]:.3g} of 1) at t = {motion.smp.t[n]:.2f} s; run ")
    assert r.violations[0].detail == f"({x:.3f}, {y:.3f})"
    assert r.violations[0].to_dict()["detail"] == f"({x:.3f}, {y:.3f})"


@pytest.mark.parametrize("kind,extra,reason", [
    ("base_force", {}, "gravity and the task wrench alone load the mounting with "),
    ("base_moment", {"task_wrench": {"frame": "panda_link8", "torque": [0.0, 0.0, 500.0]}},
     "gravity and the task wrench alone load the mounting with "),
    ("grasp_slip", {}, "the still payload slips at panda_hand: gravity alone needs "),
    ("tipping", {}, "the still robot's centre of pressure ("),
    ("tipping", {"task_wrench": {"frame": "panda_link0", "force": [0.0, 0.0, -2000.0]}},
     "the still robot and base lift off the floor"),
])
def test_no_slowdown_helps_where_the_still_pose_is_over(kind, extra, reason):
    """A limit the still pose (gravity and the task wrench) already exceeds: time_scale inf and
    the reason, as the joint kinds say it; the same at any slowdown."""
    c, _ = built(kind, only(**sections(kind, 0.3 if kind == "tipping" else 1e5), **extra))
    still = float(np.max(c.law.static_value))
    # the square shrunk until the still gauge is over 1 (lift-off: any square)
    limit = 0.3 * (0.9 * still if math.isfinite(still) else 1.0) if kind == "tipping" \
        else 0.9 * still
    model = only(**sections(kind, limit), **extra)
    r = check(model)
    assert math.isinf(r.time_scale) and r.time_scale_constraint == kind
    assert r.time_scale_joint == PLACE[kind] and not r.feasible
    assert reason in r.message and r.message.endswith("; no slowdown helps"), r.message
    assert r.message.startswith("infeasible: " + KIND[kind].describe(r.violations[0]) + "; ")
    assert not check(model, 100.0).feasible
    # inf (lift-off's gauge, the time scale) goes to the evidence as "inf", never as bare NaN/inf
    text = json.dumps(r.to_dict(), allow_nan=False)
    assert kind in text and '"time_scale": "inf"' in text


def margin_by_bisection(model) -> float:
    """The largest extra payload mass (kg) with which the check itself passes, by bisection
    (the feasible masses form an interval around the trajectory's own)."""
    p = model.payload

    def ok(extra: float) -> bool:
        return check(model.with_payload(replace(p, mass=p.mass + extra))).feasible

    assert ok(0.0)
    hi = 1.0
    while ok(hi):
        hi *= 2
        if hi > 1e4:
            return math.inf
    lo = hi / 2 if hi > 1.0 else 0.0
    while hi - lo > 1e-9 * max(1.0, hi):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return lo


@pytest.mark.parametrize("kind", list(PLACE))
def test_payload_margin_against_bisection_with_the_check(kind):
    """payload_margin_kg from the kinds' exact intervals (linear, quadratic, linear-fractional
    in the mass) against the check re-run with heavier payloads."""
    model = tuned(kind, where=1.4)            # above the peak: feasible at the given timing
    r = check(model, compute_payload_margin=True)
    assert r.feasible and 0.0 < r.payload_margin_kg < 1e3
    assert r.payload_margin_kg == pytest.approx(margin_by_bisection(model), rel=1e-6)


@pytest.mark.parametrize("kind", ["grasp_slip", "tipping"])
def test_time_scale_contract_from_a_moving_start(kind):
    """The first point 0.2 s ahead of a robot still moving: that segment does not stretch with k
    (the per-sample laws cover the rest, the start-segment search the whole); the contract
    holds on the trajectory stretched from the same state."""
    model = tuned(kind)
    traj = replace(TRAJ, times=TRAJ.times + 0.2)
    start = StartState(positions=Q0 - 0.05 * DQ, velocities=0.2 * DQ, age_s=0.0)
    dyn = Dynamics(model)

    def run(k: float):
        return check_trajectory(dyn, stretched(traj, k), replace(OPTS, sample_period=PERIOD * k),
                                start=start)

    r = run(1.0)
    k = r.time_scale
    assert r.start_segment == "checked" and not r.feasible and 1.0 < k < 10.0
    assert r.time_scale_constraint == kind
    assert run(1.001 * k).feasible and run(1.5 * k).feasible
    assert not all(run(x * k).feasible for x in (0.97, 0.99, 0.999))


def test_a_payload_lowered_fast_holds_but_no_slowdown_does():
    """The band case: the tool accelerates downward at 0.9 g, so the grasp carries a tenth of
    the payload's weight and holds at the given timing, but the still payload would slip: no k
    makes every slower k′ feasible (time_scale inf, the reason given), as for the joint
    kinds whose gravity torque alone is over."""
    R1 = rpy(0.3, 0, 0) @ rpy(0, 0.4, 0.2)
    R_tcp = R1 @ rpy(0.1, -0.2, 0.7)
    g0, mass = 9.81, 1.5
    across = R_tcp.T @ R1[:, 0]                      # a grip axis across the slide
    model = load_model(urdf=SLIDER_URDF, payload=Payload(mass, (0.0, 0.0, 0.0), "tcp"),
                       gravity=-g0 * R1[:, 2]).with_limits(
        {"joint_limits": {}, "grasp": {**GRASP, "normal_axis": across.tolist(),
                                       "grip_force": 0.5 * mass * g0}})   # μ·faces = 1
    Q, V = np.zeros((2, 2)), np.zeros((2, 2))
    A = np.array([[0.0, -0.9 * g0], [0.0, -0.95 * g0]])
    motion = motion_of(model, Q, V, A)
    c = B.GraspSlip(motion)
    np.testing.assert_allclose(c.values()[:, 0], [0.1 * mass * g0, 0.05 * mass * g0], rtol=1e-12)
    assert c.report(motion)[1] == []
    assert math.isinf(c.time_scale()[0])
    assert c.blocked().reason.startswith(
        f"the still payload slips at tcp: gravity alone needs {mass * g0:.1f} N tangential of "
        f"{0.5 * mass * g0:.1f} N at q = [0, 0]")


def test_all_four_together_share_the_time_scale():
    """Configured together, each kind keeps the factor it has alone (time_scale_by_kind), the
    largest sets time_scale, and base_limits' status carries its three kinds."""
    alone = {kind: check(tuned(kind)) for kind in PLACE}
    limit = {kind: alone[kind].per_frame[PLACE[kind]][kind]["limit"] for kind in PLACE}
    square = tuned("tipping").task_limits.base_limits.support_polygon.vertices.tolist()
    model = only(base_limits={"max_force": limit["base_force"], "max_moment": limit["base_moment"],
                              "support_polygon": square, "base_mass": BASE_MASS,
                              "base_com": BASE_COM},
                 grasp={**GRIP, "grip_force": limit["grasp_slip"] / (0.5 * 2)})
    r = check(model)
    for kind in PLACE:
        assert r.time_scale_by_kind[kind] == pytest.approx(alone[kind].time_scale, rel=1e-12)
    worst = max(PLACE, key=lambda kind: alone[kind].time_scale)
    assert r.time_scale_constraint == worst
    assert r.time_scale == pytest.approx(alone[worst].time_scale, rel=1e-12)
    assert set(r.per_frame["base_limits"]) == {"base_force", "base_moment", "tipping"}
    assert len(r.violations) == 4
