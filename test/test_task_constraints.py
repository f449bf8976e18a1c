"""The frame and robot kinds in the feasibility check (issue #18): their numbers against MuJoCo,
Pinocchio and finite differences, the task wrench in the torques, the time-scale contract, the
payload margin, the statuses and bad configuration."""
from __future__ import annotations

import math

import mujoco
import numpy as np
import pinocchio as pin
import pytest
from test_frames import _mujoco_sites

from dyn_node.core.check import feasibility, on_demand
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
from dyn_node.core.check.frames import FramePoint
from dyn_node.core.robot.model import Payload, load_model
from dyn_node.core.check.task_constraints import KineticEnergy, TransferredEnergy
from dyn_node.errors import ModelError
from dyn_node.sim.mujoco_model import mujoco_from_model

TOL = 1e-9
POINT = (0.0, 0.0, 0.1)
PAYLOAD = Payload(1.5, (0.01, -0.02, 0.08), "panda_hand")
HOME = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8])
STEP = np.array([0.8, 0.4, -0.3, 0.5, 0.2, -0.3, 0.5])
WRENCH = {"frame": "panda_link8", "force": [3.0, -2.0, 20.0], "torque": [0.4, -0.3, 0.2]}
FRAME_KINDS = {"frame_speed": "max_linear_speed", "frame_angular_speed": "max_angular_speed",
               "frame_acceleration": "max_linear_acceleration",
               "transferred_energy": "max_transferred_energy"}


def limits(frame: dict | None = None, robot: dict | None = None, wrench: dict | None = None,
           joint: dict | None = None) -> dict:
    out: dict = {"joint_limits": joint or {}}
    if frame:
        out["frame_limits"] = {"panda_link8": {"point": list(POINT), **frame}}
    if robot:
        out["robot_limits"] = robot
    if wrench:
        out["task_wrench"] = wrench
    return out


def panda(yaml: dict, payload: Payload = PAYLOAD):
    return load_model(builtin="panda", limits_yaml=yaml, payload=payload)


def traj(T: float = 1.5, n: int = 7) -> feasibility.Trajectory:
    """A rest-to-rest move, positions and velocities (cubic, as the controller runs it;
    positions alone would be linear, with velocity steps)."""
    t = np.linspace(0.0, T, n)
    P = HOME + np.outer((1 - np.cos(np.pi * t / T)) / 2, STEP)
    V = np.outer(np.pi / (2 * T) * np.sin(np.pi * t / T), STEP)
    return feasibility.Trajectory(times=t, positions=P, velocities=V)


def stretch(tr, k: float):
    return feasibility.Trajectory(times=tr.times * k, positions=tr.positions,
                                  velocities=tr.velocities / k)


def motion(model, tr):
    return feasibility._motion(Dynamics(model), tr, FeasibilityOptions(), False, [])[0]


ALL = limits(frame={"max_linear_speed": 10.0, "max_angular_speed": 50.0,
                    "max_linear_acceleration": 100.0, "max_transferred_energy": 50.0},
             robot={"max_kinetic_energy": 50.0})


