"""Trajectory feasibility core: every limit kind, the time-scale contract, payload margin.

Oracles are independent of dyn_node.core.check.feasibility: a dense per-sample loop over ``pinocchio.rnea``
on the interpolated states (plus friction), finite differences for the effort rate, a direct
windowed integral for RMS. The time scale and payload margin are checked by their definition:
re-checking the stretched (or heavier) trajectory.
"""
from __future__ import annotations

import json
import math
from functools import lru_cache

import numpy as np
import pinocchio as pin
import pytest

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.errors import PLANNING_ERROR, TrajectoryError
from dyn_node.core.check.feasibility import (FeasibilityOptions, check_trajectory, rejected_statuses,
                                        STATUS_NAME)
from dyn_node.core.robot.limits import LIMIT_KINDS
from dyn_node.core.robot.model import Payload, load_model
from dyn_node.core.robot.status import ERROR, OK, WARN
from dyn_node.core.check.trajectory import Trajectory, interpolate, validate_trajectory

SUMMARY_KEYS = ("feasible", "worst_joint", "worst_constraint", "worst_ratio",
                "first_violation_time_s", "time_scale", "payload_margin_kg", "n_points",
                "duration_s", "failure_label")
RMS_WINDOW = 0.5


@lru_cache(maxsize=None)
def base_model(name: str):
    return load_model(builtin=name)


