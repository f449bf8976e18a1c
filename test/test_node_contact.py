"""The live node's contact and energy outputs through rclpy: ~/external_torque, ~/external_wrench,
~/observer_events, the contact and energy statuses and the controller states, each output equal
to the pure core's ContactMonitor fed the same messages; bad input never gives an estimate."""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import WrenchStamped
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState

from conftest import js, kv, t_msg, t_s
from dyn_node.core.contacts.contact_monitor import ContactMonitor, ContactSettings
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.contacts.live_energy import EnergyPeriod
from dyn_node.core.contacts.observer import RESET_GAP, RESET_START
from dyn_node.errors import CONTROL_ERROR
from dyn_node.ros.convert import WrenchStampedOut
from dyn_node.ros.recording import DEFAULT_TOPICS
from test_node import FAST_DIAG, NAMES, PANDA, Q0, RELIABLE, Harness

FLANGE = "panda_link8"


class ContactHarness(Harness):
    """test_node's harness plus the three new topics."""

    def __init__(self, ctx, overrides, namespace):
        super().__init__(ctx, overrides, namespace)
        self.sub("ext", JointState, "dyn_node/external_torque", RELIABLE)
        self.sub("wrench", WrenchStamped, "dyn_node/external_wrench", RELIABLE)
        self.sub("events", DiagnosticStatus, "dyn_node/observer_events", RELIABLE)
        n = self.node
        assert self.wait(lambda: n._pub_external_torque.get_subscription_count() >= 1
                         and n._pub_external_wrench.get_subscription_count() >= 1
                         and n._pub_observer_events.get_subscription_count() >= 1), "discovery"

    def stamps(self, key: str) -> list[float]:
        return [t_s(m.header.stamp) for m in self.got[key]]

    def wait_stamp(self, key: str, stamp: float) -> None:
        assert self.wait(lambda: t_s(t_msg(stamp)) in self.stamps(key)), f"no {key} for {stamp}"


_ns = [0]


@pytest.fixture
def node(module_ros_context, request):
    _ns[0] += 1
    extra = getattr(request, "param", [])
    h = ContactHarness(module_ros_context, [Parameter("robot_model", value="panda"), *FAST_DIAG, *extra],
                       f"/contact{_ns[0]}")
    yield h
    h.close()


def pushed_effort(q: np.ndarray, force) -> np.ndarray:
    """The measured torque of the still Panda at q pushed at the flange by ``force`` (N, its
    axes): g(q) − Jᵀ·F (τ_m + τ_ext = g at rest)."""
    pm = PANDA.pin_model
    J = pin.computeFrameJacobian(pm, pm.createData(), q, pm.getFrameId(FLANGE), pin.ReferenceFrame.LOCAL)
    return Dynamics(PANDA).gravity(q) - J.T @ np.concatenate([force, np.zeros(3)])


def send(h: ContactHarness, stamps, q, effort) -> None:
    for k, s in enumerate(stamps):
        e = effort(k) if callable(effort) else effort
        h.js_pub.publish(js(NAMES, q, np.zeros(7), e, stamp=s))


def offline(rows, **settings) -> list:
    cm = ContactMonitor(Dynamics(PANDA), ContactSettings(**settings))
    out = []
    for s, q, e in rows:
        ns = t_msg(s).sec * 1_000_000_000 + t_msg(s).nanosec
        out.append(cm.update(ns, ns, q, np.zeros(7), e))
    return out


