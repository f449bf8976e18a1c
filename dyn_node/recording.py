"""Record raw CDR messages into a rosbag2-layout MCAP bag, off the caller's thread.

Pure module (no rclpy): the ROS adapter (:mod:`dyn_node.ros_recording`) hands it the serialized
bytes it received; nothing is deserialized or re-serialized. A bag is a directory::

    <directory>/<prefix>_<YYYYmmdd_HHMMSS>[_<k>]/
        metadata.yaml                      rosbag2 (Jazzy, version 9) bag information
        <dirname>_0.mcap, <dirname>_1.mcap  MCAP, profile ros2, schemas ros2msg, messages cdr

Guarantees
- :meth:`Recorder.write` never blocks on disk and never raises: messages go through a bounded
  queue to one writer thread; when the queue is full, the message is counted as dropped.
- Per topic, ``received == written + dropped`` once the recorder is closed. A message counts as
  written only once the chunk holding it has reached the OS (flushed); messages of a chunk that
  failed to write are counted as dropped.
- Chunks are closed, flushed and fsynced every ``flush_period_s`` (default 0.5 s), so after
  SIGKILL at most the last flush period (plus queue latency) is missing; ``dyn-bag-recover``
  rewrites the truncated file into an indexed one. ``metadata.yaml`` is replaced durably too
  (temp file fsynced, renamed, directory fsynced): after a power loss it is never empty.
- A write error (ENOSPC, EIO, ...) puts the recorder in the ``error`` state; later messages are
  dropped (counted) and everything flushed before remains readable.
- Every file begins with the robot description on ``/robot_description`` and an MCAP metadata
  record ``dyn_node`` (keys ``robot_description``, ``parameters`` (YAML), ``version``, and
  ``effective_log_time_ns`` when the owner says since when that configuration applies), so each
  split file is self-contained. A parameter change writes a new record, in queue order with the
  messages, each carrying the log time from which the new configuration applies. The injected description copies are counted as
  ``description_copies``, not as received messages.

The MCAP bytes come from :class:`McapFile`, a small writer of our own (chunked, indexed, CRCs
on chunks, data section and summary), not from ``mcap.writer.Writer``: per message it costs one
``struct`` pack and list appends instead of a record object and a ``BytesIO`` round trip,
which at 3 records per 1 kHz joint state was most of what recording cost the node.
"""
from __future__ import annotations

import atexit
import errno
import functools
import json
import os
import struct
import sys
import threading
import time
import weakref
import zlib
from array import array
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Callable, Mapping, Sequence

import yaml
from mcap.writer import CompressionType

from . import __version__

ROSBAG2_VERSION = 9
ROS_DISTRO = "jazzy"
METADATA_RECORD = "dyn_node"
PROFILE = "ros2"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
DESCRIPTION_TYPE = "std_msgs/msg/String"
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}
STATES = ("idle", "recording", "error", "closed")
_SEPARATOR = "=" * 80
_PRIMITIVES = frozenset(
    "bool byte char float32 float64 int8 uint8 int16 uint16 int32 uint32 int64 uint64 "
    "string wstring".split())
# rmw's "infinite" duration as rosbag2 Jazzy writes it.
_INFINITE = {"sec": 9223372036, "nsec": 854775807}


class RecordingError(ValueError):
    """Bad recorder configuration (raised at construction, never from write())."""


# --------------------------------------------------------------------------- message definitions

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


def header_stamp_ns(data: bytes | memoryview) -> int | None:
    """Stamp (ns) of a CDR message whose first field is std_msgs/Header: 4-byte encapsulation
    header (byte 1 odd = little endian), then int32 sec, uint32 nanosec. None if unusable."""
    if len(data) < 12:
        return None
    fmt = "<iI" if data[1] & 1 else ">iI"
    sec, nsec = struct.unpack_from(fmt, data, 4)
    if sec < 0 or nsec >= 1_000_000_000:
        return None
    return sec * 1_000_000_000 + nsec


def cdr_string(text: str) -> bytes:
    """CDR (little endian) of a message with one string field, e.g. std_msgs/String."""
    b = text.encode()
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(b) + 1) + b + b"\x00"


def cdr_string_value(data: bytes | memoryview) -> str | None:
    """Inverse of :func:`cdr_string` (either endianness); None when malformed."""
    if len(data) < 8:
        return None
    (n,) = struct.unpack_from("<I" if data[1] & 1 else ">I", data, 4)
    if n < 1 or 8 + n > len(data):
        return None
    return bytes(data[8:8 + n - 1]).decode("utf-8", errors="replace")


