"""The momentum observer and the contact wrench, checked against closed forms and MuJoCo.

Closed forms: the textbook planar 2-link arm (its M, C and g written out here, not Pinocchio's)
driven along an analytic trajectory with a known constant external torque; at rest, where the
observer's answer is τ_ext·(1 − e^{−K(t − t0)}) exactly for any step sequence. MuJoCo: the Panda
simulated by dyn_node.sim.simulator with a push through ``xfrc_applied``, the true external torque Jᵀ·F
computed with MuJoCo's own ``mj_jac``.
"""
from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.errors import InputError
from dyn_node.core.robot.model import load_model
from dyn_node.core.contacts.observer import (RESET_BACKWARDS, RESET_INVALID, RESET_STAMP_GAP, RESET_REQUESTED, RESET_START,
                                        MomentumObserver, ObserverOptions, WrenchEstimator, WrenchOptions,
                                        damped_wrench)
from dyn_node.sim.simulator import SimConfig, Simulator
from robots import fast_panda_points, two_link_terms

READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])


@pytest.fixture(scope="module")
def two_link():
    return load_model(builtin="planar_2link")


@pytest.fixture(scope="module")
def panda():
    return load_model(builtin="panda")


# --- the planar 2-link arm in closed form (robots.two_link_terms) ------------------------------
def two_link_motion(t):
    """An analytic motion (q, q̇, q̈) at time t (s)."""
    w = np.array([3.0, 4.5])
    A = np.array([0.6, 0.8])
    q = np.array([0.3, 0.7]) + A * np.sin(w * t)
    return q, A * w * np.cos(w * t), -A * w * w * np.sin(w * t)


def two_link_effort(t, tau_ext):
    """The motor torque that moves the arm along two_link_motion while the environment adds
    tau_ext: M q̈ + C q̇ + g − tau_ext."""
    q, v, a = two_link_motion(t)
    M, C, g = two_link_terms(q, v)
    return q, v, M @ a + C @ v + g - tau_ext


def observer_error(model, dt, tau_ext, *, timing="sampled", duration=1.0, settle=0.3):
    obs = MomentumObserver(Dynamics(model), options=ObserverOptions(effort_timing=timing))
    worst = 0.0
    for k in range(int(round(duration / dt)) + 1):
        t = k * dt
        q, v, e = two_link_effort(t, tau_ext)
        est = obs.update(t, q, v, e)
        if t >= settle:
            worst = max(worst, float(np.abs(est.tau_ext - tau_ext).max()))
    return worst


def test_two_link_closed_form_terms_are_the_models(two_link):
    """The closed form above is the model the observer uses (else the order test below means
    nothing): M, C and g agree with Dynamics to 1e-12."""
    d = Dynamics(two_link)
    rng = np.random.default_rng(3)
    for _ in range(20):
        q, v = rng.uniform(-2, 2, 2), rng.uniform(-3, 3, 2)
        M, C, g = two_link_terms(q, v)
        np.testing.assert_allclose(d.mass_matrix(q), M, atol=1e-12)
        np.testing.assert_allclose(d.coriolis_matrix(q, v), C, atol=1e-12)
        np.testing.assert_allclose(d.gravity(q), g, atol=1e-12)


def test_observer_is_second_order_for_sampled_effort(two_link):
    """Constant τ_ext on an analytic motion: after settling, the error is the trapezoid's on the
    state terms, O(dt²): halving dt divides it by ~4 (3 … 5), and at 1 kHz it is below 1e-3 N·m."""
    tau_ext = np.array([1.5, -0.7])
    e4, e2, e1 = (observer_error(two_link, dt, tau_ext) for dt in (0.004, 0.002, 0.001))
    assert e1 < 1e-3
    assert 3.0 < e4 / e2 < 5.0 and 3.0 < e2 / e1 < 5.0, (e4, e2, e1)


