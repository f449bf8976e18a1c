"""dyn_node bags in the two Python readers people use, with and without service calls: every
non-service message decodes in plain rosbags ``AnyReader`` (Jazzy typestore) and mcap_ros2; the
service events decode through ``dyn_node.bag.readers`` to the values rclpy published.

The events are recorded as the node records them: the bytes a raw subscription receives
(``serialize_message`` pads a bounded sequence with bytes the wire does not carry)."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import pytest
import yaml
from builtin_interfaces.msg import Duration
from dyn_node_interfaces.srv import CheckTrajectory
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectoryPoint

from conftest import Collected, Spinner
from dyn_node.bag.readers import mcap_decoder_factory, rosbags_typestore
from dyn_node.bag.recorder import Recorder, RecorderConfig, TopicInfo, qos_profile_dict

EVENT = "/dyn_node/check_trajectory/_service_event"
EVENT_TYPE = "dyn_node_interfaces/srv/CheckTrajectory_Event"
URDF = "<robot name='r'><link name='base'/></robot>"


def _state(i: int) -> JointState:
    m = JointState()
    m.header.stamp.sec, m.header.frame_id = 100 + i, f"s{i}"
    m.name, m.position, m.velocity = ["a", "b"], [0.25 * i, -1.5], [0.5, 2.0 * i]
    m.effort = [1.0, -3.0]  # (rosbags refuses rclpy's trailing pad after an empty last array)
    return m


def _events() -> list[CheckTrajectory.Event]:
    """A request received and the response sent, with contents."""
    req = CheckTrajectory.Event()
    req.info.event_type, req.info.sequence_number = 1, 7
    q = CheckTrajectory.Request(from_current_state=True)
    q.trajectory.joint_names = ["a", "b"]
    q.trajectory.points = [JointTrajectoryPoint(positions=[0.0, 1.0], time_from_start=Duration(sec=0)),
                           JointTrajectoryPoint(positions=[0.5, -1.0], time_from_start=Duration(sec=1, nanosec=9))]
    req.request.append(q)
    resp = CheckTrajectory.Event()
    resp.info.event_type, resp.info.sequence_number = 2, 7
    resp.response.append(CheckTrajectory.Response(accepted=True, feasible=False, time_scale=1.75,
                                                  worst_joint="b", reason=""))
    return [req, resp]


@pytest.fixture(scope="module")
def wire(module_ros_context) -> list[bytes]:
    """The two events as a raw subscription receives them (transient local: none is missed)."""
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    qos = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
    node = Node("readers_test", context=module_ros_context)
    got = Collected(["raw"])
    node.create_subscription(CheckTrajectory.Event, "/readers_test/_service_event", got.collector("raw"), qos, raw=True)
    pub = node.create_publisher(CheckTrajectory.Event, "/readers_test/_service_event", qos)
    for ev in _events():
        pub.publish(ev)
    spinner = Spinner(module_ros_context, [node])
    try:
        assert got.wait(lambda: len(got.got["raw"]) == 2, 30.0)
        return list(got.got["raw"])
    finally:
        spinner.stop()
        node.destroy_node()


def _bag(tmp_path: Path, calls: list[bytes] | None) -> Path:
    rec = Recorder(RecorderConfig(directory=str(tmp_path)), robot_description=URDF)
    rec.add_topic(TopicInfo("/joint_states", "sensor_msgs/msg/JointState", (qos_profile_dict(depth=100),)))
    rec.add_topic(TopicInfo(EVENT, EVENT_TYPE, (qos_profile_dict(),)))
    t0 = time.time_ns()
    for i in range(4):
        assert rec.write("/joint_states", serialize_message(_state(i)), t0 + i)
    for k, raw in enumerate(calls or []):
        assert rec.write(EVENT, raw, t0 + 10 + k)
    rec.close()
    return Path(rec.path)


@pytest.fixture(params=[False, True], ids=["no_calls", "calls"])
def bag(request, tmp_path) -> tuple[Path, bool]:
    calls = request.getfixturevalue("wire") if request.param else None
    return _bag(tmp_path, calls), request.param


def test_plain_anyreader_opens_and_decodes_every_non_service_message(bag):
    path, calls = bag
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        topics = sorted(c.topic for c in reader.connections)
        states = [reader.deserialize(raw, c.msgtype) for c, _t, raw in reader.messages()
                  if c.topic == "/joint_states"]
        desc = [reader.deserialize(raw, c.msgtype).data for c, _t, raw in reader.messages()
                if c.topic == "/robot_description"]
    assert topics == sorted(["/joint_states", "/robot_description"] + ([EVENT] if calls else []))
    assert [(m.header.frame_id, list(m.position), list(m.velocity)) for m in states] == \
        [(f"s{i}", [0.25 * i, -1.5], [0.5, 2.0 * i]) for i in range(4)]
    assert desc == [URDF]


def _listed_and_channels(path: Path) -> tuple[dict, dict, object]:
    info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    listed = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    with open(next(path.glob("*.mcap")), "rb") as fh:
        summary = make_reader(fh).get_summary()
    return listed, {c.topic: c for c in summary.channels.values()}, summary


def test_no_event_channel_before_the_first_event(tmp_path):
    listed, channels, _ = _listed_and_channels(_bag(tmp_path, None))
    assert sorted(listed) == sorted(channels) == ["/joint_states", "/robot_description"]


def test_event_channel_keeps_rosbag2s_layout(tmp_path, wire):
    listed, channels, summary = _listed_and_channels(_bag(tmp_path, wire))
    # `ros2 bag info` lists services from these names and types; the hash is off metadata.yaml
    # only (rosbags reads it there), the MCAP channel keeps rosidl's
    ev = listed[EVENT]
    assert (ev["topic_metadata"]["type"], ev["message_count"], ev["topic_metadata"]["type_description_hash"]) \
        == (EVENT_TYPE, 2, "")
    assert channels[EVENT].metadata["topic_type_hash"] == _rosidl_hashes()[EVENT_TYPE]
    assert summary.schemas[channels[EVENT].schema_id].name == EVENT_TYPE
    assert listed["/joint_states"]["topic_metadata"]["type_description_hash"] == \
        channels["/joint_states"].metadata["topic_type_hash"] != ""


def _rosidl_hashes() -> dict[str, str]:
    share = Path(sys.prefix) / "share/dyn_node_interfaces/srv/CheckTrajectory.json"
    return {h["type_name"]: h["hash_string"] for h in json.loads(share.read_text())["type_hashes"]}


def _check_events(got: list) -> None:
    want = _events()
    assert [(e.info.event_type, e.info.sequence_number) for e in got] == [(1, 7), (2, 7)]
    q = got[0].request[0]
    assert q.from_current_state and list(q.trajectory.joint_names) == ["a", "b"]
    assert [list(p.positions) for p in q.trajectory.points] == [list(p.positions) for p in want[0].request[0].trajectory.points]
    assert (q.trajectory.points[1].time_from_start.sec, q.trajectory.points[1].time_from_start.nanosec) == (1, 9)
    r = got[1].response[0]
    assert (r.accepted, r.feasible, r.time_scale, r.worst_joint) == (True, False, 1.75, "b")
    assert len(got[0].response) == 0 and len(got[1].request) == 0


def test_rosbags_typestore_from_the_helper_decodes_service_events(bag):
    path, calls = bag
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        typestore = rosbags_typestore(reader)
        msgs = [(c.topic, typestore.deserialize_cdr(raw, c.msgtype)) for c, _t, raw in reader.messages()]
    assert [m.position[0] for t, m in msgs if t == "/joint_states"] == [0.0, 0.25, 0.5, 0.75]
    assert len([m for t, m in msgs if t == EVENT]) == (2 if calls else 0)


def test_rosbags_service_events_decode_to_what_rclpy_published(tmp_path, wire):
    with AnyReader([_bag(tmp_path, wire)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        typestore = rosbags_typestore(reader)
        _check_events([typestore.deserialize_cdr(raw, c.msgtype) for c, _t, raw in reader.messages()
                       if c.topic == EVENT])
    # registered under ROS's own names: rosidl's hashes (which hash the names) agree
    for part in ("Request", "Response"):
        name = f"dyn_node_interfaces/srv/CheckTrajectory_{part}"
        assert typestore.hash_rihs01(name) == _rosidl_hashes()[name]


def _mcap_decoded(path: Path, factory) -> list[tuple[str, object]]:
    out = []
    for f in sorted(path.glob("*.mcap")):
        with open(f, "rb") as fh:
            reader = make_reader(fh, decoder_factories=[factory])
            out += [(ch.topic, m) for _s, ch, _msg, m in reader.iter_decoded_messages()]
    return out


def test_mcap_ros2_with_the_helper_decodes_service_events(bag):
    path, calls = bag
    msgs = _mcap_decoded(path, mcap_decoder_factory())
    assert [list(m.velocity) for t, m in msgs if t == "/joint_states"] == [[0.5, 2.0 * i] for i in range(4)]
    assert [m.data for t, m in msgs if t == "/robot_description"] == [URDF]
    assert len([m for t, m in msgs if t == EVENT]) == (2 if calls else 0)


def test_mcap_ros2_service_events_decode_to_what_rclpy_published(tmp_path, wire):
    _check_events([m for t, m in _mcap_decoded(_bag(tmp_path, wire), mcap_decoder_factory())
                   if t == EVENT])


def test_plain_mcap_ros2_reads_a_bag_without_calls(tmp_path):
    msgs = _mcap_decoded(_bag(tmp_path, None), DecoderFactory())
    assert sorted({t for t, _ in msgs}) == ["/joint_states", "/robot_description"] and len(msgs) == 5
