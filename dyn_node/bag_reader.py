"""Streaming, CRC-checked reader of MCAP files and rosbag2 bag directories (no rclpy).

Reads one top-level record at a time (a chunk is at most a few MB), so a bag larger than memory
streams in constant memory. Damage never raises mid-stream: a chunk whose CRC does not match or
that cannot be decompressed or parsed, and a file that ends early, are reported as
:class:`UnreadableRange` (the log-time range, ns since the epoch, that was lost) and reading goes
on with the next readable record or file.

Accepts: a rosbag2 directory (``metadata.yaml`` + ``*.mcap``, ours or recorded elsewhere with
``ros2 bag record -s mcap``), a directory of ``.mcap`` files, or a single ``.mcap`` file.
"""
from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, NamedTuple, Sequence

import yaml

from .errors import STATE_ERROR, DynNodeError

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_METADATA, OP_METADATA_INDEX, OP_DATA_END = 0x0C, 0x0D, 0x0F

_U8_U64 = struct.Struct("<BQ")
_MSG_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed crc
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


class BagError(DynNodeError):
    """The bag cannot be used at all (missing, not MCAP, nothing readable)."""

    failure_label = STATE_ERROR


class BagMessage(NamedTuple):
    """One message as recorded: raw CDR ``data``; times in ns since the epoch."""

    topic: str
    channel: "ChannelInfo"
    log_time_ns: int
    publish_time_ns: int
    data: bytes
    sequence: int


@dataclass(frozen=True)
class UnreadableRange:
    """A log-time range (ns since the epoch; ``None``: unknown, i.e. to the end of the recording)
    that could not be read, and why."""

    start_ns: int | None
    end_ns: int | None
    reason: str
    file: str


@dataclass(frozen=True)
class ChannelInfo:
    topic: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    metadata: dict


@dataclass
class BagStats:
    """What the reader saw: per-topic counts and log-time span of every readable message."""

    message_counts: dict[str, int] = field(default_factory=dict)
    first_ns: int | None = None
    last_ns: int | None = None
    bytes_read: int = 0
    chunks: int = 0
    chunks_bad: int = 0
    crc_checked_chunks: int = 0
    data_crc: dict[str, str] = field(default_factory=dict)  # file -> ok | mismatch | absent | unchecked


