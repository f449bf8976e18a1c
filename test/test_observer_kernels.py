"""The contact monitor's compiled pass against Pinocchio, a finite-difference identity and a
NumPy SVD; one call with N rows against N calls with one row (bit for bit)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from dyn_node.core.compiled import observer_kernels as ok
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.frames import joint_tables
from dyn_node.core.robot.model import load_model
from dyn_node.core.contacts.observer import MomentumObserver, ObserverOptions, WrenchEstimate
from robots import BRANCHED_URDF

ARMATURE = {"joint_limits": {f"panda_joint{i}": {"armature": 0.1 * i} for i in range(1, 8)}}


def _models():
    return [(load_model(builtin="panda", limits_yaml=ARMATURE), "panda_link8"),
            (load_model(urdf=BRANCHED_URDF), "c_tool"),
            (load_model(builtin="planar_2link"), None)]


def _terms(model, frame, q, v):
    pm = Dynamics(model).pin_model
    t = joint_tables(pm, pm.frames[0].name)
    f = pm.frames[pm.getFrameId(frame or model.last_link)]
    n, nv = pm.njoints, pm.nv
    scratch = [np.zeros((n, 9)), *(np.zeros((n, 3)) for _ in range(4)), np.zeros((n, 10))]
    p, ctv, g, J = np.zeros(nv), np.zeros(nv), np.zeros(nv), np.zeros((6, nv))
    fplace = np.concatenate([f.placement.rotation.reshape(9), f.placement.translation])
    ok.model_terms(q, v, t.parent, t.revolute, t.index, t.placement, t.axis, t.inertia, t.armature,
                   t.gravity, f.parentJoint, fplace, *scratch, p, ctv, g, J)
    return p, ctv, g, J


@pytest.mark.parametrize("which", range(3))
def test_model_terms_are_pinocchios(which):
    """p = M(q)q̇ (armature included), Cᵀq̇ with Pinocchio's Coriolis matrix, g(q) and the LOCAL
    frame Jacobian, on the Panda, a branched tree with prismatic joints and the 2-link arm."""
    model, frame = _models()[which]
    pm = Dynamics(model).pin_model
    d = pm.createData()
    fid = pm.getFrameId(frame or model.last_link)
    rng = np.random.default_rng(which)
    for _ in range(30):
        q, v = rng.uniform(-1.5, 1.5, pm.nv), rng.uniform(-2, 2, pm.nv)
        p, ctv, g, J = _terms(model, frame, q, v)
        M = pin.crba(pm, d, q)
        M = np.triu(M) + np.triu(M, 1).T
        np.testing.assert_allclose(p, M @ v, rtol=0, atol=1e-12)
        np.testing.assert_allclose(ctv, pin.computeCoriolisMatrix(pm, d, q, v).T @ v, rtol=0, atol=1e-12)
        np.testing.assert_allclose(g, pin.computeGeneralizedGravity(pm, d, q), rtol=0, atol=1e-12)
        np.testing.assert_allclose(J, pin.computeFrameJacobian(pm, d, q, fid, pin.ReferenceFrame.LOCAL),
                                   rtol=0, atol=1e-13)
    if which == 0:  # the armature reached p: without it M·v differs by 0.1·i·v_i
        assert np.abs(p - pin.crba(load_model(builtin="panda").pin_model,
                                   load_model(builtin="panda").pin_model.createData(), q) @ v).max() > 0.01


def test_coriolis_term_is_the_kinetic_energy_gradient():
    """Cᵀq̇ = ∂T/∂q for T = ½q̇ᵀM(q)q̇ (Lagrange's equations), by central differences of M: an
    identity that does not use Pinocchio's Coriolis matrix."""
    model, frame = _models()[1]
    pm = Dynamics(model).pin_model
    d = pm.createData()
    rng = np.random.default_rng(4)
    h = 1e-6
    for _ in range(10):
        q, v = rng.uniform(-1.5, 1.5, pm.nv), rng.uniform(-2, 2, pm.nv)
        grad = np.zeros(pm.nv)
        for i in range(pm.nv):
            e = np.zeros(pm.nv)
            e[i] = h
            Tp, Tm = (0.5 * v @ pin.crba(pm, d, q + s * e).copy() @ v for s in (1, -1))
            grad[i] = (Tp - Tm) / (2 * h)
        np.testing.assert_allclose(_terms(model, frame, q, v)[1], grad, rtol=0, atol=1e-7)


def _svd_reference(J, tau, eps=0.02, band=0.06, lam_max=0.02):
    U, s, Vt = np.linalg.svd(J, full_matrices=False)
    smin = s.min()
    lam2 = 0.0 if smin >= band else (1 - (smin / band) ** 2) * lam_max ** 2
    return U @ (s / (s * s + lam2) * (Vt @ tau)), smin, np.sqrt(lam2)


@pytest.mark.parametrize("nv", [2, 6, 7, 9])
def test_damped_solve_is_the_svd_solution(nv):
    """F, σ_min and λ as the SVD form U·s/(s² + λ²)·Vᵀτ gives them, for narrow (nv < 6), square
    and wide Jacobians, well-conditioned, in the damping band and near singular."""
    rng = np.random.default_rng(nv)
    k = min(6, nv)
    seen_damped = seen_free = False
    for scale in (1.0, 0.05, 0.01, 1e-4):
        for _ in range(20):
            U, _ = np.linalg.qr(rng.normal(size=(6, 6)))
            V, _ = np.linalg.qr(rng.normal(size=(nv, nv)))
            s = np.sort(rng.uniform(0.2, 1.5, k))[::-1]
            s[-1] *= scale
            J = U[:, :k] @ np.diag(s) @ V[:, :k].T
            tau = rng.normal(size=nv) * 3
            F = np.zeros(6)
            sigma, lam, misfit = ok.damped_solve(J, tau, 0.02, 0.06, 0.02, np.zeros((k, k)),
                                                 np.zeros((k, k)), np.zeros(k), np.zeros(k), F)
            F0, s0, l0 = _svd_reference(J, tau)
            # from the Gram matrix: σ's absolute error is ~ε‖J‖²/σ, 1e-11 at σ = 2e-5, far
            # below the 0.02 and 0.06 it is compared with
            assert sigma == pytest.approx(s0, rel=1e-9, abs=1e-10)
            assert lam == pytest.approx(l0, rel=1e-9, abs=1e-15)
            np.testing.assert_allclose(F, F0, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(F0).max()))
            assert misfit == pytest.approx(np.linalg.norm(J.T @ F0 - tau), rel=1e-7, abs=1e-9)
            seen_damped |= lam > 0
            seen_free |= lam == 0
    assert seen_damped and seen_free


