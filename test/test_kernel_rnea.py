"""The frame kernel's RNEA (issue #18, "Speed"): with a task section the check takes its torque
terms from the frame pass instead of Pinocchio's batched RNEA. Checked against Pinocchio
(rnea, computeGeneralizedGravity) with friction, armature, payload and tilted gravity, against
Dynamics.terms_batch's split, and through the check and inverse_dynamics."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pinocchio as pin
import pytest
from robots import BRANCHED_URDF, with_friction_urdf

from dyn_node.core.check import feasibility, on_demand, task_motion
from dyn_node.core.compiled import rigid_kernels
from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
from dyn_node.core.check.frames import FrameKinematics, FramePoint
from dyn_node.core.robot.model import Payload, builtin_urdf, load_model
from dyn_node.errors import ModelError

TOL = 1e-9
WRENCH = {"frame": "panda_link8", "force": [3.0, -2.0, 20.0], "torque": [0.4, -0.1, 0.2]}
SECTIONS = {
    "frame_limits": {"panda_link8": {"point": [0.0, 0.0, 0.1], "max_linear_speed": 5.0}},
    "task_wrench": WRENCH,
    "base_limits": {"max_force": 900.0, "max_moment": 400.0},
}
HOME = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8])
STEP = np.array([0.8, 0.4, -0.3, 0.5, 0.2, -0.3, 0.5])


def robot(name: str, sections: dict | None = None):
    """(model, a frame of it): friction, armature, a payload; the tree (a prismatic joint,
    branches) under tilted gravity."""
    if name == "tree":
        model = load_model(urdf=with_friction_urdf(BRANCHED_URDF), gravity=(1.1, -2.3, -9.5),
                           payload=Payload(1.5, (0.02, -0.03, 0.05), "f"))
        frame = "c_tool"
    else:
        base = load_model(builtin=name)
        model = load_model(urdf=with_friction_urdf(builtin_urdf(name)),
                           locked_joints=dict(base.locked_joints),
                           payload=Payload(1.2, (0.01, -0.02, 0.05)))
        frame = "panda_link8" if name == "panda" else "tool0"
    joints = {n: {"armature": 0.05 + 0.01 * i} for i, n in enumerate(model.joint_names)}
    return model.with_limits({"joint_limits": joints, **(sections or {})}), frame


def states(nv: int, n: int = 60, seed: int = 5):
    """Random states, with rows at rest and rows with some joints at v = 0 (sign(0) = 0)."""
    rng = np.random.default_rng(seed)
    Q, V, A = (rng.uniform(-2.5, 2.5, (n, nv)), rng.uniform(-2, 2, (n, nv)),
               rng.uniform(-6, 6, (n, nv)))
    V[:5] = A[:5] = 0.0
    V[5:10, ::2] = 0.0
    return Q, V, A


def pinocchio_terms(model, options: DynamicsOptions, Q, V, A):
    """(static, full) by Pinocchio per state: g(q) + coulomb·sign(v), rnea + friction."""
    pm = model.pin_model.copy()
    if not options.include_armature:
        pm.armature = np.zeros(pm.nv)
    data = pm.createData()
    damping, coulomb = (np.array(x) if options.include_friction else np.zeros(pm.nv)
                        for x in (pm.damping, pm.friction))
    G = np.array([pin.computeGeneralizedGravity(pm, data, q) for q in Q])
    R = np.array([pin.rnea(pm, data, q, v, a) for q, v, a in zip(Q, V, A)])
    return G + coulomb * np.sign(V), R + damping * V + coulomb * np.sign(V), damping


@pytest.mark.parametrize("name", ["panda", "ur5", "tree"])
def test_frame_pass_rnea_matches_pinocchio_whatever_else_is_computed(name):
    """τ = rnea (armature·a included) and g(q) = computeGeneralizedGravity to 1e-9, with the same
    bits whichever other parts the pass computes (the check's and inverse_dynamics' calls)."""
    model, frame = robot(name)
    Q, V, A = states(model.nv)
    fk = FrameKinematics(model, [FramePoint(frame, (0.0, 0.0, 0.1), (1.0, 2.0, 3.0, 0, 0, 0))],
                         unit_mass_point=0)
    tau, g = fk.compute(Q, V, A, inertia=False, base=False, rnea=True).rnea
    pm, data = model.pin_model, model.pin_model.createData()
    assert np.abs(pm.armature).min() > 0 and np.abs(tau).max() > 10.0
    for n in range(len(Q)):
        np.testing.assert_allclose(tau[n], pin.rnea(pm, data, Q[n], V[n], A[n]), rtol=0, atol=TOL)
        np.testing.assert_allclose(g[n], pin.computeGeneralizedGravity(pm, data, Q[n]), rtol=0,
                                   atol=TOL)
    every = fk.compute(Q, V, A, inertia=True, base=True, unit_mass=True, rnea=True)
    assert np.array_equal(every.rnea[0], tau) and np.array_equal(every.rnea[1], g)
    assert fk.compute(Q, V, A).rnea is None


@pytest.mark.parametrize("name", ["panda", "tree"])
@pytest.mark.parametrize("friction,armature", [(True, True), (False, True), (True, False)])
def test_task_torque_terms_are_terms_batch_split(name, friction, armature):
    """The split of the frame pass's RNEA: static (g + Coulomb), viscous (damping·v, the same
    bits), inertial (none at rest) and full, against Pinocchio and Dynamics.terms_batch."""
    model, frame = robot(name)
    options = DynamicsOptions(include_friction=friction, include_armature=armature)
    dyn = Dynamics(model, options)
    Q, V, A = states(model.nv)
    fk = FrameKinematics(model, [FramePoint(frame)], include_armature=armature)
    terms = task_motion.torque_terms(dyn, fk.compute(Q, V, A, inertia=False, base=False,
                                                     rnea=True), V, A)
    static, full, damping = pinocchio_terms(model, options, Q, V, A)
    np.testing.assert_allclose(terms.static, static, rtol=0, atol=TOL)
    np.testing.assert_allclose(terms.full, full, rtol=0, atol=TOL)
    assert np.array_equal(terms.viscous, damping * V) and not terms.inertial[:5].any()
    assert np.abs(terms.inertial[5:]).min() > 0
    ref = dyn.terms_batch(Q, V, A)
    for part in ("static", "viscous", "inertial", "full"):
        np.testing.assert_allclose(getattr(terms, part), getattr(ref, part), rtol=0, atol=TOL)
        assert getattr(terms, part).flags.f_contiguous      # as terms_batch's: per-joint runs


def traj(T: float = 1.2, n: int = 6) -> feasibility.Trajectory:
    t = np.linspace(0.0, T, n)
    return feasibility.Trajectory(times=t, positions=HOME + np.outer(
        (1 - np.cos(np.pi * t / T)) / 2, STEP))


def _no_pinocchio_pass(monkeypatch) -> list[int]:
    """Count Pinocchio's batched RNEA and the compiled gravity pass."""
    calls = [0]
    rigid, gravity = Dynamics._rigid_columns, rigid_kernels.gravity_rows

    def counted(f):
        def run(*args, **kwargs):
            calls[0] += 1
            return f(*args, **kwargs)
        return run

    monkeypatch.setattr(Dynamics, "_rigid_columns", counted(rigid))
    monkeypatch.setattr(rigid_kernels, "gravity_rows", counted(gravity))
    return calls