def _str(buf: memoryview, off: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(buf, off)
    off += 4
    return bytes(buf[off:off + n]).decode("utf-8", "replace"), off + n


def _map(buf: memoryview, off: int) -> tuple[dict[str, str], int]:
    (n,) = _U32.unpack_from(buf, off)
    off += 4
    end = off + n
    out: dict[str, str] = {}
    while off < end:
        k, off = _str(buf, off)
        v, off = _str(buf, off)
        out[k] = v
    return out, end


def _decompress(kind: str, data: bytes, size: int) -> bytes:
    if kind == "":
        return data
    if kind == "zstd":
        import zstandard
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if kind == "lz4":
        import lz4.frame
        return lz4.frame.decompress(data)
    raise ValueError(f"unsupported chunk compression '{kind}'")


def bag_files(path: str | Path) -> tuple[list[Path], dict | None]:
    """The MCAP files of a bag in recording order, and its parsed rosbag2 ``metadata.yaml``."""
    p = Path(path)
    if not p.exists():
        raise BagError(f"bag {p} does not exist", code="bag_missing")
    if p.is_file():
        return [p], None
    info = None
    meta = p / "metadata.yaml"
    if meta.is_file():
        try:
            info = (yaml.safe_load(meta.read_text()) or {}).get("rosbag2_bagfile_information")
        except yaml.YAMLError:
            info = None
    files: list[Path] = []
    if info and info.get("relative_file_paths"):
        files = [p / f for f in info["relative_file_paths"] if (p / f).is_file()]
    if not files:
        files = sorted(p.glob("*.mcap"), key=lambda f: (len(f.name), f.name))
    if not files:
        raise BagError(f"{p} holds no .mcap file", code="bag_empty")
    return files, info


def metadata_span_ns(info: dict | None) -> tuple[int | None, int | None]:
    """(start, end) ns from a rosbag2 metadata.yaml, when it has them."""
    try:
        start = int(info["starting_time"]["nanoseconds_since_epoch"])
        return start, start + int(info["duration"]["nanoseconds"])
    except (TypeError, KeyError, ValueError):
        return None, None


class BagReader:
    """Stream the messages of a bag in file (= recording) order.

    ``topics``: only these topics are yielded (all are counted). After iteration, ``stats``,
    ``channels``, ``metadata`` (MCAP metadata records by name) and ``unreadable`` describe what
    was read and what was lost.
    """

    def __init__(self, path: str | Path, topics: Sequence[str] | None = None):
        self.path = Path(path)
        self.files, self.info = bag_files(path)
        self.topics = set(topics) if topics else None
        self.stats = BagStats()
        self.channels: dict[str, ChannelInfo] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.unreadable: list[UnreadableRange] = []
        self.readable_files = 0

    # --- pre-scan: the description is needed before replay starts ------------------------------
    def peek_metadata(self, name: str) -> dict[str, str] | None:
        """The first MCAP metadata record ``name`` of any file, via the summary when the file has
        one, else by scanning the file's records until it appears. Never raises for damage."""
        for f in self.files:
            try:
                found = _metadata_from_summary(f, name)
                if found is None:
                    found = _metadata_by_scan(f, name)
            except (OSError, struct.error, ValueError):
                found = None
            if found is not None:
                return found
        return None

    def peek_first(self, topic: str, limit_bytes: int = 64 << 20) -> BagMessage | None:
        """The first message on ``topic`` within the first ``limit_bytes`` of each file."""
        for f in self.files:
            sub = _FileReader(f, {topic}, BagStats(), limit_bytes=limit_bytes)
            for m in sub.messages():
                if m.topic == topic:
                    return m
        return None

    def known_topics(self) -> set[str] | None:
        """Every topic of the bag from metadata.yaml or the files' summaries; None if unknown
        (a file without a summary, e.g. truncated)."""
        if self.info and self.info.get("topics_with_message_count"):
            try:
                return {t["topic_metadata"]["name"] for t in self.info["topics_with_message_count"]}
            except (KeyError, TypeError):
                pass
        topics: set[str] = set()
        for f in self.files:
            try:
                recs = _summary_records(f)
            except (OSError, struct.error, ValueError):
                return None
            if recs is None:
                return None
            for op, body in recs:
                if op == OP_CHANNEL:
                    topics.add(_str(body, 4)[0])
        return topics

    # --- streaming ---------------------------------------------------------------------------
    def messages(self) -> Iterator[BagMessage]:
        for f in self.files:
            fr = _FileReader(f, self.topics, self.stats)
            yield from fr.messages()
            self.channels.update({c.topic: c for c in fr.channels.values()})
            for k, v in fr.metadata.items():
                self.metadata.setdefault(k, v)
            self.unreadable.extend(fr.unreadable)
            self.readable_files += fr.readable
        if self.info and self.unreadable:
            self._bound_open_ranges()

    def _bound_open_ranges(self) -> None:
        # A range that runs "to the end of the recording" ends where metadata.yaml says the bag ends.
        _, end = metadata_span_ns(self.info)
        if end is None:
            return
        self.unreadable = [UnreadableRange(r.start_ns, end, r.reason, r.file)
                           if r.end_ns is None and (r.start_ns is None or r.start_ns <= end) else r
                           for r in self.unreadable]


class _FileReader:
    """One MCAP file, record by record. Damage becomes UnreadableRange entries, never exceptions."""

    def __init__(self, path: Path, topics: set[str] | None, stats: BagStats,
                 limit_bytes: int | None = None):
        self.path = path
        self.topics = topics
        self.stats = stats
        self.limit = limit_bytes
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.channels: dict[int, ChannelInfo] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.unreadable: list[UnreadableRange] = []
        self.readable = 0
        self.last_ns: int | None = None  # last log time read from this file
        self.stop_on_metadata: str | None = None

    def _lost(self, start: int | None, end: int | None, reason: str) -> None:
        self.unreadable.append(UnreadableRange(start, end, reason, self.path.name))

    def messages(self) -> Iterator[BagMessage]:
        name = self.path.name
        try:
            fh = open(self.path, "rb")
        except OSError as exc:
            self._lost(None, None, f"{name}: cannot open ({exc.strerror})")
            return
        with fh:
            size = os.fstat(fh.fileno()).st_size
            magic = fh.read(8)
            if magic != MAGIC:
                self._lost(None, None, f"{name}: not an MCAP file (bad magic)")
                return
            self.readable = 1
            crc = zlib.crc32(magic)
            pos = 8
            clean_end = False
            cut_start: int | None = None
            while True:
                if self.limit is not None and pos > self.limit:
                    return
                if self.stop_on_metadata and self.stop_on_metadata in self.metadata:
                    return
                head = fh.read(9)
                if len(head) == 0:
                    break
                if len(head) < 9:
                    break
                op, length = _U8_U64.unpack(head)
                if length > size - pos - 9:
                    # The record runs past the end of the file: truncated. A cut chunk still
                    # tells from its header where its lost messages start.
                    if op == OP_CHUNK:
                        part = fh.read(16)
                        if len(part) == 16 and _U64.unpack_from(part, 0)[0]:
                            cut_start = _U64.unpack_from(part, 0)[0]
                    break
                body = fh.read(length)
                self.stats.bytes_read += 9 + length
                if op == OP_DATA_END:
                    (want,) = _U32.unpack_from(body, 0) if length >= 4 else (0,)
                    self.stats.data_crc[name] = ("absent" if want == 0 else
                                                 "ok" if want == crc else "mismatch")
                    # A mismatch with every chunk intact means damage outside the chunks
                    # (message indexes): nothing is lost, so it is a finding, not a range.
                    clean_end = True
                    break
                crc = zlib.crc32(body, zlib.crc32(head, crc))
                pos += 9 + length
                view = memoryview(body)
                if op == OP_CHUNK:
                    yield from self._chunk(view)
                elif op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_METADATA):
                    try:
                        m = self._record(op, view)
                    except (struct.error, UnicodeDecodeError, IndexError, ValueError):
                        self._lost(self.last_ns, None, f"{name}: malformed record at byte {pos}")
                        return
                    if m is not None:
                        yield m
                elif op == OP_FOOTER:
                    clean_end = True
                    break
            if not clean_end:
                self.stats.data_crc.setdefault(name, "unchecked")
                start = cut_start if cut_start is not None else self.last_ns
                self._lost(start, None, f"{name}: file ends early at byte {pos} of {size} "
                           "(truncated; no data-end record): nothing after "
                           + ("the last readable message" if start is not None else "the header")
                           + " could be read")

    def _chunk(self, view: memoryview) -> Iterator[BagMessage]:
        stats = self.stats
        stats.chunks += 1
        try:
            start, end, usize, ucrc = _CHUNK_HEAD.unpack_from(view, 0)
            comp, off = _str(view, 28)
            (rlen,) = _U64.unpack_from(view, off)
            off += 8
            if off + rlen > len(view):
                raise ValueError("records run past the chunk")
            data = _decompress(comp, bytes(view[off:off + rlen]), usize)
            if len(data) != usize:
                raise ValueError(f"decompressed {len(data)} bytes, header says {usize}")
            if ucrc:
                stats.crc_checked_chunks += 1
                if zlib.crc32(data) != ucrc:
                    raise ValueError("chunk CRC mismatch")
            msgs = self._records(bytes(data))
        except Exception as exc:  # any decoder error means: this chunk's time range is lost
            stats.chunks_bad += 1
            try:
                start, end = _CHUNK_HEAD.unpack_from(view, 0)[:2]
            except struct.error:
                start = end = None
            self._lost(start, end, f"{self.path.name}: damaged chunk ({exc})")
            if end is not None:
                self.last_ns = max(self.last_ns or end, end)
            return
        yield from msgs

    def _records(self, buf: bytes) -> list[BagMessage]:
        """The messages of one decompressed chunk. Messages are handled inline (the hot loop of
        a replay): the same counts, span and messages as :meth:`_record` gives one by one, and
        stats updated as far as the chunk was read when it turns out malformed."""
        off, n = 0, len(buf)
        head = _U8_U64.unpack_from
        msg_head = _MSG_HEAD.unpack_from
        channels = self.channels
        topics = self.topics
        st = self.stats
        counts = st.message_counts
        first, last, flast = st.first_ns, st.last_ns, self.last_ns
        new = tuple.__new__
        out: list[BagMessage] = []
        try:
            while off < n:
                op, length = head(buf, off)
                off += 9
                end = off + length
                if end > n:
                    raise ValueError("record runs past the end of the chunk")
                if op == OP_MESSAGE:
                    if length < 22:  # raises the error _record gives for a short message record
                        _MSG_HEAD.unpack_from(memoryview(buf)[off:end], 0)
                    cid, seq, log_ns, pub_ns = msg_head(buf, off)
                    ch = channels.get(cid)
                    if ch is None:
                        raise ValueError(f"message on unknown channel {cid}")
                    topic = ch.topic
                    counts[topic] = counts.get(topic, 0) + 1
                    if first is None or log_ns < first:
                        first = log_ns
                    if last is None or log_ns > last:
                        last = log_ns
                    if flast is None or log_ns > flast:
                        flast = log_ns
                    if topics is None or topic in topics:
                        out.append(new(BagMessage, (topic, ch, log_ns, pub_ns, buf[off + 22:end], seq)))
                else:
                    m = self._record(op, memoryview(buf)[off:end])
                    if m is not None:
                        out.append(m)
                off = end
        finally:
            st.first_ns, st.last_ns, self.last_ns = first, last, flast
        return out

    def _record(self, op: int, body: memoryview) -> BagMessage | None:
        if op == OP_MESSAGE:
            cid, seq, log_ns, pub_ns = _MSG_HEAD.unpack_from(body, 0)
            ch = self.channels.get(cid)
            if ch is None:
                raise ValueError(f"message on unknown channel {cid}")
            st = self.stats
            topic = ch.topic
            st.message_counts[topic] = st.message_counts.get(topic, 0) + 1
            if st.first_ns is None or log_ns < st.first_ns:
                st.first_ns = log_ns
            if st.last_ns is None or log_ns > st.last_ns:
                st.last_ns = log_ns
            self.last_ns = log_ns if self.last_ns is None or log_ns > self.last_ns else self.last_ns
            if self.topics is not None and topic not in self.topics:
                return None
            return BagMessage(topic, ch, log_ns, pub_ns, bytes(body[22:]), seq)
        if op == OP_SCHEMA:
            (sid,) = _U16.unpack_from(body, 0)
            sname, off = _str(body, 2)
            enc, off = _str(body, off)
            (dlen,) = _U32.unpack_from(body, off)
            self.schemas[sid] = (sname, enc, bytes(body[off + 4:off + 4 + dlen]))
        elif op == OP_CHANNEL:
            cid, sid = struct.unpack_from("<HH", body, 0)
            topic, off = _str(body, 4)
            menc, off = _str(body, off)
            meta, off = _map(body, off)
            sname, senc, sdata = self.schemas.get(sid, ("", "", b""))
            self.channels[cid] = ChannelInfo(topic, sname, senc, sdata, menc, meta)
        elif op == OP_METADATA:
            mname, off = _str(body, 0)
            meta, _ = _map(body, off)
            self.metadata.setdefault(mname, meta)
        return None