def test_sample_values_match_mujoco_and_the_peaks_are_theirs():
    """Per check sample: the point's speed, the frame's angular speed (mj_objectVelocity at a
    site at the point), the classical acceleration (mj_objectAcceleration less gravity after
    mj_inverse) and the kinetic energy (energy[1]); the per_frame peaks are their maxima."""
    model = panda(ALL)
    tr = traj()
    m = motion(model, tr)
    r = check_trajectory(Dynamics(model), tr)
    mj, (site,) = _mujoco_sites(model, [FramePoint("panda_link8", POINT)])
    d = mujoco.MjData(mj)
    robot = mujoco_from_model(model)      # the payload as a body: for the energy
    robot.model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_ENERGY)
    rd = robot.make_data()
    joints = [mj.joint(n) for n in model.joint_names]
    g = np.asarray(model.gravity)
    rows = np.arange(0, len(m.smp.t), 7)
    ref = np.zeros((len(rows), 4))
    res = np.zeros(6)
    for i, n in enumerate(rows):
        robot.set_state(rd, m.Q[n], m.V[n])
        mujoco.mj_forward(robot.model, rd)
        ref[i, 3] = rd.energy[1]
        for j, J in enumerate(joints):
            d.qpos[J.qposadr[0]], d.qvel[J.dofadr[0]] = m.Q[n, j], m.V[n, j]
            d.qacc[J.dofadr[0]] = m.A[n, j]
        mujoco.mj_inverse(mj, d)
        mujoco.mj_rnePostConstraint(mj, d)
        mujoco.mj_objectVelocity(mj, d, mujoco.mjtObj.mjOBJ_SITE, site, res, 0)
        ref[i, 0], ref[i, 1] = np.linalg.norm(res[3:]), np.linalg.norm(res[:3])
        mujoco.mj_objectAcceleration(mj, d, mujoco.mjtObj.mjOBJ_SITE, site, res, 0)
        ref[i, 2] = np.linalg.norm(res[3:] + g)
    kinds = ("frame_speed", "frame_angular_speed", "frame_acceleration")
    from dyn_node.core.check import constraints
    from dyn_node.core.check.kinds import KINDS
    built = {c.kind: c for c in constraints.build(m, KINDS)}
    got = np.column_stack([built[k].value[rows, 0] for k in (*kinds, "kinetic_energy")])
    np.testing.assert_allclose(got, ref, rtol=0, atol=TOL)
    assert ref.min(axis=0)[0] < 1e-6 < ref.max(axis=0).min()   # rest at the ends, moving between
    pf = r.per_frame
    for c, k in enumerate(kinds):
        assert pf["panda_link8"][k]["value"] == built[k].value[:, 0].max()
        assert pf["panda_link8"][k]["ratio"] == pytest.approx(
            built[k].value[:, 0].max() / pf["panda_link8"][k]["limit"], rel=1e-15)
    assert pf["robot_limits"]["kinetic_energy"]["value"] == built["kinetic_energy"].value.max()
    assert set(pf) == {"panda_link8", "robot_limits"}


def test_sample_values_match_finite_differences_of_forward_kinematics():
    """v = dp/dt and a = d²p/dt² of Pinocchio's frame placement along q + t·q̇ + ½t²·q̈ (central
    differences), ω from the rotation's derivative; m_u from a dense solve."""
    model = panda(ALL)
    m = motion(model, traj())
    from dyn_node.core.check import constraints
    from dyn_node.core.check.kinds import KINDS
    built = {c.kind: c for c in constraints.build(m, KINDS)}
    pm = model.pin_model.copy()
    data = pm.createData()
    fid = pm.getFrameId("panda_link8")
    off = np.array(POINT)
    h = 1e-4

    def pose(q):
        pin.framesForwardKinematics(pm, data, q)
        M = data.oMf[fid]
        return M.translation + M.rotation @ off, M.rotation.copy()

    worst = {}
    for n in range(40, len(m.smp.t) - 40, 97):
        q, v, a = m.Q[n], m.V[n], m.A[n]
        (pm_, Rm), (p0, R0), (pp, Rp) = (pose(q + t * v + 0.5 * t * t * a) for t in (-h, 0, h))
        vel, acc = (pp - pm_) / (2 * h), (pp - 2 * p0 + pm_) / (h * h)
        W = (Rp - Rm) / (2 * h) @ R0.T
        omega = np.array([W[2, 1], W[0, 2], W[1, 0]])
        for key, got, want in (("speed", built["frame_speed"].value[n, 0], np.linalg.norm(vel)),
                               ("omega", built["frame_angular_speed"].value[n, 0],
                                np.linalg.norm(omega)),
                               ("acc", built["frame_acceleration"].value[n, 0],
                                np.linalg.norm(acc))):
            worst[key] = max(worst.get(key, 0.0), abs(got - want))
        pin.computeJointJacobians(pm, data, q)
        J = pin.getFrameJacobian(pm, data, fid, pin.LOCAL_WORLD_ALIGNED)
        Jv = J[:3] - pin.skew(data.oMf[fid].rotation @ off) @ J[3:]
        Mq = pin.crba(pm, data, q)
        Mq = np.triu(Mq) + np.triu(Mq, 1).T
        u = Jv @ v / np.linalg.norm(Jv @ v)
        e = 0.5 * np.linalg.norm(Jv @ v) ** 2 / (u @ Jv @ np.linalg.solve(Mq, Jv.T @ u))
        worst["energy"] = max(worst.get("energy", 0.0),
                              abs(built["transferred_energy"].value[n, 0] - e) / e)
    assert worst["speed"] < 1e-7 and worst["omega"] < 1e-7 and worst["acc"] < 1e-5, worst
    assert worst["energy"] < TOL, worst


