"""The rosbag2 bag layout (Jazzy, version 9): topic and file descriptions, the QoS profiles,
``metadata.yaml`` (written durably), and new bag directories."""
from __future__ import annotations

import errno
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import yaml

from dyn_node.errors import RecordingError
from dyn_node.bag.msgdefs import is_service_type, type_description_hash
from dyn_node.core.robot.limits_file import limits_sha256

ROSBAG2_VERSION = 9
ROS_DISTRO = "jazzy"
METADATA_RECORD = "dyn_node"  # the MCAP metadata record and metadata.yaml key of the node's own
# rmw's "infinite" duration as rosbag2 Jazzy writes it.
_INFINITE = {"sec": 9223372036, "nsec": 854775807}

#: keys of the metadata record holding the limits file's text and the sha256 of its bytes
LIMITS_YAML_KEY, LIMITS_SHA256_KEY = "limits_yaml", "limits_sha256"


def limits_record(text: str) -> dict[str, str]:
    """The metadata record's limits fields for the limits file text the node's model was built
    from: the text, and the sha256 (hex) of its UTF-8 bytes (the file's bytes)."""
    return {LIMITS_YAML_KEY: text, LIMITS_SHA256_KEY: limits_sha256(text)}


def qos_profile_dict(reliability: str = "reliable", durability: str = "volatile",
                     history: str = "keep_last", depth: int = 10,
                     liveliness: str = "automatic") -> dict[str, Any]:
    """One offered QoS profile in rosbag2 v9 form (enum names in lower case)."""
    return {"history": history, "depth": int(depth), "reliability": reliability,
            "durability": durability, "deadline": dict(_INFINITE), "lifespan": dict(_INFINITE),
            "liveliness": liveliness, "liveliness_lease_duration": dict(_INFINITE),
            "avoid_ros_namespace_conventions": False}


def qos_yaml(profiles: Sequence[Mapping[str, Any]]) -> str:
    """The QoS list as the YAML string rosbag2 puts in MCAP channel metadata."""
    if not profiles:
        return ""
    return yaml.safe_dump([dict(p) for p in profiles], sort_keys=False,
                          default_flow_style=False).strip()


@dataclass(frozen=True)
class TopicInfo:
    """A recorded topic: resolved name, ROS type ('pkg/msg/Type') and publishers' offered QoS."""

    name: str
    type: str
    offered_qos_profiles: tuple[Mapping[str, Any], ...] = ()


@dataclass(frozen=True)
class FileInfo:
    """One split file as metadata.yaml lists it; times in ns since the epoch (log time)."""

    path: str
    start_ns: int
    end_ns: int
    message_count: int
    topic_counts: Mapping[str, int] = field(default_factory=dict)


def _listed_hash(type_name: str) -> str:
    """The hash metadata.yaml lists: "" for service types, rosbag2's "cannot be determined".
    rosbags 0.11 registers ``pkg/srv/X_Event`` as ``pkg/srv/msg/X_Event`` and then fails every
    open on its hash check (KeyError); rosbag2 accepts "" (the MCAP channel keeps the hash)."""
    return "" if is_service_type(type_name) else type_description_hash(type_name)