def test_held_effort_on_a_continuous_torque_is_first_order(two_link):
    """The ``held`` rule integrates a continuous torque as a right-endpoint rectangle: its error
    is dt/2·τ̇, first order (halving dt halves it), which is why ``sampled`` exists."""
    tau_ext = np.array([1.5, -0.7])
    e2, e1 = (observer_error(two_link, dt, tau_ext, timing="held") for dt in (0.002, 0.001))
    assert 1.7 < e2 / e1 < 2.3, (e2, e1)


@pytest.mark.parametrize("timing", ["held", "sampled"])
def test_at_rest_the_answer_is_the_exact_first_order_rise(two_link, timing):
    """Held still against a constant τ_ext with steps from 0.1 ms to 0.3 s (K·dt up to 15,
    where explicit Euler would diverge): r(t) = τ_ext·(1 − e^{−K(t−t0)}) to 1e-12 at every sample."""
    K = 50.0
    tau_ext = np.array([2.0, -1.0])
    q, v = np.array([0.4, -0.9]), np.zeros(2)
    effort = two_link_terms(q, v)[2] - tau_ext
    obs = MomentumObserver(Dynamics(two_link), options=ObserverOptions(gain=K, effort_timing=timing))
    rng = np.random.default_rng(7)
    t = 1.25
    first = obs.update(t, q, v, effort)
    assert first.reset is not None and first.reset.code == RESET_START
    np.testing.assert_array_equal(first.tau_ext, np.zeros(2))
    t0 = t
    for dt in np.concatenate([rng.uniform(1e-4, 3e-3, 200), [0.3, 0.05, 0.3, 0.2]]):
        t += float(dt)
        est = obs.update(t, q, v, effort)
        np.testing.assert_allclose(est.tau_ext, tau_ext * (1 - np.exp(-K * (t - t0))), atol=1e-12, rtol=0)
        assert est.reset is None
        assert est.since_reset_s == pytest.approx(t - t0, abs=1e-12)
    assert est.settled


def test_settled_after_three_time_constants(two_link):
    obs = MomentumObserver(Dynamics(two_link), options=ObserverOptions(gain=[50.0, 25.0]))
    q, v = np.array([0.1, 0.2]), np.zeros(2)
    e = two_link_terms(q, v)[2]
    assert obs.settle_s == pytest.approx(3 / 25.0)
    ests = [obs.update(k * 0.001, q, v, e) for k in range(200)]
    settled = [round(x.t, 9) for x in ests if x.settled]
    assert settled[0] == pytest.approx(0.12)
    assert not any(x.settled for x in ests if x.t < 0.12 - 1e-9)
    np.testing.assert_allclose(ests[-1].tau_ext, 0.0, atol=1e-12)


def test_gain_one_value_or_one_per_joint(two_link):
    d = Dynamics(two_link)
    np.testing.assert_array_equal(MomentumObserver(d).gain, [50.0, 50.0])
    np.testing.assert_array_equal(MomentumObserver(d, options=ObserverOptions(gain=[10.0])).gain, [10.0, 10.0])
    np.testing.assert_array_equal(MomentumObserver(d, options=ObserverOptions(gain=(10.0, 20.0))).gain, [10.0, 20.0])
    for bad in ([1.0, 2.0, 3.0], [0.0], [-5.0], [math.nan]):
        with pytest.raises(ValueError, match="observer gain"):
            MomentumObserver(d, options=ObserverOptions(gain=bad))
    with pytest.raises(ValueError, match="effort_timing"):
        MomentumObserver(d, options=ObserverOptions(effort_timing="both"))
    with pytest.raises(ValueError, match="max_gap_s"):
        MomentumObserver(d, options=ObserverOptions(max_gap_s=0.0))


# --- resets and bad input -----------------------------------------------------------------------
def _pushed_still(model, tau_ext):
    q, v = np.array([0.4, -0.9]), np.zeros(2)
    return q, v, two_link_terms(q, v)[2] - tau_ext


