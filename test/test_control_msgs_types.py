"""The control_msgs types the gate uses are wire-identical with ros-controls/control_msgs 5.x (Jazzy).

Three references we did not write: (1) RIHS01 hashes published by real Jazzy builds of control_msgs
(a generated ``follow_joint_trajectory__description.c`` / type-description JSON of a colcon build,
and the hash a live joint_trajectory_controller reports in ``ros2 topic info --verbose``);
(2) the ``rosbags`` library's own RIHS01 implementation applied to the field lists of the issue;
(3) the field lists themselves, compared with our generated type descriptions. Constants are not
part of the hash, so they are tested on their own against the issue's values.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

control_msgs = pytest.importorskip("control_msgs", reason="control_msgs not built into the venv (make)")

# Published by real Jazzy builds (see the module docstring), not computed here.
PUBLISHED = {
    "control_msgs/action/FollowJointTrajectory":
        "RIHS01_738ebcb7a2d7cfa42f9f1001cc99ce3a4383d1cfe508015d9be8485e4b1c66f6",
    "control_msgs/action/FollowJointTrajectory_Goal":
        "RIHS01_8a9060704b269608f5a340934cc26e66869dd14bdac29e2e7fd9ec8b9882d205",
    "control_msgs/action/FollowJointTrajectory_Result":
        "RIHS01_8002e99ed2c14c6faa522f2a93c26d744c5982f254f9e98ff9c6f19789bdb220",
    "control_msgs/action/FollowJointTrajectory_Feedback":
        "RIHS01_3fd0aaecf71725121ae1ff7f01098a5e0da581e672be18a6b2c286cb43d96b49",
    "control_msgs/msg/JointTolerance":
        "RIHS01_c254f9cece0f3b733017b6990fd46d1326e25242d6b8844398c97d9a88e7d648",
    "control_msgs/msg/JointComponentTolerance":
        "RIHS01_739ea7566931944d33830fa10f1bf5e7a7fbdc3172bce7a7eaac642bd6e3ffa4",
    "control_msgs/msg/JointTrajectoryControllerState":
        "RIHS01_51d8dd89cc624cbe9daaeeb4d80d6de9b86168ffdc3be41fefc0953e3c26e480",
}

JTP, MDP = "trajectory_msgs/msg/JointTrajectoryPoint", "trajectory_msgs/msg/MultiDOFJointTrajectoryPoint"
# The issue's field lists (name, .msg type), in order.
FIELDS: dict[str, list[tuple[str, str]]] = {
    "control_msgs/msg/JointTolerance": [
        ("name", "string"), ("position", "float64"), ("velocity", "float64"),
        ("acceleration", "float64")],
    "control_msgs/msg/JointComponentTolerance": [
        ("joint_name", "string"), ("component", "uint16"), ("position", "float64"),
        ("velocity", "float64"), ("acceleration", "float64")],
    "control_msgs/msg/JointTrajectoryControllerState": [
        ("header", "std_msgs/msg/Header"), ("joint_names", "string[]"),
        ("reference", JTP), ("feedback", JTP), ("error", JTP), ("output", JTP),
        ("multi_dof_joint_names", "string[]"), ("multi_dof_reference", MDP),
        ("multi_dof_feedback", MDP), ("multi_dof_error", MDP), ("multi_dof_output", MDP),
        ("speed_scaling_factor", "float64")],
    "control_msgs/action/FollowJointTrajectory_Goal": [
        ("trajectory", "trajectory_msgs/msg/JointTrajectory"),
        ("multi_dof_trajectory", "trajectory_msgs/msg/MultiDOFJointTrajectory"),
        ("path_tolerance", "control_msgs/msg/JointTolerance[]"),
        ("component_path_tolerance", "control_msgs/msg/JointComponentTolerance[]"),
        ("goal_tolerance", "control_msgs/msg/JointTolerance[]"),
        ("component_goal_tolerance", "control_msgs/msg/JointComponentTolerance[]"),
        ("goal_time_tolerance", "builtin_interfaces/msg/Duration")],
    "control_msgs/action/FollowJointTrajectory_Result": [
        ("error_code", "int32"), ("error_string", "string")],
    "control_msgs/action/FollowJointTrajectory_Feedback": [
        ("header", "std_msgs/msg/Header"), ("joint_names", "string[]"),
        ("desired", JTP), ("actual", JTP), ("error", JTP),
        ("multi_dof_joint_names", "string[]"), ("multi_dof_desired", MDP),
        ("multi_dof_actual", MDP), ("multi_dof_error", MDP)],
}
# type_description_interfaces/msg/FieldType ids for the kinds used above
_TYPE_IDS = {"nested": 1, "uint16": 5, "int32": 6, "float64": 11, "string": 17}
_SEQ = 144  # FIELD_TYPE_*_UNBOUNDED_SEQUENCE = type id + 144


def _share() -> Path:
    """share/control_msgs of the installation that provides the imported module."""
    prefix = Path(control_msgs.__file__).resolve().parents[4]  # <prefix>/lib/pythonX.Y/site-packages/control_msgs
    for base in [*filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)), str(prefix)]:
        if (Path(base) / "share" / "control_msgs" / "package.xml").is_file():
            return Path(base) / "share" / "control_msgs"
    raise AssertionError(f"no share/control_msgs beside {control_msgs.__file__}")


def _generated() -> dict[str, dict]:
    """Every type description (own and referenced) and hash from the installed JSON files."""
    descs: dict[str, dict] = {}
    hashes: dict[str, str] = {}
    for f in _share().glob("*/*.json"):
        data = json.loads(f.read_text())
        tdm = data["type_description_msg"]
        for d in [tdm["type_description"], *tdm["referenced_type_descriptions"]]:
            descs.setdefault(d["type_name"], d)
        hashes.update({h["type_name"]: h["hash_string"] for h in data["type_hashes"]})
    return {"descs": descs, "hashes": hashes}


def _expected_type(msg_type: str) -> tuple[int, str]:
    seq = msg_type.endswith("[]")
    base = msg_type[:-2] if seq else msg_type
    if base in _TYPE_IDS:
        return _TYPE_IDS[base] + (_SEQ if seq else 0), ""
    return _TYPE_IDS["nested"] + (_SEQ if seq else 0), base


def test_generated_hashes_equal_published_jazzy_hashes():
    hashes = _generated()["hashes"]
    assert {k: hashes.get(k) for k in PUBLISHED} == PUBLISHED


@pytest.mark.parametrize("type_name", sorted(FIELDS))
def test_generated_fields_equal_the_issue_field_lists(type_name):
    desc = _generated()["descs"][type_name]
    got = [(f["name"], f["type"]["type_id"], f["type"]["nested_type_name"], f["type"]["capacity"],
            f["type"]["string_capacity"]) for f in desc["fields"]]
    want = [(n, *_expected_type(t), 0, 0) for n, t in FIELDS[type_name]]
    assert got == want


def test_rosbags_hashes_of_the_issue_field_lists_equal_ours():
    """rosbags' RIHS01 of the issue's field lists (Jazzy's std types underneath) equals our hashes."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    assert "control_msgs/msg/JointTolerance" not in store.fielddefs  # ours are the only definitions
    for name in ("control_msgs/msg/JointTolerance", "control_msgs/msg/JointComponentTolerance",
                 *[n for n in FIELDS if n not in ("control_msgs/msg/JointTolerance",
                                                  "control_msgs/msg/JointComponentTolerance")]):
        text = "\n".join(f"{t.replace('/msg/', '/')} {n}" for n, t in FIELDS[name])
        store.register(get_types_from_msg(text, name))
    hashes = _generated()["hashes"]
    assert {n: store.hash_rihs01(n) for n in FIELDS} == {n: hashes[n] for n in FIELDS}


def test_constants_are_control_msgs_5x():
    from control_msgs.action import FollowJointTrajectory
    from control_msgs.msg import JointComponentTolerance

    r = FollowJointTrajectory.Result
    assert (r.SUCCESSFUL, r.INVALID_GOAL, r.INVALID_JOINTS, r.OLD_HEADER_TIMESTAMP,
            r.PATH_TOLERANCE_VIOLATED, r.GOAL_TOLERANCE_VIOLATED) == (0, -1, -2, -3, -4, -5)
    c = JointComponentTolerance
    assert (c.X_AXIS, c.Y_AXIS, c.Z_AXIS, c.TRANSLATION, c.ROTATION) == (1, 2, 3, 4, 5)
    # nothing else: a stray constant would mean a different definition
    consts = lambda cls: sorted(k for k in dir(cls) if k.isupper() and k != "SLOT_TYPES")  # noqa: E731
    assert consts(r) == sorted(["SUCCESSFUL", "INVALID_GOAL", "INVALID_JOINTS", "OLD_HEADER_TIMESTAMP",
                                "PATH_TOLERANCE_VIOLATED", "GOAL_TOLERANCE_VIOLATED"])
    assert consts(c) == ["ROTATION", "TRANSLATION", "X_AXIS", "Y_AXIS", "Z_AXIS"]


def test_built_files_are_not_committed():
    import subprocess

    repo = Path(__file__).resolve().parents[1]
    tracked = subprocess.run(["git", "ls-files", "interfaces/control_msgs"], cwd=repo,
                             capture_output=True, text=True, check=True).stdout.split()
    assert sorted(tracked) == sorted([
        "interfaces/control_msgs/CMakeLists.txt", "interfaces/control_msgs/package.xml",
        "interfaces/control_msgs/action/FollowJointTrajectory.action",
        "interfaces/control_msgs/msg/JointComponentTolerance.msg",
        "interfaces/control_msgs/msg/JointTolerance.msg",
        "interfaces/control_msgs/msg/JointTrajectoryControllerState.msg"])
