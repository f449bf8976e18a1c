"""Limit edge cases (issue 9): values exactly at, and ε either side of, every limit kind.

Classification must match ros2_control's: bounds are inclusive (a value equal to its limit is
allowed, |τ| ≤ max is OK), lower and upper position bounds and negative efforts/velocities are
treated symmetrically, and continuous joints have no position limit at all.

Method for the derived kinds (velocity, acceleration, jerk, effort, effort rate, power, RMS effort,
torque-speed envelope): the value a limit is compared against does not depend on the limit, so a
first check with a very loose limit gives the exact peak value; the limit is then set to that
peak (must be feasible, ratio exactly 1, time_scale ≤ 1) and to the peak·(1 ∓ 1e-9) (must be
infeasible / feasible). Position is checked on held poses, where the interpolated value equals the
waypoint bit for bit. The live :class:`~dyn_node.core.live.monitor.Monitor` is checked the same way with
single messages.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
from dyn_node.core.check.joint_constraints import POSITION_RTOL
from dyn_node.core.robot.model import builtin_urdf, load_model
from dyn_node.core.live.monitor import EFFORT, LIMITS, Monitor
from dyn_node.core.robot.settings import Settings
from dyn_node.core.robot.status import ERROR, OK, WARN
from dyn_node.core.check.trajectory import validate_trajectory

PLANAR = load_model(builtin="planar_2link")
NAMES = list(PLANAR.joint_names)
EPS = 1e-9
OPTS = FeasibilityOptions(sample_period=0.005, compute_payload_margin=False)
LOOSE = 1e12


def _with(model, **arrays):
    """The model with limit arrays replaced (limits only: the pinocchio model is unchanged)."""
    return replace(model, limits=replace(model.limits, **arrays))


def _moving_traj():
    # a quintic motion with a sign change of velocity and torque, so peaks of |x| can be negative x
    times = [0.0, 0.4, 1.0]
    P = [[0.0, 0.2], [0.8, -0.6], [-0.3, 0.4]]
    V = [[0.0, 0.0], [1.5, -2.0], [0.0, 0.0]]
    A = [[0.0, 0.0], [-3.0, 4.0], [0.0, 0.0]]
    return validate_trajectory(NAMES, NAMES, times, P, V, A)


TRAJ = _moving_traj()


def _unlimited_except(model, kind_arrays: dict):
    inf = np.full(model.nv, np.inf)
    base = dict(velocity=inf, acceleration=inf, deceleration=inf, jerk=inf, effort=inf, effort_rate=inf, power=inf,
                rms_effort=inf, effort_speed_curve=(None,) * model.nv,
                position_lower=np.full(model.nv, -np.inf), position_upper=inf,
                soft_lower=np.full(model.nv, -np.inf), soft_upper=inf)
    base.update(kind_arrays)
    return _with(model, **base)


def _check(model, traj=TRAJ):
    return check_trajectory(Dynamics(model), traj, OPTS)


def _limit_arrays(kind: str, j: int, value: float, nv: int) -> dict:
    inf = np.full(nv, np.inf)
    arr = inf.copy()
    arr[j] = value
    if kind == "effort_speed":
        curve = [None] * nv
        curve[j] = np.array([[0.0, value], [1e3, value]])  # flat envelope: |τ| ≤ value at any speed
        return {"effort_speed_curve": tuple(curve)}
    if kind == "rms_effort":
        win = np.full(nv, 0.2)
        return {"rms_effort": arr, "rms_window": win}
    return {kind: arr}


DERIVED = ("velocity", "acceleration", "deceleration", "jerk", "effort", "effort_rate", "power",
           "rms_effort", "effort_speed")


@pytest.mark.parametrize("kind", DERIVED)
@pytest.mark.parametrize("j", [0, 1])
def test_feasibility_at_and_either_side_of_every_limit_kind(kind, j):
    loose = _unlimited_except(PLANAR, _limit_arrays(kind, j, LOOSE, PLANAR.nv))
    peak = _check(loose).per_joint[NAMES[j]][kind]["value"]
    assert peak > 0
    at = _check(_unlimited_except(PLANAR, _limit_arrays(kind, j, peak, PLANAR.nv)))
    assert at.feasible, (kind, j, at.message)
    assert at.per_joint[NAMES[j]][kind]["ratio"] == 1.0
    assert at.time_scale <= 1.0 and not at.violations
    inside = _check(_unlimited_except(PLANAR, _limit_arrays(kind, j, peak * (1 + EPS), PLANAR.nv)))
    assert inside.feasible and inside.time_scale <= 1.0
    below = _check(_unlimited_except(PLANAR, _limit_arrays(kind, j, peak * (1 - EPS), PLANAR.nv)))
    assert not below.feasible
    assert [(v.joint, v.kind) for v in below.violations] == [(NAMES[j], kind)]
    assert below.time_scale > 1.0
    assert below.failure_label == "planning error"


def test_negative_peaks_use_magnitude():
    """The trajectory's peak |velocity| and |τ| of some joint are negative values; at exactly the
    magnitude they are allowed (|x| ≤ max), so a negative extreme is classified like a positive one."""
    from dyn_node.core.check.trajectory import interpolate

    pp = interpolate(TRAJ, "quintic")
    t = np.linspace(0, 1.0, 2001)
    q, qd, qdd, _ = pp.evaluate(t)
    tau = Dynamics(PLANAR).rnea_batch(q, qd, qdd)
    assert (qd.min(axis=0) < 0).all() and (tau.min() < 0)
    for kind in ("velocity", "effort"):
        for j in range(2):
            loose = _unlimited_except(PLANAR, _limit_arrays(kind, j, LOOSE, 2))
            e = _check(loose).per_joint[NAMES[j]][kind]
            assert _check(_unlimited_except(PLANAR, _limit_arrays(kind, j, e["value"], 2))).feasible


def _hold(q_row):
    q = [list(q_row), list(q_row)]
    z = [[0.0, 0.0], [0.0, 0.0]]
    return validate_trajectory(NAMES, NAMES, [0.0, 0.5], q, z, z)


@pytest.mark.parametrize("j", [0, 1])
@pytest.mark.parametrize("side", ["lower", "upper"])
def test_feasibility_position_exactly_at_and_beyond(j, side):
    lim = PLANAR.limits
    bound = float(lim.position_lower[j] if side == "lower" else lim.position_upper[j])
    out = -1.0 if side == "lower" else 1.0
    model = _unlimited_except(PLANAR, {"position_lower": lim.position_lower.copy(),
                                       "position_upper": lim.position_upper.copy()})
    # the check's position bound is the limit widened by POSITION_RTOL of its size (issue 39: a
    # waypoint on a limit within 1e-9 is on it): half of that past is on it, twice is beyond
    tol = POSITION_RTOL * max(1.0, abs(bound))
    for delta, ok in ((0.0, True), (-out * EPS, True), (0.5 * out * tol, True), (2.0 * out * tol, False)):
        q = [0.0, 0.0]
        q[j] = bound + delta
        r = _check(model, _hold(q))
        assert r.feasible is ok, (side, j, delta, r.message)
        if not ok:
            assert [(v.joint, v.kind) for v in r.violations] == [(NAMES[j], "position")]


CONTINUOUS_URDF = builtin_urdf("planar_2link").replace('name="joint1" type="revolute"',
                                                       'name="joint1" type="continuous"', 1)


def test_continuous_joint_has_no_position_limit():
    assert 'type="continuous"' in CONTINUOUS_URDF
    model = load_model(urdf=CONTINUOUS_URDF)
    assert bool(model.limits.continuous[0]) and not bool(model.limits.continuous[1])
    assert model.limits.position_lower[0] == -np.inf and model.limits.position_upper[0] == np.inf
    for q0 in (7.0, -50.0, 1e3):  # many turns either way
        r = _check(_with(model, effort=np.full(2, np.inf), velocity=np.full(2, np.inf)),
                   _hold([q0, 0.0]))
        assert r.feasible and not r.violations
        assert r.per_joint["joint1"]["position"]["ratio"] is None
        m = Monitor(model, Settings())
        res = m.process(NAMES, [q0, 0.0], [0.0, 0.0], [], 1.0, 1.0)
        assert res.accepted
        st = {s.name: s for s in m.statuses(1.1, "t")}[LIMITS]
        assert st.values["position_violations"] == 0


# --- the live monitor ----------------------------------------------------------------------
def _monitor_statuses(model, q, v, e):
    m = Monitor(model, Settings(acceleration_source="zero", include_friction=False))
    r = m.process(NAMES, q, v, e, 1.0, 1.0)
    assert r.accepted, r.error
    return r, {s.name: s for s in m.statuses(1.1, "t")}


@pytest.mark.parametrize("j", [0, 1])
@pytest.mark.parametrize("side", ["lower", "upper"])
def test_monitor_position_at_and_beyond(j, side):
    lim = PLANAR.limits
    bound = float(lim.position_lower[j] if side == "lower" else lim.position_upper[j])
    out = -1.0 if side == "lower" else 1.0
    for delta, violations in ((0.0, 0), (-out * EPS, 0), (out * EPS, 1)):
        q = [0.0, 0.0]
        q[j] = bound + delta
        _, st = _monitor_statuses(PLANAR, q, [0.0, 0.0], [])
        assert st[LIMITS].values["position_violations"] == violations, (side, j, delta)
        assert (st[LIMITS].level == ERROR) is (violations == 1)


@pytest.mark.parametrize("j", [0, 1])
@pytest.mark.parametrize("side", ["lower", "upper"])
def test_monitor_soft_limit_at_and_beyond(j, side):
    lim = PLANAR.limits
    bound = float(lim.soft_lower[j] if side == "lower" else lim.soft_upper[j])
    assert bound != float(lim.position_lower[j] if side == "lower" else lim.position_upper[j])
    out = -1.0 if side == "lower" else 1.0
    for delta, violations in ((0.0, 0), (-out * EPS, 0), (out * EPS, 1)):
        q = [0.0, 0.0]
        q[j] = bound + delta
        _, st = _monitor_statuses(PLANAR, q, [0.0, 0.0], [])
        assert st[LIMITS].values["soft_limit_violations"] == violations, (side, j, delta)
        assert st[LIMITS].values["position_violations"] == 0
        assert st[LIMITS].level == (WARN if violations else OK)


@pytest.mark.parametrize("j", [0, 1])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_monitor_velocity_at_and_beyond(j, sign):
    vmax = float(PLANAR.limits.velocity[j])
    for scale, violations in ((1.0, 0), (1 - EPS, 0), (1 + EPS, 1)):
        v = [0.0, 0.0]
        v[j] = sign * vmax * scale
        _, st = _monitor_statuses(PLANAR, [0.1, 0.2], v, [])
        assert st[LIMITS].values["velocity_violations"] == violations, (j, sign, scale)


@pytest.mark.parametrize("j", [0, 1])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_monitor_measured_effort_at_and_beyond(j, sign):
    """|τ_measured| = max is allowed (WARN for being above effort_warn_ratio, not ERROR); ε more is
    ERROR; the same for negative efforts."""
    emax = float(PLANAR.limits.effort[j])
    for scale, level in ((1.0, WARN), (1 - EPS, WARN), (1 + EPS, ERROR)):
        e = [0.0, 0.0]
        e[j] = sign * emax * scale
        r, st = _monitor_statuses(PLANAR, [0.0, 0.0], [0.0, 0.0], e)
        assert st[EFFORT].level == level, (j, sign, scale, st[EFFORT].message)
        assert r.utilisation[j] == pytest.approx(scale, rel=0, abs=1e-15)
        if level == ERROR:
            assert st[EFFORT].values["worst_joint"] == NAMES[j]


def test_monitor_model_torque_exactly_at_effort_limit():
    """The model torque (gravity at a held pose) as the effort limit: utilisation exactly 1, not
    an ERROR; the limit one ulp-ish below makes it an ERROR."""
    q = [0.4, -0.3]
    g = np.abs(Dynamics(PLANAR).gravity(np.array(q)))
    j = int(np.argmax(g))
    for lim_j, level in ((g[j], WARN), (g[j] * (1 - EPS), ERROR)):
        eff = np.full(2, np.inf)
        eff[j] = lim_j
        r, st = _monitor_statuses(_with(PLANAR, effort=eff), q, [0.0, 0.0], [])
        assert st[EFFORT].level == level


# --- limit semantics shared by the check and the monitor (issue 16) -----------------------------
def _fd_monitor(model):
    return Monitor(model, Settings(acceleration_source="finite_difference", include_friction=False))


@pytest.mark.parametrize("j", [0, 1])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_monitor_deceleration_at_and_beyond(j, sign):
    """Live: |q̈̂| against max_deceleration where q̇·q̈̂ < 0. Two messages 0.25 s apart with
    |q̇| 1 → 0.5 give q̈̂ = ∓2 rad/s² exactly; at the limit 2 it is allowed, 1e-9 below it is a
    deceleration violation and nothing else; the same magnitude while speeding up never is."""
    for limit, v0, v1, violations in ((2.0, 1.0, 0.5, 0), (2.0 * (1 + EPS), 1.0, 0.5, 0),
                                      (2.0 * (1 - EPS), 1.0, 0.5, 1), (1.0, 0.5, 1.0, 0)):
        dec = np.full(2, np.inf)
        dec[j] = limit
        m = _fd_monitor(_with(PLANAR, deceleration=dec))
        vel = [[0.0, 0.0], [0.0, 0.0]]
        vel[0][j], vel[1][j] = sign * v0, sign * v1
        m.process(NAMES, [0.1, 0.2], vel[0], [], 1.0, 1.0)
        r = m.process(NAMES, [0.1, 0.2], vel[1], [], 1.25, 1.25)
        assert r.a_hat[j] == sign * (v1 - v0) / 0.25
        st = {s.name: s for s in m.statuses(1.3, "t")}[LIMITS]
        assert st.values["deceleration_violations"] == violations, (limit, v0, v1)
        assert st.values["position_violations"] == st.values["velocity_violations"] == 0
        key = f"{NAMES[j]}_deceleration_rad_s2"
        if violations:
            assert st.level == ERROR and st.values[key] == sign * (v1 - v0) / 0.25
            assert st.message.startswith(f"{NAMES[j]} decelerating at 2 rad/s²")
        else:
            assert st.level == OK and key not in st.values


def _cube(reverse: bool):
    """joint1 follows q = t³ (speeding up: q̇·q̈ ≥ 0) or q = (1 − t)³ (slowing down from
    q̇ = −3, q̈ = 6 at t = 0) on [0, 1] s; the quintic through these boundary values is exactly
    that cubic. joint2 holds still."""
    P = [[1.0, 0.2], [0.0, 0.2]] if reverse else [[0.0, 0.2], [1.0, 0.2]]
    V = [[-3.0, 0.0], [0.0, 0.0]] if reverse else [[0.0, 0.0], [3.0, 0.0]]
    A = [[6.0, 0.0], [0.0, 0.0]] if reverse else [[0.0, 0.0], [6.0, 0.0]]
    return validate_trajectory(NAMES, NAMES, [0.0, 1.0], P, V, A)


def _scaled(traj, k: float):
    return validate_trajectory(NAMES, NAMES, traj.times * k, traj.positions,
                               traj.velocities / k, traj.accelerations / k ** 2)


def test_deceleration_counts_only_where_speed_decreases_and_scales_as_acceleration():
    dec = np.array([1.5, 1e-6])
    model = _unlimited_except(PLANAR, {"deceleration": dec})
    up = _check(model, _cube(reverse=False))
    assert up.feasible and up.per_joint["joint1"]["deceleration"]["ratio"] == 0.0
    assert up.time_scale == 0.0 and up.time_scale_by_kind["deceleration"] == 0.0
    down = _check(model, _cube(reverse=True))
    e = down.per_joint["joint1"]["deceleration"]
    assert e["time_s"] == 0.0 and e["value"] == pytest.approx(6.0, rel=1e-12)
    assert e["ratio"] == pytest.approx(4.0, rel=1e-12)
    assert [(v.joint, v.kind) for v in down.violations] == [("joint1", "deceleration")]
    assert down.violations[0].unit == "rad/s²"
    # q̈ ÷ k² under time scaling: k = √(6 / 1.5) = 2, by the definition of time_scale
    k = down.time_scale
    assert k == pytest.approx(2.0, rel=1e-12)
    assert (down.time_scale_constraint, down.time_scale_joint) == ("deceleration", "joint1")
    assert _check(model, _scaled(_cube(reverse=True), 1.001 * k)).feasible
    slow = _check(model, _scaled(_cube(reverse=True), 0.97 * k))
    assert not slow.feasible and [v.kind for v in slow.violations] == ["deceleration"]
    st = {s.name: s for s in down.statuses()}["dyn_node: trajectory feasibility/joint1"]
    assert st.values["deceleration_ratio"] == e["ratio"] and st.values["deceleration_time_s"] == 0.0
    assert "deceleration" in down.to_dict()["per_joint"]["joint1"]


ZERO_URDF = builtin_urdf("planar_2link").replace('effort="40.0" velocity="3.0"',
                                                 'effort="0" velocity="0"', 1)


def test_urdf_zero_is_unlimited_in_the_check_and_the_monitor():
    assert 'effort="0" velocity="0"' in ZERO_URDF
    model = load_model(urdf=ZERO_URDF)
    assert model.limits.velocity[0] == np.inf and model.limits.effort[0] == np.inf
    assert model.warnings == ()
    r = _check(model)
    for kind in ("velocity", "effort"):
        assert r.per_joint["joint1"][kind]["ratio"] is None
    assert not [v for v in r.violations if v.joint == "joint1"]
    res, st = _monitor_statuses(model, [0.1, 0.2], [50.0, 0.0], [1e4, 0.0])
    assert res.utilisation[0] == 0.0 and res.effort_limit[0] == np.inf
    assert st[LIMITS].values["velocity_violations"] == 0
    assert st[EFFORT].values["joint1_utilisation"] == 0.0


def test_yaml_zero_is_a_real_limit_in_the_check_and_the_monitor():
    model = PLANAR.with_limits("joint_limits:\n  joint1: {max_velocity: 0.0, max_effort: 0.0}\n"
                               "  joint2: {max_velocity: 0.0}\n")
    assert model.limits.velocity.tolist() == [0.0, 0.0] and model.limits.effort[0] == 0.0
    assert len(model.warnings) == 3 and all("applied as a real limit" in w for w in model.warnings)
    r = _check(model)
    assert not r.feasible and r.time_scale == np.inf
    assert {(v.joint, v.kind) for v in r.violations} == {
        ("joint1", "velocity"), ("joint1", "effort"), ("joint2", "velocity")}
    assert r.per_joint["joint1"]["velocity"]["ratio"] == np.inf
    # a joint that does not move satisfies a zero velocity limit at every time scale
    still = _check(model, validate_trajectory(NAMES, NAMES, [0.0, 1.0], [[0.0, 0.3], [0.0, 0.3]],
                                              [[0.0, 0.0]] * 2, [[0.0, 0.0]] * 2))
    assert [(v.joint, v.kind) for v in still.violations] == [("joint1", "effort")]  # gravity
    model2 = PLANAR.with_limits("joint_limits:\n  joint2: {max_velocity: 0.0}\n")
    held = _check(model2, validate_trajectory(NAMES, NAMES, [0.0, 1.0], [[0.0, 0.3], [0.5, 0.3]],
                                              [[0.0, 0.0]] * 2, None))   # cubic: linear would step
    assert held.feasible and held.time_scale <= 1.0, held.message
    assert held.per_joint["joint2"]["velocity"]["ratio"] == 0.0
    # live: the same limits, the same verdicts
    _, st = _monitor_statuses(model, [0.1, 0.2], [0.0, 0.0], [])
    assert st[LIMITS].values["velocity_violations"] == 0          # |q̇| = 0 ≤ 0
    res, st = _monitor_statuses(model, [0.1, 0.2], [1e-12, 0.0], [1e-12, 0.0])
    assert st[LIMITS].values["velocity_violations"] == 1
    assert res.utilisation[0] == np.inf and res.measured_ratio == np.inf
    assert st[EFFORT].level == ERROR and st[EFFORT].values["worst_joint"] == "joint1"
    assert st[EFFORT].values["joint1_effort_limit_nm"] == 0.0


def test_angle_wraps_means_no_position_limit_in_the_check_and_the_monitor():
    model = PLANAR.with_limits("joint_limits:\n  joint1: {angle_wraps: true}\n")
    assert bool(model.limits.continuous[0]) and not bool(model.limits.continuous[1])
    for q0 in (7.0, -50.0):
        r = _check(model, _hold([q0, 0.0]))
        assert r.feasible and not r.violations and not r.warnings, r.message
        assert r.per_joint["joint1"]["position"]["ratio"] is None
        _, st = _monitor_statuses(model, [q0, 0.0], [0.0, 0.0], [])
        assert st[LIMITS].values["position_violations"] == 0
        assert st[LIMITS].values["soft_limit_violations"] == 0
    assert not _check(PLANAR, _hold([7.0, 0.0])).feasible   # without it: beyond ±3 rad


@pytest.mark.parametrize("kind", ["velocity", "acceleration", "deceleration", "jerk", "effort"])
def test_has_false_disables_the_limit_in_the_check(kind):
    tiny = f"max_{kind}: 0.001"
    on = _check(PLANAR.with_limits(f"joint_limits:\n  joint1: {{{tiny}, has_{kind}_limits: true}}\n"))
    assert ("joint1", kind) in {(v.joint, v.kind) for v in on.violations}
    off = _check(PLANAR.with_limits(f"joint_limits:\n  joint1: {{{tiny}, has_{kind}_limits: false}}\n"))
    assert off.per_joint["joint1"][kind]["ratio"] is None
    assert ("joint1", kind) not in {(v.joint, v.kind) for v in off.violations}


def test_has_false_disables_position_and_soft_limits_in_the_check_and_the_monitor():
    q = [2.95, 0.0]   # inside the URDF's ±3 rad, beyond its ±2.9 rad soft limits
    assert any("soft-limit zone" in w for w in _check(PLANAR, _hold(q)).warnings)
    soft_off = PLANAR.with_limits("joint_limits:\n  joint1: {has_soft_limits: false}\n")
    assert not _check(soft_off, _hold(q)).warnings
    assert _monitor_statuses(soft_off, q, [0.0, 0.0], [])[1][LIMITS].values["soft_limit_violations"] == 0
    pos_off = PLANAR.with_limits("joint_limits:\n  joint1: {has_position_limits: false,"
                                 " min_position: -0.1, max_position: 0.1}\n")
    assert _check(pos_off, _hold([5.0, 0.0])).per_joint["joint1"]["position"]["ratio"] is None
    assert _monitor_statuses(pos_off, [5.0, 0.0], [0.0, 0.0], [])[1][LIMITS].values[
        "position_violations"] == 0


def test_audit_live_episode_at_a_zero_effort_limit_reports_the_effort():
    """The audit's live statistics take the monitor's utilisation (inf at a YAML zero limit):
    an episode must carry the |effort| itself (not inf·0 = NaN, which its schema rejects)."""
    from dyn_node.audit.bag_audit import LiveStats

    model = PLANAR.with_limits("joint_limits:\n  joint1: {max_effort: 0.0}\n")
    m = Monitor(model, Settings(acceleration_source="zero", include_friction=False))
    live = LiveStats(2, model.limits.position_lower, model.limits.position_upper,
                     model.limits.velocity)
    for k, t_ns in enumerate((1_000_000_000, 1_010_000_000)):
        measured = np.array([100.0 * (k + 1), 1.0])
        r = m.process(NAMES, [0.1, 0.2], [0.0, 0.0], measured, t_ns * 1e-9, t_ns * 1e-9)
        assert r.utilisation[0] == np.inf and abs(r.tau[0]) < 100.0
        live.add(t_ns, r.tau, r.utilisation, r.effort_limit, r.q, r.v, measured)
    live.flush()
    live.episodes.finish()
    (ep,) = [e for e in live.episodes.closed if e["kind"] == "effort"]
    assert ep["j"] == 0 and ep["limit"] == 0.0 and ep["n"] == 2
    # every sample is at ratio inf, so the first one stays the peak (as for any tie)
    assert ep["peak"] == 100.0