def test_task_wrench_torques_against_mujoco_xfrc_applied_and_the_jacobian_identity():
    """τ at the waypoints (the check's waypoint_effort, ~/trajectory_effort) and from
    inverse_dynamics_request: RNEA + J_localᵀW (Pinocchio's LOCAL Jacobian), bit-identical
    between the two, and with MuJoCo pushing the flange with −W (xfrc_applied) those joint
    torques give back q̈."""
    model = panda(limits(wrench=WRENCH))
    bare = panda(limits())
    tr = traj(n=5)
    dyn = Dynamics(model)
    r = check_trajectory(dyn, tr)
    r0 = check_trajectory(Dynamics(bare), tr)
    m = motion(model, tr)
    idx = np.concatenate((m.smp.first, m.smp.last[-1:]))
    Q, V, A = m.Q[idx], np.ascontiguousarray(m.V[idx]), np.ascontiguousarray(m.A[idx])
    tau = on_demand.inverse_dynamics(dyn, Q, V, A)
    assert np.array_equal(tau, r.waypoint_effort)
    pm = model.pin_model.copy()
    data = pm.createData()
    fid = pm.getFrameId("panda_link8")
    W = np.array(WRENCH["force"] + WRENCH["torque"])
    robot = mujoco_from_model(model)
    mj, d = robot.model, robot.make_data()
    body = mj.body("panda_link8").id
    worst = 0.0
    for n in range(len(Q)):
        J = pin.computeFrameJacobian(pm, data, Q[n], fid, pin.LOCAL)
        np.testing.assert_allclose(tau[n] - r0.waypoint_effort[n], J.T @ W, rtol=0, atol=TOL)
        robot.set_state(d, Q[n], V[n])
        mujoco.mj_kinematics(mj, d)
        mujoco.mj_comPos(mj, d)
        R, o = d.xmat[body].reshape(3, 3), d.xpos[body]
        f, t = R @ W[:3], R @ W[3:]
        d.xfrc_applied[:] = 0.0
        d.xfrc_applied[body, :3] = -f
        d.xfrc_applied[body, 3:] = -(t + np.cross(o - d.xipos[body], f))
        robot.apply_torque(d, tau[n])
        mujoco.mj_forward(mj, d)
        worst = max(worst, np.abs(robot.get_qacc(d) - A[n]).max())
    assert worst < 1e-8
    assert np.abs(tau - r0.waypoint_effort).max() > 1.0


def test_task_wrench_enters_the_effort_time_scale_and_says_when_no_slowdown_helps():
    """The wrench is static: an effort limit below gravity + J_ᵀW at rest blocks every
    slowdown; between, the time scale keeps its contract with the wrench included."""
    model = panda(limits(wrench=WRENCH))
    m = motion(model, traj())
    j = int(np.argmax(np.abs(m.task.task_torque).max(axis=0)))   # the joint the wrench loads most
    peak_static = np.abs(m.S[:, j]).max()
    name = model.joint_names[j]
    blocked = panda(limits(wrench=WRENCH, joint={name: {"max_effort": 0.99 * peak_static}}))
    rb = check_trajectory(Dynamics(blocked), traj())
    assert not rb.feasible and rb.time_scale == math.inf
    assert "task wrench" in rb.message and "no slowdown helps" in rb.message
    peak = np.abs(m.tau[:, j]).max()
    lim = 0.5 * (peak + peak_static)
    limited = panda(limits(wrench=WRENCH, joint={name: {"max_effort": lim}}))
    _contract(limited, "effort")


def _contract(model, kind: str) -> float:
    """1.001·k feasible, some k′ in [0.97·k, k) not; returns k."""
    dyn = Dynamics(model)
    tr = traj()
    r = check_trajectory(dyn, tr)
    k = r.time_scale
    assert r.time_scale_constraint == kind and 1.0 < k < 10.0, (r.message, k)
    assert check_trajectory(dyn, stretch(tr, 1.001 * k)).feasible
    assert any(not check_trajectory(dyn, stretch(tr, f * k)).feasible
               for f in (0.999, 0.99, 0.97))
    return k