def test_bad_effort_gives_no_estimate_and_restarts(two_link):
    tau_ext = np.array([2.0, -1.0])
    q, v, e = _pushed_still(two_link, tau_ext)
    obs = MomentumObserver(Dynamics(two_link))
    for k in range(100):
        good = obs.update(k * 0.001, q, v, e)
    assert np.abs(good.tau_ext - tau_ext).max() < 0.02
    bad = obs.update(0.100, q, v, [e[0], math.nan])
    assert bad.tau_ext is None and bad.unavailable == "effort not finite for joint2"
    none = obs.update(0.101, q, v, None)
    assert none.tau_ext is None and none.unavailable == "effort not measured"
    novel = obs.update(0.1015, q, None, e)
    assert novel.tau_ext is None and novel.unavailable == "velocity not measured"
    nanq = obs.update(0.1017, [math.nan, 0.0], v, e)
    assert nanq.tau_ext is None and nanq.unavailable == "position not finite for joint1"
    back = obs.update(0.102, q, v, e)
    assert back.reset is not None and back.reset.code == RESET_INVALID
    assert "effort not finite for joint2" in back.reset.detail
    # restarted: the estimate rises from 0 again, never jumps to a value from the broken history
    np.testing.assert_array_equal(back.tau_ext, np.zeros(2))
    assert back.since_reset_s == 0.0 and not back.settled
    assert obs.counts == {RESET_START: 1, "non_finite_effort": 1, "effort_missing": 1,
                          "velocity_missing": 1, "non_finite_position": 1, RESET_INVALID: 1}


def test_gap_backwards_duplicate_and_requested_reset(two_link):
    tau_ext = np.array([2.0, -1.0])
    q, v, e = _pushed_still(two_link, tau_ext)
    obs = MomentumObserver(Dynamics(two_link), options=ObserverOptions(max_gap_s=0.5))
    obs.update(0.0, q, v, e)
    a = obs.update(0.5, q, v, e)                 # exactly max_gap_s: integrated
    assert a.reset is None
    np.testing.assert_allclose(a.tau_ext, tau_ext * (1 - math.exp(-25.0)), atol=1e-12)
    gap = obs.update(1.0000001, q, v, e)
    assert gap.reset.code == RESET_STAMP_GAP and "stamp gap of 0.5000001 s > 0.5 s" == gap.reset.detail
    dup = obs.update(1.0000001, q, v, e)         # the same instant: same answer, no restart
    assert dup.reset is None and dup.since_reset_s == 0.0
    np.testing.assert_array_equal(dup.tau_ext, gap.tau_ext)
    back = obs.update(0.9, q, v, e)
    assert back.reset.code == RESET_BACKWARDS
    obs.update(0.91, q, v, e)
    said = obs.reset("model changed")
    assert said.code == RESET_REQUESTED and said.detail == "model changed"
    nxt = obs.update(0.92, q, v, e)
    assert nxt.reset == said and nxt.since_reset_s == 0.0
    with pytest.raises(ValueError, match="effort needs 2 values"):
        obs.update(0.93, q, v, [1.0, 2.0, 3.0])


def test_friction_of_the_model_is_subtracted(panda):
    """With URDF damping (0.003 N·m·s/rad on the Panda) the observer sees the measured torque
    net of the model friction: a still robot moving at constant joint speed against no external
    torque reads zero only when friction is modelled, and −damping·v without it."""
    q, v = READY.copy(), np.zeros(7)
    v[0] = 1.0  # joint 1 spinning at constant speed: M, C, g do not depend on q1
    d_f = Dynamics(panda)
    d_n = Dynamics(panda, DynamicsOptions(include_friction=False))
    effort = d_f.rnea(q, v, np.zeros(7))
    for d, expect in ((d_f, 0.0), (d_n, -0.003)):
        obs = MomentumObserver(d)
        for k in range(400):
            t = k * 0.001
            qk = q.copy()
            qk[0] = t * v[0]
            est = obs.update(t, qk, v, effort)
        assert est.tau_ext[0] == pytest.approx(expect * (1 - math.exp(-50 * 0.399)), abs=1e-9)


