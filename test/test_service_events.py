"""The question services' introspection events in a bag: recorded by dyn_node's recorder by
default, with schemas built from the .srv as rosbag2 builds them, decoded by the official `mcap`
reader (mcap-ros2-support) and by `rosbags`, and re-checked by dyn-audit. A bag whose only inputs
are service calls audits with exit 0, infeasible questions included.

One node process (Panda, recording) serves the module; the bag holds nothing but the calls."""
from __future__ import annotations

import importlib.util
import json
import math
import re
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from dyn_node_interfaces.srv import CheckTrajectory, ComputeInverseDynamics, RetimeTrajectory
from rclpy.node import Node
from std_srvs.srv import Trigger

from conftest import REPO, ChildProcess, Collected, Spinner, child_env, python_cmd
from service_event_counts import question_counts
from dyn_node.bag import msgdefs
from dyn_node.ros.client import states_message, trajectory_message
from dyn_node.ros.demo import READY, demo_trajectories

NAMES = [f"panda_joint{i}" for i in range(1, 8)]
SERVICES = ("check_trajectory", "compute_inverse_dynamics", "retime_trajectory")
EVENTS = {f"/dyn_node/{s}/_service_event" for s in SERVICES}
QUESTION_TYPES = {f"/dyn_node/{s}/_service_event": t for s, t in
                  zip(SERVICES, ("CheckTrajectory", "ComputeInverseDynamics", "RetimeTrajectory"))}


@pytest.fixture(scope="module")
def bag(module_ros_context, tmp_path_factory) -> Path:
    """The bag of a node that was only asked questions (one of each kind, some refused)."""
    bag_dir = tmp_path_factory.mktemp("service_events")
    cp = ChildProcess(python_cmd("dyn_node.ros.node", "--ros-args", "-p", "robot_model:=panda",
                                 "-p", "record.enabled:=true", "-p", f"record.directory:={bag_dir}"),
                      env=child_env(), cwd=str(REPO))
    node = Node("service_events_test", context=module_ros_context)
    spinner = Spinner(module_ros_context, [node])
    got = Collected()
    try:
        clis = {s: node.create_client(t, f"/dyn_node/{s}") for s, t in
                zip(SERVICES, (CheckTrajectory, ComputeInverseDynamics, RetimeTrajectory))}
        up = got.wait(lambda: cp.proc.poll() is not None or (
            all(c.service_is_ready() for c in clis.values())
            and all(node.count_subscribers(t) for t in EVENTS)), 60.0)
        assert cp.proc.poll() is None and up, "dyn_node did not come up (or its recorder did not listen)"

        def call(name: str, request):
            fut = clis[name].call_async(request)
            done = threading.Event()
            fut.add_done_callback(lambda _f: done.set())
            assert done.wait(30), f"no response from {name}"
            return fut.result()

        comfortable, aggressive = demo_trajectories(short=True)
        z = np.zeros((len(aggressive.times), 7))
        shake = trajectory_message(NAMES, aggressive.times, aggressive.positions, z, z)
        assert not call("check_trajectory", CheckTrajectory.Request(trajectory=shake)).feasible
        # at rest at its points (quintic), as the demo's: positions alone would be linear
        zc = np.zeros((len(comfortable.times), 7))
        late = trajectory_message(NAMES, [t + 1.0 for t in comfortable.times], comfortable.positions, zc, zc)
        assert call("check_trajectory", CheckTrajectory.Request(trajectory=late, from_current_state=True)).accepted
        bad = trajectory_message(NAMES, comfortable.times, comfortable.positions)
        bad.points[1].positions[0] = math.nan
        assert call("check_trajectory", CheckTrajectory.Request(trajectory=bad)).reason == "non_finite"
        # an effort list neither empty nor one per joint: refused as joint_trajectory_controller does
        two = trajectory_message(NAMES, comfortable.times, comfortable.positions)
        two.points[1].effort = [1.0, 2.0]
        assert call("check_trajectory", CheckTrajectory.Request(trajectory=two)).reason == "length_mismatch"
        assert call("retime_trajectory", RetimeTrajectory.Request(trajectory=two)).reason == "length_mismatch"
        q = np.array([READY, [0.3, 0.2, -0.1, -1.5, 0.2, 1.0, 0.1]])
        assert call("compute_inverse_dynamics",
                    ComputeInverseDynamics.Request(states=states_message(NAMES, q, q * 0.5, q * 0.1))).accepted
        call("retime_trajectory", RetimeTrajectory.Request(trajectory=shake))
        stop = node.create_client(Trigger, "/dyn_node/stop_recording")
        assert stop.wait_for_service(timeout_sec=10)
        fut = stop.call_async(Trigger.Request())
        done = threading.Event()
        fut.add_done_callback(lambda _f: done.set())
        assert done.wait(30) and fut.result().success, fut.result()
        return Path(fut.result().message)
    finally:
        spinner.stop()
        node.destroy_node()
        cp.stop()