@pytest.mark.timeout(60)
def test_outputs_are_the_cores_and_contact_is_reported(node):
    """60 samples 1 ms apart of a 30 N push: every ~/external_torque and ~/external_wrench is
    the ContactMonitor's for the same input, to the bit, with the input's header, joint order and
    frame_id = the flange; the first sample's restart is on ~/observer_events; the contact
    reaches /diagnostics (WARN/ERROR, control error) and ~/controller_status."""
    stamps = [round(10.0 + 0.001 * k, 6) for k in range(60)]
    e = pushed_effort(Q0, [30.0, 0.0, 0.0])
    send(node, stamps, Q0, e)
    node.wait_stamp("wrench", stamps[-1])
    want = offline([(s, Q0, e) for s in stamps])
    assert node.stamps("ext") == [t_s(t_msg(s)) for s in stamps]
    for m, w in zip(node.got["ext"], want):
        assert list(m.name) == NAMES and list(m.effort) == w.tau_ext.tolist()
    for m, w in zip(node.got["wrench"], want):
        assert m.header.frame_id == FLANGE
        f, t = m.wrench.force, m.wrench.torque
        assert [f.x, f.y, f.z, t.x, t.y, t.z] == w.wrench.wrench.tolist()
    assert want[-1].state in ("contact", "collision")
    ev = kv(node.got["events"][0])
    assert ev["event"] == "reset" and ev["reason"] == RESET_START and float(ev["time_s"]) == t_s(t_msg(stamps[0]))
    st = node.status("dyn_node: contact", lambda s: s.level in (bytes([1]), bytes([2])))
    assert st.message.startswith(f"{want[-1].state}: ") and f" N at {FLANGE} (" in st.message
    assert kv(st)["failure_label"] == CONTROL_ERROR
    assert node.wait(lambda: any(kv(c)["state"] == want[-1].state for c in node.got["ctrl"]))
    energy = node.status("dyn_node: energy")
    assert math.isfinite(float(kv(energy)["kinetic_energy_j"]))


@pytest.mark.timeout(60)
def test_gravity_goes_out_before_the_observer_and_energy_is_evaluated_off_the_lock(node, monkeypatch):
    """Per message ~/inverse_dynamics, ~/gravity_torque, then ~/external_torque (the observer
    runs after both model outputs); the energy period's frame kernel runs with the joint_states
    lock free (only the period's buffers are swapped under it)."""
    n = node.node
    order, held = [], []
    publish = n._publish
    names = {id(n._pub_inverse): "inverse", id(n._pub_gravity): "gravity", id(n._pub_external_torque): "ext"}

    def spy(pub, data):
        if id(pub) in names:
            order.append(names[id(pub)])
        return publish(pub, data)

    evaluate = EnergyPeriod.evaluate

    def spy_eval(period):
        held.append(n._io_lock.locked())
        return evaluate(period)

    monkeypatch.setattr(n, "_publish", spy)
    monkeypatch.setattr(EnergyPeriod, "evaluate", spy_eval)
    send(node, [60.0, 60.001], Q0, Dynamics(PANDA).gravity(Q0))
    node.wait_stamp("ext", 60.001)
    assert order[:6] == ["inverse", "gravity", "ext"] * 2
    node.status("dyn_node: energy")
    assert held and not any(held)


@pytest.mark.timeout(60)
def test_missing_and_nan_effort_publish_no_estimate(node):
    """No effort: no ~/external_torque, the contact status says why; NaN effort on one joint:
    none for that message either (counted); the valid message after it restarts the observer
    (said on ~/observer_events) and is answered."""
    g = Dynamics(PANDA).gravity(Q0)
    s0 = [round(20.0 + 0.001 * k, 6) for k in range(5)]
    for s in s0:
        node.js_pub.publish(js(NAMES, Q0, np.zeros(7), stamp=s))
    node.wait_stamp("inverse", s0[-1])
    st = node.status("dyn_node: contact", lambda s: "effort not measured" in s.message)
    assert st.level == bytes([0]) and int(kv(st)["unavailable_effort_missing"]) >= 5
    bad = g.copy()
    bad[2] = math.nan
    s1 = [round(21.0 + 0.001 * k, 6) for k in range(4)]
    send(node, s1, Q0, lambda k: bad if k == 2 else g)
    node.wait_stamp("ext", s1[-1])
    assert t_s(t_msg(s1[2])) not in node.stamps("ext") and t_s(t_msg(s1[2])) in node.stamps("inverse")
    assert not any(math.isnan(x) for m in node.got["ext"] for x in m.effort)
    st = node.status("dyn_node: contact", lambda s: "unavailable_non_finite_effort" in kv(s))
    assert int(kv(st)["unavailable_non_finite_effort"]) == 1
    reasons = [kv(m)["reason"] for m in node.got["events"]]
    assert reasons[-1] == "after_invalid_input"