# --- the wrench --------------------------------------------------------------------------------
def mujoco_jacobian(sim: Simulator, body: str, point: np.ndarray, data: mujoco.MjData | None = None) -> np.ndarray:
    """MuJoCo's 6×nv world-axes Jacobian of a point on a body (model joint order), at the
    kinematics of ``data`` (default the simulation's)."""
    jp, jr = np.zeros((3, sim.mj.nv)), np.zeros((3, sim.mj.nv))
    mujoco.mj_jac(sim.mj, sim.data if data is None else data, jp, jr, point, sim.mj.body(body).id)
    return np.vstack([jp, jr])[:, sim.robot.dof_ids]


def test_wrench_from_mujoco_torque_is_exact(panda):
    """τ = J_mujocoᵀ·[R f; R m] at the flange's origin (MuJoCo's Jacobian, world axes): the
    estimator recovers [f; m] in the flange's axes to 1e-9 at random poses outside the damping
    band (σ_min ≥ β)."""
    sim = Simulator(panda)
    est = WrenchEstimator(panda, "panda_link8")
    rng = np.random.default_rng(11)
    done = 0
    while done < 10:
        q = rng.uniform(panda.limits.position_lower, panda.limits.position_upper)
        sim.reset(q)
        b = sim.mj.body("panda_link8").id
        R, p = sim.data.xmat[b].reshape(3, 3), sim.data.xpos[b].copy()
        w = rng.normal(size=6) * np.array([20, 20, 20, 2, 2, 2])
        tau = mujoco_jacobian(sim, "panda_link8", p).T @ np.concatenate([R @ w[:3], R @ w[3:]])
        got = est.estimate(q, tau)
        if got.sigma_min < est.options.damping_band:
            continue
        done += 1
        np.testing.assert_allclose(got.wrench, w, atol=1e-9)
        assert got.damping == 0.0 and got.misfit < 1e-9 and got.determined


def test_singular_frame_is_damped_and_bounded(panda):
    """At q = 0 the Panda's flange Jacobian loses rank (σ_min ~ 1e-16): the estimate is finite,
    flagged singular, λ = λ_max, and satisfies the damped normal equations (JJᵀ + λ²I)F = Jτ;
    its norm is at most ‖τ‖/(2λ), the largest gain σ/(σ²+λ²) can have."""
    est = WrenchEstimator(panda, "panda_link8", options=WrenchOptions(singular_value=0.02, max_damping=0.02))
    q = np.zeros(7)
    J = est.jacobian(q)
    tau = np.random.default_rng(5).normal(size=7) * 5
    got = est.estimate(q, tau)
    assert got.singular and got.sigma_min < 1e-12
    assert got.damping == pytest.approx(0.02, rel=1e-12)
    np.testing.assert_allclose((J @ J.T + got.damping**2 * np.eye(6)) @ got.wrench, J @ tau, atol=1e-9)
    assert np.linalg.norm(got.wrench) <= np.linalg.norm(tau) / (2 * 0.02) + 1e-9


def test_damping_grows_as_the_smallest_singular_value_falls():
    """λ² = (1 − (σ_min/β)²)·λ_max² below the damping band β, 0 above: checked on a 6×7 matrix
    with chosen singular values, against numpy's least squares above β and the damped normal
    equations below it."""
    rng = np.random.default_rng(2)
    U, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    V, _ = np.linalg.qr(rng.normal(size=(7, 7)))
    tau = rng.normal(size=7)
    opts = WrenchOptions(singular_value=0.01, damping_band=0.1, max_damping=0.05)
    for smin, lam2 in ((0.2, 0.0), (0.1, 0.0), (0.05, 0.75 * 0.05**2), (0.0, 0.05**2)):
        s = np.array([2.0, 1.5, 1.0, 0.7, 0.4, smin])
        J = U @ np.diag(s) @ V[:, :6].T
        F, sigma_min, lam = damped_wrench(J, tau, options=opts)
        # from the Gram matrix JJᵀ: a zero σ reads as ~√ε·‖J‖ (1e-8), far below ε = 0.01
        assert sigma_min == pytest.approx(smin, abs=1e-8 if smin == 0 else 1e-12)
        assert lam**2 == pytest.approx(lam2, abs=1e-15)
        if lam2 == 0.0:
            np.testing.assert_allclose(F, np.linalg.lstsq(J.T, tau, rcond=None)[0], atol=1e-9)
        np.testing.assert_allclose((J @ J.T + lam2 * np.eye(6)) @ F, J @ tau, atol=1e-9)