def _mcap_files(bag: Path) -> list[Path]:
    return sorted(bag.glob("*.mcap")) if bag.is_dir() else [bag]


def _events(bag: Path) -> dict[str, list[tuple[Any, Any]]]:
    """Each event topic's messages, decoded twice from the schema embedded in the bag (read with
    the official mcap reader): by mcap_ros2's dynamic decoder and by rosbags' typesys."""
    from mcap.reader import make_reader
    from mcap_ros2._dynamic import generate_dynamic
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    out: dict[str, list[tuple[Any, Any]]] = {}
    for f in _mcap_files(bag):
        with open(f, "rb") as fh:
            for schema, channel, msg in make_reader(fh).iter_messages(topics=sorted(EVENTS)):
                assert (schema.name, schema.encoding) == (
                    f"dyn_node_interfaces/srv/{QUESTION_TYPES[channel.topic]}_Event", "ros2msg")
                text = schema.data.decode()
                # mcap_ros2 0.6 accepts no '_' in a type name: renamed (CDR carries no names)
                plain = re.sub(r"_(Request|Response|Event)\b", r"\1", text)
                mc = generate_dynamic(schema.name.replace("_Event", "Event"), plain)
                mc_ev = mc[schema.name.replace("_Event", "Event")](msg.data)
                ts = get_typestore(Stores.EMPTY)
                types = get_types_from_msg(text, schema.name)
                ts.register(types)
                rb_ev = ts.deserialize_cdr(msg.data, next(k for k in types if k.endswith("_Event")))
                out.setdefault(channel.topic, []).append((mc_ev, rb_ev))
    return out


def _channels(f: Path) -> list:
    from mcap.reader import make_reader

    with open(f, "rb") as fh:
        return list(make_reader(fh).get_summary().channels.values())


def _message_counts(f: Path) -> dict[int, int]:
    """channel id → messages in the file (channels without messages are absent)."""
    from mcap.reader import make_reader

    with open(f, "rb") as fh:
        stats = make_reader(fh).get_summary().statistics
    return {k: n for k, n in stats.channel_message_counts.items() if n}


def test_events_decode_with_mcap_and_rosbags_alike(bag):
    events = _events(bag)
    assert set(events) == EVENTS
    check = events["/dyn_node/check_trajectory/_service_event"]
    kinds = [mc.info.event_type for mc, _ in check]
    # per call: request received (1), response sent (2); 4 calls
    assert kinds.count(1) == 4 and kinds.count(2) == 4 and [rb.info.event_type for _, rb in check] == kinds
    for mc, rb in check:
        assert mc.info.sequence_number == rb.info.sequence_number
        assert len(mc.request) == len(rb.request) and len(mc.response) == len(rb.response)
    responses = [(mc.response[0], rb.response[0]) for mc, rb in check if mc.info.event_type == 2]
    assert [m.reason for m, _ in responses] == [r.reason for _, r in responses] == ["", "", "non_finite",
                                                                                 "length_mismatch"]
    m, r = responses[0]
    assert m.accepted and not m.feasible and r.accepted and not r.feasible
    assert m.message == r.message and m.time_scale == r.time_scale and m.worst_joint == r.worst_joint
    n = len(demo_trajectories(short=True)[1].times)
    assert len(m.effort.points) == len(r.effort.points) == n
    np.testing.assert_array_equal(np.array([list(p.effort) for p in m.effort.points]),
                                  np.array([p.effort for p in r.effort.points]))
    # the second call asked from the robot's state, and the bag holds no joint_states (the
    # fixture publishes none): both readers decode the same "no state" answer, none invented
    assert not [c for f in _mcap_files(bag) for c in _channels(f) if c.topic == "/joint_states"
                and c.id in _message_counts(f)]
    for resp in responses[1]:
        assert resp.accepted and list(resp.start_state.name) == [] and math.isnan(resp.start_state_age)
        assert resp.start_segment == "not_checked (no current state within stale_timeout)"
    ids = events["/dyn_node/compute_inverse_dynamics/_service_event"]
    req = next(mc.request[0] for mc, _ in ids if mc.info.event_type == 1)
    resp = next(rb.response[0] for _, rb in ids if rb.info.event_type == 2)
    assert list(req.states.joint_names) == NAMES and resp.accepted
    assert np.asarray(resp.effort.points[0].effort).shape == (7,)


