"""ROS message definitions from the installed interface files (no rclpy): the ``ros2msg``
schema text rosbag2 writes, the RIHS01 type hash, and whether a type starts with a Header.
Service request, response and introspection event types (``pkg/srv/<Service>_Event``) too."""
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
    if len(parts) == 3 and parts[1] == "srv" and parts[2].endswith(("_Request", "_Response", "_Event")):
        return parts[0], f"srv/{parts[2]}"  # see _definition_text
    if len(parts) == 2:
        return parts[0], parts[1]
    raise RecordingError(f"not a ROS message type name: {type_name!r}")


def _find_interface_file(pkg: str, name: str, suffix: str, kind: str = "msg") -> Path | None:
    for share in _share_dirs():
        f = share / pkg / kind / f"{name}{suffix}"
        if f.is_file():
            return f
    return None


# A service's request and response are named pkg/srv/<Service>_Request and _Response; its
# introspection events pkg/srv/<Service>_Event, whose definition no file holds: rosbag2 builds it
# from the .srv (both halves) and service_msgs/ServiceEventInfo, and so does message_definition.
_SRV_PARTS = ("_Request", "_Response")


def _service_part(pkg: str, name: str) -> str | None:
    """The text of ``srv/<Service>_Request`` or ``_Response`` from the installed .srv, else None."""
    service, part = name[len("srv/"):].rsplit("_", 1)
    f = _find_interface_file(pkg, service, ".srv", kind="srv")
    if f is None or f"_{part}" not in _SRV_PARTS:
        return None
    halves = f.read_text().split("\n---", 1)
    text = halves[0] if part == "Request" else (halves[1] if len(halves) > 1 else "")
    return text.lstrip("\n") if part == "Response" else text


def _definition_text(pkg: str, name: str) -> str | None:
    """A message's own text: ``name`` is 'Type' (share/<pkg>/msg/Type.msg) or
    'srv/<Service>_Request|_Response|_Event' (built from share/<pkg>/srv/<Service>.srv)."""
    if not name.startswith("srv/"):
        f = _find_interface_file(pkg, name, ".msg")
        if f is None and name.endswith(_SRV_PARTS):  # an event's field: pkg/<Service>_Request
            return _service_part(pkg, f"srv/{name}")
        return f.read_text() if f is not None else None
    if name.endswith("_Event"):
        service = name[len("srv/"):-len("_Event")]
        if _find_interface_file(pkg, service, ".srv", kind="srv") is None:
            return None
        # field types as pkg/Type: mcap_ros2 (0.6) resolves no other form, rosbags both
        return (f"service_msgs/ServiceEventInfo info\n"
                f"{pkg}/{service}_Request[<=1] request\n{pkg}/{service}_Response[<=1] response\n")
    return _service_part(pkg, name)


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
    text = _definition_text(pkg, name)
    if text is None:
        return ""
    parts = [text.rstrip("\n")]
    done: set[tuple[str, str]] = {(pkg, name)}
    stack = list(reversed(_field_dependencies(pkg, text)))
    while stack:
        dep = stack.pop()
        if dep in done:
            continue
        done.add(dep)
        dep_text = _definition_text(dep[0], dep[1])
        if dep_text is None:
            return ""  # incomplete definitions mislead decoders more than none
        parts.append(f"{_SEPARATOR}\nMSG: {dep[0]}/{dep[1]}\n{dep_text.rstrip(chr(10))}")
        stack.extend(reversed(_field_dependencies(dep[0], dep_text)))
    return "\n".join(parts) + "\n"


def is_service_type(type_name: str) -> bool:
    """True for ``pkg/srv/<Service>_Request|_Response|_Event`` (rosbags 0.11 misnames these)."""
    parts = type_name.strip().split("/")
    return len(parts) == 3 and parts[1] == "srv"


@functools.lru_cache(maxsize=None)
def type_description_hash(type_name: str) -> str:
    """RIHS01 type hash from the installed ``<Type>.json`` (rosidl), or "" if unavailable."""
    try:
        pkg, name = _split_type(type_name)
        if name.startswith("srv/"):  # all of a service's hashes are in share/<pkg>/srv/<Service>.json
            f = _find_interface_file(pkg, name[len("srv/"):].rsplit("_", 1)[0], ".json", kind="srv")
            full = f"{pkg}/{name}"
        else:
            f = _find_interface_file(pkg, name, ".json")
            full = f"{pkg}/msg/{name}"
        if f is None:
            return ""
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