@pytest.mark.parametrize("kind", [*FRAME_KINDS, "kinetic_energy"])
def test_time_scale_contract_per_kind(kind):
    """The limit set below the move's peak: the check's k keeps the contract, and it is the
    closed form (speeds ∝ 1/k: k = peak/limit; accelerations and energies ∝ 1/k²: √)."""
    base = check_trajectory(Dynamics(panda(ALL)), traj())
    place = "robot_limits" if kind == "kinetic_energy" else "panda_link8"
    peak = base.per_frame[place][kind]["value"]
    lim = 0.6 * peak
    yaml = limits(robot={"max_kinetic_energy": lim}) if kind == "kinetic_energy" else \
        limits(frame={FRAME_KINDS[kind]: lim})
    k = _contract(panda(yaml), kind)
    power = 1 if kind in ("frame_speed", "frame_angular_speed") else 2
    assert k == pytest.approx((1 / 0.6) ** (1 / power), rel=1e-12)
    r = check_trajectory(Dynamics(panda(yaml)), traj())
    (v,) = r.violations
    assert (v.joint, v.kind, v.limit) == (place, kind, lim)


def test_payload_margin_of_the_energies_is_exact():
    """Kinetic energy: the band's end puts the peak on the limit (affine in mass); transferred
    energy: the bisection's end likewise, on the model re-loaded with that payload."""
    y = limits(frame={"max_transferred_energy": 0.5}, robot={"max_kinetic_energy": 0.8})
    model = panda(y)
    m = motion(model, traj())
    for cls, place in ((KineticEnergy, "robot_limits"), (TransferredEnergy, "panda_link8")):
        lo, hi = cls(m).payload_band(m, None)
        assert lo == -math.inf and 0.0 < hi < 50.0, (cls, hi)
        heavy = panda(y, Payload(PAYLOAD.mass + hi, PAYLOAD.com, PAYLOAD.frame))
        r = check_trajectory(Dynamics(heavy), traj(), FeasibilityOptions(
            compute_payload_margin=False))
        lim = 0.8 if cls is KineticEnergy else 0.5
        assert r.per_frame[place][cls.kind]["value"] == pytest.approx(lim, rel=1e-8)
    r = check_trajectory(Dynamics(model), traj())
    assert 0.0 < r.payload_margin_kg < 50.0


def test_statuses_per_place_and_the_summary():
    y = limits(frame={"max_linear_speed": 0.25, "max_transferred_energy": 2.0},
               robot={"max_kinetic_energy": 5.0})
    r = check_trajectory(Dynamics(panda(y)), traj())
    sts = {s.name: s for s in r.statuses()}
    frame = sts["dyn_node: trajectory feasibility/panda_link8"]
    robot = sts["dyn_node: trajectory feasibility/robot_limits"]
    assert frame.level == 2 and robot.level == 0
    assert frame.message.startswith("panda_link8 speed ") and "of 0.25 m/s at t = " in frame.message
    assert set(frame.values) == {f"{k}_{x}" for k in ("frame_speed", "transferred_energy")
                                 for x in ("ratio", "time_s", "peak", "limit", "unit")} | {"failure_label"}
    assert (frame.values["frame_speed_unit"], robot.values["kinetic_energy_unit"]) == ("m/s", "J")
    assert frame.values["frame_speed_ratio"] == r.per_frame["panda_link8"]["frame_speed"]["ratio"]
    assert robot.values["kinetic_energy_limit"] == 5.0 and robot.values["failure_label"] == ""
    assert r.worst_joint == "panda_link8" and r.worst_constraint == "frame_speed"
    assert r.time_scale_joint == "panda_link8" and r.time_scale_constraint == "frame_speed"
    assert r.message.startswith("infeasible: panda_link8 speed ")
    d = r.to_dict()
    assert d["per_frame"]["robot_limits"]["kinetic_energy"]["unit"] == "J"
    assert "task_curves" not in d
    # the plot curves: each bin's largest sample, so the peak and its time survive
    for place, kinds in r.per_frame.items():
        for kind, e in kinds.items():
            t, v = r.task_curves[place][kind]
            assert len(t) == len(v) == feasibility.CURVE_POINTS < r.n_samples
            assert v.max() == e["value"] and t[np.argmax(v)] == e["time_s"]
            assert np.all(np.diff(t) > 0)
    assert d["violations"][0]["joint"] == "panda_link8"
    # feasible: the worst place's kind leads the message
    ok = check_trajectory(Dynamics(panda(limits(robot={"max_kinetic_energy": 0.05}))),
                          stretch(traj(), 3.0))
    assert ok.feasible and ok.message.startswith("feasible: worst robot_limits kinetic energy ")


