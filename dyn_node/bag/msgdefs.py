"""ROS message definitions from the installed interface files (no rclpy): the ``ros2msg``
schema text rosbag2 writes, the RIHS01 type hash, and whether a type starts with a Header."""
from __future__ import annotations

import functools
import json
import os
import sys
from pathlib import Path

from dyn_node.errors import RecordingError

_SEPARATOR = "=" * 80
_PRIMITIVES = frozenset(
    "bool byte char float32 float64 int8 uint8 int16 uint16 int32 uint32 int64 uint64 "
    "string wstring".split())

def _share_dirs() -> list[Path]:
    prefixes = [sys.prefix, *os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)]
    seen: list[Path] = []
    for p in prefixes:
        if p and (Path(p) / "share").is_dir() and Path(p) / "share" not in seen:
            seen.append(Path(p) / "share")
    return seen


def _split_type(type_name: str) -> tuple[str, str]:
    """'sensor_msgs/msg/JointState' or 'sensor_msgs/JointState' -> ('sensor_msgs', 'JointState')."""
    parts = type_name.strip().split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise RecordingError(f"not a ROS message type name: {type_name!r}")


def _find_interface_file(pkg: str, name: str, suffix: str) -> Path | None:
    for share in _share_dirs():
        f = share / pkg / "msg" / f"{name}{suffix}"
        if f.is_file():
            return f
    return None


def _field_dependencies(pkg: str, text: str) -> list[tuple[str, str]]:
    """Complex field types of a .msg text, in order of first appearance."""
    deps: list[tuple[str, str]] = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        tokens = line.split()
        if len(tokens) < 2 or "=" in tokens[1]:
            continue  # a constant ("int8 FOO=1") or a malformed line
        base = tokens[0].split("[", 1)[0].split("<=", 1)[0]
        if base in _PRIMITIVES:
            continue
        if "/" in base:
            dep = _split_type(base)
        elif base == "Header":
            dep = ("std_msgs", "Header")
        else:
            dep = (pkg, base)
        if dep not in deps:
            deps.append(dep)
    return deps


@functools.lru_cache(maxsize=None)
def message_definition(type_name: str) -> str:
    """The full ``ros2msg`` definition of a message type, dependencies included, built from the
    installed ``share/<pkg>/msg/*.msg`` files in the concatenated format rosbag2 writes
    (main definition, then ``====...==\\nMSG: pkg/Type\\n<text>`` per dependency, depth first).

    Returns "" when the .msg file is not installed (the bag is still written; readers that need
    the schema then need the type from elsewhere)."""
    pkg, name = _split_type(type_name)
    main = _find_interface_file(pkg, name, ".msg")
    if main is None:
        return ""
    text = main.read_text()
    parts = [text.rstrip("\n")]
    done: set[tuple[str, str]] = {(pkg, name)}
    stack = list(reversed(_field_dependencies(pkg, text)))
    while stack:
        dep = stack.pop()
        if dep in done:
            continue
        done.add(dep)
        f = _find_interface_file(dep[0], dep[1], ".msg")
        if f is None:
            return ""  # incomplete definitions mislead decoders more than none
        dep_text = f.read_text()
        parts.append(f"{_SEPARATOR}\nMSG: {dep[0]}/{dep[1]}\n{dep_text.rstrip(chr(10))}")
        stack.extend(reversed(_field_dependencies(dep[0], dep_text)))
    return "\n".join(parts) + "\n"


@functools.lru_cache(maxsize=None)
def type_description_hash(type_name: str) -> str:
    """RIHS01 type hash from the installed ``<Type>.json`` (rosidl), or "" if unavailable."""
    try:
        pkg, name = _split_type(type_name)
        f = _find_interface_file(pkg, name, ".json")
        if f is None:
            return ""
        full = f"{pkg}/msg/{name}"
        for h in json.loads(f.read_text()).get("type_hashes", []):
            if h.get("type_name") == full:
                return str(h.get("hash_string", ""))
    except (OSError, ValueError, RecordingError):
        pass
    return ""


@functools.lru_cache(maxsize=None)
def has_header_first(type_name: str) -> bool:
    """True when the first field of the message is a std_msgs/Header (so the CDR payload starts
    with the stamp right after the 4-byte encapsulation header)."""
    try:
        pkg, name = _split_type(type_name)
    except RecordingError:
        return False
    f = _find_interface_file(pkg, name, ".msg")
    if f is None:
        return False
    for line in f.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            return line.split()[0] in ("std_msgs/Header", "std_msgs/msg/Header", "Header")
    return False
