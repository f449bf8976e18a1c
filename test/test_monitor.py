"""The pure live monitor: torques, acceleration estimate, rejections, statuses, controller tracker."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.errors import CONTROL_ERROR, EVALUATION_ERROR, STATE_ERROR, ModelError
from dyn_node.core.robot.model import load_model
from dyn_node.core.robot.model_source import build_model
from dyn_node.core.robot.model_status import model_error_status, model_status, waiting_model_status
from dyn_node.core.live.monitor import Monitor
from dyn_node.core.robot.settings import Settings
from dyn_node.core.robot.status import ERROR, OK, STALE, WARN
from dyn_node.core.live.tracker import ControllerTracker
from dyn_node.core.check.execution import Timing
from dyn_node.core.check.trajectory import validate_trajectory

PANDA = load_model(builtin="panda")
PLANAR = load_model(builtin="planar_2link")
NAMES = list(PANDA.joint_names)
Q0 = np.array([0.1, -0.4, 0.2, -1.8, 0.3, 1.5, -0.2])


def by_name(statuses, suffix):
    return next(s for s in statuses if s.name == "dyn_node: " + suffix)


def test_torques_match_dynamics_and_identity():
    mon = Monitor(PANDA, Settings())
    dyn = Dynamics(PANDA)
    v1, v2 = np.full(7, 0.2), np.linspace(-0.5, 0.5, 7)
    mon.process(NAMES, Q0, v1, [], 10.0, 10.0)
    r = mon.process(NAMES, Q0 + 0.001, v2, [], 10.002, 10.003)
    a = (v2 - v1) / (10.002 - 10.0)
    np.testing.assert_array_equal(r.a_hat, a)
    np.testing.assert_allclose(r.tau, dyn.rnea(Q0 + 0.001, v2, a), rtol=0, atol=1e-9)
    np.testing.assert_allclose(r.gravity, dyn.gravity(Q0 + 0.001), rtol=0, atol=1e-9)
    # independent identity: τ = M a + h
    np.testing.assert_allclose(r.tau, dyn.mass_matrix(Q0 + 0.001) @ a + dyn.bias(Q0 + 0.001, v2), atol=1e-9)


def test_input_order_and_ignored_names_are_handled():
    mon = Monitor(PANDA, Settings())
    perm = [6, 2, 0, 1, 5, 4, 3]
    names = [NAMES[i] for i in perm] + ["panda_finger_joint1", "some_other_joint"]
    q = list(Q0[perm]) + [0.04, 1.0]
    r = mon.process(names, q, [], [], 1.0, 1.0)
    assert r.accepted
    np.testing.assert_array_equal(r.q, Q0)
    np.testing.assert_array_equal(r.v, np.zeros(7))
    assert mon.counts.ignored_joint_values == 2


def test_acceleration_resets_and_filter():
    s = Settings(acceleration_filter_hz=20.0, stale_timeout=0.5)
    mon = Monitor(PANDA, s)
    vs = [np.full(7, x) for x in (0.0, 0.01, 0.03, 0.04)]
    ts = [1.0, 1.001, 1.002, 1.004]
    r0 = mon.process(NAMES, Q0, vs[0], [], ts[0], ts[0])
    np.testing.assert_array_equal(r0.a_hat, 0.0)  # first message: no difference yet
    r1 = mon.process(NAMES, Q0, vs[1], [], ts[1], ts[1])
    raw1 = (vs[1] - vs[0]) / (ts[1] - ts[0])
    np.testing.assert_array_equal(r1.a_hat, raw1)  # the filter starts at the first raw value
    r2 = mon.process(NAMES, Q0, vs[2], [], ts[2], ts[2])
    raw2 = (vs[2] - vs[1]) / (ts[2] - ts[1])
    alpha = 1 - math.exp(-2 * math.pi * 20.0 * (ts[2] - ts[1]))
    np.testing.assert_allclose(r2.a_hat, raw1 + alpha * (raw2 - raw1), rtol=1e-15)
    # stamp going backwards: counted, outputs computed, estimate reset
    r3 = mon.process(NAMES, Q0, vs[3], [], 1.0005, 1.005)
    assert r3.accepted and r3.out_of_order
    np.testing.assert_array_equal(r3.a_hat, 0.0)
    assert mon.counts.out_of_order == 1
    # gap beyond stale_timeout: reset, not differentiated across the gap
    mon.process(NAMES, Q0, vs[0], [], 2.0, 2.0)
    r5 = mon.process(NAMES, Q0, vs[3], [], 2.6, 2.6)
    np.testing.assert_array_equal(r5.a_hat, 0.0)


def test_acceleration_source_zero():
    mon = Monitor(PANDA, Settings(acceleration_source="zero"))
    mon.process(NAMES, Q0, np.zeros(7), [], 1.0, 1.0)
    r = mon.process(NAMES, Q0, np.ones(7), [], 1.001, 1.001)
    np.testing.assert_array_equal(r.a_hat, 0.0)
    np.testing.assert_allclose(r.tau, Dynamics(PANDA).rnea(Q0, np.ones(7), np.zeros(7)), atol=1e-9)


def test_zero_stamp_uses_receipt_time():
    mon = Monitor(PANDA, Settings())
    mon.process(NAMES, Q0, np.zeros(7), [], 0.0, 5.0)
    r = mon.process(NAMES, Q0, np.full(7, 0.01), [], 0.0, 5.001)
    assert r.zero_stamp and r.stamp_s == 5.001
    np.testing.assert_allclose(r.a_hat, np.full(7, 0.01) / (5.001 - 5.0), rtol=1e-12)
    st = by_name(mon.statuses(5.01, "panda"), "joint_states")
    assert st.level == WARN and "zero stamp" in st.message
    assert st.values["zero_stamp_messages"] == 2 and st.values["failure_label"] == STATE_ERROR


BAD = [
    ("length_mismatch", NAMES, list(Q0[:6]), [], []),
    ("non_finite", NAMES, [math.nan] + list(Q0[1:]), [], []),
    ("non_finite", NAMES, list(Q0[:6]) + [math.inf], [], []),
    ("non_finite", NAMES, list(Q0), [math.nan] * 7, []),
    ("no_model_joints", ["a", "b"], [0.0, 1.0], [], []),
    ("missing_joints", NAMES[:6], list(Q0[:6]), [], []),
    ("empty", [], [], [], []),
    ("duplicate_names", NAMES + [NAMES[0]], list(Q0) + [0.0], [], []),
    ("length_mismatch", NAMES, list(Q0), [0.0] * 3, []),
]


@pytest.mark.parametrize("code,names,q,v,e", BAD)
def test_bad_input_rejected_counted_and_next_valid_correct(code, names, q, v, e):
    mon = Monitor(PANDA, Settings())
    r = mon.process(names, q, v, e, 1.0, 1.0)
    assert not r.accepted and r.error.code == code and r.tau is None
    st = by_name(mon.statuses(1.01, "panda"), "joint_states")
    assert st.level == ERROR and st.values["invalid_messages"] == 1
    assert st.values[f"invalid_{code}"] == 1 and st.values["failure_label"] == STATE_ERROR
    r2 = mon.process(NAMES, Q0, np.full(7, 0.1), [], 1.02, 1.02)
    assert r2.accepted
    np.testing.assert_allclose(r2.tau, Dynamics(PANDA).rnea(Q0, np.full(7, 0.1), np.zeros(7)), atol=1e-9)
    assert by_name(mon.statuses(1.03, "panda"), "joint_states").level == OK


def test_nan_effort_means_not_available():
    mon = Monitor(PANDA, Settings())
    r = mon.process(NAMES, Q0, [], [math.nan] * 7, 1.0, 1.0)
    assert r.accepted and r.residual is None
    st = by_name(mon.statuses(1.1, "panda"), "residual")
    assert st.level == OK and st.values["effort_measured"] is False


def test_effort_status_levels_and_message():
    mon = Monitor(PANDA, Settings())
    g = Dynamics(PANDA).gravity(Q0)
    effort = g.copy()
    effort[3] = 1.04 * 87.0
    mon.process(NAMES, Q0, np.zeros(7), effort, 1.0, 1.0)
    st = by_name(mon.statuses(1.5, "panda"), "effort")
    assert st.level == ERROR and st.values["failure_label"] == CONTROL_ERROR
    assert st.message.startswith("panda_joint4 at 104% of its 87 N·m effort limit")
    assert st.values["panda_joint4_utilisation"] == pytest.approx(1.04, abs=1e-12)
    assert st.values["worst_joint"] == "panda_joint4"
    effort[3] = 0.95 * 87.0
    mon.process(NAMES, Q0, np.zeros(7), effort, 2.0, 2.0)
    st = by_name(mon.statuses(2.5, "panda"), "effort")
    assert st.level == WARN and "95%" in st.message
    mon.process(NAMES, Q0, np.zeros(7), g, 3.0, 3.0)
    st = by_name(mon.statuses(3.5, "panda"), "effort")
    assert st.level == OK
    np.testing.assert_allclose(st.values["panda_joint2_utilisation"], abs(g[1]) / 87.0, rtol=1e-12)


def test_a_closed_window_keeps_its_messages_and_the_next_gets_the_rest():
    """The node closes a window under its joint_states lock and writes its statuses after
    releasing it, while messages go on: a message taken in between belongs to the next window."""
    mon = Monitor(PANDA, Settings())
    g = Dynamics(PANDA).gravity(Q0)
    over = g.copy()
    over[3] = 1.04 * 87.0
    # more rows than one fold batch, so the closed window holds folded and unfolded rows
    n = mon._w.FOLD_ROWS + 7
    for k in range(n):
        mon.process(NAMES, Q0, np.zeros(7), g, 1.0 + k * 1e-3, 1.0 + k * 1e-3)
    closed = mon.close_window(2.0, "panda")
    mon.process(NAMES, Q0, np.zeros(7), over, 2.001, 2.001)
    first = {s.name: s for s in closed.statuses()}
    assert first["dyn_node: effort"].level == OK
    assert first["dyn_node: joint_states"].values["received_messages"] == n
    np.testing.assert_allclose(first["dyn_node: effort"].values["panda_joint4_utilisation"],
                               abs(g[3]) / 87.0, rtol=1e-12)
    second = by_name(mon.statuses(3.0, "panda"), "effort")
    assert second.level == ERROR and second.values["panda_joint4_utilisation"] == pytest.approx(1.04, abs=1e-12)


def test_residual_rms():
    mon = Monitor(PANDA, Settings(residual_warn_ratio=0.1))
    dyn = Dynamics(PANDA)
    g = dyn.gravity(Q0)
    offsets = [3.0, -5.0, 4.0]
    for k, d in enumerate(offsets):
        e = g.copy()
        e[1] += d
        e[5] = math.nan  # joint 6 not measured
        mon.process(NAMES, Q0, np.zeros(7), e, 1.0 + k, 1.0 + k)
    st = by_name(mon.statuses(4.0, "panda"), "residual")
    rms = math.sqrt(sum(d * d for d in offsets) / 3)
    assert st.values["panda_joint2_residual_rms_nm"] == pytest.approx(rms, abs=1e-9)
    assert "panda_joint6_residual_rms_nm" not in st.values
    assert st.level == OK  # 4.08 N·m < 10 % of 87 N·m
    for k in range(3):
        e = g.copy()
        e[4] += 2.0  # 2 N·m of a 12 N·m limit: 17 %
        mon.process(NAMES, Q0, np.zeros(7), e, 5.0 + k, 5.0 + k)
    st = by_name(mon.statuses(8.0, "panda"), "residual")
    assert st.level == WARN and st.values["worst_joint"] == "panda_joint5"
    assert st.values["failure_label"] == CONTROL_ERROR and "panda_joint5 effort residual 2 N·m" in st.message


def test_limits_status():
    mon = Monitor(PLANAR, Settings())
    names = list(PLANAR.joint_names)
    mon.process(names, [0.0, 0.0], [0.0, 0.0], [], 1.0, 1.0)
    st = by_name(mon.statuses(1.1, "planar"), "limits")
    assert st.level == OK
    mon.process(names, [2.95, 0.0], [0.0, 0.0], [], 2.0, 2.0)  # soft limit 2.9, hard 3.0
    st = by_name(mon.statuses(2.1, "planar"), "limits")
    assert st.level == WARN and st.values["soft_limit_violations"] == 1 and "joint1" in st.message
    mon.process(names, [0.0, -2.7], [0.0, 4.5], [], 3.0, 3.0)
    st = by_name(mon.statuses(3.1, "planar"), "limits")
    assert st.level == ERROR and st.values["failure_label"] == CONTROL_ERROR
    assert st.values["joint2_position_rad"] == -2.7 and st.values["joint2_velocity_rad_s"] == 4.5
    assert st.message.startswith("joint2 position -2.7 rad below its lower limit -2.6 rad")
    # exactly at the limits is within them (inclusive bounds, |v| ≤ max)
    mon.process(names, [3.0, -2.6], [3.0, -4.0], [], 4.0, 4.0)
    st = by_name(mon.statuses(4.1, "planar"), "limits")
    assert st.values["position_violations"] == 0 and st.values["velocity_violations"] == 0


def test_staleness_and_rate():
    mon = Monitor(PANDA, Settings(stale_timeout=0.5))
    st = mon.statuses(0.0, "panda")
    assert by_name(st, "joint_states").level == STALE and by_name(st, "effort").level == STALE
    for k in range(100):  # 100 messages in the window (0, 1] s after the first report
        mon.process(NAMES, Q0, [], [], 0.01 * (k + 1), 0.01 * (k + 1))
    st = by_name(mon.statuses(1.01, "panda"), "joint_states")
    assert st.level == OK and st.values["rate_hz"] == pytest.approx(100 / 1.01)
    assert st.values["age_s"] == pytest.approx(0.01)
    st = mon.statuses(1.6, "panda")
    assert by_name(st, "joint_states").level == STALE and "stale_timeout" in by_name(st, "joint_states").message


def test_dropped_messages_counted():
    mon = Monitor(PANDA, Settings())
    mon.process(NAMES, Q0, [], [], 1.0, 1.0)
    assert "drop_counting" not in by_name(mon.statuses(1.05, "panda"), "joint_states").values
    mon.process(NAMES, Q0, [], [], 1.06, 1.06)
    mon.note_dropped(7, "sequence_numbers")
    mon.note_dropped(5, "middleware_lost_events")    # a running total: a smaller one adds nothing
    st = by_name(mon.statuses(1.1, "panda"), "joint_states")
    assert st.level == WARN and st.values["dropped_messages"] == 7 and "7 dropped" in st.message
    assert st.values["drop_counting"] == "middleware_lost_events"


def test_deterministic_replay():
    rng = np.random.default_rng(3)
    seq = [(Q0 + rng.normal(0, 0.01, 7), rng.normal(0, 0.3, 7), rng.normal(0, 5, 7), 1 + 0.001 * k)
           for k in range(50)]
    runs = []
    for _ in range(2):
        mon = Monitor(PANDA, Settings(acceleration_filter_hz=30.0))
        runs.append([mon.process(NAMES, q, v, e, t, t + 1e-4) for q, v, e, t in seq])
    for a, b in zip(*runs):
        assert a.tau.tobytes() == b.tau.tobytes() and a.a_hat.tobytes() == b.a_hat.tobytes()


def test_model_statuses():
    st = model_status(PANDA, "panda")
    assert st.level == OK and st.values["dof"] == 7 and st.values["urdf_sha256"] == PANDA.urdf_hash
    assert st.values["total_mass_kg"] == PANDA.total_mass
    assert waiting_model_status("x").level == STALE
    assert waiting_model_status("x").message == "waiting for robot_description"
    err = model_error_status(ModelError("bad"), "panda", PANDA)
    assert err.level == ERROR and err.values["failure_label"] == EVALUATION_ERROR
    with pytest.raises(ModelError):
        build_model(Settings(), "<robot name='x'>")
    m = build_model(Settings(robot_model="panda", payload_mass=2.0))
    assert m.payload.mass == 2.0


def _tracker_traj(times, positions):
    return validate_trajectory(NAMES, NAMES, times, positions, min_points=1)


def test_controller_tracker_states():
    s = Settings(tracking_tolerance=0.05, stale_timeout=0.5)
    mon, tr = Monitor(PANDA, s), ControllerTracker(PANDA, s)
    assert tr.tick(0.0) is False and tr.state == "stale"
    r = mon.process(NAMES, Q0, [], [], 1.0, 1.0)
    assert tr.update(r, 1.0) and tr.state == "idle"
    q1 = Q0 + 0.2
    tr.follow(_tracker_traj([0.0, 1.0], [Q0, q1]), timing=Timing(0.0, 2.0))
    # linear reference at t = 2.25: Q0 + 0.25·0.2
    np.testing.assert_allclose(tr.reference(2.25), Q0 + 0.05, rtol=0, atol=1e-15)
    r = mon.process(NAMES, Q0 + 0.05 + 0.01, [], [], 2.25, 2.25)
    assert tr.update(r, 2.25) and tr.state == "tracking"
    st = tr.status(2.3, "panda")
    assert st.level == OK and st.values["panda_joint1_tracking_error_rad"] == pytest.approx(0.01, abs=1e-12)
    assert st.values["time_in_state_s"] == pytest.approx(0.05)
    r = mon.process(NAMES, Q0 + 0.5 * 0.2 + 0.08, [], [], 2.5, 2.5)
    assert tr.update(r, 2.5) and tr.state == "deviating"
    st = tr.status(2.5, "panda")
    assert st.level == WARN and st.values["failure_label"] == CONTROL_ERROR and "0.05" in st.message
    effort = np.zeros(7)
    effort[0] = 90.0
    r = mon.process(NAMES, Q0 + 0.12, [], effort, 2.6, 2.6)
    assert tr.update(r, 2.6) and tr.state == "saturated" and tr.status(2.6, "p").level == ERROR
    r = mon.process(NAMES[:3], Q0[:3], [], [], 2.7, 2.7)
    assert tr.update(r, 2.7) and tr.state == "fault"
    assert tr.status(2.7, "p").values["failure_label"] == STATE_ERROR
    r = mon.process(NAMES, q1, [], [], 3.5, 3.5)  # after the last point: idle
    assert tr.update(r, 3.5) and tr.state == "idle"
    assert tr.tick(4.1) and tr.state == "stale" and tr.status(4.1, "p").level == STALE


def test_tracker_reference_quintic_matches_interpolation():
    from dyn_node.core.check.trajectory import interpolate

    rng = np.random.default_rng(1)
    P = Q0 + rng.normal(0, 0.1, (4, 7))
    V = rng.normal(0, 0.1, (4, 7))
    A = rng.normal(0, 0.1, (4, 7))
    V[-1] = A[-1] = 0.0   # the controller refuses a non-zero end velocity by default
    traj = validate_trajectory(NAMES, NAMES, [0.0, 0.4, 1.0, 1.5], P, V, A)
    tr = ControllerTracker(PANDA, Settings())
    tr.follow(traj, timing=Timing(0.0, 10.0))
    expected = interpolate(traj, "quintic").evaluate(np.array([0.7]))[0][0]
    np.testing.assert_allclose(tr.reference(10.7), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tr.reference(10.4), P[1], rtol=0, atol=1e-12)
    assert tr.reference(11.6) is None and tr.reference(9.9) is None


def test_worst_case_window_over_many_messages_matches_a_direct_computation():
    """The window is folded in batches; its report must equal the per-message definition:
    per joint the largest utilisation (and the limit at that message), the worst position and
    velocity excess with the value that caused it, and the RMS residual over measured messages."""
    rng = np.random.default_rng(11)
    mon = Monitor(PANDA, Settings(acceleration_source="zero", include_friction=False))
    dyn = Dynamics(PANDA, DynamicsOptions(include_friction=False))
    lim = PANDA.limits
    n = 1300  # more than one fold batch, with a report in between
    Q = rng.uniform(lim.position_lower - 0.2, lim.position_upper + 0.2, (n, 7))
    V = rng.normal(0, 1.5, (n, 7))
    E = rng.normal(0, 40, (n, 7))
    E[rng.random((n, 7)) < 0.2] = np.nan  # unmeasured joints
    split = 700
    for k in range(n):
        mon.process(NAMES, Q[k], V[k], E[k], 1.0 + 1e-3 * k, 1.0 + 1e-3 * k)
        if k == split - 1:
            mon.statuses(1.0 + 1e-3 * k, "panda")
    sts = mon.statuses(2.5, "panda")
    eff, lims, res = by_name(sts, "effort"), by_name(sts, "limits"), by_name(sts, "residual")
    part = slice(split, n)
    tau = np.array([dyn.rnea(q, v, np.zeros(7)) for q, v in zip(Q[part], V[part])])
    util = np.fmax(np.abs(tau), np.abs(E[part])) / lim.effort
    for j, name in enumerate(NAMES):
        assert eff.values[f"{name}_utilisation"] == pytest.approx(util[:, j].max(), rel=1e-12)
        r = E[part, j] - tau[:, j]
        r = r[~np.isnan(r)]
        assert res.values[f"{name}_residual_rms_nm"] == pytest.approx(math.sqrt(np.mean(r * r)), rel=1e-12)
        pex = np.maximum(lim.position_lower[j] - Q[part, j], Q[part, j] - lim.position_upper[j])
        if pex.max() > 0:
            assert lims.values[f"{name}_position_rad"] == Q[part, j][np.argmax(pex)]
        else:
            assert f"{name}_position_rad" not in lims.values
        vex = np.abs(V[part, j]) - lim.velocity[j]
        if vex.max() > 0:
            assert lims.values[f"{name}_velocity_rad_s"] == V[part, j][np.argmax(vex)]
    assert lims.values["position_violations"] == int(np.sum(
        (Q[part] < lim.position_lower).any(axis=0) | (Q[part] > lim.position_upper).any(axis=0)))


def test_result_arrays_are_fresh_copies_of_the_input():
    """Callers and the batched window keep the result arrays: they must not alias the input."""
    mon = Monitor(PANDA, Settings())
    q, v, e = Q0.copy(), np.full(7, 0.1), np.full(7, 1.0)
    r = mon.process(NAMES, q, v, e, 1.0, 1.0)
    q[:] = 9.0
    v[:] = 9.0
    e[:] = 9.0
    np.testing.assert_array_equal(r.q, Q0)
    np.testing.assert_array_equal(r.v, 0.1)
    np.testing.assert_allclose(r.residual + r.tau, np.full(7, 1.0), rtol=0, atol=1e-12)
    assert r.effort_limit is not None and np.all(r.effort_limit == PANDA.limits.effort)


def _same(a, b) -> bool:
    """Bitwise equality of results (None, floats, bools or arrays; NaN equals NaN, −0 ≠ +0)."""
    if a is None or b is None:
        return a is None and b is None
    a, b = np.asarray(a), np.asarray(b)
    return (a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
            and np.array_equal(np.signbit(a), np.signbit(b)))


@pytest.mark.parametrize("seed", range(4))
def test_process_batch_equals_process_message_by_message(seed):
    """The audit's fast path: process_batch + update_batch must leave exactly the results, counts,
    statuses and tracker transitions of N process/update calls (random models, settings, name
    orders, stamps with repeats, jumps back, stale gaps and zero stamps, NaN efforts, with and
    without velocities, with and without an active trajectory)."""
    rng = np.random.default_rng(seed)
    # planar_limited: live deceleration limits and a real (YAML) zero effort limit
    models = {"panda": PANDA, "planar_2link": PLANAR, "ur5": load_model(builtin="ur5"),
              "planar_limited": PLANAR.with_limits(
                  "joint_limits:\n  joint1: {max_deceleration: 50.0, max_effort: 0.0}\n"
                  "  joint2: {max_deceleration: 20.0}\n")}
    fields = ("stamp_s", "q", "v", "a_hat", "gravity", "tau", "residual", "utilisation",
              "measured_ratio", "zero_stamp", "out_of_order", "effort_limit")
    decelerations = 0
    for trial in range(25):
        model = models[str(rng.choice(list(models)))]
        nv, names = model.nv, list(model.joint_names)
        settings = Settings(acceleration_filter_hz=float(rng.choice([0.0, 0.0, 15.0])),
                            acceleration_source=str(rng.choice(["finite_difference", "zero"],
                                                               p=[.8, .2])),
                            include_friction=bool(rng.integers(2)), tracking_tolerance=0.3)
        order = rng.permutation(nv) if rng.integers(2) else np.arange(nv)
        msg_names = tuple(names[i] for i in order)
        n = int(rng.integers(1, 200))
        t = 1.0 + np.cumsum(rng.choice([1e-3, 0.0, -2e-3, 0.7], size=n, p=[.85, .05, .05, .05]))
        if rng.integers(2):
            t[rng.integers(n)] = 0.0
        receipt = 1.0 + 1e-3 * np.arange(n) + 1e-4
        P = rng.uniform(-2.5, 2.5, (n, nv))
        V = rng.uniform(-3, 3, (n, nv)) if rng.integers(4) else None
        E = rng.uniform(-150, 150, (n, nv)) if rng.integers(3) else None
        if E is not None and rng.integers(2):
            E[rng.random((n, nv)) < 0.3] = np.nan
            E[rng.random(n) < 0.2] = np.nan  # whole messages without effort
        one, many = Monitor(model, settings), Monitor(model, settings)
        tr_one, tr_many = ControllerTracker(model, settings), ControllerTracker(model, settings)
        if rng.integers(2):
            q_mid = np.zeros(nv) + 0.5
            traj = validate_trajectory(names, names, [0.0, 0.05, 0.1],
                                       [np.zeros(nv), q_mid, np.zeros(nv)], min_points=1)
            start = 1.0 + 0.02 * float(rng.integers(0, 4))
            for tr in (tr_one, tr_many):
                tr.follow(traj, timing=Timing(0.0, start))
        for k in range(int(rng.integers(0, 3))):  # a common history before the batch
            for mon, tr in ((one, tr_one), (many, tr_many)):
                r = mon.process(msg_names, P[0], [] if V is None else V[0], [], 0.5 + 1e-3 * k, 0.5)
                tr.update(r, 0.5)
        results, changes = [], []
        for k in range(n):
            r = one.process(msg_names, P[k], [] if V is None else V[k], [] if E is None else E[k],
                            float(t[k]), float(receipt[k]))
            results.append(r)
            if tr_one.update(r, float(receipt[k])):
                changes.append((k, tr_one.state))
        batch = many.process_batch(msg_names, P, V, E, t, receipt)
        assert batch is not None and len(batch) == n
        assert tr_many.update_batch(batch, receipt) == changes
        for k, r in enumerate(results):
            rb = batch.result(k)
            for f in fields:
                assert _same(getattr(r, f), getattr(rb, f)), (trial, k, f)
        assert _same(one._a, many._a) and _same(one._prev_v, many._prev_v)
        assert (one._prev_t, one._filtered) == (many._prev_t, many._filtered)
        assert vars(one.counts) == vars(many.counts)
        assert _same(one.last_result.tau, many.last_result.tau)
        # the next message continues identically, and so do the reports
        for mon in (one, many):
            mon.process(msg_names, P[0], [] if V is None else V[0], [], float(t[-1]) + 1e-3, 9.0)
        assert _same(one.last_result.a_hat, many.last_result.a_hat)
        # repr: the values hold NaN (no tracking error known), which == never matches
        reports = one.statuses(9.5, "h")
        assert repr(reports) == repr(many.statuses(9.5, "h"))
        limits_vals = next(s.values for s in reports if s.name == "dyn_node: limits")
        decelerations += limits_vals.get("deceleration_violations", 0)
        assert (tr_one.state, tr_one.since_s) == (tr_many.state, tr_many.since_s)
        assert repr(tr_one.status(9.5, "h")) == repr(tr_many.status(9.5, "h"))
    assert decelerations > 0   # the live deceleration check took part in the comparison


def test_process_batch_declines_what_process_must_judge_and_changes_nothing():
    """Invalid or special messages (non-finite values, infinite effort, unknown names, wrong
    shapes, non-finite stamps) are left to process: process_batch returns None, state untouched."""
    mon = Monitor(PANDA, Settings())
    mon.process(NAMES, Q0, np.zeros(7), [], 1.0, 1.0)
    before = (vars(mon.counts).copy(), mon._prev_t, mon._a.copy(), mon.last_result)
    P = np.tile(Q0, (5, 1))
    t = 1.001 + 1e-3 * np.arange(5)
    cases = []
    bad = P.copy()
    bad[2, 3] = np.nan
    cases.append((NAMES, bad, None, None, t))
    inf_e = np.ones((5, 7))
    inf_e[1, 0] = np.inf
    cases.append((NAMES, P, None, inf_e, t))
    cases.append((NAMES[:6], P[:, :6], None, None, t))        # a model joint missing
    cases.append((NAMES + ["extra"], P, None, None, t))       # shape does not match the names
    bad_t = t.copy()
    bad_t[3] = np.inf
    cases.append((NAMES, P, None, None, bad_t))
    for names, pos, vel, eff, stamps in cases:
        assert mon.process_batch(names, pos, vel, eff, stamps, stamps) is None
    assert (vars(mon.counts), mon._prev_t) == (before[0], before[1])
    assert np.array_equal(mon._a, before[2]) and mon.last_result is before[3]


def _urdf_prismatic(urdf: str) -> dict[str, bool]:
    """joint name → prismatic?, read with ElementTree (not with dyn_node's model code)."""
    import xml.etree.ElementTree as ET

    return {j.get("name"): j.get("type") == "prismatic" for j in ET.fromstring(urdf).iter("joint")}


def test_live_statuses_use_each_joints_own_units():
    """A model with prismatic joints: the live effort, limits, residual and controller statuses
    give prismatic joints m, m/s and N (keys and messages), revolute joints rad, rad/s and N·m."""
    from robots import BRANCHED_URDF

    model = load_model(urdf=BRANCHED_URDF, limits_yaml={"joint_limits": {"j2": {
        "has_soft_limits": True, "soft_lower_limit": -0.4, "soft_upper_limit": 0.4}}})
    prismatic = _urdf_prismatic(BRANCHED_URDF)
    names = list(model.joint_names)
    assert [n for n in names if prismatic[n]] == ["j2", "j5"]  # the case this test is about
    s = Settings(acceleration_source="zero", residual_warn_ratio=0.1, tracking_tolerance=0.05)
    mon, dyn = Monitor(model, s), Dynamics(model)
    i2, i5 = names.index("j2"), names.index("j5")
    q = np.zeros(6)
    q[i2] = 0.7  # above j2's 0.5 m limit (and its 0.4 m soft limit)
    v = np.zeros(6)
    v[i2] = 1.5  # beyond j2's 1 m/s
    e = dyn.rnea(q, v, np.zeros(6))
    e[i5] = 150.0  # 150 % of j5's 100 N
    mon.process(names, q, v, e, 1.0, 1.0)
    st = {x.name.removeprefix("dyn_node: "): x for x in mon.statuses(1.1, "b")}
    lim, eff, res = st["limits"], st["effort"], st["residual"]
    assert lim.values["j2_position_m"] == 0.7 and lim.values["j2_velocity_m_s"] == 1.5
    assert lim.values["j2_soft_position_m"] == 0.7
    assert not [k for k in lim.values if k.endswith(("_rad", "_rad_s"))]
    assert lim.message == "j2 position 0.7 m above its upper limit 0.5 m (+2 more)"
    assert eff.message.startswith("j5 at 150% of its 100 N effort limit (measured effort)")
    for n in names:
        assert eff.values[f"{n}_effort_limit_{'n' if prismatic[n] else 'nm'}"] == float(
            model.limits.effort[names.index(n)])
        assert f"{n}_effort_limit_{'nm' if prismatic[n] else 'n'}" not in eff.values
        assert f"{n}_residual_rms_{'n' if prismatic[n] else 'nm'}" in res.values
    assert res.values["worst_joint"] == "j5" and "worst_residual_rms_nm" not in res.values
    assert res.values["worst_residual_rms_n"] == pytest.approx(150.0 - dyn.rnea(q, v, np.zeros(6))[i5],
                                                              abs=1e-9)
    assert res.level == WARN and " N RMS (" in res.message and "N·m" not in res.message
    # revolute joints keep rad: j1 beyond its 3 rad limit
    q1 = np.zeros(6)
    q1[names.index("j1")] = 3.5
    mon.process(names, q1, np.zeros(6), [], 2.0, 2.0)
    lim = by_name(mon.statuses(2.1, "b"), "limits")
    assert lim.message == "j1 position 3.5 rad above its upper limit 3 rad"
    assert lim.values["j1_position_rad"] == 3.5
    # controller status: j2 0.1 m off a held reference
    tr = ControllerTracker(model, s)
    tr.follow(validate_trajectory(names, names, [0.0, 10.0], [np.zeros(6), np.zeros(6)],
                                  min_points=1), timing=Timing(0.0, 0.0))
    off = np.zeros(6)
    off[i2] = 0.1
    tr.update(mon.process(names, off, np.zeros(6), [], 3.0, 3.0), 3.0)
    ctrl = tr.status(3.0, "b")
    assert tr.state == "deviating"
    assert ctrl.message == "j2 is +0.1 m off the trajectory (tolerance 0.05 m)"
    assert ctrl.values["j2_tracking_error_m"] == pytest.approx(0.1, abs=1e-15)
    assert "j2_tracking_error_rad" not in ctrl.values and "j1_tracking_error_rad" in ctrl.values
    assert ctrl.values["tracking_tolerance_m"] == ctrl.values["tracking_tolerance_rad"] == 0.05


def test_every_kind_of_message_lands_in_exactly_one_count():
    """received = accepted + invalid (+ before_model, which only the node counts) after valid,
    rejected and undecodable messages; an undecodable one is reported like any rejection."""
    from dyn_node.errors import InputError

    mon = Monitor(PANDA, Settings())
    mon.process(NAMES, Q0, [], [], 1.0, 1.0)
    mon.process(NAMES[:3], Q0[:3], [], [], 1.1, 1.1)          # missing joints
    mon.process(NAMES, [math.nan] + list(Q0[1:]), [], [], 1.2, 1.2)  # non-finite
    mon.process(NAMES, Q0, [], [], 0.0, 1.3)                  # zero stamp: accepted
    r = mon.reject_message(InputError("16 bytes that are no JointState", code="undecodable"), 1.4)
    assert not r.accepted and r.error.code == "undecodable"
    c = mon.counts
    assert (c.received, c.accepted, c.invalid, c.before_model) == (5, 2, 3, 0)
    assert c.invalid_by_reason == {"missing_joints": 1, "non_finite": 1, "undecodable": 1}
    st = by_name(mon.statuses(1.5, "panda"), "joint_states")
    assert st.level == ERROR and st.message.startswith("last joint_states rejected (undecodable)")
    assert st.values["invalid_undecodable"] == 1 and st.values["before_model_messages"] == 0
    assert st.values["received_messages"] == st.values["accepted_messages"] + st.values["invalid_messages"]


def test_every_limit_kind_has_a_unit_for_both_joint_types():
    """The feasibility statuses and the live statuses read units from one table."""
    from dyn_node.core.robot.limits import LIMIT_KINDS
    from dyn_node.core.robot.units import LINEAR, ROTARY, unit_key

    for kind in LIMIT_KINDS:
        assert unit_key(ROTARY[kind]) and unit_key(LINEAR[kind])  # KeyError: no unit or no key
    assert ROTARY["effort"] == "N·m" and LINEAR["effort"] == "N" and LINEAR["position"] == "m"


def test_feasibility_verdict_and_live_status_give_a_prismatic_joint_the_same_units():
    from robots import BRANCHED_URDF

    from dyn_node.core.check.feasibility import check_trajectory

    model = load_model(urdf=BRANCHED_URDF)
    names = list(model.joint_names)
    i1, i2 = names.index("j1"), names.index("j2")
    end = np.zeros(6)
    end[i1], end[i2] = 2.0, 0.4  # in 0.5 s: beyond j1's 3 rad/s and j2's 1 m/s
    # at rest at both ends (cubic: peak 1.5× the mean speed); positions alone would be linear
    traj = validate_trajectory(names, names, [0.0, 0.5], [np.zeros(6), end], [np.zeros(6)] * 2, min_points=2)
    res = check_trajectory(Dynamics(model), traj)
    units = {(v.joint, v.kind): v.unit for v in res.violations}
    assert units[("j2", "velocity")] == "m/s" and units[("j1", "velocity")] == "rad/s"
    mon = Monitor(model, Settings(acceleration_source="zero"))
    v = np.zeros(6)
    v[i2] = 1.5
    mon.process(names, np.zeros(6), v, [], 1.0, 1.0)
    lim = by_name(mon.statuses(1.1, "b"), "limits")
    assert lim.message == f"j2 velocity 1.5 {units[('j2', 'velocity')]} beyond its limit 1 m/s"


def test_last_inputs_are_the_measured_arrays_in_model_order():
    """What the contact monitor is fed: q, v (None without velocities) and the effort (NaN
    joints kept, None when absent or all NaN), reordered to the model's joints."""
    mon = Monitor(PANDA, Settings())
    order = list(reversed(range(7)))
    e = np.arange(7.0)
    e[2] = math.nan
    mon.process([NAMES[i] for i in order], Q0[order], [], e[order], 1.0, 1.0)
    q, v, eff = mon.last_inputs
    assert q.tolist() == Q0.tolist() and v is None
    assert np.array_equal(eff, e, equal_nan=True)
    mon.process(NAMES, Q0, np.ones(7), [math.nan] * 7, 1.1, 1.1)
    assert mon.last_inputs[1].tolist() == [1.0] * 7 and mon.last_inputs[2] is None
    mon.process(NAMES, Q0, [], [], 1.2, 1.2)
    assert mon.last_inputs[2] is None


def test_contact_and_collision_rank_below_fault_and_stale_above_saturated():
    s = Settings(stale_timeout=0.5)
    mon, tr = Monitor(PANDA, s), ControllerTracker(PANDA, s)
    effort = np.zeros(7)
    effort[0] = 90.0  # saturated
    r = mon.process(NAMES, Q0, [], effort, 1.0, 1.0)
    tr.note_contact("contact")
    assert tr.update(r, 1.0) and tr.state == "contact"
    st = tr.status(1.0, "p")
    assert st.level == WARN and st.values["failure_label"] == CONTROL_ERROR
    tr.note_contact("collision")
    assert tr.update(r, 1.01) and tr.state == "collision" and tr.status(1.01, "p").level == ERROR
    bad = mon.process(NAMES[:3], Q0[:3], [], [], 1.02, 1.02)
    assert tr.update(bad, 1.02) and tr.state == "fault"
    assert tr.update(r, 1.03) and tr.state == "collision"
    assert tr.tick(1.6) and tr.state == "stale"
    tr.note_contact("none")
    assert tr.update(r, 1.7) and tr.state == "saturated"


def test_contact_state_message_is_the_episode_on_the_stamp_clock():
    """The controller status names the episode as dyn_node: contact does, its duration counted
    on the samples' stamps (here 100 s behind the receipt clock)."""
    from dyn_node.core.contacts.contact import ContactEpisode, JointPeak

    s = Settings()
    mon, tr = Monitor(PANDA, s), ControllerTracker(PANDA, s)
    ep = ContactEpisode(start_s=1.0, level="contact", joints=(JointPeak("panda_joint4", 9.0, 0.1, 87.0, "N·m"),),
                        frame="panda_link8", peak_force_n=20.0)
    r = mon.process(NAMES, Q0, [], [], 1.25, 101.25)
    tr.note_contact("contact", ep)
    tr.update(r, 101.25)
    assert tr.status(101.3, "p").message == "contact: 20 N at panda_link8 (panda_joint4 9 N·m of 87), 0.25 s"