def test_event_channels_carry_rosidls_type_hash(bag):
    from mcap.reader import make_reader

    for f in _mcap_files(bag):
        with open(f, "rb") as fh:
            chans = make_reader(fh).get_summary().channels.values()
        for c in chans:
            if c.topic in EVENTS:
                want = msgdefs.type_description_hash(f"dyn_node_interfaces/srv/{QUESTION_TYPES[c.topic]}_Event")
                share = Path(sys.prefix) / "share/dyn_node_interfaces/srv" / f"{QUESTION_TYPES[c.topic]}.json"
                hashes = {h["type_name"]: h["hash_string"] for h in json.loads(share.read_text())["type_hashes"]}
                assert c.metadata["topic_type_hash"] == want == \
                    hashes[f"dyn_node_interfaces/srv/{QUESTION_TYPES[c.topic]}_Event"]


def test_a_bag_of_questions_only_audits_with_exit_0_and_each_answer_identical(bag, tmp_path):
    from dyn_node.audit.bag_audit import AuditOptions, run_audit

    res = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "audit"), robot_model="panda",
                                 report=False))
    rec = res.record
    assert res.exit_code == 0, rec["verdict"]
    rc = rec["outputs"]["recheck"]
    check = rc["/dyn_node/check_trajectory/_service_event"]
    # four calls re-answered from the bag alone, identical, the refused ones included
    assert check["matched"] == 4 and check["unmatched"] == 0 and check["unanswered"] == 0
    assert check["identical"], check
    ids = rc["/dyn_node/compute_inverse_dynamics/_service_event"]
    assert ids["matched"] == 1 and ids["identical"], ids
    q = rec["outputs"]["questions"]
    assert q["check"]["requests"] == 4 and q["check"]["infeasible"] >= 1
    assert q["check"]["not_accepted"] == {"non_finite": 1, "length_mismatch": 1}
    retime = rc["/dyn_node/retime_trajectory/_service_event"]
    # the refused one re-answered; the other only where the retimer is there to answer it again
    has_retimer = importlib.util.find_spec("dyn_node.retime") is not None
    assert retime["matched"] == (2 if has_retimer else 1) and retime["identical"], retime
    assert q["retime"]["not_accepted"] == ({"length_mismatch": 1} if has_retimer else
                                           {"length_mismatch": 1, "retimer_unavailable": 1})
    # a question answered "infeasible" is not a violation of the run
    assert rec["outputs"]["trajectories_infeasible_or_rejected"] == 0
    assert rec["verdict"]["result"] == "feasible"


def test_a_tampered_answer_is_caught(bag):
    """The re-check can fail: one recorded response changed after the fact (its time_scale, or
    one torque) is no longer identical to the re-answer, the others still are."""
    from dyn_node.audit.replay.services import RESPONSE_SENT, ServiceReplay, service_role
    from dyn_node.bag.reader import BagReader, MessageDecoder
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.robot.model import load_model
    from dyn_node.core.robot.settings import Settings

    class Tampering(MessageDecoder):
        def __init__(self, field: str):
            super().__init__()
            self.field, self.done = field, False

        def decode(self, channel, data):
            ev = super().decode(channel, data)
            if (not self.done and channel.schema_name.endswith("CheckTrajectory_Event")
                    and ev.info.event_type == RESPONSE_SENT and ev.response[0].accepted):
                if self.field == "time_scale":
                    ev.response[0].time_scale = np.nextafter(ev.response[0].time_scale, 0.0)
                else:
                    ev.response[0].effort.points[2].effort[3] += 1e-12
                self.done = True
            return ev

    dyn, settings = Dynamics(load_model(builtin="panda")), Settings(robot_model="panda")
    for field in ("time_scale", "effort"):
        replay, decoder = ServiceReplay(), Tampering(field)
        for m in BagReader(str(bag)).messages():
            if service_role(m.topic, m.channel.schema_name):
                replay.feed(m, decoder, dyn, settings)
        check, _ = replay._own["/dyn_node/check_trajectory/_service_event"]
        assert decoder.done and check.matched == 4
        assert not check.to_dict()["identical"] and 0.0 < check.max_diff < 1e-6, (field, check.to_dict())