def _motion(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Home pose and per-joint amplitude (rad) of a smooth test motion, and its duration."""
    if name == "panda":
        home = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.6, 0.8])
        amp = np.array([0.8, 0.5, 0.6, 0.5, 0.9, 0.6, 1.0])
    elif name == "ur5":
        home = np.array([0.0, -1.2, 1.0, -1.4, -1.5, 0.0])
        amp = np.array([0.9, 0.6, 0.7, 0.8, 0.9, 1.0])
    else:
        home = np.array([0.3, 0.5])
        amp = np.array([0.9, 1.1])
    return home, amp, 2.0


def make_traj(name: str, mode: str, n_pts: int = 7) -> Trajectory:
    """q(t) = home + amp·sin(πt/T)·(1 − cos(2πt/T))/2 sampled at n_pts waypoints; velocities and
    accelerations from its derivatives when the mode needs them."""
    home, amp, T = _motion(name)
    t = np.linspace(0.0, T, n_pts)
    w1, w2 = np.pi / T, 2 * np.pi / T
    f = np.sin(w1 * t) * (1 - np.cos(w2 * t)) / 2
    fd = (w1 * np.cos(w1 * t) * (1 - np.cos(w2 * t)) + np.sin(w1 * t) * w2 * np.sin(w2 * t)) / 2
    fdd = (-w1 ** 2 * np.sin(w1 * t) * (1 - np.cos(w2 * t))
           + 2 * w1 * w2 * np.cos(w1 * t) * np.sin(w2 * t)
           + np.sin(w1 * t) * w2 ** 2 * np.cos(w2 * t)) / 2
    P = home + np.outer(f, amp)
    names = base_model(name).joint_names
    vel = acc = None
    if mode in ("cubic", "quintic"):
        vel = np.outer(fd, amp)
    if mode == "quintic":
        acc = np.outer(fdd, amp)
    return validate_trajectory(names, names, t, P, vel, acc)


def stretch(traj: Trajectory, k: float) -> Trajectory:
    return Trajectory(times=traj.times * k, positions=traj.positions,
                      velocities=None if traj.velocities is None else traj.velocities / k,
                      accelerations=None if traj.accelerations is None else traj.accelerations / k ** 2)


def oracle(model, traj: Trajectory, step: float = 5e-4) -> dict[str, np.ndarray]:
    """Dense brute-force samples: each segment on its own uniform grid (ends just inside it),
    torques by pinocchio.rnea per sample plus friction, rate by np.gradient within a segment."""
    pp = interpolate(traj)
    pm = model.pin_model
    data = pm.createData()
    damping, coulomb = np.array(pm.damping), np.array(pm.friction)
    out = {k: [] for k in ("t", "q", "v", "a", "j", "tau", "g", "rate")}
    for i in range(traj.n_points - 1):
        t0, t1 = traj.times[i], traj.times[i + 1]
        n = max(3, int(math.ceil((t1 - t0) / step)) + 1)
        ts = np.linspace(t0, t1 - 1e-10 * (t1 - t0), n)
        q, v, a, j = pp.evaluate(ts)
        tau = np.array([pin.rnea(pm, data, q[m], v[m], a[m]) + damping * v[m] + coulomb * np.sign(v[m])
                        for m in range(n)])
        g = np.array([pin.computeGeneralizedGravity(pm, data, q[m]) for m in range(n)])
        for key, val in zip(("t", "q", "v", "a", "j", "tau", "g"), (ts, q, v, a, j, tau, g)):
            out[key].append(val)
        out["rate"].append(np.gradient(tau, ts, axis=0, edge_order=2))
    res = {k: np.concatenate(v) for k, v in out.items()}
    res["g0"] = pin.computeGeneralizedGravity(pm, data, traj.positions[0])
    return res


def oracle_rms(o: dict[str, np.ndarray], window: float) -> np.ndarray:
    """Peak windowed RMS per joint: windows ending at every sample, holding g(q0) before t0."""
    t, tau2 = o["t"], o["tau"] ** 2
    cum = np.vstack([np.zeros(tau2.shape[1]),
                     np.cumsum(0.5 * (tau2[1:] + tau2[:-1]) * np.diff(t)[:, None], axis=0)])
    peak = np.zeros(tau2.shape[1])
    for j in range(tau2.shape[1]):
        start = t - window
        integral = cum[:, j] - np.interp(start, t, cum[:, j]) + np.maximum(t[0] - start, 0) * o["g0"][j] ** 2
        peak[j] = np.sqrt(integral.max() / window)
    return peak


def oracle_peaks(o, curves=None) -> dict[str, np.ndarray]:
    peaks = {"velocity": np.abs(o["v"]).max(0), "acceleration": np.abs(o["a"]).max(0),
             "deceleration": np.where(o["v"] * o["a"] < 0, np.abs(o["a"]), 0.0).max(0),
             "jerk": np.abs(o["j"]).max(0), "effort": np.abs(o["tau"]).max(0),
             "effort_rate": np.abs(o["rate"]).max(0), "power": np.abs(o["tau"] * o["v"]).max(0),
             "rms_effort": oracle_rms(o, RMS_WINDOW), "gravity": np.abs(o["g"]).max(0)}
    if curves is not None:
        env = np.column_stack([np.interp(np.abs(o["v"][:, j]), c[:, 0], c[:, 1])
                               for j, c in enumerate(curves)])
        peaks["effort_speed"] = (np.abs(o["tau"]) / env).max(0)
    return peaks


def limits_for(model, kind: str, peaks: dict[str, np.ndarray], frac: float):
    """A limits dict where only ``kind`` (plus position) limits the motion, at frac × its peak."""
    entries = {}
    curves = []
    for j, n in enumerate(model.joint_names):
        e = {"has_velocity_limits": kind == "velocity", "has_effort_limits": kind == "effort"}
        gmax = peaks["gravity"][j]
        if kind == "velocity":
            e["max_velocity"] = float(frac * peaks["velocity"][j])
        elif kind == "acceleration":
            e["max_acceleration"] = float(frac * peaks["acceleration"][j])
        elif kind == "deceleration":
            e["max_deceleration"] = float(frac * peaks["deceleration"][j])
        elif kind == "jerk":
            e["max_jerk"] = float(frac * peaks["jerk"][j])
        elif kind == "effort":
            e["max_effort"] = float(max(frac * peaks["effort"][j], 1.2 * gmax + 1e-3))
        elif kind == "effort_rate":
            e["max_effort_rate"] = float(frac * peaks["effort_rate"][j])
        elif kind == "power":
            e["max_power"] = float(frac * peaks["power"][j])
        elif kind == "rms_effort":
            e["max_rms_effort"] = float(max(frac * peaks["rms_effort"][j], 1.2 * gmax + 1e-3))
            e["rms_window"] = RMS_WINDOW
        elif kind == "effort_speed":
            vmax = max(peaks["velocity"][j], 1e-3)
            top = max(frac * peaks["effort"][j], 1.3 * gmax + 1e-3)
            c = [[0.0, top], [0.5 * vmax, top], [1.5 * vmax, 0.4 * top]]
            e["effort_speed_curve"] = c
            curves.append(np.array(c))
        entries[n] = e
    return {"joint_limits": entries}


# positions only is no longer among them: the controller interpolates it linearly, velocity
# steps no slowdown fixes (test_positions_only_is_linear_with_velocity_steps)
ROBOT_MODES = {"panda": "quintic", "ur5": "cubic", "planar_2link": "cubic"}
CASES = [(robot, kind) for robot in ROBOT_MODES for kind in LIMIT_KINDS if kind != "position"]


@lru_cache(maxsize=None)
def base_case(robot: str):
    model = base_model(robot)
    traj = make_traj(robot, ROBOT_MODES[robot])
    return model, traj, oracle(model, traj)


@pytest.mark.parametrize("robot,kind", CASES)
def test_time_scale_contract_each_kind_binding(robot, kind):
    model, traj, o = base_case(robot)
    peaks = oracle_peaks(o)
    frac = 0.8 if (LIMIT_KINDS.index(kind) + list(ROBOT_MODES).index(robot)) % 2 else 1.25
    lim = limits_for(model, kind, peaks, frac)
    m = model.with_limits(lim)
    dyn = Dynamics(m)
    r = check_trajectory(dyn, traj)
    k = r.time_scale
    assert math.isfinite(k) and k > 0, r.message
    assert r.time_scale_constraint == kind
    assert r.feasible == (k <= 1.0)
    assert check_trajectory(dyn, stretch(traj, 1.001 * k)).feasible, (kind, k)
    for f in (0.99, 0.97):
        slow = check_trajectory(dyn, stretch(traj, f * k))
        assert not slow.feasible, (kind, k, f)
        assert any(v.kind == kind for v in slow.violations)

    # peak ratios agree with the brute-force dense check
    curves = [np.array(lim["joint_limits"][n]["effort_speed_curve"]) for n in m.joint_names] \
        if kind == "effort_speed" else None
    ref = oracle_peaks(o, curves)
    limit_arr = {"velocity": m.limits.velocity, "acceleration": m.limits.acceleration,
                 "deceleration": m.limits.deceleration,
                 "jerk": m.limits.jerk, "effort": m.limits.effort,
                 "effort_rate": m.limits.effort_rate, "power": m.limits.power,
                 "rms_effort": m.limits.rms_effort}
    got = np.array([r.per_joint[n][kind]["ratio"] for n in m.joint_names])
    want = ref[kind] if kind == "effort_speed" else ref[kind] / limit_arr[kind]
    rtol = 5e-3 if kind in ("effort_rate", "rms_effort") else 1e-3
    np.testing.assert_allclose(got, want, rtol=rtol, atol=1e-9)
    assert r.worst_constraint == kind
    assert r.worst_ratio == pytest.approx(got.max())
    # the level from the dense check's ratio and the mode's documented warning (cubic: the
    # torque steps at waypoints; quintic: none)
    assert abs(want.max() - 1.0) > 0.05            # far enough from the limit to decide
    assert r.feasible == (want.max() < 1.0)
    warned = ROBOT_MODES[robot] != "quintic"
    assert r.level == (ERROR if want.max() > 1.0 else WARN if warned or want.max() > 0.9 else OK)


PAYLOAD_KINDS = ("effort", "effort_rate", "power", "rms_effort", "effort_speed")


@pytest.mark.parametrize("kind", PAYLOAD_KINDS)
@pytest.mark.parametrize("frac", (0.9, 1.3))
def test_payload_margin_by_recheck(kind, frac):
    model = base_model("planar_2link").with_payload(Payload(mass=2.0, com=(0.05, 0.0, 0.0)))
    traj = make_traj("planar_2link", "quintic")
    peaks = oracle_peaks(oracle(model, traj))
    lim = limits_for(model, kind, peaks, frac)
    m = model.with_limits(lim)
    r = check_trajectory(Dynamics(m), traj)
    margin = r.payload_margin_kg
    assert math.isfinite(margin)
    assert (margin >= 0) == r.feasible
    eps = 2e-3 * max(1.0, abs(margin))
    heavier = m.with_payload(Payload(mass=2.0 + margin + eps, com=(0.05, 0.0, 0.0)))
    assert not check_trajectory(Dynamics(heavier), traj).feasible
    if 2.0 + margin - eps >= 0:
        lighter = m.with_payload(Payload(mass=2.0 + margin - eps, com=(0.05, 0.0, 0.0)))
        assert check_trajectory(Dynamics(lighter), traj).feasible


def test_payload_margin_infinite_without_effort_limits():
    model = base_model("planar_2link").with_limits(
        {"joint_limits": {n: {"has_effort_limits": False} for n in ("joint1", "joint2")}})
    r = check_trajectory(Dynamics(model), make_traj("planar_2link", "spline"))
    assert r.payload_margin_kg == math.inf
    assert r.to_dict()["payload_margin_kg"] == "inf"


def test_violation_between_waypoints_is_caught():
    """Rest-to-rest quintic: both waypoints have zero velocity, the middle peaks at 1.875·Δq/T."""
    model = base_model("planar_2link")
    names = model.joint_names
    traj = validate_trajectory(names, names, [0.0, 1.0], [[0.0, 0.0], [2.0, 0.5]],
                               [[0, 0], [0, 0]], [[0, 0], [0, 0]])
    r = check_trajectory(Dynamics(model), traj)   # joint1 velocity limit 3 rad/s, peak 3.75 rad/s
    assert np.all(np.abs(traj.velocities) <= model.limits.velocity)
    assert not r.feasible and r.level == ERROR and r.failure_label == PLANNING_ERROR
    v = next(v for v in r.violations if v.joint == "joint1" and v.kind == "velocity")
    assert v.peak_value == pytest.approx(3.75, rel=1e-9)
    assert v.peak_time_s == pytest.approx(0.5, abs=1e-3)
    assert v.limit == 3.0
    # |v(t)| > 3 on an interval symmetric about 0.5 s: solve 30 s²(1−s)²·2 = 3 → duration
    s = np.linspace(0, 1, 200001)
    vel = 2.0 * 30 * s ** 2 * (1 - s) ** 2
    assert v.duration_s == pytest.approx((vel > 3.0).mean(), abs=2e-3)
    assert v.first_time_s == pytest.approx(s[np.argmax(vel > 3.0)], abs=1.1e-3)
    assert r.first_violation_time_s == pytest.approx(v.first_time_s)
    assert r.time_scale == pytest.approx(1.25, rel=1e-9)
    assert "run 1.25× slower" in r.message and r.message.startswith("infeasible: joint1 velocity 125%")


def _static_case(kind: str):
    model = base_model("planar_2link")
    # joint1 at q = 0 (horizontal) holds (1.5·0.5 + 1.0·0.9)·9.81 = 16.19 N·m of gravity
    g1 = (1.5 * 0.5 + 1.0 * 0.9) * 9.81
    e = {"joint1": {}, "joint2": {}}
    if kind == "effort":
        e["joint1"]["max_effort"] = g1 - 1.0
    elif kind == "rms_effort":
        e["joint1"]["max_rms_effort"] = g1 - 1.0
    else:
        e["joint1"]["effort_speed_curve"] = [[0.0, g1 - 1.0], [5.0, g1 - 1.0]]
    names = model.joint_names
    # at rest at each point (cubic): positions alone would be linear, with velocity steps
    traj = validate_trajectory(names, names, [0.0, 1.0, 2.0], [[0.5, 0.0], [0.0, 0.0], [0.5, 0.0]],
                               [[0.0, 0.0]] * 3)
    return model.with_limits({"joint_limits": e}), traj, g1


@pytest.mark.parametrize("kind", ("effort", "rms_effort", "effort_speed"))
def test_gravity_alone_exceeding_a_limit_gives_infinite_time_scale(kind):
    model, traj, g1 = _static_case(kind)
    r = check_trajectory(Dynamics(model), traj)
    assert not r.feasible and r.time_scale == math.inf
    assert r.failure_label == PLANNING_ERROR and r.level == ERROR
    assert r.time_scale_joint == "joint1" and r.time_scale_constraint == kind
    assert "joint1" in r.message and "q = [0, 0]" in r.message and "no slowdown helps" in r.message
    assert f"need {g1:.3g} N·m" in r.message   # the worst pose: horizontal, closed-form gravity
    assert not check_trajectory(Dynamics(model), stretch(traj, 50.0)).feasible
    assert r.to_dict()["time_scale"] == "inf"


def test_position_violation_is_infinite_and_soft_limit_warns():
    model = base_model("planar_2link")
    names = model.joint_names
    # cubic through 0 → 2.95 → 0, at rest at each point: inside the hard limit 3.0 but past the
    # soft limit 2.9
    rest = [[0.0, 0.0]] * 3
    traj = validate_trajectory(names, names, [0.0, 2.0, 4.0], [[0.0, 0.0], [2.95, 0.0], [0.0, 0.0]], rest)
    r = check_trajectory(Dynamics(model), traj)
    assert r.feasible and r.level == WARN
    assert any("soft-limit" in w for w in r.warnings)
    far = validate_trajectory(names, names, [0.0, 2.0, 4.0], [[0.0, 0.0], [3.05, 0.0], [0.0, 0.0]], rest)
    r = check_trajectory(Dynamics(model), far)
    assert not r.feasible and r.time_scale == math.inf and r.time_scale_constraint == "position"
    v = r.violations[0]
    assert (v.joint, v.kind, v.limit) == ("joint1", "position", 3.0)
    assert v.peak_value == pytest.approx(3.05)
    assert "no slowdown helps" in r.message


def test_limit_exactly_reached_is_feasible():
    """Inclusive bounds, as ros2_control: a peak equal to the limit is OK, a hair above is not."""
    model = base_model("planar_2link")
    names = model.joint_names
    traj = validate_trajectory(names, names, [0.0, 1.0], [[0.0, 0.0], [1.6, 0.4]],
                               [[0, 0], [0, 0]], [[0, 0], [0, 0]])
    peak = 1.875 * 1.6   # quintic rest-to-rest peak velocity, exactly 3.0 rad/s = the limit
    r = check_trajectory(Dynamics(model), traj)
    assert r.per_joint["joint1"]["velocity"]["value"] == pytest.approx(peak, rel=1e-12)
    assert r.feasible == (r.per_joint["joint1"]["velocity"]["value"] <= 3.0)
    tight = model.with_limits({"joint_limits": {"joint1": {
        "max_velocity": r.per_joint["joint1"]["velocity"]["value"]}}})
    assert check_trajectory(Dynamics(tight), traj).feasible
    tighter = model.with_limits({"joint_limits": {"joint1": {
        "max_velocity": float(np.nextafter(r.per_joint["joint1"]["velocity"]["value"], 0))}}})
    assert not check_trajectory(Dynamics(tighter), traj).feasible


def test_a_waypoint_exactly_on_a_position_limit_is_on_it():
    """Issue 39: a rest-to-rest quintic ending exactly at panda_joint7's upper limit evaluates a few
    1e-15 rad past it in floating point; within POSITION_RTOL of the limit's size it is on it.
    A millionth of a radian past stays a violation, as does twice the tolerance."""
    from dyn_node.core.check.joint_constraints import POSITION_RTOL
    from dyn_node.retime import retime
    model = base_model("panda")
    names = model.joint_names
    hi = float(model.limits.position_upper[6])
    start = [0.0, -0.3, 0.0, -2.0, 0.0, 1.6, 2.4864888888888883]

    def move(end: float):
        return validate_trajectory(names, names, [0.0, 2.0], [start, start[:6] + [end]],
                                   [[0.0] * 7] * 2, [[0.0] * 7] * 2)

    r = check_trajectory(Dynamics(model), move(hi))
    assert r.feasible, r.message
    peak = r.per_joint["panda_joint7"]["position"]["value"]
    assert hi < peak < hi + 1e-12   # the polynomial really ends past the limit, by rounding
    answer = retime(Dynamics(model), move(hi))
    assert answer.feasible and answer.blocked == "", answer.message
    for past in (1e-6, 2.0 * POSITION_RTOL * max(1.0, hi)):
        r = check_trajectory(Dynamics(model), move(hi + past))
        assert not r.feasible and r.time_scale_constraint == "position", (past, r.message)
        assert r.violations[0].limit == hi


def test_waypoint_effort_is_rnea_at_waypoints_and_statuses():
    model = base_model("panda")
    dyn = Dynamics(model)
    traj = make_traj("panda", "quintic")
    r = check_trajectory(dyn, traj)
    q, v, a, _ = interpolate(traj).evaluate(traj.times)
    want = np.array([dyn.rnea(q[i], v[i], a[i]) for i in range(traj.n_points)])
    np.testing.assert_allclose(r.waypoint_effort, want, rtol=0, atol=1e-9)
    assert r.interpolation == "quintic"
    sts = r.statuses("panda")
    assert sts[0].name == STATUS_NAME and sts[0].hardware_id == "panda"
    for key in SUMMARY_KEYS:
        assert key in sts[0].values
    assert [s.name for s in sts[1:]] == [f"{STATUS_NAME}/{n}" for n in model.joint_names]
    limited = 0
    for s, name in zip(sts[1:], model.joint_names):
        for kind in LIMIT_KINDS:
            got = r.per_joint[name][kind]
            if got["limit"] is None:
                assert (s.values[f"{kind}_ratio"], s.values[f"{kind}_time_s"]) == ("unlimited", "")
                continue
            limited += 1
            assert (s.values[f"{kind}_ratio"], s.values[f"{kind}_time_s"]) == (got["ratio"],
                                                                               got["time_s"])
            if kind != "position":   # position ratios are taken against the bound approached
                assert got["ratio"] == pytest.approx(got["value"] / got["limit"], rel=1e-12)
            assert 0.0 <= got["time_s"] <= traj.times[-1]
    assert limited == 3 * model.nv   # panda: position, velocity and effort limits on every joint
    assert sts[1].values["effort_ratio"] == r.per_joint["panda_joint1"]["effort"]["ratio"]
    assert sts[1].values["acceleration_ratio"] == "unlimited"
    d = r.to_dict()
    json.dumps(d, allow_nan=False)
    assert d["first_violation_time_s"] is None
    assert len(d["waypoint_effort"]) == traj.n_points


def test_feasible_message_and_levels():
    model = base_model("panda")
    traj = stretch(make_traj("panda", "quintic"), 3.0)
    r = check_trajectory(Dynamics(model), traj)
    assert r.feasible and r.time_scale < 1
    assert r.message.startswith(f"feasible: worst {r.worst_joint} ")
    assert f"could run {1 / r.time_scale:.2f}× faster" in r.message
    assert r.level == (WARN if r.worst_ratio > 0.9 else OK)
    assert r.failure_label == ("" if r.level == OK else PLANNING_ERROR)
    strict = check_trajectory(Dynamics(model), traj, FeasibilityOptions(effort_warn_ratio=0.01))
    assert strict.level == WARN and strict.feasible


def test_cubic_acceleration_jump_is_reported_as_effort_step():
    model = base_model("ur5").with_limits({"joint_limits": {"elbow_joint": {"max_effort_rate": 1e6}}})
    r = check_trajectory(Dynamics(model), make_traj("ur5", "cubic"))
    assert r.interpolation == "cubic"
    assert max(r.effort_step.values()) > 1e-3
    assert any("torque step" in w for w in r.warnings)
    rq = check_trajectory(Dynamics(model), make_traj("ur5", "quintic"))
    assert max(rq.effort_step.values()) < 1e-6 * max(np.abs(rq.waypoint_effort).max(), 1)


def test_positions_only_is_linear_with_velocity_steps():
    """Positions only: joint_trajectory_controller interpolates linearly (trajectory.cpp
    interpolate_between_points 315-333, jazzy ed360c9), so the velocity steps at every inner
    point and at the end (the held last point, 240-244): infeasible, and no slowdown helps.
    (It used to be checked as a C² spline the controller never runs.)"""
    traj = make_traj("planar_2link", "spline")
    r = check_trajectory(Dynamics(base_model("planar_2link")), traj)
    assert r.interpolation == "linear" and not r.feasible and r.level == ERROR
    n = traj.n_points - 1                 # the inner points and the end (the start is at rest)
    assert r.message.startswith(f"infeasible: positions only: velocity steps at {n} points as "
                                "the controller interpolates them"), r.message
    assert "send velocities (cubic) or velocities and accelerations (quintic)" in r.message
    assert r.time_scale == math.inf
    d = r.to_dict()
    assert d["velocity_steps"] == n and d["interpolation_segments"] == f"linear {n}"
    assert d["linear_segments"] == ", ".join(map(str, range(n)))


@pytest.mark.parametrize("kwargs,code", [
    (dict(times=[], positions=[]), "empty_points"),
    (dict(times=[0.0], positions=[[0.0, 0.0]]), "too_few_points"),
    (dict(times=[0.0, 1.0, 1.0], positions=[[0, 0]] * 3), "bad_times"),
    (dict(times=[0.0, 1.0, 0.5], positions=[[0, 0]] * 3), "bad_times"),
    (dict(times=[0.0, 1.0], positions=[[0, 0]]), "length_mismatch"),
    (dict(times=[0.0, 1.0], positions=[[0, 0], [0]]), "length_mismatch"),
    (dict(times=[0.0, 1.0], positions=[[0, 0], [0, float("nan")]]), "non_finite"),
    (dict(names=["joint1", "elbow"], times=[0.0, 1.0], positions=[[0, 0]] * 2), "unknown_joints"),
    (dict(names=["joint1"], times=[0.0, 1.0], positions=[[0]] * 2), "missing_joints"),
    (dict(names=[], times=[0.0, 1.0], positions=[[]] * 2), "empty_names"),
])
def test_bad_input_rejected_with_code_and_label(kwargs, code):
    model = base_model("planar_2link")
    names = kwargs.pop("names", list(model.joint_names))
    with pytest.raises(TrajectoryError) as info:
        validate_trajectory(model.joint_names, names, **kwargs)
    assert info.value.code == code
    sts = rejected_statuses(info.value, "hw", n_points=len(kwargs["times"]), duration_s=1.0)
    assert len(sts) == 1 and sts[0].level == ERROR and sts[0].name == STATUS_NAME
    # every summary key, with what a rejected trajectory has: nothing was computed (NaN), the
    # counts and duration given, the error's label and code
    want = {"feasible": False, "worst_joint": "", "worst_constraint": "", "worst_ratio": math.nan,
            "first_violation_time_s": math.nan, "time_scale": math.nan,
            "payload_margin_kg": math.nan, "n_points": len(kwargs["times"]), "duration_s": 1.0,
            "failure_label": PLANNING_ERROR}
    assert set(want) == set(SUMMARY_KEYS)
    got = sts[0].values
    for key, value in want.items():
        if isinstance(value, float) and math.isnan(value):
            assert isinstance(got[key], float) and math.isnan(got[key]), key
        else:
            assert type(got[key]) is type(value) and got[key] == value, (key, got[key])
    assert got["reason"] == code
    assert str(info.value) in sts[0].message


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the interpolation itself overflows
def test_overflowing_motion_raises_instead_of_passing():
    model = base_model("planar_2link")
    names = model.joint_names
    traj = validate_trajectory(names, names, [0.0, 1e-300], [[0.0, 0.0], [1e300, 0.0]])
    with pytest.raises(TrajectoryError) as info:
        check_trajectory(Dynamics(model), traj)
    assert info.value.code == "non_finite"


def test_single_point_trajectory_raises_in_core():
    t = Trajectory(times=np.array([0.0]), positions=np.zeros((1, 2)))
    with pytest.raises(TrajectoryError) as info:
        check_trajectory(Dynamics(base_model("planar_2link")), t)
    assert info.value.code == "too_few_points"


@pytest.mark.timeout(60)
def test_hundred_thousand_points_finish():
    model = base_model("panda")
    n = 100_000
    t = np.linspace(0.0, 100.0, n)
    home, amp, _ = _motion("panda")
    P = home + np.outer(0.3 * (1 - np.cos(2 * np.pi * t / 20.0)), amp)  # at rest at both ends
    traj = validate_trajectory(model.joint_names, model.joint_names, t, P)
    r = check_trajectory(Dynamics(model), traj)
    assert r.n_points == n and r.n_samples >= 2 * (n - 1)
    assert r.compute_time_s > 0 and math.isfinite(r.time_scale)
    assert r.waypoint_effort.shape == (n, 7)
    assert r.feasible


# ----------------------------------------------------------------------------------------------
# The fast paths inside the checker (bounds that skip exact roots, the RMS time-scale search on
# a sparse grid with gap bounds) against straightforward references on random data: every
# sample solved exactly, and the RMS contract checked by a direct windowed integral.

def _random_terms(rng: np.random.Generator, M: int, m: int):
    """Random static / viscous / inertial torque columns, smooth plus noise, some sign changes."""
    t = np.sort(rng.uniform(0.0, 3.0, M))
    t[0] = 0.0
    dup = rng.choice(np.arange(1, M - 1), 3, replace=False)
    t[dup] = t[dup - 1]                        # waypoints appear twice, as in the sampler
    ph = rng.uniform(0, 2 * np.pi, (3, m))
    fr = rng.uniform(0.5, 6.0, (3, m))
    amp = rng.uniform(0.1, 20.0, (3, m))
    S, W, I = (amp[k] * np.sin(fr[k] * t[:, None] + ph[k]) + rng.normal(0, 0.05 * amp[k], (M, m))
               for k in range(3))
    return t, S, W, I


# references: every sample solved by the scalar kernels, no bounds, no pruning
def quadratic_exits(c0, c1, c2, limit):
    from dyn_node.core.compiled import kernels as K
    return np.array([K.quadratic_exit(*e, limit) for e in zip(c0, c1, c2)])


def cubic_exits(c1, c2, c3, limit):
    from dyn_node.core.compiled import kernels as K
    return np.array([K.cubic_exit(*e, limit) for e in zip(c1, c2, c3)])


def envelope_exits(s, w, i, speed, curve):
    from dyn_node.core.compiled import kernels as K
    sp, ef = np.ascontiguousarray(curve[:, 0]), np.ascontiguousarray(curve[:, 1])
    return np.array([K.envelope_exit(*e, sp, ef, len(sp)) for e in zip(s, w, i, speed)])


@pytest.mark.parametrize("seed", range(6))
def test_exit_shortcuts_match_per_sample_exact_roots(seed):
    from dyn_node.core.compiled import kernels as K

    rng = np.random.default_rng(100 + seed)
    M, m = 2000, 4
    _, S, W, I = _random_terms(rng, M, m)
    L = np.abs(S).max(axis=0) * rng.uniform(0.7, 1.6, m)   # some columns statically infeasible
    got = K.band_exit(S, W, I, L)
    for c in range(m):
        # every sample solved exactly (elementwise; no bounds, no pruning)
        ref = float(quadratic_exits(S[:, c], W[:, c], I[:, c], L[c]).min())
        if np.any(np.abs(S[:, c]) > L[c]):
            ref = 0.0
        assert got[c] == ref
    Lp = rng.uniform(5.0, 50.0, m)
    got = K.odd_exit(S, W, I, np.ones_like(S), Lp)
    speed = rng.normal(size=S.shape)           # as power scales torque by joint speed
    got_scaled = K.odd_exit(S, W, I, speed, Lp)
    for c in range(m):
        ref = float(cubic_exits(S[:, c], W[:, c], I[:, c], Lp[c]).min())
        assert got[c] == ref
        v = speed[:, c]
        ref = float(cubic_exits(S[:, c] * v, W[:, c] * v, I[:, c] * v, Lp[c]).min())
        assert got_scaled[c] == ref


def _rms_ok(t, s, w, i, hold2, window, R, k) -> bool:
    """Direct check of the stretched trajectory: time t·k, torque s + w/k + i/k², windowed
    mean square by trapezoids and linear interpolation, hold torque before the start."""
    tk = t * k
    f = (s + w / k + i / (k * k)) ** 2
    cum = np.concatenate(([0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(tk))))
    start = tk - window
    inside = cum - np.interp(start, tk, cum) + np.maximum(tk[0] - start, 0.0) * hold2
    return bool(np.all(inside / window <= R * R))


@pytest.mark.parametrize("seed", range(8))
def test_rms_time_scale_meets_its_contract_on_random_torques(seed):
    from dyn_node.core.check import feasibility as F
    from dyn_node.core.compiled import kernels as K

    rng = np.random.default_rng(200 + seed)
    M, m = 1500, 3
    t, S, W, I = _random_terms(rng, M, m)
    hold2 = S[0] ** 2
    window = rng.uniform(0.05, 1.0, m)
    peak = np.abs(S + W + I).max(axis=0)
    s_max = np.maximum(np.abs(S).max(axis=0), np.sqrt(hold2))
    R = s_max + rng.uniform(0.02, 1.5, m) * (peak - s_max).clip(0.1)
    k_up = 1.0 / K.band_exit(S, W, I, R)
    k = F._rms_time_scale(t, S, W, I, hold2, window, R, k_up)
    for c in range(m):
        args = (t, S[:, c], W[:, c], I[:, c], hold2[c], window[c], R[c])
        assert k[c] > 0
        assert _rms_ok(*args, k[c]), (seed, c)
        assert _rms_ok(*args, k[c] * 1.001)
        assert not _rms_ok(*args, k[c] / (1 + 1e-5)), (seed, c)


@pytest.mark.parametrize("seed", range(6))
def test_envelope_time_scale_matches_per_sample_exact_exits(seed):
    """Random curves (rising and falling pieces; at high speed some fall below what gravity
    alone needs, so samples start outside parts of the envelope) against every sample solved
    exactly with no bounds."""
    from dyn_node.core.check import feasibility as F, task_motion

    rng = np.random.default_rng(300 + seed)
    model = base_model("panda")
    names = model.joint_names
    limits = {}
    for j, n in enumerate(names):
        eff = float(rng.uniform(15.0, 90.0))
        pts = np.sort(rng.uniform(0.05, 1.5, int(rng.integers(1, 4))))
        curve = [[0.0, eff]] + [[float(p), eff * float(rng.uniform(0.05, 1.0))] for p in pts]
        limits[n] = dict(has_effort_limits=True, max_effort=1e6, effort_speed_curve=curve)
    m = model.with_limits(None).with_limits({"joint_limits": limits})
    traj = make_traj("panda", ("quintic", "cubic")[seed % 2])
    dyn = Dynamics(m)
    r = check_trajectory(dyn, traj, FeasibilityOptions(sample_period=0.004,
                                                       compute_payload_margin=False))
    smp = F._sample(traj.times, 0.004, 250_000)
    pp = interpolate(traj, traj.natural_interpolation)
    Q, V, A = F._evaluate(pp.coeffs, pp.breaks, smp, 3)
    terms = task_motion.joint_terms(dyn, Q, V, A)[0]      # the check's own torque route
    x = min(float(envelope_exits(terms.static[:, j], terms.viscous[:, j], terms.inertial[:, j],
                                 V[:, j], m.limits.effort_speed_curve[j]).min())
            for j in range(m.nv))
    curves = m.limits.effort_speed_curve
    if any(np.any(np.abs(terms.static[:, j]) > curves[j][0, 1]) for j in range(m.nv)):
        # gravity alone exceeds the zero-speed envelope: no slowdown helps
        assert r.time_scale_by_kind["effort_speed"] == math.inf and not r.feasible
    else:
        assert r.time_scale_by_kind["effort_speed"] == (0.0 if math.isinf(x) else 1.0 / x)


def test_pathological_input_raises_trajectory_error_only():
    model = base_model("planar_2link")
    names = model.joint_names
    # finite but astronomically fast: squares would overflow inside the checks
    traj = validate_trajectory(names, names, [0.0, 1.0], [[0.0, 0.0], [1e120, 0.0]])
    with pytest.raises(TrajectoryError) as info:
        check_trajectory(Dynamics(model), traj)
    assert info.value.code == "non_finite"
    ok = validate_trajectory(names, names, [0.0, 1.0], [[0.0, 0.0], [0.1, 0.0]])
    with pytest.raises(TrajectoryError) as info:
        check_trajectory(Dynamics(model), ok, FeasibilityOptions(sample_period=0.0))
    assert info.value.code == "bad_options"


def test_thread_count_does_not_change_the_result():
    """threads=2 runs the batched RNEA passes on two OpenMP threads and the RMS time-scale
    search beside the other checks: the verdict must be the same, number for number."""
    from benchmarks.feasibility_bench import every_limit_kind

    model = base_model("panda").with_limits(None)
    model = model.with_limits(every_limit_kind(model))
    dyn = Dynamics(model)
    for traj in (make_traj("panda", "quintic"), stretch(make_traj("panda", "cubic"), 0.4)):
        one = check_trajectory(dyn, traj, FeasibilityOptions(sample_period=0.002, threads=1))
        two = check_trajectory(dyn, traj, FeasibilityOptions(sample_period=0.002, threads=2))
        assert one.time_scale_by_kind["rms_effort"] > 0   # the RMS search did run
        d1, d2 = one.to_dict(), two.to_dict()
        d1.pop("compute_time_s"), d2.pop("compute_time_s")
        assert json.dumps(d1) == json.dumps(d2)


def test_background_job_reraises_on_the_caller():
    from dyn_node.core.check import feasibility as F

    def boom(x):
        raise FloatingPointError(f"bad {x}")

    for background in (False, True):
        job = F._Job(boom, (3,), background=background)
        with pytest.raises(FloatingPointError, match="bad 3"):
            job.result()
    assert F._Job(lambda a, b: a + b, (2, 5), background=True).result() == 7


@pytest.mark.parametrize("seed", range(3))
def test_column_reductions_equal_numpy(seed):
    from dyn_node.core.check import feasibility as F

    rng = np.random.default_rng(400 + seed)
    X = rng.normal(size=(500, 5))
    X[rng.integers(0, 500, 3), rng.integers(0, 5, 3)] = np.nan
    X[:, 2] = 7.0                                           # ties: the same value
    assert np.array_equal(F._colmax(X), X.max(axis=0), equal_nan=True)
    cols = np.arange(5)
    assert F._take(X, cols) is X
    np.testing.assert_array_equal(F._take(X, np.array([0, 2, 4])), X[:, [0, 2, 4]])
    np.testing.assert_array_equal(F._take(X, np.array([1, 2, 3])), X[:, 1:4])


# --- the segment from the robot's current state to the first point ----------------------------

def _start_case(mode: str = "quintic", t0: float = 0.5):
    """planar_2link: joint1 from 0.5 to 1.5 rad, the first point at t0 > 0."""
    model = base_model("planar_2link")
    names = model.joint_names
    t = [t0, t0 + 1.5]
    P = [[0.5, 0.3], [1.5, 0.8]]
    V = [[0.0, 0.0], [0.0, 0.0]] if mode != "spline" else None
    A = [[0.0, 0.0], [0.0, 0.0]] if mode == "quintic" else None
    return model, validate_trajectory(names, names, t, P, V, A)


def _segment_oracle(model, qm, vm, p0, v0, a0, t0, step=2e-4):
    """Dense samples of the start segment from the boundary conditions (a linear solve per
    joint, q̈ = 0 at the start, quintic when a0 is given), torques by pinocchio.rnea + friction."""
    quintic = a0 is not None
    deg = 5 if quintic else 3
    ts = np.linspace(0.0, t0, int(math.ceil(t0 / step)) + 1)
    q, v, a = (np.zeros((len(ts), model.nv)) for _ in range(3))
    for j in range(model.nv):
        rows, rhs = [], []
        for t, vals in ((0.0, (qm[j], vm[j], 0.0)), (t0, (p0[j], v0[j], a0[j] if quintic else 0.0))):
            for d in range(3 if quintic else 2):
                rows.append([math.prod(range(p - d + 1, p + 1)) * t ** (p - d) if p >= d else 0.0
                             for p in range(deg + 1)])
                rhs.append(vals[d])
        c = np.linalg.solve(np.array(rows), np.array(rhs))[::-1]
        q[:, j], v[:, j] = np.polyval(c, ts), np.polyval(np.polyder(c), ts)
        a[:, j] = np.polyval(np.polyder(c, 2), ts)
    pm = model.pin_model
    data = pm.createData()
    damping, coulomb = np.array(pm.damping), np.array(pm.friction)
    tau = np.array([pin.rnea(pm, data, q[m], v[m], a[m]) + damping * v[m] + coulomb * np.sign(v[m])
                    for m in range(len(ts))])
    return {"t": ts, "q": q, "v": v, "a": a, "tau": tau}


@pytest.mark.parametrize("mode", ["quintic", "cubic"])   # positions only: test_execution
def test_start_segment_is_checked_from_the_current_state(mode):
    """Robot at q = 0 moving at −2.5 rad/s, away from a first point 0.5 s ahead: the segment the
    controller runs to it holds the worst velocity, acceleration and torque, equal to a dense
    independent evaluation of that segment; without the state the verdict says so (WARN)."""
    from dyn_node.core.check.feasibility import START_CHECKED, StartState

    model, traj = _start_case(mode)
    dyn = Dynamics(model)
    qm, vm = np.array([0.0, 0.3]), np.array([-2.5, 0.0])
    r = check_trajectory(dyn, traj, start=StartState(qm, vm, age_s=0.004))
    o = _segment_oracle(model, qm, vm, traj.positions[0], np.zeros(2),
                        np.zeros(2) if mode == "quintic" else None, 0.5)
    assert r.start_segment == START_CHECKED and r.start_state_age_s == 0.004
    assert r.summary_values()["start_segment"] == "checked"
    j1 = r.per_joint["joint1"]
    # the peaks lie in the start segment (t < 0.5 s) and match the independent segment
    for kind, ref in (("velocity", np.abs(o["v"][:, 0])), ("effort", np.abs(o["tau"][:, 0]))):
        assert j1[kind]["time_s"] < 0.5, (kind, j1[kind])
        assert j1[kind]["value"] == pytest.approx(ref.max(), rel=2e-4), kind
    assert not r.feasible        # reversing in time needs more than joint1's 40 N·m
    assert r.violations[0].first_time_s < 0.5
    # one row per message point (not the prepended state): at rest there (quintic), gravity
    assert r.n_points == 2 and r.waypoint_effort.shape == (2, 2)
    if mode == "quintic":
        pm = model.pin_model
        data = pm.createData()
        for row, q in zip(r.waypoint_effort, traj.positions):
            np.testing.assert_allclose(row, pin.computeGeneralizedGravity(pm, data, q),
                                       rtol=0, atol=1e-9)
    unknown = check_trajectory(dyn, traj)
    assert unknown.start_segment == "not_checked (no current state given)"
    assert math.isnan(unknown.start_state_age_s)
    assert unknown.level == WARN, unknown.message
    assert unknown.feasible
    assert "start segment not checked (no current state given)" in unknown.message
    assert unknown.per_joint["joint1"]["velocity"]["time_s"] >= 0.5


def test_first_point_at_zero_has_no_start_segment_the_distance_is_a_jump():
    """First point at t = 0: no segment from the robot's state (trajectory.cpp sample 147-169,
    jazzy ed360c9); the controller steps to it. A robot there at rest changes nothing; one away
    from it or moving is a jump: infeasible, no slowdown helps. (It used to ignore the state.)"""
    from dyn_node.core.check.feasibility import START_NONE, StartState

    model = base_model("planar_2link")
    names = model.joint_names
    traj = validate_trajectory(names, names, [0.0, 1.5], [[0.5, 0.3], [1.5, 0.8]],
                               [[0.0, 0.0]] * 2, [[0.0, 0.0]] * 2)
    dyn = Dynamics(model)
    a = check_trajectory(dyn, traj)
    there = check_trajectory(dyn, traj, start=StartState(np.array([0.5, 0.3]), np.zeros(2), 0.01))
    assert a.start_segment == there.start_segment == START_NONE
    assert a.level == OK and there.level == OK, (a.message, there.message)
    assert a.time_scale == there.time_scale and a.message == there.message
    away = check_trajectory(dyn, traj, start=StartState(np.zeros(2), np.array([-2.5, 1.0]), 0.01))
    assert away.start_segment == START_NONE and not away.feasible and away.time_scale == math.inf
    assert away.message.startswith("infeasible: the first point is 0.5 rad from the robot (joint1): "
                                   "the controller steps to it at once"), away.message


def _start_scenarios():
    """(name, mode, t0, start q, start q̇): the start segment is the worst part of each."""
    return [
        # moving fast away from the first point: reversing in time needs the torque
        ("reversing", "quintic", 0.5, [0.0, 0.3], [-2.5, 0.0]),
        ("reversing_cubic", "cubic", 0.5, [0.0, 0.3], [-2.5, 0.0]),
        # far from the first point with a short first time, at rest (stretches like the rest)
        ("far_at_rest", "quintic", 0.3, [-1.5, -0.6], [0.0, 0.0]),
        # far away and moving towards it: feasible with margin, the start segment binds
        ("approaching", "quintic", 1.2, [-0.5, 0.3], [0.8, 0.0]),
    ]


@pytest.mark.parametrize("name,mode,t0,qm,vm", _start_scenarios())
def test_time_scale_contract_when_the_start_segment_binds(name, mode, t0, qm, vm):
    """README: time_scale k — the trajectory stretched by 1.001·k is feasible and by some k′ in
    [0.97·k, k) it is not — when the worst part is the segment from the robot's current state,
    whose velocity does not scale with k (each stretched trajectory checked from the same state)."""
    from dyn_node.core.check.feasibility import StartState

    model, traj = _start_case(mode, t0)
    dyn = Dynamics(model)
    st = StartState(np.array(qm), np.array(vm), age_s=0.0)
    r = check_trajectory(dyn, traj, start=st)
    k = r.time_scale
    assert math.isfinite(k) and k > 0, r.message
    assert r.feasible == (k <= 1.0)
    # the binding part: in the start segment (t < t0) at k′ just below k
    below = check_trajectory(dyn, stretch(traj, 0.99 * k), start=st)
    assert not below.feasible, (name, k)
    assert any(v.first_time_s < 0.99 * k * t0 for v in below.violations), below.violations
    assert check_trajectory(dyn, stretch(traj, 1.001 * k), start=st).feasible, (name, k)
    assert not check_trajectory(dyn, stretch(traj, 0.97 * k), start=st).feasible, (name, k)
    assert r.time_scale_constraint == below.violations[0].kind
    # the same trajectory without its start segment would run faster: the segment binds
    alone = check_trajectory(dyn, traj)
    assert alone.time_scale < k
    if any(vm):
        assert r.time_scale_start_segment and "the segment from the current state binds" in r.message
    level = ERROR if not r.feasible else (WARN if r.worst_ratio > 0.9 or r.warnings else OK)
    assert r.level == level


def test_start_segment_that_no_slowdown_fixes_is_infinite():
    """Rushing at 2.9 rad/s towards joint1's upper limit (3 rad) with the first point behind:
    short times need more torque than 40 N·m, long ones overshoot the limit."""
    from dyn_node.core.check.feasibility import StartState

    model, traj = _start_case("quintic", 0.05)
    st = StartState(np.array([2.9, 0.3]), np.array([2.9, 0.0]), age_s=0.0)
    r = check_trajectory(Dynamics(model), traj, start=st)
    assert not r.feasible
    assert r.time_scale == math.inf and r.time_scale_start_segment
    assert "no slowdown up to 1000× makes the segment from the current state feasible" in r.message
    for f in (1.5, 4.0, 30.0, 300.0):
        assert not check_trajectory(Dynamics(model), stretch(traj, f), start=st).feasible, f


@pytest.mark.parametrize("t1,window,v0,rms_limit", [(0.9, 1.0, -2.5, 30.0), (1.1, 1.5, -2.0, 22.0)])
def test_time_scale_contract_when_rms_windows_reach_into_the_start_segment(t1, window, v0, rms_limit):
    """Only joint1's RMS effort is limited, the robot turning round in a 0.3 s start segment and
    then moving 1.5 rad: the worst window ends after the segment and reaches back into it, so
    the time scale is found on the whole stretched trajectory (the segment alone, or the rest's
    per-sample search, miss it: 1.001·k was infeasible)."""
    from dyn_node.core.check.feasibility import StartState

    model = base_model("planar_2link")
    names = model.joint_names
    traj = validate_trajectory(names, names, [0.3, t1], [[0.5, 0.3], [2.0, 0.8]],
                               [[0.0, 0.0]] * 2, [[0.0, 0.0]] * 2)
    lim = {"joint_limits": {
        "joint1": {"has_effort_limits": False, "has_velocity_limits": False,
                   "max_rms_effort": rms_limit, "rms_window": window},
        "joint2": {"has_effort_limits": False, "has_velocity_limits": False}}}
    dyn = Dynamics(model.with_limits(lim))
    st = StartState(np.array([0.0, 0.3]), np.array([v0, 0.0]), age_s=0.0)
    r = check_trajectory(dyn, traj, start=st)
    k = r.time_scale
    assert not r.feasible and 1.0 < k < math.inf, r.message
    assert r.per_joint["joint1"]["rms_effort"]["time_s"] > 0.3   # the worst window ends later
    assert r.time_scale_constraint == "rms_effort" and r.time_scale_start_segment
    assert check_trajectory(dyn, stretch(traj, 1.001 * k), start=st).feasible
    for f in (0.99, 0.97):
        below = check_trajectory(dyn, stretch(traj, f * k), start=st)
        assert [v.kind for v in below.violations] == ["rms_effort"], f