def test_damping_starts_above_the_refusal_threshold(panda):
    """Between ε and β the estimate is damped but not singular: F̂ = Σ σᵢ/(σᵢ² + λ²)·(vᵢᵀτ)·uᵢ
    (J = Σ σᵢ uᵢ vᵢᵀ) with λ² = (1 − (σ_min/β)²)·λ_max², to 1e-11, on a 6×7 matrix with
    σ_min = 2ε; below ε singular; the options refuse β ≤ ε. On the Panda, a pose on the way to
    the q = 0 singularity with ε < σ_min < β is damped and not singular."""
    rng = np.random.default_rng(4)
    U, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    V, _ = np.linalg.qr(rng.normal(size=(7, 7)))
    tau = rng.normal(size=7)
    o = WrenchOptions()
    eps, beta, lmax = o.singular_value, o.damping_band, o.max_damping
    assert eps < beta
    s = np.array([2.0, 1.5, 1.0, 0.7, 0.4, 2 * eps])
    J = U @ np.diag(s) @ V[:, :6].T
    lam2 = (1 - (2 * eps / beta) ** 2) * lmax**2
    want = sum(s[i] / (s[i] ** 2 + lam2) * (V[:, i] @ tau) * U[:, i] for i in range(6))
    F, sigma_min, lam = damped_wrench(J, tau)
    # the Gram matrix squares J's condition number (50 here): κ²·ε·‖F‖ ≈ 6e-12 N
    np.testing.assert_allclose(F, want, rtol=0, atol=1e-11)
    assert lam == pytest.approx(math.sqrt(lam2), rel=1e-12)
    with pytest.raises(ValueError, match="damping_band must exceed singular_value"):
        WrenchEstimator(panda, "panda_link8", options=WrenchOptions(singular_value=0.05, damping_band=0.05))
    est = WrenchEstimator(panda, "panda_link8")
    q1 = np.array([0.0, -0.6, 0.0, -2.0, 0.0, 1.6, 0.8])
    found = []
    for k in range(1, 200):
        q = q1 * (k / 200)
        got = est.estimate(q, tau)
        if eps < got.sigma_min < beta:
            found.append(got)
            assert not got.singular and got.damping > 0
        elif got.sigma_min < eps:
            assert got.singular
    assert found, "no pose in the damping band"


def test_fewer_joints_than_six_gives_the_minimum_norm_wrench(two_link):
    est = WrenchEstimator(two_link, "tool")
    q = np.array([0.3, 0.9])
    tau = np.array([1.2, -0.4])
    got = est.estimate(q, tau)
    assert not got.determined and not got.singular
    np.testing.assert_allclose(got.wrench, np.linalg.pinv(est.jacobian(q).T) @ tau, atol=1e-12)
    assert got.misfit < 1e-12


def test_unknown_contact_frame(panda):
    with pytest.raises(InputError, match="'panda_link9' is not a frame") as info:
        WrenchEstimator(panda, "panda_link9")
    assert info.value.code == "unknown_frame"


# --- against MuJoCo ------------------------------------------------------------------------------
def panda_sim(model) -> Simulator:
    """The Panda at READY with the gains dyn_sim's config gives it (computed at READY)."""
    return Simulator(model, SimConfig(initial_positions=tuple(READY)))


MOVE = np.array([0.5, 0.3, -0.4, 0.5, 0.6, -0.5, 0.8])


#: seconds per segment of the quintic READY → READY + MOVE → READY: "moving" peaks at
#: 0.75 rad/s (joint 7; ~30 % of the Panda's speed limits), "fast" at 1.5 rad/s
SEGMENT_S = {"moving": 2.0, "fast": 1.0}


