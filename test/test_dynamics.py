"""Dynamics checked against the closed-form 2-link equation and rigid-body identities."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.core.robot.model import Payload, load_model
from robots import G, L1, L2, M1, M2, two_link_terms, with_friction_urdf

TOL = 1e-9


@pytest.fixture(scope="module")
def two_link():
    return Dynamics(load_model(builtin="planar_2link"))


def friction_limits(model):
    """A limits mapping giving every joint a distinct armature (kg·m²)."""
    return {"joint_limits": {n: {"armature": 0.05 + 0.01 * i} for i, n in enumerate(model.joint_names)}}


@pytest.fixture(scope="module", params=["panda", "ur5"])
def arm(request):
    from dyn_node.core.robot.model import builtin_urdf
    base = load_model(builtin=request.param)
    text = with_friction_urdf(builtin_urdf(request.param))
    model = load_model(urdf=text, locked_joints=dict(base.locked_joints))
    model = model.with_limits(friction_limits(model))
    return model


def random_states(model, n, seed):
    rng = np.random.default_rng(seed)
    lo = np.maximum(model.limits.position_lower, -np.pi)
    hi = np.minimum(model.limits.position_upper, np.pi)
    Q = rng.uniform(lo, hi, (n, model.nv))
    V = rng.uniform(-2, 2, (n, model.nv))
    A = rng.uniform(-8, 8, (n, model.nv))
    return Q, V, A


def test_two_link_named_state(two_link):
    q, v, a = np.array([0.4, -0.7]), np.array([1.2, 0.9]), np.array([0.3, -0.5])
    M, C, g = two_link_terms(q, v)
    np.testing.assert_allclose(two_link.rnea(q, v, a), M @ a + C @ v + g, rtol=0, atol=TOL)
    np.testing.assert_allclose(two_link.mass_matrix(q), M, rtol=0, atol=TOL)
    np.testing.assert_allclose(two_link.bias(q, v), C @ v + g, rtol=0, atol=TOL)
    np.testing.assert_allclose(two_link.gravity(q), g, rtol=0, atol=TOL)


def test_two_link_random_states(two_link):
    rng = np.random.default_rng(20261122)
    Q = rng.uniform(-np.pi, np.pi, (1000, 2))
    V = rng.uniform(-5, 5, (1000, 2))
    A = rng.uniform(-20, 20, (1000, 2))
    expected = np.empty((1000, 2))
    for i in range(1000):
        M, C, g = two_link_terms(Q[i], V[i])
        expected[i] = M @ A[i] + C @ V[i] + g
        if i % 50 == 0:
            np.testing.assert_allclose(two_link.mass_matrix(Q[i]), M, rtol=0, atol=TOL)
            np.testing.assert_allclose(two_link.bias(Q[i], V[i]), C @ V[i] + g, rtol=0, atol=TOL)
            np.testing.assert_allclose(two_link.gravity(Q[i]), g, rtol=0, atol=TOL)
        np.testing.assert_allclose(two_link.rnea(Q[i], V[i], A[i]), expected[i], rtol=0, atol=TOL)
    np.testing.assert_allclose(two_link.rnea_batch(Q, V, A), expected, rtol=0, atol=TOL)


def test_arm_identities(arm):
    """rnea = M a + h, gravity = rnea(q, 0, 0), M symmetric positive definite; friction on."""
    dyn = Dynamics(arm)
    assert np.all(dyn._damping > 0) and np.all(dyn._coulomb > 0)
    assert np.all(arm.limits.armature > 0)
    Q, V, A = random_states(arm, 100, 7)
    z = np.zeros(arm.nv)
    for q, v, a in zip(Q, V, A):
        M = dyn.mass_matrix(q)
        np.testing.assert_array_equal(M, M.T)
        assert np.linalg.eigvalsh(M).min() > 0
        np.testing.assert_allclose(dyn.rnea(q, v, a), M @ a + dyn.bias(q, v), rtol=0, atol=TOL)
        # Coulomb sign(0) = 0, so with v = 0 friction vanishes and rnea is pure gravity.
        np.testing.assert_allclose(dyn.gravity(q), dyn.rnea(q, z, z), rtol=0, atol=TOL)
        np.testing.assert_allclose(dyn.friction(v), dyn._damping * v + dyn._coulomb * np.sign(v))


def test_arm_armature_and_friction_switches(arm):
    q, v, a = (x[0] for x in random_states(arm, 1, 3))
    full = Dynamics(arm)
    rigid = Dynamics(arm, DynamicsOptions(include_friction=False, include_armature=False))
    pm = arm.pin_model.copy()
    pm.armature[:] = 0.0
    plain = pin.rnea(pm, pm.createData(), q, v, a)
    np.testing.assert_allclose(rigid.rnea(q, v, a), plain, rtol=0, atol=TOL)
    expected = plain + arm.limits.armature * a + full._damping * v + full._coulomb * np.sign(v)
    np.testing.assert_allclose(full.rnea(q, v, a), expected, rtol=0, atol=TOL)
    np.testing.assert_allclose(np.diag(full.mass_matrix(q)) - np.diag(rigid.mass_matrix(q)),
                               arm.limits.armature, rtol=0, atol=TOL)


def test_batches_equal_single_state(arm):
    dyn = Dynamics(arm, threads=2)
    Q, V, A = random_states(arm, 64, 11)
    V[3, 1] = 0.0  # Coulomb sign(0)
    single = np.array([dyn.rnea(q, v, a) for q, v, a in zip(Q, V, A)])
    grav = np.array([dyn.gravity(q) for q in Q])
    np.testing.assert_allclose(dyn.rnea_batch(Q, V, A), single, rtol=0, atol=TOL)
    np.testing.assert_allclose(dyn.gravity_batch(Q), grav, rtol=0, atol=TOL)
    assert np.array_equal(dyn.gravity_batch(Q), grav)   # to the bit: the audit's replay needs it
    terms = dyn.terms_batch(Q, V, A)
    np.testing.assert_allclose(terms.total(), single, rtol=0, atol=TOL)
    np.testing.assert_array_equal(terms.full, terms.total())
    for k in (0.5, 1.7, 3.0):
        scaled = np.array([dyn.rnea(q, v / k, a / k**2) for q, v, a in zip(Q, V, A)])
        np.testing.assert_allclose(terms.total(k), scaled, rtol=0, atol=TOL)
    assert np.any(terms.viscous != 0) and np.any(terms.static != grav)
    assert dyn.rnea_batch(Q[:0], V[:0], A[:0]).shape == (0, arm.nv)


def test_batch_thread_count_changes_no_bit(arm):
    """Each state is one sequential RNEA whatever the OpenMP thread count: the batched results
    with 1 and 2 threads (per call, or from the constructor) are bit-identical."""
    import os
    Q, V, A = random_states(arm, 257, 12)
    one = Dynamics(arm)
    two = Dynamics(arm, threads=2)
    ref = one.rnea_batch(Q, V, A)
    assert np.array_equal(two.rnea_batch(Q, V, A), ref)
    assert np.array_equal(one.rnea_batch(Q, V, A, threads=2), ref)
    assert np.array_equal(two.rnea_batch(Q, V, A, threads=1), ref)
    t1, t2 = one.terms_batch(Q, V, A, 1), one.terms_batch(Q, V, A, 2)
    for a, b in ((t1.static, t2.static), (t1.viscous, t2.viscous), (t1.inertial, t2.inertial)):
        assert np.array_equal(a, b)
    assert np.array_equal(one.gravity_batch(Q, threads=2), one.gravity_batch(Q))
    cores = os.cpu_count() or 1
    assert one.batch_threads() == 1 and one.batch_threads(0) == 1
    assert one.batch_threads(10_000) == cores and two.batch_threads() == min(2, cores)


def point_jacobian(model, q, frame, com):
    """Linear Jacobian (world axes) of the point ``com`` fixed in ``frame``, from Pinocchio's frame
    Jacobian and frame placement: J_p = J_v − [r]× J_ω with r the world-axes offset of the point."""
    pm = model.base_model
    data = pm.createData()
    fid = pm.getFrameId(frame)
    J = pin.computeFrameJacobian(pm, data, q, fid, pin.LOCAL_WORLD_ALIGNED)
    r = data.oMf[fid].rotation @ np.asarray(com, dtype=float)
    return J[:3] - pin.skew(r) @ J[3:]


@pytest.mark.parametrize("name,frame,com", [
    ("panda", "", (0.0, 0.0, 0.0)),
    ("panda", "panda_link8", (0.02, -0.03, 0.08)),
    ("panda", "panda_hand_tcp", (0.0, 0.01, 0.0)),
    ("ur5", "", (0.0, 0.05, 0.0)),
    ("ur5", "tool0", (0.01, 0.0, 0.1)),
])
def test_payload_is_a_point_mass(name, frame, com):
    model = load_model(builtin=name)
    if name == "panda":
        assert model.last_link == "panda_link8"
    mass = 2.5
    rng = np.random.default_rng(5)
    for gvec in ((0, 0, -9.81), (9.81, 0, 0), (0, 3.0, -9.0)):
        base = model.with_gravity(gvec)
        loaded = base.with_payload(Payload(mass, com, frame))
        assert loaded.payload.frame == (frame or model.last_link)
        d0, d1 = Dynamics(base), Dynamics(loaded)
        for q in rng.uniform(-2, 2, (10, model.nv)):
            Jp = point_jacobian(model, q, frame or model.last_link, com)
            expected = -Jp.T @ (mass * np.asarray(gvec, dtype=float))
            np.testing.assert_allclose(d1.gravity(q) - d0.gravity(q), expected, rtol=0, atol=TOL)
    assert loaded.total_mass == pytest.approx(model.total_mass + mass, abs=1e-12)
    # Removing the payload restores the original torques exactly.
    q = rng.uniform(-2, 2, model.nv)
    np.testing.assert_array_equal(Dynamics(loaded.with_payload(Payload())).gravity(q),
                                  Dynamics(base).gravity(q))


def test_gravity_vector_matches_center_of_mass_jacobian():
    """g(q) = −m_total J_comᵀ g_vec for any gravity vector (tilted, wall, ceiling mounts)."""
    model = load_model(builtin="panda")
    rng = np.random.default_rng(9)
    pm = model.base_model
    data = pm.createData()
    for gvec in ((0, 0, -9.81), (9.81, 0, 0), (0, -9.81, 0), (0, 0, 9.81), (1.7, -2.2, -9.4)):
        dyn = Dynamics(model.with_gravity(gvec))
        for q in rng.uniform(-2, 2, (10, model.nv)):
            Jc = pin.jacobianCenterOfMass(pm, data, q)
            mass = data.mass[0]
            np.testing.assert_allclose(dyn.gravity(q), -mass * Jc.T @ np.asarray(gvec, float),
                                       rtol=0, atol=TOL)
    from dyn_node.errors import ModelError
    for bad in ((0, 0), (0, np.nan, 1), "x"):
        with pytest.raises(ModelError) as e:
            model.with_gravity(bad)
        assert e.value.code == "bad_gravity"


def test_bad_payload():
    from dyn_node.errors import ModelError
    model = load_model(builtin="planar_2link")
    for payload, code in ((Payload(-1.0), "bad_payload"), (Payload(float("nan")), "bad_payload"),
                          (Payload(1.0, (0, float("inf"), 0)), "bad_payload"),
                          (Payload(1.0, frame="nope"), "bad_frame")):
        with pytest.raises(ModelError) as e:
            model.with_payload(payload)
        assert e.value.code == code
    assert model.last_link == "tool"
    # A payload at the tip of the 2-link arm is the closed form with m2 → m2 + m at l2.
    loaded = model.with_payload(Payload(0.7))
    q = np.array([0.3, 0.9])
    c1, c12 = np.cos(q[0]), np.cos(q.sum())
    m2 = M2 + 0.7
    g = np.array([(M1 + m2) * G * L1 * c1 + m2 * G * L2 * c12, m2 * G * L2 * c12])
    np.testing.assert_allclose(Dynamics(loaded).gravity(q), g, rtol=0, atol=TOL)


def test_variants_keep_each_other():
    """with_payload / with_gravity / with_limits change only their own part of the model."""
    model = load_model(builtin="ur5")
    a = (model.with_payload(Payload(1.5, (0, 0, 0.1), "tool0")).with_gravity((0, 9.81, 0))
         .with_limits({"joint_limits": {"elbow_joint": {"armature": 0.2}}}))
    b = (model.with_limits({"joint_limits": {"elbow_joint": {"armature": 0.2}}})
         .with_gravity((0, 9.81, 0)).with_payload(Payload(1.5, (0, 0, 0.1), "tool0")))
    assert a.payload == b.payload and a.payload.frame == "tool0"
    np.testing.assert_array_equal(a.gravity, [0, 9.81, 0])
    q, v, acc = (x[0] for x in random_states(model, 1, 12))
    np.testing.assert_allclose(Dynamics(a).rnea(q, v, acc), Dynamics(b).rnea(q, v, acc),
                               rtol=0, atol=TOL)
    assert a.limits.armature[2] == 0.2 and a.urdf_hash == model.urdf_hash
    assert model.payload.mass == 0.0 and np.all(model.pin_model.armature == 0)
    np.testing.assert_array_equal(model.gravity, [0, 0, -9.81])  # the original is untouched


def test_terms_batch_gravity_kernel_matches_pinocchio_pass(arm):
    """terms_batch takes gravity from the compiled kernel; Pinocchio's RNEA at v = a = 0 (what
    it falls back to for a joint the kernel does not know) gives the same split to 1e-12."""
    from dyn_node.core.robot.dynamics import gravity_tables

    Q, V, A = random_states(arm, 300, 13)
    dyn = Dynamics(arm)
    fast = dyn.terms_batch(Q, V, A)
    dyn._gravity_tables = None
    slow = dyn.terms_batch(Q, V, A)
    for a, b in ((fast.static, slow.static), (fast.inertial, slow.inertial),
                 (fast.viscous, slow.viscous), (fast.full, slow.full)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.static - dyn._coulomb * np.sign(V), dyn.gravity_batch(Q),
                               rtol=0, atol=1e-12)
    # a joint with more than one degree of freedom: no tables, so Pinocchio's pass is used
    pm = pin.Model()
    pm.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
    assert gravity_tables(pm) is None


def test_two_link_gravity_split_is_the_closed_form(two_link):
    Q, V, A = random_states(two_link.model, 50, 14)
    terms = two_link.terms_batch(Q, V, A)
    np.testing.assert_allclose(terms.static, [two_link_terms(q, v)[2] for q, v in zip(Q, V)],
                               rtol=0, atol=TOL)