# --------------------------------------------------------------------------- QoS and metadata.yaml

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
                                "type_description_hash": type_description_hash(t.type)},
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
    leaves the old or the new file whole: temp file, fsync it, rename over, fsync the directory
    (without the first fsync the rename can reach the disk before the data: an empty file)."""
    path = Path(bag_dir) / "metadata.yaml"
    tmp = path.with_name("metadata.yaml.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(yaml.safe_dump(dict(doc), sort_keys=False, default_flow_style=False))
        f.flush()
        if fsync:
            os.fsync(f.fileno())
    os.replace(tmp, path)
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


# --------------------------------------------------------------------------- MCAP records

MCAP_MAGIC = b"\x89MCAP0\r\n"
# Opcodes (MCAP spec, https://mcap.dev/spec).
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_OP_MESSAGE_INDEX, _OP_CHUNK_INDEX, _OP_STATISTICS, _OP_METADATA = 0x07, 0x08, 0x0B, 0x0C
_OP_METADATA_INDEX, _OP_SUMMARY_OFFSET, _OP_DATA_END = 0x0D, 0x0E, 0x0F
# Message record up to its data: opcode, record length, channel id, sequence, log time,
# publish time (31 bytes; the record length counts the 22 bytes after it plus the data).
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_RECORD_HEAD = struct.Struct("<BQ")
_NEED_SWAP = sys.byteorder != "little"


def _mcap_str(text: str) -> bytes:
    b = text.encode()
    return struct.pack("<I", len(b)) + b


def _mcap_map(values: Mapping[str, str]) -> bytes:
    body = b"".join(_mcap_str(k) + _mcap_str(v) for k, v in values.items())
    return struct.pack("<I", len(body)) + body


def _mcap_record(opcode: int, body: bytes) -> bytes:
    return _RECORD_HEAD.pack(opcode, len(body)) + body


def _compressor(name: str) -> tuple[bytes, Callable[[bytes], bytes] | None]:
    """(compression name as the chunk record spells it, function) for a record.compression."""
    if name == "zstd":
        import zstandard
        # Level -1 (zstd's fast mode). On 7-DoF joint states (noisy doubles, ~360 B each):
        # level 3 (mcap's default) 2.9 µs/message, ratio 2.16; level 1 1.2 µs, 2.16;
        # level -1 0.7 µs, 2.10. Compression is the largest per-message cost left, and the
        # node pays it at 3 messages per joint state.
        return b"zstd", zstandard.ZstdCompressor(level=-1).compress
    if name == "lz4":
        import lz4.frame
        return b"lz4", lz4.frame.compress
    return b"", None


class McapFile:
    """A minimal chunked, indexed MCAP writer for the recorder (spec: https://mcap.dev/spec).

    Why not ``mcap.writer.Writer``: it builds a ``Message`` dataclass and writes six fields
    through a ``BytesIO`` per message (~7 µs each, the recorder's dominant cost). Here a message
    is one ``struct`` pack plus list appends; the chunk is joined once when it closes.

    The file has what mcap's writer produces with ``enable_crcs`` and ``enable_data_crcs``:
    Header; Schema, Channel and Metadata records in the data section (before any chunk that
    uses them, so a streaming reader or ``dyn-bag-recover`` sees them first); Chunk records
    (uncompressed CRC) each followed by one Message Index per channel; Data End with the
    data-section CRC; a summary (schemas, channels, statistics, chunk indexes, metadata
    indexes, summary offsets) and a Footer with the summary CRC.

    ``stream`` needs ``write`` and ``tell`` (see :class:`_CountingFile`). Nothing is buffered
    except the open chunk, which :meth:`close_chunk` writes in one ``write`` call."""

    def __init__(self, stream: Any, compression: str = "zstd", profile: str = PROFILE,
                 library: str = ""):
        self._stream = stream
        self._crc = 0  # data-section CRC, from the magic on
        self._cname, self._compress = _compressor(compression)
        self._cname_field = _mcap_str(self._cname.decode())
        self._schemas: list[bytes] = []
        self._channels: list[bytes] = []
        self._channel_counts: dict[int, int] = {}
        self._chunk_indexes: list[bytes] = []
        self._metadata_indexes: list[bytes] = []
        self.message_count = 0
        self._start = 0
        self._end = 0
        # The open chunk: records as a list of bytes, per channel [log, offset, log, offset...].
        self.parts: list[bytes] = []
        self.size = 0  # uncompressed bytes in the open chunk
        self.index: dict[int, list[int]] = {}
        self.lo: int | None = None
        self.hi = 0
        self._emit(MCAP_MAGIC + _mcap_record(_OP_HEADER, _mcap_str(profile) + _mcap_str(library)))

    def _emit(self, data: bytes) -> None:
        self._crc = zlib.crc32(data, self._crc)
        self._stream.write(data)

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = len(self._schemas) + 1
        rec = _mcap_record(_OP_SCHEMA, struct.pack("<H", sid) + _mcap_str(name)
                           + _mcap_str(encoding) + struct.pack("<I", len(data)) + data)
        self._emit(rec)
        self._schemas.append(rec)
        return sid

    def add_channel(self, topic: str, message_encoding: str, schema_id: int,
                    metadata: Mapping[str, str]) -> int:
        cid = len(self._channels) + 1
        rec = _mcap_record(_OP_CHANNEL, struct.pack("<HH", cid, schema_id) + _mcap_str(topic)
                           + _mcap_str(message_encoding) + _mcap_map(metadata))
        self._emit(rec)
        self._channels.append(rec)
        return cid

    def add_metadata(self, name: str, values: Mapping[str, str]) -> None:
        offset = self._stream.tell()
        rec = _mcap_record(_OP_METADATA, _mcap_str(name) + _mcap_map(values))
        self._emit(rec)
        self._metadata_indexes.append(_mcap_record(
            _OP_METADATA_INDEX, struct.pack("<QQ", offset, len(rec)) + _mcap_str(name)))

    def add_message(self, channel_id: int, log_ns: int, pub_ns: int, data: bytes) -> None:
        """Append one Message record to the open chunk (no I/O)."""
        off = self.size
        n = len(data)
        self.parts += (_MESSAGE_HEAD.pack(_OP_MESSAGE, 22 + n, channel_id, 0, log_ns, pub_ns), data)
        self.size = off + 31 + n
        idx = self.index.get(channel_id)
        if idx is None:
            idx = self.index[channel_id] = []
        idx += (log_ns, off)
        if self.lo is None or log_ns < self.lo:
            self.lo = log_ns
        if log_ns > self.hi:
            self.hi = log_ns

    def close_chunk(self, on_written: Callable[[dict[int, list[int]], int, int], None] | None = None
                    ) -> bool:
        """Write the open chunk and its message indexes; False if it held no message.
        ``on_written(index, lo, hi)`` runs once the chunk record itself is in the stream (its
        messages are then in the file even if writing the indexes fails): ``index`` maps channel
        id to [log time, offset, ...], ``lo``/``hi`` the chunk's log-time range. When the chunk
        write fails, :attr:`index` still holds the unwritten messages."""
        if not self.parts:
            return False
        records = b"".join(self.parts)
        lo, hi, index = self.lo or 0, self.hi, self.index
        data = self._compress(records) if self._compress is not None else records
        head = struct.pack("<BQQQQI", _OP_CHUNK, 8 * 3 + 4 + len(self._cname_field) + 8 + len(data),
                           lo, hi, len(records), zlib.crc32(records)) \
            + self._cname_field + struct.pack("<Q", len(data))
        chunk_start = self._stream.tell()
        self._emit(head + data)
        self.parts, self.size, self.index, self.lo, self.hi = [], 0, {}, None, 0
        if on_written is not None:
            on_written(index, lo, hi)
        chunk_len = len(head) + len(data)
        pos = index_start = chunk_start + chunk_len
        recs, offsets = [], []
        n_messages = 0
        for cid, entries in index.items():
            arr = array("Q", entries)
            if _NEED_SWAP:
                arr.byteswap()
            rec = _RECORD_HEAD.pack(_OP_MESSAGE_INDEX, 6 + 8 * len(arr)) \
                + struct.pack("<HI", cid, 8 * len(arr)) + arr.tobytes()
            recs.append(rec)
            offsets.append(struct.pack("<HQ", cid, pos))
            pos += len(rec)
            n = len(entries) // 2
            n_messages += n
            self._channel_counts[cid] = self._channel_counts.get(cid, 0) + n
        self._emit(b"".join(recs))
        if self.message_count == 0 or lo < self._start:
            self._start = lo
        self._end = max(self._end, hi)
        self.message_count += n_messages
        self._chunk_indexes.append(_mcap_record(
            _OP_CHUNK_INDEX,
            struct.pack("<QQQQ", lo, hi, chunk_start, chunk_len)
            + struct.pack("<I", 10 * len(offsets)) + b"".join(offsets)
            + struct.pack("<Q", pos - index_start) + self._cname_field
            + struct.pack("<QQ", len(data), len(records))))
        return True

    def finish(self, on_written: Callable[[dict[int, list[int]], int, int], None] | None = None
               ) -> None:
        """Close the open chunk, then write Data End, the summary, the Footer and the magic."""
        self.close_chunk(on_written)
        self._stream.write(_mcap_record(_OP_DATA_END, struct.pack("<I", self._crc)))
        summary_start = pos = self._stream.tell()
        counts = b"".join(struct.pack("<HQ", c, n) for c, n in sorted(self._channel_counts.items()))
        statistics = _mcap_record(_OP_STATISTICS, struct.pack(
            "<QHIIIIQQ", self.message_count, len(self._schemas), len(self._channels), 0,
            len(self._metadata_indexes), len(self._chunk_indexes), self._start, self._end)
            + struct.pack("<I", len(counts)) + counts)
        groups, offsets = [], []
        for opcode, recs in ((_OP_SCHEMA, self._schemas), (_OP_CHANNEL, self._channels),
                             (_OP_STATISTICS, [statistics]), (_OP_CHUNK_INDEX, self._chunk_indexes),
                             (_OP_METADATA_INDEX, self._metadata_indexes)):
            if not recs:
                continue
            blob = b"".join(recs)
            groups.append(blob)
            offsets.append(_mcap_record(_OP_SUMMARY_OFFSET,
                                        struct.pack("<BQQ", opcode, pos, len(blob))))
            pos += len(blob)
        summary = b"".join(groups) + b"".join(offsets)
        footer = struct.pack("<BQQQ", _OP_FOOTER, 20, summary_start, pos)
        crc = zlib.crc32(footer, zlib.crc32(summary))
        self._stream.write(summary + footer + struct.pack("<I", crc) + MCAP_MAGIC)


# --------------------------------------------------------------------------- the recorder

@dataclass(frozen=True)
class RecorderConfig:
    """Recorder settings. Sizes in MB (10^6 bytes), durations in seconds; 0 disables a split."""

    directory: str = "bags"
    compression: str = "zstd"
    max_bag_size_mb: float = 0.0
    max_bag_duration_s: float = 0.0
    prefix: str = "dyn_node"
    queue_size: int = 20_000
    queue_bytes: int = 256 * 1024 * 1024
    flush_period_s: float = 0.5
    chunk_size: int = 1024 * 1024
    fsync: bool = True
    description_topic: str = "/robot_description"

    def validate(self) -> None:
        if self.compression not in COMPRESSIONS:
            raise RecordingError(f"record.compression must be one of {sorted(COMPRESSIONS)}, "
                                 f"got {self.compression!r}")
        for key in ("max_bag_size_mb", "max_bag_duration_s"):
            v = getattr(self, key)
            if not (v >= 0 and v < float("inf")):
                raise RecordingError(f"record.{key} must be finite and >= 0 (0 = off), got {v!r}")
        if not (0 < self.flush_period_s <= 1.0):
            raise RecordingError("flush_period_s must be in (0, 1] s: at most 1 s may be lost")
        if self.queue_size < 1 or self.queue_bytes < 1 or self.chunk_size < 1:
            raise RecordingError("queue_size, queue_bytes and chunk_size must be positive")


@dataclass(frozen=True)
class TopicCounts:
    received: int = 0
    written: int = 0
    dropped: int = 0


@dataclass(frozen=True)
class RecorderStats:
    """Snapshot of the recorder: state in STATES, error text ("" if none), bag directory,
    files so far, per-topic counts, messages waiting in the queue, injected description copies."""

    state: str
    error: str
    path: str
    files: tuple[str, ...]
    topics: Mapping[str, TopicCounts]
    queued: int
    description_copies: int

    @property
    def dropped(self) -> int:
        return sum(c.dropped for c in self.topics.values())


class _CountingFile:
    """Wrap the binary file so the MCAP writer's ``tell()`` works on any file-like and we know
    the size without a stat call. Writes loop until done (a raw file may write partially)."""

    def __init__(self, raw: BinaryIO):
        self.raw = raw
        self.pos = 0

    def write(self, data: bytes) -> int:
        if not data:
            return 0
        view = memoryview(data)
        while view:
            n = self.raw.write(view)
            n = len(view) if n is None else n
            if n <= 0:
                raise OSError(errno.EIO, "write made no progress")
            self.pos += n
            view = view[n:]
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        self.raw.flush()

    def fsync(self) -> None:
        fileno = getattr(self.raw, "fileno", None)
        if fileno is not None:
            try:
                fd = fileno()
            except (OSError, ValueError):
                return
            os.fsync(fd)

    def close(self) -> None:
        self.raw.close()


# Recorder.write's publish time "the header stamp of the message" (parsed on the writer thread).
HEADER_STAMP = -1

# Queue items: a message is (topic, data, log_ns, publish_ns); anything else is
# (None, kind, payload) with kind one of these.
_TOPIC, _DESC, _META, _STOP = range(4)

_LIVE: "weakref.WeakSet[Recorder]" = weakref.WeakSet()


@atexit.register
def _close_live_recorders() -> None:
    # Interpreter exit (e.g. an unhandled KeyboardInterrupt) still writes summaries.
    for rec in list(_LIVE):
        rec.close(timeout=5.0)


class Recorder:
    """One recording: a bag directory written by a background thread.

    ``opener(path) -> binary file`` is injectable (tests simulate ENOSPC with it);
    ``on_state(stats)`` is called from the writer thread when the state changes."""

    # The writer takes messages in batches: it wakes every _BATCH_S or once _BATCH_N messages
    # wait, not per message. A wake-up per message (a thread switch and a trip through the
    # lock at 3 kHz: joint_states plus two outputs) cost the recording node more CPU than
    # writing the messages.
    _BATCH_S = 0.1
    _BATCH_N = 1024

    def __init__(self, config: RecorderConfig = RecorderConfig(), *,
                 robot_description: str = "", parameters_yaml: str = "",
                 effective_log_time_ns: int | None = None,
                 opener: Callable[[str], BinaryIO] | None = None,
                 on_state: Callable[[RecorderStats], None] | None = None,
                 clock_ns: Callable[[], int] = time.time_ns):
        config.validate()
        self.config = config
        # Unbuffered: McapFile writes whole records (a chunk in one call), and a full disk then
        # surfaces at the write that failed rather than at some later buffer flush.
        self._opener = opener or (lambda p: open(p, "xb", buffering=0))
        self._on_state = on_state
        self._clock_ns = clock_ns
        self.path = new_bag_directory(config.directory, config.prefix, fsync=config.fsync)
        # Re-entrant: the on_state observer runs under the lock and may call stats().
        self._lock = threading.RLock()
        self._wake = threading.Condition(self._lock)
        # Callers append without the lock (see write); only the writer thread (or a drain under
        # the lock) takes items out. A message counts as received once it leaves the queue;
        # stats() adds the ones still in it.
        self._queue: deque[tuple] = deque()
        self._bytes_in = 0  # payload bytes ever queued (callers) ...
        self._bytes_out = 0  # ... and taken out (under the lock)
        self._queue_size, self._queue_bytes = config.queue_size, config.queue_bytes
        self._counts: dict[str, list[int]] = {}  # topic -> [received, written, dropped]
        self._declared: set[str] = set()
        self._accepting = True  # recording and not closing (read by write() under the lock)
        self._state = "recording"
        self._error = ""
        self._closing = False
        self._topics: dict[str, TopicInfo] = {}
        self._description = robot_description
        self._description_raw: bytes | None = None
        self._parameters_yaml = parameters_yaml
        self._effective_ns = effective_log_time_ns
        # the configuration the writer has reached in queue order (what each file's record says)
        self._w_parameters = (parameters_yaml, effective_log_time_ns)
        self._description_copies = 0
        self._files: list[FileInfo] = []
        # Writer-thread state.
        self._mcap: McapFile | None = None
        self._stream: _CountingFile | None = None
        self._channels: dict[str, int] = {}
        self._channel_topics: dict[int, str] = {}
        self._schemas: dict[str, int] = {}
        self._file_index = -1
        self._file_start = 0
        self._file_end = 0
        self._file_counts: dict[str, int] = {}
        self._pending_copies = 0  # description copies in the open chunk
        self._file_first_ns: int | None = None  # first recorded (not copied) message of the file
        self._current: str | None = None
        self._meta_desc: str | None = None
        self._chunk_limit = config.chunk_size
        self._file_written_desc = ""
        self._thread = threading.Thread(target=self._run, name="dyn_node recorder", daemon=True)
        self._closed = threading.Event()
        _LIVE.add(self)
        self._thread.start()

    # ---------------------------------------------------------------- caller side (any thread)
    def add_topic(self, topic: TopicInfo) -> None:
        """Declare a topic before its first message (the channel carries its QoS)."""
        with self._lock:
            self._counts.setdefault(topic.name, [0, 0, 0])
            self._declared.add(topic.name)
            if not self._accepting:
                return
            self._queue.append((None, _TOPIC, topic))
            self._wake.notify()

    def write(self, topic: str, data: bytes, log_time_ns: int,
              publish_time_ns: int | None = None) -> bool:
        """Queue one serialized message; True if queued, False if dropped (counted). Never raises
        for I/O, never blocks on disk. Unknown topics must be added first with add_topic().

        ``publish_time_ns``: None = the log time; :data:`HEADER_STAMP` = the message's header
        stamp (:func:`header_stamp_ns`, the log time if unusable), read on the writer thread so
        the caller's thread does not pay for it."""
        # No lock on this path: it runs on the node's hot thread up to 3 times per joint state,
        # and deque.append is atomic. The byte bound is approximate: the counters are updated
        # without a lock, and a lost update only ever errs towards accepting a message.
        q = self._queue
        n = len(data)
        if (self._accepting and topic in self._declared and len(q) < self._queue_size
                and self._bytes_in - self._bytes_out + n <= self._queue_bytes):
            self._bytes_in += n
            q.append((topic, data, log_time_ns,
                      log_time_ns if publish_time_ns is None else publish_time_ns))
            if len(q) == self._BATCH_N:
                with self._lock:
                    self._wake.notify()
            return True
        with self._lock:
            c = self._counts.get(topic)
            if c is None:
                c = self._counts[topic] = [0, 0, 0]
            c[0] += 1
            c[2] += 1
        return False

    def set_robot_description(self, urdf: str) -> None:
        """The description to repeat at the start of every file and in the metadata record."""
        with self._lock:
            if urdf == self._description or not self._accepting:
                self._description = urdf
                return
            self._description = urdf
            self._queue.append((None, _DESC, urdf))
            self._wake.notify()

    def set_parameters_yaml(self, text: str, *, effective_log_time_ns: int | None = None) -> None:
        """New parameter snapshot: a new ``dyn_node`` metadata record is written if it (or the
        log time from which it applies, ``effective_log_time_ns``) changed. The record follows
        the messages queued before this call, so every file's record is the configuration in
        force at that point of the recording."""
        with self._lock:
            if effective_log_time_ns is None:
                effective_log_time_ns = self._effective_ns
            if (text, effective_log_time_ns) == (self._parameters_yaml, self._effective_ns):
                return
            self._parameters_yaml, self._effective_ns = text, effective_log_time_ns
            if self._accepting:
                self._queue.append((None, _META, (text, effective_log_time_ns)))
                self._wake.notify()

    def stats(self) -> RecorderStats:
        with self._lock:
            return self._stats_locked()

    def _stats_locked(self) -> RecorderStats:
        # Messages still in the queue are received (not yet counted); once the writer has
        # finished, nothing will take them out: they are dropped.
        queued: dict[str, int] = {}
        for item in list(self._queue):  # list(): one atomic copy while callers append
            if item[0] is not None:
                queued[item[0]] = queued.get(item[0], 0) + 1
        gone = self._closed.is_set()
        return RecorderStats(
            state=self._state, error=self._error, path=str(self.path),
            files=tuple(f.path for f in self._files) + (
                (str(self._file_path(self._file_index)),) if self._mcap is not None else ()),
            topics={t: TopicCounts(c[0] + queued.get(t, 0), c[1],
                                   c[2] + (queued.get(t, 0) if gone else 0))
                    for t, c in self._counts.items()},
            queued=sum(queued.values()), description_copies=self._description_copies)

    def close(self, timeout: float = 10.0) -> RecorderStats:
        """Drain the queue, write summaries and metadata.yaml; idempotent. Messages still queued
        when ``timeout`` expires are counted as dropped."""
        with self._lock:
            if not self._closing:
                self._closing = True
                self._accepting = False
                self._queue.append((None, _STOP, None))
                self._wake.notify()
        self._closed.wait(timeout)
        with self._lock:
            if not self._closed.is_set():
                # The writer is stuck (e.g. a hung disk): account for what it will never write.
                self._drop_locked(self._queue, taken=False)
                self._set_state_locked("error", self._error or "writer did not finish in time")
            return self._stats_locked()

    # ---------------------------------------------------------------- writer thread
    def _file_path(self, index: int) -> Path:
        return self.path / f"{self.path.name}_{index}.mcap"

    def _set_state_locked(self, state: str, error: str = "") -> None:
        changed = state != self._state
        self._state = state
        if state != "recording":
            self._accepting = False
        if error:
            self._error = error
        if changed and self._on_state is not None:
            stats = self._stats_locked()
            try:
                self._on_state(stats)
            except Exception:  # a faulty observer must not kill the writer
                pass

    def _drop_locked(self, items: "deque[tuple]", taken: bool) -> None:
        """Count the messages among ``items`` as dropped (and as received unless ``taken``, i.e.
        already taken from the queue) and remove them."""
        counts = self._counts
        pop = items.popleft
        while items:  # popleft, not iteration: callers may append to the queue meanwhile
            item = pop()
            if item[0] is not None:
                c = counts[item[0]]
                c[2] += 1
                if not taken:
                    c[0] += 1
                    self._bytes_out += len(item[1])

    def _take_locked(self) -> "deque[tuple]":
        """Take what is in the queue now; its messages count as received from here on."""
        q = self._queue
        pop = q.popleft
        batch = deque([pop() for _ in range(len(q))])
        counts = self._counts
        n_bytes = 0
        for item in batch:
            if item[0] is not None:
                counts[item[0]][0] += 1
                n_bytes += len(item[1])
        self._bytes_out += n_bytes
        return batch

    def _run(self) -> None:
        next_flush = time.monotonic() + self.config.flush_period_s
        try:
            self._open_file()
            self._write_metadata_yaml()
        except Exception as exc:  # noqa: BLE001 - any I/O failure becomes the error state
            self._fail(exc)
        stop = False
        while not stop:
            with self._lock:
                q = self._queue
                if len(q) < self._BATCH_N and not self._urgent():
                    self._wake.wait(max(0.0, min(next_flush - time.monotonic(), self._BATCH_S)))
                batch = self._take_locked()
            try:
                stop = self._write_batch(batch)
            except Exception as exc:  # noqa: BLE001
                self._fail(exc)
                stop = self._drain_failed(batch)
            if self._state == "recording" and (stop or time.monotonic() >= next_flush):
                try:
                    self._flush()
                except Exception as exc:  # noqa: BLE001
                    self._fail(exc)
                next_flush = time.monotonic() + self.config.flush_period_s
        self._finish()

    def _urgent(self) -> bool:
        """Whether the queue holds anything but messages (stop, a topic, a new description)."""
        q = self._queue
        return bool(q) and (q[-1][0] is None or q[0][0] is None or self._closing)

    def _drain_failed(self, batch: "deque[tuple]") -> bool:
        """After a failure: count the rest of the batch as dropped; True if it held the stop."""
        stop = any(item[0] is None and item[1] == _STOP for item in batch)
        with self._lock:
            self._drop_locked(batch, taken=True)
        return stop

    def _write_batch(self, batch: "deque[tuple]") -> bool:
        """Write a batch of queue items in order; True once the stop item was reached. On an
        exception, the items not yet consumed stay in ``batch``."""
        if self._state != "recording":
            return self._drain_failed(batch)
        cfg = self.config
        split = cfg.max_bag_size_mb > 0 or cfg.max_bag_duration_s > 0
        desc_topic = cfg.description_topic
        pop = batch.popleft
        while batch:
            item = pop()
            topic = item[0]
            if topic is None:
                if item[1] == _STOP:
                    with self._lock:  # nothing follows the stop item, but be exact
                        self._drop_locked(batch, taken=True)
                    return True
                self._control(item)
                continue
            mcap = self._mcap
            if split:
                self._current = topic  # not in a chunk yet: _fail must count it if we fail now
                self._maybe_split(item[2], len(item[1]))
                self._current = None
                mcap = self._mcap
            cid = self._channels.get(topic)
            if cid is None:  # writes Schema and Channel records: may fail like any write
                self._current = topic
                cid = self._channel(self._topics[topic])
                self._current = None
            if topic == desc_topic:
                self._record_description(cid, item)
                continue
            pub = item[3]
            if pub == HEADER_STAMP:
                pub = header_stamp_ns(item[1]) or item[2]
            mcap.add_message(cid, item[2], pub, item[1])
            if self._file_first_ns is None:
                self._file_first_ns = item[2]
            if mcap.size >= self._chunk_limit:
                self._flush_chunk()
        return False

    def _record_description(self, cid: int, item: tuple) -> None:
        _topic, data, log_ns, pub_ns = item
        if pub_ns == HEADER_STAMP:
            pub_ns = header_stamp_ns(data) or log_ns
        text = cdr_string_value(data)
        if text is not None:
            self._description_raw = bytes(data)
            with self._lock:
                self._description = text
            self._file_written_desc = text
        assert self._mcap is not None
        self._mcap.add_message(cid, log_ns, pub_ns, data)
        if self._file_first_ns is None:
            self._file_first_ns = log_ns
        if self._meta_desc != self._description:
            self._write_metadata_record()  # the record follows the description in use
        if self._mcap.size >= self._chunk_limit:
            self._flush_chunk()

    def _control(self, item: tuple) -> None:
        kind = item[1]
        if kind == _TOPIC:
            topic: TopicInfo = item[2]
            # The first registration of a name wins for the whole recording: a channel cannot
            # change once written, and metadata.yaml must describe the channels in the files
            # (readers such as rosbags match them by QoS too). The injected description copy
            # registers /robot_description as reliable + transient local.
            if topic.name not in self._topics:
                self._topics[topic.name] = topic
                if self._mcap is not None:
                    self._channel(topic)
        elif kind == _DESC:
            if item[2] != self._file_written_desc:
                self._description_raw = None
                self._write_description(self._clock_ns())
                self._write_metadata_record()
        elif kind == _META:
            self._w_parameters = item[2]
            self._write_metadata_record()

    def _channel(self, info: TopicInfo) -> int:
        assert self._mcap is not None
        cid = self._channels.get(info.name)
        if cid is not None:
            return cid
        sid = self._schemas.get(info.type)
        if sid is None:
            definition = message_definition(info.type)
            sid = self._mcap.add_schema(info.type, SCHEMA_ENCODING, definition.encode())
            self._schemas[info.type] = sid
        meta = {"offered_qos_profiles": qos_yaml(info.offered_qos_profiles)}
        h = type_description_hash(info.type)
        if h:
            meta["topic_type_hash"] = h
        cid = self._mcap.add_channel(info.name, MESSAGE_ENCODING, sid, meta)
        self._channels[info.name] = cid
        self._channel_topics[cid] = info.name
        return cid

    def _open_file(self, log_ns: int | None = None) -> None:
        self._file_index += 1
        path = self._file_path(self._file_index)
        self._stream = _CountingFile(self._opener(str(path)))
        chunk = self.config.chunk_size
        if self.config.max_bag_size_mb > 0:
            chunk = max(4096, min(chunk, int(self.config.max_bag_size_mb * 1e6 / 4)))
        self._chunk_limit = chunk
        self._mcap = McapFile(self._stream, self.config.compression, PROFILE,
                              f"dyn_node/{__version__}")
        self._channels, self._channel_topics, self._schemas = {}, {}, {}
        self._file_counts = {}
        self._file_start = self._file_end = 0
        self._file_first_ns = None
        for info in list(self._topics.values()):
            self._channel(info)
        # The copy of a split file takes the log time of the message that caused the split, so
        # it lies inside the file's time range.
        self._write_description(self._clock_ns() if log_ns is None else log_ns)
        self._write_metadata_record()
        self._flush()

    def _write_description(self, log_ns: int) -> None:
        with self._lock:
            text = self._description
        if not text and self._description_raw is None:
            return
        raw = self._description_raw if self._description_raw is not None else cdr_string(text)
        topic = self.config.description_topic
        if topic not in self._topics:
            self._topics[topic] = TopicInfo(topic, DESCRIPTION_TYPE, (qos_profile_dict(
                durability="transient_local", depth=1),))
        assert self._mcap is not None
        self._mcap.add_message(self._channel(self._topics[topic]), log_ns, log_ns, raw)
        self._pending_copies += 1
        self._file_written_desc = text

    def _write_metadata_record(self) -> None:
        assert self._mcap is not None
        with self._lock:
            desc = self._description
        params, effective_ns = self._w_parameters
        self._meta_desc = desc
        values = {"robot_description": desc, "parameters": params, "version": __version__}
        if effective_ns is not None:
            values["effective_log_time_ns"] = str(effective_ns)
        self._mcap.add_metadata(METADATA_RECORD, values)

    def _maybe_split(self, log_ns: int, size: int) -> None:
        # Only split a file that holds a recorded message: a file with just the description
        # copy cannot get smaller, and splitting it again would loop.
        cfg = self.config
        first = self._file_first_ns
        if first is None or self._stream is None or self._mcap is None:
            return
        too_long = cfg.max_bag_duration_s > 0 and log_ns - first >= cfg.max_bag_duration_s * 1e9
        # Compressed size is known only for closed chunks; the open chunk counts uncompressed.
        too_big = cfg.max_bag_size_mb > 0 and \
            self._stream.tell() + self._mcap.size + size >= cfg.max_bag_size_mb * 1e6
        if too_long or too_big:
            self._close_file()
            self._open_file(log_ns)
            self._write_metadata_yaml()

    def _flush_chunk(self, final: bool = False) -> None:
        """Close the open chunk and hand it to the OS; its messages then count as written
        (also when writing its message indexes fails afterwards: they are in the file)."""
        assert self._mcap is not None
        if final:
            self._mcap.finish(self._commit)
        else:
            self._mcap.close_chunk(self._commit)

    def _flush(self) -> None:
        """Close the open chunk, flush it to the OS and fsync (the periodic durability point)."""
        if self._mcap is None or self._stream is None:
            return
        self._flush_chunk()
        self._stream.flush()
        if self.config.fsync:
            self._stream.fsync()

    def _commit(self, index: dict[int, list[int]], lo: int, hi: int) -> None:
        """A chunk reached the file: its messages (from its message index) count as written."""
        topics = self._channel_topics
        desc_topic = self.config.description_topic
        copies, self._pending_copies = self._pending_copies, 0
        with self._lock:
            for cid, entries in index.items():
                topic = topics[cid]
                n = len(entries) // 2
                self._file_counts[topic] = self._file_counts.get(topic, 0) + n
                if topic == desc_topic:
                    n -= copies
                if n:
                    self._counts.setdefault(topic, [0, 0, 0])[1] += n
            self._description_copies += copies
        self._file_start = lo if self._file_start == 0 else min(lo, self._file_start)
        self._file_end = max(hi, self._file_end)

    def _close_file(self) -> None:
        assert self._mcap is not None and self._stream is not None
        self._flush_chunk(final=True)
        self._stream.flush()
        if self.config.fsync:
            self._stream.fsync()
        self._stream.close()
        self._files.append(self._file_info())
        self._mcap, self._stream = None, None

    def _file_info(self) -> FileInfo:
        return FileInfo(str(self._file_path(self._file_index)), self._file_start,
                        self._file_end, sum(self._file_counts.values()), dict(self._file_counts))

    def _fail(self, exc: BaseException) -> None:
        name = errno.errorcode.get(getattr(exc, "errno", None) or -1, type(exc).__name__)
        with self._lock:
            # Messages in the chunk that did not reach the disk are lost: count them.
            if self._mcap is not None:
                desc_topic = self.config.description_topic
                for cid, entries in self._mcap.index.items():
                    topic = self._channel_topics[cid]
                    n = len(entries) // 2 - (self._pending_copies if topic == desc_topic else 0)
                    if n:
                        self._counts.setdefault(topic, [0, 0, 0])[2] += n
                self._mcap.index = {}
                self._mcap.parts = []
            self._pending_copies = 0
            if self._current is not None:
                self._counts[self._current][2] += 1
                self._current = None
            self._drop_locked(self._queue, taken=False)
            self._set_state_locked("error", f"write failed ({name}): {exc}")
            # What was flushed stays on disk; keep the partial file for dyn-bag-recover.
            if self._mcap is not None and self._stream is not None:
                self._files.append(self._file_info())
        if self._stream is not None:
            try:
                self._stream.close()
            except Exception:  # noqa: BLE001 - the file is already broken
                pass
        self._mcap, self._stream = None, None

    def _write_metadata_yaml(self) -> None:
        with self._lock:
            files = list(self._files)
            counts = {t: {"received": c[0], "written": c[1], "dropped": c[2]}
                      for t, c in self._counts.items()}
            extra = {"version": __version__, "state": self._state, "error": self._error,
                     "description_copies": self._description_copies, "topics": counts}
        if self._mcap is not None:
            files.append(self._file_info())
        topics = [t for t in self._topics.values()]
        write_metadata_yaml(self.path, bag_metadata(topics, files, extra),
                            fsync=self.config.fsync)

    def _finish(self) -> None:
        if self._state == "recording" and self._mcap is not None:
            try:
                self._close_file()
            except Exception as exc:  # noqa: BLE001
                self._fail(exc)
        with self._lock:
            if self._state == "recording":
                self._set_state_locked("closed")
            # A caller that passed write()'s check just before close() may have queued after
            # the stop item; a message queued later still shows as dropped in stats().
            self._drop_locked(self._queue, taken=False)
        try:
            self._write_metadata_yaml()
        except Exception as exc:  # noqa: BLE001 - e.g. the disk is still full
            with self._lock:
                self._error = self._error or f"metadata.yaml not written: {exc}"
        _LIVE.discard(self)
        self._closed.set()