def _summary_records(path: Path) -> list[tuple[int, memoryview]] | None:
    """The records of a file's summary section, or None when it has none (or no footer)."""
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if size < 8 + 9 + 20 + 8:
            return None
        fh.seek(size - 8 - 29)
        tail = fh.read(29 + 8)
        if tail[-8:] != MAGIC or tail[0] != OP_FOOTER:
            return None
        summary_start = struct.unpack_from("<Q", tail, 9)[0]
        if summary_start == 0 or summary_start >= size:
            return None
        fh.seek(summary_start)
        summary = memoryview(fh.read(size - 8 - 29 - summary_start))
    out = []
    off = 0
    while off + 9 <= len(summary):
        op, length = _U8_U64.unpack_from(summary, off)
        out.append((op, summary[off + 9:off + 9 + length]))
        off += 9 + length
    return out


def _metadata_from_summary(path: Path, name: str) -> dict[str, str] | None:
    """The metadata record ``name`` found through the summary's metadata index, if any."""
    for op, body in _summary_records(path) or ():
        if op != OP_METADATA_INDEX:
            continue
        moff, mlen = struct.unpack_from("<QQ", body, 0)
        if _str(body, 16)[0] != name:
            continue
        with open(path, "rb") as fh:
            fh.seek(moff)
            rec = memoryview(fh.read(mlen))
        if len(rec) < 9 or rec[0] != OP_METADATA:
            return None
        _rname, o = _str(rec, 9)
        return _map(rec, o)[0]
    return None