def _observer(model, frame):
    return MomentumObserver(Dynamics(model), options=ObserverOptions(gain=[30.0]), frame=frame,
                            contact_at=np.full(model.nv, 0.5))


def _rows(nv, N, rng):
    T = np.cumsum(rng.choice([0.001, 0.001, 0.002, 0.0], size=N))
    T[N // 2] = T[N // 2 - 1] - 0.003          # a step back
    T[N // 2 + 1:] += 1.0                        # then a stamp gap
    Q = np.cumsum(rng.normal(scale=0.01, size=(N, nv)), axis=0)
    V, E = rng.normal(size=(N, nv)), rng.normal(scale=3, size=(N, nv))
    E[N // 4, 1] = np.nan                        # a sample without estimate
    return T, Q, V, E


@pytest.mark.parametrize("which", range(3))
def test_rows_at_once_equal_rows_one_by_one(which):
    """The audit calls the pass with thousands of rows, the node with one: every output and the
    carried state are bit-identical, restarts (step back, stamp gap, invalid sample) included."""
    model, frame = _models()[which]
    rng = np.random.default_rng(10 + which)
    T, Q, V, E = _rows(model.nv, 400, rng)
    a, b = _observer(model, frame), _observer(model, frame)
    rows = a.update_rows(T, Q, V, E)
    singles, force_n = [], np.full(len(T), np.nan)
    for k in range(len(T)):
        singles.append(b.update(float(T[k]), Q[k], V[k], E[k]))
        if singles[-1].tau_ext is not None:  # what the live path's detector reads as the force
            force_n[k] = WrenchEstimate.from_row(frame, b.last_wrench.copy(), b.last_info,
                                                 b.wrench_options, model.nv).force_n
    tau = np.array([s.tau_ext if s.tau_ext is not None else np.full(model.nv, np.nan) for s in singles])
    np.testing.assert_array_equal(rows.tau_ext, tau)
    for x, y in ((a.state, b.state), (a.clock, b.clock), (a.power, b.power)):
        np.testing.assert_array_equal(x, y)
    assert a.counts == b.counts
    assert {k: r.code for k, r in rows.resets.items()} == {
        k: s.reset.code for k, s in enumerate(singles) if s.reset is not None}
    assert set(a.counts) >= {"start", "backwards", "stamp_gap", "after_invalid_input", "non_finite_effort"}
    np.testing.assert_array_equal(rows.wrench[-1], b.last_wrench)
    # the batched replay's detector reads the pass's force column: the live force is its bits
    assert np.isfinite(force_n).sum() > len(T) // 2
    np.testing.assert_array_equal(force_n, rows.info[:, ok.I_FORCE])
    # the level flags were exercised both ways
    over = rows.info[:, ok.I_OVER]
    assert 0 < np.nansum(over) < len(T) - 1
