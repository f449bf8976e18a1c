"""The demo's notes (issue 27): where a run writes, and the reason beside "not answered live N"
(the node's own before-model count, read back from a bag)."""
from __future__ import annotations

import json
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.serialization import serialize_message

from dyn_node.bag.recorder import Recorder, RecorderConfig, TopicInfo
from dyn_node.ros.demo import audit_recheck_lines
from dyn_node.ros.demo.output import before_model_in_bag, unanswered_reason, where_line


def _diag(before_model: int, name: str = "dyn_node: joint_states") -> bytes:
    arr = DiagnosticArray()
    arr.status = [DiagnosticStatus(name="dyn_node: model", values=[KeyValue(key="x", value="1")]),
                  DiagnosticStatus(name=name, values=[
                      KeyValue(key="received_messages", value="900"),
                      KeyValue(key="before_model_messages", value=str(before_model))])]
    return serialize_message(arr)


def _bag(tmp_path: Path, payloads: list[bytes]) -> Path:
    rec = Recorder(RecorderConfig(directory=str(tmp_path), fsync=False))
    rec.add_topic(TopicInfo("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"))
    for k, data in enumerate(payloads):
        assert rec.write("/diagnostics", data, 10**18 + k * 10**9)
    stats = rec.close()
    assert stats.topics["/diagnostics"].written == len(payloads)
    return Path(stats.path)


def test_before_model_count_is_the_last_recorded(tmp_path):
    assert before_model_in_bag(_bag(tmp_path / "a", [_diag(3), _diag(55), _diag(55, "other")])) == 55
    assert before_model_in_bag(_bag(tmp_path / "b", [_diag(7, "dyn_node: effort")])) is None
    assert before_model_in_bag(tmp_path / "missing") is None


def test_reason_beside_not_answered_live(tmp_path):
    evidence = tmp_path / "evidence.json"
    evidence.write_text(json.dumps({"outputs": {"recheck": {
        "gravity": {"topic": "/dyn_node/gravity_torque", "matched": 8205, "unmatched": 0,
                    "unanswered": 55, "max_abs_difference": 0.0, "identical": True},
        "external": {"matched": 10, "unmatched": 0, "unanswered": 0,
                     "max_abs_difference": 0.0, "identical": True}}}}))
    lines = audit_recheck_lines(evidence, 55)
    assert "matched 8205, unmatched 0, not answered live 55 (all taken before dyn_node had its " \
           "model from /robot_description), max |difference| 0.0" in lines[2]
    assert "not answered live 0, max |difference|" in lines[1]
    assert unanswered_reason(55, 50) == (" (dyn_node counted 50 joint_states taken before it "
                                         "had its model from /robot_description)")
    assert unanswered_reason(55, None) == " (the bag has no joint_states status to say why)"
    assert unanswered_reason(0, 3) == ""


def test_where_line_names_the_bag_folder_and_counts_earlier_bags(tmp_path):
    assert "bags/dyn_node_<UTC time>/ (each run adds one; 0 from earlier runs kept)" in \
        where_line(tmp_path)
    for name in ("dyn_node_20260101_000000", "dyn_node_20260101_000001"):
        (tmp_path / "bags" / name).mkdir(parents=True)
    (tmp_path / "bags" / "stray.txt").write_text("")
    line = where_line(tmp_path)
    assert line.startswith(f"writing to {tmp_path}: a new bag in {tmp_path / 'bags'}/dyn_node_")
    assert "2 from earlier runs kept" in line