def bag_metadata(topics: Sequence[TopicInfo], files: Sequence[FileInfo],
                 extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The metadata.yaml document (rosbag2 Jazzy, version 9) for these files.

    ``extra`` goes under a top-level ``dyn_node`` key, beside ``rosbag2_bagfile_information``,
    which rosbag2 and rosbags ignore."""
    counts: dict[str, int] = {}
    for f in files:
        for t, n in f.topic_counts.items():
            counts[t] = counts.get(t, 0) + n
    nonempty = [f for f in files if f.message_count]
    start = min((f.start_ns for f in nonempty), default=0)
    end = max((f.end_ns for f in nonempty), default=start)
    info: dict[str, Any] = {
        "version": ROSBAG2_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": max(0, end - start)},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": sum(f.message_count for f in files),
        "topics_with_message_count": [
            {"topic_metadata": {"name": t.name, "type": t.type, "serialization_format": "cdr",
                                "offered_qos_profiles": [dict(p) for p in t.offered_qos_profiles],
                                "type_description_hash": _listed_hash(t.type)},
             "message_count": counts.get(t.name, 0)}
            for t in topics],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [Path(f.path).name for f in files],
        "files": [{"path": Path(f.path).name,
                   "starting_time": {"nanoseconds_since_epoch":
                                     f.start_ns if f.message_count else 0},
                   "duration": {"nanoseconds": max(0, f.end_ns - f.start_ns)},
                   "message_count": f.message_count} for f in files],
        "custom_data": None,
        "ros_distro": ROS_DISTRO,
    }
    doc: dict[str, Any] = {"rosbag2_bagfile_information": info}
    if extra:
        doc[METADATA_RECORD] = dict(extra)
    return doc


def write_metadata_yaml(bag_dir: str | os.PathLike[str], doc: Mapping[str, Any], *,
                        fsync: bool = True) -> None:
    """Write metadata.yaml atomically, so a reader never sees half of it and a power loss
    leaves the old or the new file whole (temp file, fsync, rename over, fsync the directory).
    No temp file is ever left behind; on a full disk, the old file is removed rather than kept
    stale (see below)."""
    path = Path(bag_dir) / "metadata.yaml"
    tmp = path.with_name("metadata.yaml.tmp")
    text = yaml.safe_dump(dict(doc), sort_keys=False, default_flow_style=False)
    try:
        _replace_with(tmp, path, text, fsync=fsync)
    except OSError as exc:
        if exc.errno not in _NO_SPACE or not path.exists():
            raise
        # A full disk: an old metadata.yaml (say, the start's "recording", no counts) beside
        # the new one's failed copy would mislead more than none. Removing it frees its space
        # for one more try; if that fails too, there is no metadata.yaml, never a stale one.
        path.unlink()
        _replace_with(tmp, path, text, fsync=fsync)


#: errno values of "the file system has no room" (a full disk, a user's quota)
_NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


def _replace_with(tmp: Path, path: Path, text: str, *, fsync: bool) -> None:
    """Write ``text`` to ``tmp``, fsync it, rename it over ``path``, fsync the directory
    (without the first fsync the rename can reach the disk before the data: an empty file).
    On failure ``tmp`` is removed and ``path`` is as it was."""
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            if fsync:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if fsync:
        fsync_directory(path.parent)


def fsync_directory(path: str | os.PathLike[str]) -> None:
    """fsync a directory, so the names created or renamed in it survive a power loss."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP):  # a file system without dir fsync
            raise
    finally:
        os.close(fd)


def new_bag_directory(parent: str | os.PathLike[str], prefix: str = "dyn_node",
                      now: float | None = None, *, fsync: bool = True) -> Path:
    """Create ``parent/<prefix>_<YYYYmmdd_HHMMSS>`` (UTC), suffixed ``_1``, ``_2`` ... when it
    exists; ``mkdir`` is exclusive, so two recorders never share (or overwrite) a directory.
    ``fsync``: the directories holding each new name are fsynced, so a power loss cannot lose
    the bag directory (with every file in it) from its parent."""
    base = Path(parent)
    created = [p for p in (base, *base.parents) if not p.exists()]
    base.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d_%H%M%S", time.gmtime(time.time() if now is None else now))
    for k in range(10_000):
        d = base / (f"{prefix}_{stamp}" if k == 0 else f"{prefix}_{stamp}_{k}")
        try:
            d.mkdir()
        except FileExistsError:
            continue
        if fsync:
            for p in (d, *created):
                fsync_directory(p.parent)
        return d
    raise RecordingError(f"cannot create a new bag directory in {base}")