def test_a_bag_with_the_old_request_topics_still_audits(tmp_path):
    """Bags recorded before the services (questions on the ~/check_trajectory and
    ~/inverse_dynamics_request topics) audit as before: the check is listed as a question."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from dyn_node.audit.bag_audit import AuditOptions, run_audit

    ts = get_typestore(Stores.ROS2_JAZZY)
    JT = ts.types["trajectory_msgs/msg/JointTrajectory"]
    JTP = ts.types["trajectory_msgs/msg/JointTrajectoryPoint"]
    H, T, D = (ts.types[t] for t in ("std_msgs/msg/Header", "builtin_interfaces/msg/Time",
                                     "builtin_interfaces/msg/Duration"))
    _, aggressive = demo_trajectories(short=True)
    empty = np.array([], dtype=float)

    def traj(frame_id: str, times, positions) -> object:
        pts = [JTP(positions=np.asarray(p, float), velocities=empty, accelerations=empty, effort=empty,
                   time_from_start=D(sec=int(t), nanosec=int(round((t % 1) * 1e9)))) for t, p in zip(times, positions)]
        return JT(header=H(stamp=T(sec=100, nanosec=0), frame_id=frame_id), joint_names=NAMES, points=pts)

    bag = tmp_path / "old_bag"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/dyn_node/check_trajectory", JT.__msgtype__, typestore=ts)
        s = w.add_connection("/dyn_node/inverse_dynamics_request", JT.__msgtype__, typestore=ts)
        w.write(c, 10**9, ts.serialize_cdr(traj("q1", aggressive.times, aggressive.positions), JT.__msgtype__))
        w.write(s, 2 * 10**9, ts.serialize_cdr(traj("q2", [0.0], [READY]), JT.__msgtype__))
    res = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "audit"), robot_model="panda", report=False))
    checks = [t for t in res.record["outputs"]["trajectories"] if t["request"] == "check"]
    assert len(checks) == 1 and checks[0]["accepted"] and not checks[0]["feasible"]
    assert res.exit_code == 0 and res.record["outputs"]["trajectories_infeasible_or_rejected"] == 0
    assert res.record["outputs"]["questions"] == {}


def test_the_audit_refuses_an_effort_list_of_the_wrong_length_as_the_node_does(tmp_path):
    """joint_trajectory (and the old check topic) replayed with the controller's effort rule:
    two efforts for seven joints are rejected, seven are not."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from dyn_node.audit.bag_audit import AuditOptions, run_audit

    ts = get_typestore(Stores.ROS2_JAZZY)
    JT, JTP, D = (ts.types[t] for t in ("trajectory_msgs/msg/JointTrajectory",
                                        "trajectory_msgs/msg/JointTrajectoryPoint",
                                        "builtin_interfaces/msg/Duration"))
    H, T = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    empty = np.array([], dtype=float)

    def traj(k: int, effort) -> object:
        pts = [JTP(positions=np.asarray(READY, float) + 0.1 * i, velocities=empty, accelerations=empty,
                   effort=np.asarray(effort if i == 1 else [], float), time_from_start=D(sec=2 * i, nanosec=0))
               for i in range(2)]
        return JT(header=H(stamp=T(sec=100 + k, nanosec=0), frame_id=""), joint_names=NAMES, points=pts)

    bag = tmp_path / "efforts"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        ex = w.add_connection("/joint_trajectory", JT.__msgtype__, typestore=ts)
        ck = w.add_connection("/dyn_node/check_trajectory", JT.__msgtype__, typestore=ts)
        w.write(ex, 10**9, ts.serialize_cdr(traj(0, [1.0, 2.0]), JT.__msgtype__))
        w.write(ck, 2 * 10**9, ts.serialize_cdr(traj(1, [1.0, 2.0]), JT.__msgtype__))
        w.write(ex, 3 * 10**9, ts.serialize_cdr(traj(2, [0.5] * 7), JT.__msgtype__))
    res = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "audit"), robot_model="panda", report=False))
    t = res.record["outputs"]["trajectories"]
    assert [(e["request"], e["accepted"], e.get("error_code")) for e in t] == [
        ("execute", False, "length_mismatch"), ("check", False, "length_mismatch"), ("execute", True, None)]
    assert "point 1: 2 effort for 7 joints" in t[0]["message"]


def _counts_line(counts: dict[str, tuple[int, int]]) -> str:
    """The audit's questions sentence, written here from the independently decoded calls."""
    n, no = sum(c[0] for c in counts.values()), sum(c[1] for c in counts.values())
    kinds = ", ".join(f"{k} {c[0]}" for k, c in sorted(counts.items()))
    return f"{no} of {n} questions answered infeasible or rejected ({kinds})"


