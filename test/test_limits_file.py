"""One reader, one hash, one locator and one top-level validator of the limits file (issue 17):
the model, the recorder and the audit see the same text and the same digest."""
from __future__ import annotations

import hashlib

import pytest

from dyn_node.bag.metadata import LIMITS_SHA256_KEY, limits_record
from dyn_node.core.robot.limits import load_limits_yaml
from dyn_node.core.robot.limits_file import limits_sha256, read_limits_file
from dyn_node.core.robot.model import load_model
from dyn_node.core.robot.model_source import build_model, limits_text
from dyn_node.core.robot.settings import Settings
from dyn_node.core.robot.task_limits import limits_mapping, locate_limits
from dyn_node.errors import ModelError

CRLF = b"joint_limits:\r\n  joint1: {max_velocity: 1.5}\r\n"


def test_the_reader_keeps_the_files_bytes(tmp_path):
    f = tmp_path / "limits.yaml"
    f.write_bytes(CRLF)
    text = read_limits_file(f)
    assert text.encode("utf-8") == CRLF               # no newline translation
    ref = hashlib.sha256(CRLF).hexdigest()            # independent digest of the bytes on disk
    assert limits_sha256(text) == limits_sha256(CRLF) == ref
    assert limits_record(text)[LIMITS_SHA256_KEY] == ref
    # the model built from the file (path or settings) uses the same reader
    assert load_model(builtin="planar_2link", limits_yaml=f).limits.velocity[0] == 1.5
    model = build_model(Settings(robot_model="planar_2link", limits_file=str(f)))
    assert limits_text(model).encode("utf-8") == CRLF


def test_the_reader_refuses_what_is_not_utf8_or_missing(tmp_path):
    f = tmp_path / "latin1.yaml"
    f.write_bytes("joint_limits: {}  # caf\xe9\n".encode("latin-1"))
    for source in (f, str(f)):
        with pytest.raises(ModelError) as err:
            load_limits_yaml(source)
        assert err.value.code == "limits_bad_yaml" and "not UTF-8" in str(err.value)
    with pytest.raises(ModelError) as err:
        read_limits_file(tmp_path / "none.yaml")
    assert err.value.code == "limits_file_missing"


def test_one_locator_for_both_parsers():
    nested = {"ctl": {"ros__parameters": {"rate": 1}},
              "dyn_node": {"ros__parameters": {"joint_limits": {}, "robot_model": "panda"}}}
    mapping, where, node_parameters = locate_limits(nested, source="f")
    assert mapping is nested["dyn_node"]["ros__parameters"]
    assert where == "f: dyn_node.ros__parameters" and node_parameters is True
    bare = {"grasp": {}}
    assert locate_limits(bare, source="f") == (bare, "f", False)
    # node parameters may stand beside joint_limits for the joint-limit parser, not the task one
    assert load_limits_yaml(nested) == {}
    with pytest.raises(ModelError) as err:
        limits_mapping(nested, source="f")
    assert err.value.code == "limits_unknown_section"


def test_one_top_level_message_for_both_parsers():
    with pytest.raises(ModelError) as joint:
        load_limits_yaml("joint_limits: {}\ngrsp: {}\n")
    with pytest.raises(ModelError) as task:
        limits_mapping({"joint_limits": {}, "grsp": {}}, source="limits")
    assert str(joint.value) == str(task.value)
    assert joint.value.code == task.value.code == "limits_unknown_section"
    assert "did you mean 'grasp'" in str(joint.value) and "a limits file holds" in str(joint.value)