def _metadata_by_scan(path: Path, name: str) -> dict[str, str] | None:
    fr = _FileReader(path, set(), BagStats())
    fr.stop_on_metadata = name
    for _ in fr.messages():
        if name in fr.metadata:
            break
    return fr.metadata.get(name)


# --- CDR decoding ----------------------------------------------------------------------------
def _empty():
    import numpy as np

    e = np.empty(0)
    e.setflags(write=False)
    return e


class JointStateData(NamedTuple):
    """A decoded sensor_msgs/JointState: header stamp (sec, nanosec as in the message, and ns);
    arrays as read-only float64 NumPy arrays."""

    sec: int
    nanosec: int
    stamp_ns: int
    frame_id: str
    names: tuple[str, ...]
    position: "np.ndarray"
    velocity: "np.ndarray"
    effort: "np.ndarray"


_EMPTY = _empty()
_LE_U32 = struct.Struct("<I")
_BE_U32 = struct.Struct(">I")
_name_cache: dict[bytes, tuple[str, ...]] = {}
_last_names: list = [b"", ()]  # raw name section of the last little-endian message, and its names


def decode_joint_state(data: bytes) -> JointStateData:
    """Decode the CDR bytes of a sensor_msgs/JointState (little- or big-endian XCDR1).

    Written by hand because it is the hot path of an audit (1 kHz for hours); it is checked
    against rclpy's serializer in the tests. The name list, the same in almost every message, is
    cached by its raw bytes. Raises ValueError on bytes that do not parse.
    """
    import numpy as np

    if len(data) < 12 or data[0] != 0 or data[1] not in (0, 1):
        raise ValueError("not a CDR encapsulation header")
    le = data[1] == 1
    u32 = (_LE_U32 if le else _BE_U32).unpack_from
    buf = memoryview(data)[4:]
    n = len(buf)
    try:
        sec, nsec = struct.unpack_from("<iI" if le else ">iI", buf, 0)
        ln = u32(buf, 8)[0]
        off = 12 + ln
        if off > n:
            raise ValueError("JointState CDR string runs past the end")
        frame = bytes(buf[12:off - 1]).decode("utf-8", "replace") if ln else ""
        off = (off + 3) & ~3
        start = off
        last_raw, last_names = _last_names
        end = start + len(last_raw)
        if last_raw and end <= n and buf[start:end] == last_raw:
            names, off = last_names, end  # the usual case: the same names as the last message
        else:
            count = u32(buf, off)[0]
            off += 4
            if count > n:
                raise ValueError("JointState CDR name count is impossible")
            for _ in range(count):
                off = (off + 3) & ~3
                ln = u32(buf, off)[0]
                off += 4 + ln
            if off > n:
                raise ValueError("JointState CDR names run past the end")
            raw = bytes(buf[start:off])
            names = _name_cache.get(raw)
            if names is None:
                names = _parse_names(raw, u32)
                if len(_name_cache) < 64:
                    _name_cache[raw] = names
            if le:
                _last_names[:] = [raw, names]
        layout = _layouts.get((off, n)) if le else None
        if layout is not None and layout[0].unpack_from(buf, off) == layout[1]:
            # Same array sizes where the last such message had them: one view, three slices.
            _, _, first, span, parts = layout
            whole = np.frombuffer(buf, dtype="<f8", count=span, offset=first) if span else _EMPTY
            arrays = [whole[i:j] if j else _EMPTY for i, j in parts]
        else:
            arrays = []
            dt = "<f8" if le else ">f8"
            off0, count_at, counts, starts = off, [], [], []
            for _ in range(3):
                off = (off + 3) & ~3
                count = u32(buf, off)[0]
                count_at.append(off)
                counts.append(count)
                off += 4
                if count:
                    off = (off + 7) & ~7
                    if off + 8 * count > n:
                        raise ValueError("JointState CDR array runs past the end")
                    a = np.frombuffer(buf, dtype=dt, count=count, offset=off)
                    arrays.append(a.astype(float) if not le else a)  # read-only view
                    starts.append(off)
                    off += 8 * count
                else:
                    arrays.append(_EMPTY)
                    starts.append(None)
            if le and len(_layouts) < 64:
                _layouts[(off0, n)] = _layout(off0, count_at, counts, starts)
    except struct.error as exc:
        raise ValueError(f"JointState CDR ends early ({exc})") from None
    return JointStateData(sec, nsec, sec * 1_000_000_000 + nsec, frame, names, *arrays)