@pytest.mark.timeout(60)
def test_singular_contact_frame_publishes_torque_but_no_wrench(node):
    q = np.zeros(7)  # the flange Jacobian loses rank
    stamps = [round(30.0 + 0.001 * k, 6) for k in range(5)]
    send(node, stamps, q, Dynamics(PANDA).gravity(q))
    node.wait_stamp("ext", stamps[-1])
    assert node.got["wrench"] == []
    st = node.status("dyn_node: contact", lambda s: int(kv(s)["wrench_singular_samples"]) == 5)
    assert float(kv(st)["contact_frame_sigma_min"]) < 1e-12


@pytest.mark.timeout(60)
@pytest.mark.parametrize("node", [[Parameter("stale_timeout", value=0.2)]], indirect=True)
def test_gap_longer_than_stale_timeout_resets_the_observer(node):
    """After joint_states stop for longer than stale_timeout (the node reports STALE), the next
    message restarts the observer: reason gap on ~/observer_events, τ̂_ext = 0 on it."""
    e = pushed_effort(Q0, [20.0, 0.0, 0.0])
    send(node, [40.0, 40.001, 40.002], Q0, e)
    node.wait_stamp("ext", 40.002)
    assert node.got["ext"][-1].effort.tolist() != [0.0] * 7
    node.status("dyn_node: joint_states", lambda s: s.level == bytes([3]), timeout=5.0)
    send(node, [40.5], Q0, e)
    node.wait_stamp("ext", 40.5)
    assert list(node.got["ext"][-1].effort) == [0.0] * 7
    assert node.wait(lambda: any(kv(m)["reason"] == RESET_GAP for m in node.got["events"]))


@pytest.mark.timeout(60)
def test_parameter_change_resets_and_bad_values_are_refused(node):
    send(node, [50.0, 50.001], Q0, Dynamics(PANDA).gravity(Q0))
    node.wait_stamp("ext", 50.001)
    res = node.set_params([Parameter("observer_gain", value=[20.0])])
    assert res[0].successful
    for bad in ([Parameter("observer_gain", value=[1.0, 2.0])], [Parameter("contact_frame", value="nowhere")]):
        r = node.set_params(bad)
        assert not r[0].successful and "contact monitor" in r[0].reason
    send(node, [50.002], Q0, Dynamics(PANDA).gravity(Q0))
    assert node.wait(lambda: any(kv(m)["reason"] == "parameter_change" for m in node.got["events"]))
    assert node.node._core.contact.observer.gain.tolist() == [20.0] * 7


def test_wrench_codec_matches_rclpy_and_topics_are_recorded():
    for frame in ("", "a", "panda_link8", "abcd"):
        m = deserialize_message(WrenchStampedOut(frame).encode(7, 9, np.arange(6.0) - 2.5), WrenchStamped)
        f, t = m.wrench.force, m.wrench.torque
        assert (m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id) == (7, 9, frame)
        assert [f.x, f.y, f.z, t.x, t.y, t.z] == [-2.5, -1.5, -0.5, 0.5, 1.5, 2.5]
    assert {"~/external_torque", "~/external_wrench", "~/observer_events"} <= set(DEFAULT_TOPICS)


@pytest.mark.timeout(60)
def test_recording_start_resets_the_observer_and_records_the_new_topics(node, tmp_path):
    """Starting a recording resets the observer before the bag's first message (reason
    recording_start on the first sample after it), and the bag records ~/external_torque,
    ~/external_wrench and ~/observer_events from the node's own publish calls."""
    send(node, [60.0, 60.001], Q0, pushed_effort(Q0, [10.0, 0.0, 0.0]))
    node.wait_stamp("wrench", 60.001)
    assert node.set_params([Parameter("record.directory", value=str(tmp_path))])[0].successful
    ok, path = node.node.recording.start()
    assert ok
    try:
        send(node, [60.002, 60.003], Q0, pushed_effort(Q0, [10.0, 0.0, 0.0]))
        node.wait_stamp("wrench", 60.003)
        ext = {t_s(m.header.stamp): list(m.effort) for m in node.got["ext"]}
        assert ext[t_s(t_msg(60.002))] == [0.0] * 7  # restarted: r = 0 on the restarting sample
        assert node.wait(lambda: any(kv(m)["reason"] == "recording_start" for m in node.got["events"]))
        rec = node.node.recording
        for pub in (node.node._pub_external_torque, node.node._pub_external_wrench, node.node._pub_observer_events):
            assert rec.records(pub)
    finally:
        node.node.recording.stop()
