"""ContactMonitor: the observer, the wrench, episodes and the power balance composed, against MuJoCo
pushes of the Panda (dyn_node.sim.simulator) and the pieces it is made of; resets, bad input and
the two statuses."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pinocchio as pin
import pytest

from dyn_node.core.contacts.contact_monitor import (CONTACT_STATUS, ENERGY_STATUS, RESET_RECORDING, UNAVAILABLE,
                                                    ContactMonitor, ContactSettings, contact_settings)
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import load_model
from dyn_node.core.contacts.observer import (RESET_GAP, RESET_STAMP_GAP, RESET_START, MomentumObserver, WrenchEstimator,
                                             damped_wrench)
from dyn_node.core.contacts.power_balance import PowerBalance
from dyn_node.core.robot.settings import Settings
from dyn_node.core.robot.status import ERROR, OK, WARN
from dyn_node.errors import CONTROL_ERROR, InputError, STATE_ERROR
from test_observer import READY, _trajectory, panda_sim

DT_NS = 1_000_000


@pytest.fixture(scope="module")
def panda():
    return load_model(builtin="panda")


def monitor(model, **kw) -> ContactMonitor:
    return ContactMonitor(Dynamics(model), ContactSettings(**kw))


def simulate(model, *, kind="still", force=(0.0, 0.0, 0.0), push=(0.3, 0.6), duration=0.8):
    """(t_ns, q, v, effort, pushed) per 1 kHz step of the Panda, pushed at panda_link8 with
    ``force`` (N, the link's axes) over ``push`` (s)."""
    sim = panda_sim(model)
    _trajectory(sim, model, kind)
    st = sim.state()
    rows = [(int(round(st.t * 1e9)), st.q.copy(), st.v.copy(), st.effort.copy(), False)]
    start, end = (int(round(x / sim.config.timestep)) for x in push)
    for k in range(int(round(duration / sim.config.timestep))):
        if k == start and any(force):
            sim.apply_wrench("panda_link8", np.array(force), np.zeros(3), hold_s=(end - start) * sim.config.timestep)
        st = sim.step(1)
        rows.append((int(round(st.t * 1e9)), st.q.copy(), st.v.copy(), st.effort.copy(), start < k + 1 <= end))
    return rows


def feed(cm: ContactMonitor, rows, offset_ns: int = 0):
    return [cm.update(t + offset_ns, t + offset_ns, q, v, e) for t, q, v, e, _ in rows]


@pytest.fixture(scope="module")
def pushed_30(panda):
    return simulate(panda, kind="moving", force=(30.0, 0.0, 0.0))


def test_estimates_are_the_pieces_and_the_push(panda, pushed_30):
    """τ̂_ext is exactly the MomentumObserver's (same inputs, same gain), the wrench the
    WrenchEstimator's to 1e-12 (its Jacobian is Pinocchio's, the monitor's the compiled pass's), and after 5/K of push the flange force is within 2 % (0.6 N; measured
    0.26 N) of the 30 N applied passed through the observer's first-order lag (K = 50/s, from
    the push at 0.3 s), its magnitude within 0.5 % (measured 0.07 N), while the robot moves."""
    cm = monitor(panda)
    obs, west = MomentumObserver(Dynamics(panda)), WrenchEstimator(panda, "panda_link8")
    assert cm.frame == "panda_link8"  # the default: the flange
    checked = 0
    for (t, q, v, e, pushed), s in zip(pushed_30, feed(cm, pushed_30)):
        ref = obs.update(t * 1e-9, q, v, e).tau_ext
        np.testing.assert_array_equal(s.tau_ext, ref)
        np.testing.assert_allclose(s.wrench.wrench, west.estimate(q, ref).wrench, rtol=0, atol=1e-12)
        if pushed and t >= 400_000_000:
            checked += 1
            rise = 1.0 - math.exp(-50.0 * (t - 300_000_000) * 1e-9)
            assert np.linalg.norm(s.wrench.force - [30.0 * rise, 0.0, 0.0]) <= 0.02 * 30
            assert abs(np.linalg.norm(s.wrench.force) - 30.0 * rise) <= 0.005 * 30
    assert checked == 201  # samples 0.400 … 0.600 s


def test_push_makes_one_contact_episode_and_status(panda, pushed_30):
    """30 N at the flange: one contact episode starting within 50 ms of the push (the first
    sample over 5 % of a limit, held 20 ms), reported as WARN contact with the message format of
    the issue, its peak force near 30 N; it ends after the push (hysteresis), and the next
    period's status is OK again."""
    cm = monitor(panda)
    samples = feed(cm, pushed_30)
    first = next(s for s in samples if s.state != "none")
    assert first.state == "contact" and 300_000_000 < first.stamp_ns < 350_000_000
    assert len(cm.episodes) == 1
    ep = cm.episodes[0]
    assert ep.end_s is not None and 0.6 < ep.end_s < 0.8 and ep.level == "contact"
    assert abs(ep.peak_force_n - 30.0) <= 0.01 * 30  # measured 0.045 N (the lag has settled)
    st = cm.contact_status(pushed_30[-1][0])
    assert st.name == CONTACT_STATUS and st.level == WARN
    assert st.values["failure_label"] == CONTROL_ERROR and st.values["peak_joint"] == ep.joints[0].joint
    assert st.message.startswith(f"contact: {ep.peak_force_n:.3g} N at panda_link8 ({ep.joints[0].joint} ")
    assert st.message.endswith(" s (ended)")
    assert cm.contact_status(pushed_30[-1][0]).level == OK


def test_collision_is_an_error(panda):
    """60 N down at the flange of the still Panda: over 20 % of joint 2's limit → ERROR
    collision, with the joint torque keys equal to the last estimate."""
    rows = simulate(panda, force=(0.0, 0.0, 60.0), duration=0.5, push=(0.1, 0.5))
    cm = monitor(panda)
    samples = feed(cm, rows)
    assert samples[-1].state == "collision"
    st = cm.contact_status(rows[-1][0])
    assert st.level == ERROR and st.message.startswith("collision: ")
    for i, n in enumerate(panda.joint_names):
        assert st.values[f"{n}_external_torque_nm"] == float(samples[-1].tau_ext[i])
    assert st.values["external_force_z_n"] == float(samples[-1].wrench.wrench[2])


def test_no_push_no_contact(panda):
    rows = simulate(panda, kind="moving", duration=1.0)
    cm = monitor(panda)
    assert {s.state for s in feed(cm, rows)} == {"none"}
    st = cm.contact_status(rows[-1][0])
    assert st.level == OK and st.message.startswith("no contact: largest |τ̂_ext|")


def test_resets_gap_recording_and_events(panda):
    """A receipt gap > stale_timeout resets the observer (code gap, said in the event); a
    requested reset shows on the next sample with its own code; the events come in order."""
    rows = simulate(panda, duration=0.1)
    cm = monitor(panda, stale_timeout=0.05)
    s = feed(cm, rows[:50])
    assert s[0].reset.code == RESET_START and all(x.reset is None for x in s[1:])
    late = cm.update(rows[50][0] + 60_000_000, rows[50][0] + 60_000_000, *rows[50][1:4])
    assert late.reset.code == RESET_GAP and "(> stale_timeout 0.05 s)" in late.reset.detail
    np.testing.assert_array_equal(late.tau_ext, np.zeros(7))
    said = cm.reset(RESET_RECORDING, "recording started")
    nxt = cm.update(rows[51][0] + 60_000_000, rows[51][0] + 60_000_000, *rows[51][1:4])
    assert nxt.reset == said
    events = cm.pop_events()
    assert [(e.event, e.reason) for e in events] == [("reset", RESET_START), ("reset", RESET_GAP),
                                                     ("reset", RESET_RECORDING)]
    assert events[2].time_s == nxt.stamp_ns * 1e-9 and cm.resets == 3
    assert events[1].status("panda").values["reason"] == RESET_GAP
    # receipts 1 ms apart but the stamps 101 ms apart: the observer's own code, not the receipt gap's
    t = rows[52][0] + 60_000_000
    jump = cm.update(t, t + 100_000_000, *rows[52][1:4])
    assert jump.reset.code == RESET_STAMP_GAP and [e.reason for e in cm.pop_events()] == [RESET_STAMP_GAP]


def test_missing_and_nan_effort_give_no_estimate(panda):
    """No effort: no estimate, the status says why (OK: nothing is wrong); NaN effort on one
    joint: no estimate, counted, WARN with a state-error label; nothing contact-like ever."""
    rows = simulate(panda, duration=0.05)
    cm = monitor(panda)
    for t, q, v, e, _ in rows[:10]:
        s = cm.update(t, t, q, v, None)
        assert s.tau_ext is None and s.wrench is None and s.state == UNAVAILABLE
    st = cm.contact_status(rows[9][0])
    assert st.level == OK and st.message == "no external-torque estimate: effort not measured"
    assert st.values["unavailable_effort_missing"] == 10
    assert math.isnan(st.values["panda_joint1_external_torque_nm"])
    e = rows[10][3].copy()
    e[3] = math.nan
    s = cm.update(rows[10][0], rows[10][0], rows[10][1], rows[10][2], e)
    assert s.tau_ext is None and s.unavailable == "effort not finite for panda_joint4"
    st = cm.contact_status(rows[10][0])
    assert st.level == WARN and st.values["failure_label"] == STATE_ERROR
    s = cm.update(rows[11][0], rows[11][0], rows[11][1], None, rows[11][3])
    assert s.tau_ext is None and s.unavailable == "velocity not measured"
    assert cm.contact_status(rows[11][0]).level == OK  # not measured: said, nothing wrong
    assert st.values["unavailable_non_finite_effort"] == 1


def test_singular_contact_frame_publishes_no_wrench(panda):
    """At q = 0 the flange Jacobian is singular: τ̂_ext is still estimated, the wrench is not
    given (counted), and the status reports σ_min."""
    cm = monitor(panda)
    q, v = np.zeros(7), np.zeros(7)
    g = Dynamics(panda).gravity(q)
    for k in range(5):
        s = cm.update(k * DT_NS, k * DT_NS, q, v, g)
        assert s.tau_ext is not None and s.wrench is None and s.wrench_singular
    st = cm.contact_status(4 * DT_NS)
    assert st.values["wrench_singular_samples"] == 5 and st.values["contact_frame_sigma_min"] < 1e-12
    assert math.isnan(st.values["external_force_n"])


def test_energy_status_and_period_event(panda, pushed_30):
    """Kinetic energy = ½vᵀMv by Pinocchio's CRBA at the last sample; the period's balance is
    PowerBalance's over the same samples, and its end is an event with the sample count."""
    cm = monitor(panda)
    feed(cm, pushed_30[:300])
    cm.pop_events()
    st = cm.energy_status(300 * DT_NS)
    _, q, v, _, _ = pushed_30[299]
    pm = panda.pin_model
    M = pin.crba(pm, pm.createData(), q)
    M = np.triu(M) + np.triu(M, 1).T
    assert st.name == ENERGY_STATUS and st.level == OK
    assert st.values["kinetic_energy_j"] == pytest.approx(0.5 * v @ M @ v, rel=1e-12)
    assert st.values["kinetic_energy_j"] > 1e-5  # it has begun to move
    ref = PowerBalance(Dynamics(panda))
    for t, q, v, e, _ in pushed_30[:300]:
        ref.update(t * 1e-9, q, v, e)
    p = ref.close()
    assert st.values["power_balance_j"] == p.balance_j and st.values["measured_work_j"] == p.measured_work_j
    assert st.values["energy_change_j"] == p.delta_energy_j and st.values["period_s"] == p.end_s - p.start_s
    ev = cm.pop_events()
    assert [(e.event, e.samples) for e in ev] == [("period", 300)]
    assert ev[0].time_s == pushed_30[299][0] * 1e-9
    empty = cm.energy_status(300 * DT_NS)
    assert empty.message == (f"kinetic energy {st.values['kinetic_energy_j']:.3g} J; no power balance this "
                             "period: fewer than two usable samples since the last period")
    assert "power_balance_j" not in empty.values and empty.values["energy_states"] == 0


def test_near_singular_frame_publishes_the_damped_wrench(panda):
    """The still Panda on the way to the q = 0 flange singularity: where ε ≤ σ_min < β the
    sample carries the damped wrench of its τ̂_ext (the closed form through damped_wrench on
    Pinocchio's Jacobian, to 1e-12); below ε it carries none and is counted."""
    q1 = np.array([0.0, -0.6, 0.0, -2.0, 0.0, 1.6, 0.8])
    est, d = WrenchEstimator(panda, "panda_link8"), Dynamics(panda)
    o = est.options
    damped = refused = 0
    for k in range(1, 120):
        q = q1 * (k / 120)
        cm = monitor(panda)
        e = d.gravity(q) + 0.5  # a torque no model term explains: τ̂_ext ≠ 0
        for i in range(20):
            s = cm.update(i * DT_NS, i * DT_NS, q, np.zeros(7), e)
        sigma = est.estimate(q, s.tau_ext).sigma_min
        if o.singular_value <= sigma < o.damping_band:
            damped += 1
            F, _, lam = damped_wrench(est.jacobian(q), s.tau_ext)
            assert s.wrench is not None and lam > 0
            np.testing.assert_allclose(s.wrench.wrench, F, rtol=0, atol=1e-12)
        elif sigma < o.singular_value:
            refused += 1
            assert s.wrench is None and s.wrench_singular and cm.wrench_singular == 20
    assert damped and refused


def test_energy_period_is_taken_without_evaluating(panda, pushed_30):
    """close_energy_period (what the node does under its joint_states lock) runs no frame
    kernel; its status, evaluated afterwards, is energy_status's to the bit."""
    import yaml
    lim = load_model(builtin="panda", limits_yaml=yaml.safe_load(
        "joint_limits: {}\nframe_limits: {panda_link8: {max_linear_speed: 5.0}}\n"
        "robot_limits: {max_kinetic_energy: 50.0}\n"))
    a, b = monitor(lim), monitor(lim)
    feed(a, pushed_30[:300]), feed(b, pushed_30[:300])
    kin = b.energy._kin
    compute, kin.compute = kin.compute, None  # any evaluation now raises TypeError
    closed = b.close_energy_period(300 * DT_NS)
    kin.compute = compute
    want = a.energy_status(300 * DT_NS, "panda")
    assert closed.status("panda") == want and want.values["energy_states"] == 300
    assert [(e.event, e.samples) for e in b.pop_events()][-1] == ("period", 300)


def test_effort_missing_is_keyed_on_its_code(panda, pushed_30):
    """The energy status says effort is not measured from the sample's reason code, not its
    text: a reworded observer message still gives it."""
    cm = monitor(panda)
    t, q, v, _, _ = pushed_30[0]
    s = cm.update(t, t, q, v, None)
    assert s.unavailable_code == "effort_missing"
    cm.last = dataclasses.replace(s, unavailable="no effort in the message")
    st = cm.energy_status(t + DT_NS)
    assert st.message.endswith("no power balance this period: effort not measured")


def test_settings_the_model_cannot_take(panda):
    with pytest.raises(ValueError, match="observer_gain needs 1 or 7 values"):
        monitor(panda, observer_gain=(1.0, 2.0))
    with pytest.raises(InputError, match="'nowhere' is not a frame"):
        monitor(panda, contact_frame="nowhere")
    cs = contact_settings(Settings(observer_gain=(20.0,), contact_frame="panda_hand"))
    assert cs.observer_gain == (20.0,) and cs.contact_frame == "panda_hand" and cs.stale_timeout == 0.5


def test_frame_speed_transferred_and_kinetic_energy_against_limits(panda, pushed_30):
    """With frame_limits (a point 0.1 m along the flange's z) and robot_limits: the period's peak
    speed is Pinocchio's |v| of that point (LOCAL_WORLD_ALIGNED frame velocity moved to the
    point) over the same samples, to 1e-9; the peak kinetic energy is ½vᵀMv's; a speed limit
    below the peak makes the status ERROR naming the frame, the transferred energy (advisory)
    over its limit alone WARN."""
    yaml_text = ("joint_limits: {}\nframe_limits: {panda_link8: {point: [0.0, 0.0, 0.1], max_linear_speed: 0.05, "
                 "max_transferred_energy: 1000.0}}\nrobot_limits: {max_kinetic_energy: 5.0}\n")
    import yaml
    limited = load_model(builtin="panda", limits_yaml=yaml.safe_load(yaml_text))
    cm = monitor(limited)
    feed(cm, pushed_30)
    st = cm.energy_status(pushed_30[-1][0])
    pm = limited.pin_model
    data = pm.createData()
    fid = pm.getFrameId("panda_link8")
    speeds, kinetic = [], []
    for _, q, v, _, _ in pushed_30:
        pin.forwardKinematics(pm, data, q, v)
        pin.updateFramePlacements(pm, data)
        vel = pin.getFrameVelocity(pm, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        r = data.oMf[fid].rotation @ np.array([0.0, 0.0, 0.1])
        speeds.append(np.linalg.norm(vel.linear + np.cross(vel.angular, r)))
        M = pin.crba(pm, data, q)
        kinetic.append(0.5 * v @ (np.triu(M) + np.triu(M, 1).T) @ v)
    v = st.values
    assert v["panda_link8_speed_m_s"] == pytest.approx(max(speeds), abs=1e-9) and max(speeds) > 0.05
    assert v["kinetic_energy_peak_j"] == pytest.approx(max(kinetic), abs=1e-9)
    assert v["kinetic_energy_limit_j"] == 5.0 and v["energy_states"] == len(pushed_30)
    assert st.level == ERROR and st.message.startswith("panda_link8 at ") and "over its 0.05 m/s limit" in st.message
    assert 0 < v["panda_link8_transferred_energy_j"] < 1000.0
    adv = load_model(builtin="panda", limits_yaml={"joint_limits": {}, "frame_limits": {"panda_link8": {"max_transferred_energy": 1e-9}}})
    cm = monitor(adv)
    feed(cm, pushed_30)
    st = cm.energy_status(pushed_30[-1][0])
    assert st.level == WARN and "transferred energy" in st.message and "(advisory)" in st.message
    assert st.values["failure_label"] == CONTROL_ERROR


def _episode_fields(ep):
    d = dataclasses.asdict(ep)
    d["peak_wrench"] = None if ep.peak_wrench is None else ep.peak_wrench.tobytes()
    return d


@pytest.mark.parametrize("chunk", [1, 7, 256, 10_000])
def test_rows_at_once_are_the_row_by_row_monitor(panda, pushed_30, chunk):
    """update_rows (dyn-audit's batches) against update row by row (the node) over the 30 N push
    with a receipt gap, a step back in the stamps, rows without effort and a NaN effort: the
    same τ̂_ext and wrenches bit for bit, episodes, events, counts, power sums, and the next
    energy status; in chunks of any size."""
    rows = [list(r) for r in pushed_30]
    t = np.array([r[0] for r in rows], dtype=np.int64)
    t[500:] += 700_000_000                 # a receipt and stamp gap over stale_timeout
    stamps = t.copy()
    stamps[200] = stamps[199] - 5_000_000  # a stamp going back
    Q = np.array([r[1] for r in rows])
    V = np.array([r[2] for r in rows])
    E = np.array([r[3] for r in rows])
    measured = np.ones(len(rows), dtype=bool)
    measured[300:303] = False              # effort missing on three rows
    measured[-1] = False                   # and on the last (the last wrench stays the one before)
    E[350, 2] = np.nan                     # a NaN effort
    one, many = monitor(panda), monitor(panda)
    singles = [one.update(int(t[k]), int(stamps[k]), Q[k], V[k], E[k] if measured[k] else None)
               for k in range(len(rows))]
    taus, wrenches = [], []
    for a in range(0, len(rows), chunk):
        b = min(a + chunk, len(rows))
        rs = many.update_rows(t[a:b], stamps[a:b], Q[a:b], V[a:b], E[a:b], measured=measured[a:b])
        taus.append(rs.tau_ext)
        wrenches.append(np.where(rs.has_wrench[:, None], rs.wrench, np.nan))
    tau = np.array([s.tau_ext if s.tau_ext is not None else np.full(7, np.nan) for s in singles])
    wr = np.array([s.wrench.wrench if s.wrench is not None else np.full(6, np.nan) for s in singles])
    np.testing.assert_array_equal(np.concatenate(taus), tau)
    np.testing.assert_array_equal(np.concatenate(wrenches), wr)
    assert [_episode_fields(e) for e in many.episodes] == [_episode_fields(e) for e in one.episodes]
    assert len(one.episodes) >= 1
    assert ([dataclasses.astuple(e) for e in many.pop_events()]
            == [dataclasses.astuple(e) for e in one.pop_events()])
    assert many.unavailable_by_code == one.unavailable_by_code == {"effort_missing": 4, "non_finite_effort": 1}
    assert many.observer.counts == one.observer.counts
    assert {"backwards", "gap", "after_invalid_input"} <= set(one.observer.counts)
    assert (many.estimates, many.resets, many.wrench_singular) == (one.estimates, one.resets, one.wrench_singular)
    np.testing.assert_array_equal(many.power.state, one.power.state)
    assert many.detector.state == one.detector.state and many.last.state == one.last.state
    sa, sb = one.energy_status(int(t[-1])), many.energy_status(int(t[-1]))
    # repr: the values hold NaN (no limit, no wrench), which == never matches
    assert repr(sorted(sa.values.items())) == repr(sorted(sb.values.items())) and sa.message == sb.message
    assert "no power balance this period: effort not measured" in sa.message  # the last row's
    assert sa.values["broken_periods"] == 5
    ca, cb = one.contact_status(int(t[-1])), many.contact_status(int(t[-1]))
    assert repr(sorted(ca.values.items())) == repr(sorted(cb.values.items())) and ca.message == cb.message


def test_a_reset_before_an_empty_batch_applies_to_the_next_rows(panda, pushed_30):
    """reset() then a batch of no rows, then rows: the restart happens on the first of them, as
    update row by row does it (the empty batch does not swallow it)."""
    rows = pushed_30[:40]
    T = np.array([r[0] for r in rows], dtype=np.int64)
    Q, V, E = (np.array([r[i] for r in rows]) for i in (1, 2, 3))
    one, many = monitor(panda), monitor(panda)
    for k in range(20):
        one.update(int(T[k]), int(T[k]), Q[k], V[k], E[k])
    many.update_rows(T[:20], T[:20], Q[:20], V[:20], E[:20])
    one.reset(RESET_RECORDING, "recording started")
    many.reset(RESET_RECORDING, "recording started")
    many.update_rows(T[:0], T[:0], Q[:0], V[:0], E[:0])
    for k in range(20, 40):
        one.update(int(T[k]), int(T[k]), Q[k], V[k], E[k])
    rs = many.update_rows(T[20:], T[20:], Q[20:], V[20:], E[20:])
    assert many.resets == one.resets == 2
    assert [e.reason for e in many.pop_events()] == [e.reason for e in one.pop_events()] == [
        "start", RESET_RECORDING]
    np.testing.assert_array_equal(rs.tau_ext[0], np.zeros(7))
    np.testing.assert_array_equal(many.power.state, one.power.state)