@pytest.mark.parametrize("section, words", [
    ({"frame_limits": {"panda_lnk8": {"max_linear_speed": 0.25}}}, ["frame 'panda_lnk8'",
                                                                    "panda_link8"]),
    ({"task_wrench": {"frame": "tool", "force": [0, 0, 20]}}, ["task_wrench.frame", "'tool'"]),
    ({"frame_limits": {"panda_link8": {"max_linear_speed": float("nan")}}},
     ["frame_limits.panda_link8.max_linear_speed"]),
    ({"robot_limits": {"max_kinetic_energy": -1.0}}, ["robot_limits.max_kinetic_energy"]),
    ({"frame_limits": {"panda_link8": {"max_linear_sped": 0.25}}}, ["did you mean "
                                                                     "'max_linear_speed'"]),
])
def test_bad_configuration_is_named(section, words):
    with pytest.raises(ModelError) as err:
        load_model(builtin="panda", limits_yaml={"joint_limits": {}, **section})
    for w in words:
        assert w in str(err.value), str(err.value)


def test_without_task_sections_nothing_changes():
    """A file with joint limits only: no task motion, no places, and the same verdict bits as
    before (the joint tables and message)."""
    y = {"joint_limits": {"panda_joint1": {"max_velocity": 0.3}}}
    model = panda(y)
    assert motion(model, traj()).task is None
    r = check_trajectory(Dynamics(model), traj())
    assert r.per_frame == {} and "per_frame" in r.to_dict()
    assert [s.name for s in r.statuses()][-1] == "dyn_node: trajectory feasibility/panda_joint7"


def test_the_mounting_takes_the_task_wrench_back():
    """TaskMotion.base: with a task wrench, its static part gains +W moved to the root origin
    (root axes: Pinocchio's oMf of the frame), the dynamic part is unchanged; the task torque
    is J_localᵀ·W."""
    base = {"base_limits": {"max_force": 1000.0}}
    m1 = motion(panda({**limits(wrench=WRENCH), **base}), traj())
    m0 = motion(panda({**limits(), **base}), traj())
    assert m1.task.base is not None and m0.task.task_torque is None
    pm = m1.dynamics.model.pin_model.copy()
    data = pm.createData()
    fid = pm.getFrameId("panda_link8")
    W = np.array(WRENCH["force"] + WRENCH["torque"])
    rows = np.arange(0, len(m1.smp.t), 211)
    for n in rows:
        pin.framesForwardKinematics(pm, data, m1.Q[n])
        R, p = data.oMf[fid].rotation, data.oMf[fid].translation
        f = R @ W[:3]
        want = np.concatenate([f, R @ W[3:] + np.cross(p, f)])
        np.testing.assert_allclose(m1.task.base.static[n] - m0.task.base.static[n], want,
                                   rtol=0, atol=TOL)
        J = pin.computeFrameJacobian(pm, data, m1.Q[n], fid, pin.LOCAL)
        np.testing.assert_allclose(m1.task.task_torque[n], J.T @ W, rtol=0, atol=TOL)
        np.testing.assert_allclose(m1.task.rotation[m1.task.roles["wrench"], n], R, rtol=0,
                                   atol=1e-12)
    assert np.array_equal(m1.task.base.dynamic, m0.task.base.dynamic)
    # the joint torques carry it as a static term: S and τ move by it, the rest does not
    np.testing.assert_allclose(m1.S - m0.S, m1.tau - m0.tau, rtol=0, atol=1e-12)
    np.testing.assert_allclose(m1.S - m0.S, m1.task.task_torque, rtol=0, atol=1e-12)
    assert np.array_equal(m1.I, m0.I) and np.array_equal(m1.W, m0.W)


def test_a_moving_start_segment_keeps_the_contract_with_a_task_kind():
    """With the robot moving when the trajectory arrives (a start segment that does not
    stretch), the frame speed's k still holds: 1.001·k feasible, 0.99·k not."""
    model = panda(limits(frame={"max_linear_speed": 0.25}, wrench=WRENCH))
    dyn = Dynamics(model)
    tr = traj()
    late = feasibility.Trajectory(times=tr.times + 0.5, positions=tr.positions, velocities=tr.velocities)
    st = feasibility.StartState(positions=HOME - 0.05, velocities=np.full(7, 0.1), age_s=0.0)
    r = check_trajectory(dyn, late, start=st)
    k = r.time_scale
    assert r.time_scale_constraint == "frame_speed" and 1.0 < k < 5.0

    def at(f):
        return check_trajectory(dyn, feasibility.Trajectory(times=late.times * k * f, positions=late.positions,
                                                            velocities=late.velocities / (k * f)), start=st)
    assert at(1.001).feasible and not at(0.99).feasible