def test_service_questions_are_counted_in_the_summary_and_trajectory_counts(bag, tmp_path):
    """Each recorded call counted once (request and response events are one call), its "no" from
    the recorded response, decoded here by mcap + rosbags: refused calls count as "no"."""
    from dyn_node.audit.bag_audit import AuditOptions, run_audit

    want = question_counts(bag)
    # what the fixture asked: 4 checks (shake infeasible, NaN and effort refused), 1 torque
    # question, 2 retimes (the effort one refused; the other retimed or not)
    assert {k: n for k, (n, _) in want.items()} == {"check": 4, "inverse_dynamics": 1, "retime": 2}
    assert want["check"][1] == 3 and want["inverse_dynamics"][1] == 0 and want["retime"][1] >= 1
    rec = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "audit"), robot_model="panda",
                                 report=True)).record
    c = rec["outputs"]["trajectory_counts"]
    assert (c["executed"], c["executed_infeasible_or_rejected"]) == (0, 0)
    assert (c["questions"], c["questions_infeasible_or_rejected"]) == (7, sum(no for _, no in want.values()))
    assert c["by_request"] == {k: {"total": n, "infeasible_or_rejected": no} for k, (n, no) in want.items()}
    assert rec["verdict"]["summary"] == "all feasible: 0 executed trajectories; " + _counts_line(want)
    html = (tmp_path / "audit" / "report.html").read_text()
    assert f"<b>{c['questions_infeasible_or_rejected']} of 7</b> answered infeasible or rejected" in html


def test_a_fleet_row_counts_the_service_questions(bag, tmp_path):
    from dyn_node.fleet import engine as fleet

    want = question_counts(bag)
    cfg = fleet.FleetConfig(robot_model="panda", report=False)
    job = fleet.BagJob(str(bag), fleet.bag_id(bag), str(tmp_path / "out"), cfg, fleet.config_hash(cfg))
    row = fleet.audit_bag(job).row
    assert row["verdict"] == "feasible" and row["exit_code"] == 0, row
    assert (row["trajectories"], row["trajectories_bad"]) == (0, 0)
    assert (row["questions"], row["questions_infeasible"]) == (
        sum(n for n, _ in want.values()), sum(no for _, no in want.values()))


def test_a_bag_with_service_events_and_old_request_topics_counts_each_once(bag, tmp_path):
    """The old request topics and the services in one bag: every question counted, none twice
    (the service events copied byte for byte from the node's bag, beside two topic requests)."""
    from mcap.reader import make_reader
    from rclpy.serialization import serialize_message

    from dyn_node.audit.bag_audit import AuditOptions, run_audit
    from dyn_node.bag.metadata import TopicInfo
    from dyn_node.bag.recorder import Recorder, RecorderConfig

    _, aggressive = demo_trajectories(short=True)
    z = np.zeros((len(aggressive.times), 7))
    shake = trajectory_message(NAMES, aggressive.times, aggressive.positions, z, z)
    shake.header.frame_id = "q1"
    states = states_message(NAMES, np.array([READY]))
    states.header.frame_id = "q2"
    rec = Recorder(RecorderConfig(directory=str(tmp_path), prefix="both", fsync=False), clock_ns=lambda: 1)
    rec.add_topic(TopicInfo("/dyn_node/check_trajectory", "trajectory_msgs/msg/JointTrajectory"))
    rec.add_topic(TopicInfo("/dyn_node/inverse_dynamics_request", "trajectory_msgs/msg/JointTrajectory"))
    rec.write("/dyn_node/check_trajectory", serialize_message(shake), 10)
    rec.write("/dyn_node/inverse_dynamics_request", serialize_message(states), 20)
    t, added = 100, set()
    for f in sorted(bag.glob("*.mcap")):
        with open(f, "rb") as fh:
            for schema, channel, msg in make_reader(fh).iter_messages(topics=sorted(EVENTS)):
                if channel.topic not in added:
                    rec.add_topic(TopicInfo(channel.topic, schema.name))
                    added.add(channel.topic)
                rec.write(channel.topic, msg.data, t)
                t += 10
    both = Path(rec.close(timeout=60.0).path)
    want = question_counts(bag)
    want["check"] = (want["check"][0] + 1, want["check"][1] + 1)  # the shake asked on the topic too
    want["inverse_dynamics"] = (want["inverse_dynamics"][0] + 1, want["inverse_dynamics"][1])
    r = run_audit(AuditOptions(bag=str(both), out=str(tmp_path / "audit"), robot_model="panda",
                               report=False)).record
    c = r["outputs"]["trajectory_counts"]
    assert c["by_request"] == {k: {"total": n, "infeasible_or_rejected": no} for k, (n, no) in want.items()}
    assert c["questions"] == 9 and c["executed"] == 0
    assert r["verdict"]["summary"] == "all feasible: 0 executed trajectories; " + _counts_line(want)