@pytest.mark.parametrize("margin", [True, False])
def test_a_check_makes_one_compiled_pass_and_pinocchios_only_where_the_kernel_cannot(
        monkeypatch, margin):
    calls = _no_pinocchio_pass(monkeypatch)
    model, _ = robot("panda", SECTIONS)
    check_trajectory(Dynamics(model), traj(),
                     FeasibilityOptions(compute_payload_margin=margin, threads=2))
    assert calls[0] == 0
    bare, _ = robot("panda")           # no task section: the frame pass on the payload point
    check_trajectory(Dynamics(bare), traj(), FeasibilityOptions(compute_payload_margin=margin))
    assert calls[0] == 0
    # a model the kernels do not take: Pinocchio's passes (gravity, RNEA, the margin's RNEA)
    def unsupported(dynamics):
        raise ModelError("a joint the frame kernels do not take", code="urdf_joint_type")

    monkeypatch.setattr(task_motion, "kinematics", unsupported)
    check_trajectory(Dynamics(bare), traj(), FeasibilityOptions(compute_payload_margin=margin))
    assert calls[0] == (3 if margin else 2)


def _close(x, y, path: str = "") -> None:
    """Equal structure; numbers within 1e-9 relative (1e-12 absolute for rounding around 0)."""
    if isinstance(x, dict):
        assert set(x) == set(y), path
        for k in x:
            _close(x[k], y[k], f"{path}/{k}")
    elif isinstance(x, (list, tuple)):
        assert len(x) == len(y), path
        for i, (u, v) in enumerate(zip(x, y)):
            _close(u, v, f"{path}[{i}]")
    elif isinstance(x, float) and not isinstance(x, bool):
        assert (math.isnan(x) and math.isnan(y)) or x == y or \
            abs(x - y) <= 1e-9 * max(abs(x), abs(y)) + 1e-12, (path, x, y)
    else:
        assert x == y, (path, x, y)