def _trajectory(sim: Simulator, model, kind: str) -> None:
    if kind == "still":
        return
    seg = SEGMENT_S[kind]
    times = np.array([0.2, 0.2 + seg, 0.2 + 2 * seg])
    pos = np.vstack([READY, READY + MOVE, READY])
    zero = np.zeros_like(pos)
    sim.execute(model.joint_names, times, pos, zero, zero)


def run_pushed(model, kind, force, moment, *, push=(0.3, 1.3), duration=1.3, frame="panda_link8"):
    """Simulate at 1 kHz, push at ``frame`` over ``push`` (s), feed the observer every step.
    Returns per-step (t, τ̂_ext, true Jᵀ·xfrc, q, pushed)."""
    sim = panda_sim(model)
    _trajectory(sim, model, kind)
    obs = MomentumObserver(Dynamics(model))
    body = sim.link_mount(frame).body
    bid = sim.mj.body(body).id
    st = sim.state()
    obs.update(st.t, st.q, st.v, st.effort)
    rows = []
    n = int(round(duration / sim.config.timestep))
    start, end = (int(round(x / sim.config.timestep)) for x in push)
    mid = mujoco.MjData(sim.mj)
    for k in range(n):
        if k == start:
            sim.apply_wrench(frame, force, moment, hold_s=(end - start) * sim.config.timestep)
        pushed = sim.wrench is not None and sim.time < sim.wrench.end_step * sim.config.timestep - 1e-12
        q0 = sim.data.qpos.copy()
        st = sim.step(1)
        true = np.zeros(model.nv)
        if pushed:
            # RK4 (dyn_sim's default) applies the step's world-axes xfrc at the body's CoM in each
            # stage: to O(h²) that is Jᵀ at the step's midpoint configuration (hinges: the mean q)
            mid.qpos[:] = 0.5 * (q0 + sim.data.qpos)
            mujoco.mj_kinematics(sim.mj, mid)
            mujoco.mj_comPos(sim.mj, mid)
            true = mujoco_jacobian(sim, body, mid.xipos[bid], mid).T @ sim.data.xfrc_applied[bid]
        est = obs.update(st.t, st.q, st.v, st.effort)
        rows.append((st.t, est.tau_ext, true, st.q, pushed))
    return rows