_layouts: dict[tuple[int, int], tuple] = {}  # (offset after the names, size) → array layout


def _layout(off0: int, count_at: list[int], counts: list[int], starts: list[int | None]) -> tuple:
    """The little-endian array layout of a JointState whose arrays start at ``off0``: a Struct
    reading the three counts, the counts, and where the doubles lie (all 8-aligned, so one
    float64 view from the first array covers all three)."""
    fmt, pos = "<", off0
    for at in count_at:
        fmt += f"{at - pos}xI"
        pos = at + 4
    present = [s for s in starts if s is not None]
    if not present:
        return struct.Struct(fmt), tuple(counts), 0, 0, [(0, 0)] * 3
    first = present[0]
    last = max(s + 8 * c for s, c in zip(starts, counts) if s is not None)
    parts = [((s - first) // 8, (s - first) // 8 + c) if s is not None else (0, 0)
             for s, c in zip(starts, counts)]
    return struct.Struct(fmt), tuple(counts), first, (last - first) // 8, parts


class JointStateBatch(NamedTuple):
    """N decoded JointStates with one byte layout (same names, frame and array sizes): header
    stamps as (N,) int64 arrays, value arrays N×len(names) float64 (None when the messages have
    none). Row k equals :func:`decode_joint_state` of message k."""

    names: tuple[str, ...]
    sec: "np.ndarray"
    nanosec: "np.ndarray"
    stamp_ns: "np.ndarray"
    position: "np.ndarray | None"
    velocity: "np.ndarray | None"
    effort: "np.ndarray | None"


def _array_spans(data: bytes) -> tuple[list[tuple[int, int]], list[tuple[int, int]]] | None:
    """Byte offsets (into ``data``) and counts of position, velocity and effort of a
    little-endian JointState, and the (offset, length) of every alignment padding run; None when
    it is not one that parses. Padding matters because CDR leaves it unspecified: Fast CDR
    serialises whatever the buffer held there, so two equal messages may differ in those bytes."""
    if len(data) < 12 or data[0] != 0 or data[1] != 1:
        return None
    u32 = _LE_U32.unpack_from
    n = len(data)
    pads: list[tuple[int, int]] = []

    def align(off: int, to: int) -> int:
        aligned = 4 + ((off - 4 + to - 1) & ~(to - 1))
        if aligned > off:
            pads.append((off, aligned - off))
        return aligned

    try:
        off = align(16 + u32(data, 12)[0], 4)
        count = u32(data, off)[0]
        off += 4
        if count > n:
            return None
        for _ in range(count):
            off = align(off, 4)
            off += 4 + u32(data, off)[0]
        spans = []
        for _ in range(3):
            off = align(off, 4)
            count = u32(data, off)[0]
            off += 4
            if count:
                off = align(off, 8)
            if off + 8 * count > n:
                return None
            spans.append((off, count))
            off += 8 * count
    except struct.error:
        return None
    return spans, pads


def decode_joint_state_batch(datas: Sequence[bytes]) -> JointStateBatch | None:
    """Decode N little-endian JointStates of equal size at once, or None unless every message
    has exactly the first one's bytes outside its stamp, its float64 values and its alignment
    padding (then the caller decodes them one by one with :func:`decode_joint_state`, which
    reports the bad ones)."""
    import numpy as np

    if not datas:
        return None
    first = datas[0]
    size = len(first)
    layout = _array_spans(first)
    if layout is None or any(len(d) != size for d in datas):
        return None
    spans, pads = layout
    try:
        names = decode_joint_state(first).names
    except ValueError:
        return None
    joined = b"".join(datas)
    rows = np.frombuffer(joined, dtype=np.uint8).reshape(len(datas), size)
    keep = np.ones(size, dtype=bool)
    keep[4:12] = False
    for off, count in spans:
        keep[off:off + 8 * count] = False
    for off, length in pads:
        keep[off:off + length] = False
    fixed = rows[:, keep]
    if not (fixed == fixed[0]).all():
        return None
    stride = (size,)
    sec = np.ndarray(len(datas), dtype="<i4", buffer=joined, offset=4, strides=stride).astype(np.int64)
    nsec = np.ndarray(len(datas), dtype="<u4", buffer=joined, offset=8, strides=stride).astype(np.int64)
    arrays = []
    for off, count in spans:
        if count:
            view = np.ndarray((len(datas), count), dtype="<f8", buffer=joined, offset=off,
                              strides=(size, 8))
            arrays.append(np.array(view, dtype=float))  # aligned, contiguous, writable copy
        else:
            arrays.append(None)
    return JointStateBatch(names, sec, nsec, sec * 1_000_000_000 + nsec, *arrays)


def _parse_names(raw: bytes, u32) -> tuple[str, ...]:
    count = u32(raw, 0)[0]
    off = 4
    out = []
    for _ in range(count):
        off = (off + 3) & ~3
        ln = u32(raw, off)[0]
        off += 4
        out.append(raw[off:off + ln - 1 if ln else off].decode("utf-8", "replace"))
        off += ln
    return tuple(out)


class MessageDecoder:
    """Decodes any ros2msg-schema CDR message with mcap_ros2's dynamic decoder (cached per type)."""

    def __init__(self) -> None:
        self._decoders: dict[tuple[str, bytes], object] = {}

    def decode(self, channel: ChannelInfo, data: bytes):
        key = (channel.schema_name, channel.schema_data)
        dec = self._decoders.get(key)
        if dec is None:
            from mcap_ros2._dynamic import generate_dynamic

            if channel.schema_encoding != "ros2msg":
                raise ValueError(f"schema encoding '{channel.schema_encoding}' is not ros2msg")
            types = generate_dynamic(channel.schema_name, channel.schema_data.decode())
            dec = self._decoders[key] = types[channel.schema_name]
        return dec(data)