@pytest.mark.parametrize("sections", [SECTIONS, {"frame_limits": SECTIONS["frame_limits"]}, {}])
def test_verdicts_match_the_pinocchio_pass(monkeypatch, sections):
    """The whole verdict (ratios, time scale, payload margin, efforts) of a check, with a task
    section or none, equals the one made from Dynamics.terms_batch (Pinocchio's RNEA) and, for
    the margin, Pinocchio's RNEA with 1 kg more, to 1e-9."""
    model, _ = robot("panda", sections)
    dyn = Dynamics(model)
    options = FeasibilityOptions(compute_payload_margin=True)
    fast = check_trajectory(dyn, traj(), options).to_dict()
    build = task_motion.build

    def pinocchio_build(dynamics, Q, V, A, **kwargs):
        task = build(dynamics, Q, V, A, **{**kwargs, "rnea": False})
        return None if task is None else dataclasses.replace(task,
                                                             terms=dynamics.terms_batch(Q, V, A))

    monkeypatch.setattr(task_motion, "build", pinocchio_build)
    monkeypatch.setattr(task_motion, "joint_terms", lambda *a, **k: (None, None))
    slow = check_trajectory(dyn, traj(), options).to_dict()
    assert fast["per_joint"] and (fast["per_frame"] or not sections)
    _close(fast | {"compute_time_s": 0.0}, slow | {"compute_time_s": 0.0})


@pytest.mark.parametrize("sections", [SECTIONS, {}])
def test_inverse_dynamics_takes_the_checks_route(sections):
    """inverse_dynamics gives the check's sample torques bit for bit (the frame pass, plus
    J_localᵀ·W with a task wrench), and Pinocchio's rnea + friction + J_localᵀ·W to 1e-9."""
    model, _ = robot("panda", sections)
    dyn = Dynamics(model)
    m, _ = feasibility._motion(dyn, traj(), FeasibilityOptions(), False, [])
    idx = np.arange(0, len(m.Q), 37)
    Q, V, A = m.Q[idx], np.ascontiguousarray(m.V[idx]), np.ascontiguousarray(m.A[idx])
    tau = on_demand.inverse_dynamics(dyn, Q, V, A)
    assert np.array_equal(tau, m.tau[idx])
    _, ref, _ = pinocchio_terms(model, DynamicsOptions(), Q, V, A)
    if sections:
        pm, data = model.pin_model, model.pin_model.createData()
        fid = pm.getFrameId(WRENCH["frame"])
        W = np.array(WRENCH["force"] + WRENCH["torque"])
        ref += np.array([pin.computeFrameJacobian(pm, data, q, fid, pin.LOCAL).T @ W for q in Q])
    np.testing.assert_allclose(tau, ref, rtol=0, atol=TOL)


def test_a_wrench_on_a_limited_frame_shares_its_point_and_the_mounting_takes_it_back():
    """task_wrench on a frame_limits entry's frame rides on that entry's (offset) point; the
    mounting's static wrench still gets +W moved from the frame's ORIGIN (Pinocchio's oMf)."""
    model, _ = robot("panda", SECTIONS)
    dyn = Dynamics(model)
    Q, V, A = states(model.nv, n=20)
    task = task_motion.build(dyn, Q, V, A, rnea=True)
    assert task.roles["wrench"] == task.roles["frame:panda_link8"]
    assert len(task.batch.frames) == 2                       # panda_link8's point, the payload
    gravity = FrameKinematics(model, []).compute(Q, V, A, inertia=False).base.static
    pm, data = model.pin_model, model.pin_model.createData()
    fid = pm.getFrameId(WRENCH["frame"])
    assert np.allclose(pm.frames[pm.getFrameId("panda_link0")].placement.homogeneous, np.eye(4))
    for n, q in enumerate(Q):
        pin.framesForwardKinematics(pm, data, q)
        R, o = data.oMf[fid].rotation, data.oMf[fid].translation
        f = R @ WRENCH["force"]
        ref = np.concatenate([f, R @ WRENCH["torque"] + np.cross(o, f)]) + gravity[n]
        np.testing.assert_allclose(task.base.static[n], ref, rtol=0, atol=TOL)