CASES = [
    ("still", (0.0, 0.0, -50.0), (0.0, 0.0, 0.0)),
    ("still", (5.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    ("still", (12.0, -20.0, 8.0), (0.0, 0.0, 1.5)),
    ("moving", (30.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    ("moving", (-20.0, 15.0, 10.0), (0.0, 0.0, 0.0)),
    ("moving", (0.0, 40.0, -25.0), (1.0, 0.0, 0.0)),
    ("moving", (0.0, 0.0, 5.0), (0.0, 0.0, 0.0)),
]


@pytest.mark.parametrize("kind,force,moment", CASES)
def test_estimates_match_mujoco_push(panda, kind, force, moment):
    """The observer is a first-order lag of gain K = 50/s on the true external torque, so the
    reference is MuJoCo's Jᵀ·F (J at each step's midpoint, where RK4 applies it) passed through
    that lag (exact for the 1 ms steps; as in test_fast_motion_error_is_the_observer_lag). After
    5/K = 0.1 s of push, at every 1 kHz sample until it ends: τ̂_ext within 1e-5 N·m of it on
    every joint (measured ≤ 4.7e-6; with J at the step's start 3.6e-3, Euler's 2.8e-3), the
    flange force's magnitude within 1 % + 0.02 N of the lagged applied |F|·(1 − e^(−K·t))
    (measured ≤ 0.43 %: the lag of a force on a moving J), the force vector within 2.5 % + 0.05 N
    of F·(1 − e^(−K·t)) and the moment within 0.06 N·m of the applied one (measured ≤ 2.1 % and
    0.047 N·m). The bounds used to be 5 % + 0.2 N·m and 10 % + 1 N: 30 % of a 5 N push."""
    rows = run_pushed(panda, kind, force, moment)
    est = WrenchEstimator(panda, "panda_link8")
    F, Mo = np.array(force), np.array(moment)
    a = math.exp(-50.0 * 0.001)
    lagged = np.zeros(7)
    checked = 0
    worst_tau = worst_mag = worst_f = worst_m = 0.0
    for t, tau_hat, true, q, pushed in rows:
        lagged = a * lagged + (1 - a) * true
        if not pushed or t < 0.4 - 1e-9:
            continue
        checked += 1
        rise = 1.0 - math.exp(-50.0 * (t - 0.3))  # the push acts from t = 0.3 s
        worst_tau = max(worst_tau, float(np.abs(tau_hat - lagged).max()) / 1e-5)
        w = est.estimate(q, tau_hat)
        mag_bound = 0.01 * np.linalg.norm(F) + 0.02
        worst_mag = max(worst_mag, abs(np.linalg.norm(w.force) - rise * np.linalg.norm(F)) / mag_bound)
        worst_f = max(worst_f, float(np.linalg.norm(w.force - rise * F) / (0.025 * np.linalg.norm(F) + 0.05)))
        worst_m = max(worst_m, float(np.linalg.norm(w.moment - rise * Mo) / 0.06))
    assert checked == 901  # samples 0.400 … 1.300 s
    # each worst-case is the error as a fraction of its bound
    assert max(worst_tau, worst_mag, worst_f, worst_m) <= 1.0, (worst_tau, worst_mag, worst_f, worst_m)


def test_no_false_contact_over_a_fast_trajectory(panda):
    """No push, the Panda at 90 % of its speed limits (quintic, 0.6 s segments, no joint
    saturating) and the same points interpolated linearly (velocity jumps at the waypoints, the
    torque saturating with them): |τ̂_ext| stays below 0.05 × the effort limit on every joint at
    every sample (measured: ≤ 0.001 and ≤ 0.0015 of it)."""
    times, pos = fast_panda_points(panda.limits, READY)
    for mode in ("quintic", "linear"):
        sim = panda_sim(panda)
        if mode == "quintic":
            zero = np.zeros_like(pos)
            sim.execute(panda.joint_names, times, pos, zero, zero)
        else:
            sim.execute(panda.joint_names, times, pos)
        obs = MomentumObserver(Dynamics(panda))
        peak, speed, saturated = np.zeros(7), np.zeros(7), 0
        for st in sim.run(times[-1] + 0.3):
            est = obs.update(st.t, st.q, st.v, st.effort)
            peak = np.maximum(peak, np.abs(est.tau_ext))
            speed = np.maximum(speed, np.abs(st.v))
            saturated += int(st.saturated.any())
        ratio = peak / panda.limits.effort
        assert ratio.max() < 0.05, (mode, ratio)
        if mode == "quintic":
            assert (speed / panda.limits.velocity).max() > 0.85 and saturated == 0
        else:
            assert saturated > 0


@pytest.mark.parametrize("force", [(30.0, 0.0, 0.0), (-20.0, 15.0, 10.0)])
def test_fast_motion_error_is_the_observer_lag(panda, force):
    """Moving twice as fast (1.5 rad/s peak), Jᵀ·F changes by up to ~15 N·m/s and the estimate
    trails it by the observer's own lag (≈ rate/K: up to 0.36 N·m, beyond 5 % + 0.2 N·m). That
    is the continuous observer's response, not an estimation error: against Jᵀ·F passed through
    the same first-order lag (exact for the 1 ms steps) the estimate is within 1e-5 N·m
    (measured 4.9e-6 with J at each RK4 step's midpoint; 4e-3 with J at its start)."""
    rows = run_pushed(panda, "fast", force, (0.0, 0.0, 0.0))
    a = math.exp(-50.0 * 0.001)
    lagged = np.zeros(7)
    worst = 0.0
    for t, tau_hat, true, q, pushed in rows:
        lagged = a * lagged + (1 - a) * true
        if pushed and t >= 0.4 - 1e-9:
            worst = max(worst, float(np.abs(tau_hat - lagged).max()))
    assert worst < 1e-5
