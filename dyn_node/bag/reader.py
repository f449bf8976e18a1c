"""Streaming, CRC-checked reader of MCAP files and rosbag2 bag directories (no rclpy).

Reads one top-level record at a time (a chunk is at most a few MB), so a bag larger than memory
streams in constant memory. Damage never raises mid-stream: a chunk whose CRC does not match or
that cannot be decompressed or parsed, and a file that ends early, are reported as
:class:`UnreadableRange` (the log-time range, ns since the epoch, that was lost) and reading goes
on with the next readable record or file. A string that is not UTF-8 is damage (its record is
skipped and reported), never a value with replacement characters in it.

Accepts: a rosbag2 directory (``metadata.yaml`` + ``*.mcap``, ours or recorded elsewhere with
``ros2 bag record -s mcap``), a directory of ``.mcap`` files, or a single ``.mcap`` file.
"""
from __future__ import annotations

import os
import re
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, NamedTuple, Sequence

import yaml

from dyn_node.bag.cdr import _array_spans, decode_joint_state, decode_joint_state_batch  # noqa: F401 - for tests
from dyn_node.bag.records import (_CHUNK_HEAD, _MSG_HEAD, _U8_U64, _U16, _U32, _U64, MAGIC, OP_CHANNEL,
                                  OP_CHUNK, OP_DATA_END, OP_FOOTER, OP_HEADER, OP_MESSAGE, OP_METADATA,
                                  OP_SCHEMA, _decompress, _map, _salvage_map, _str)
from dyn_node.bag.summary import (_all_metadata_from_summary, _metadata_from_summary, _summary_records,
                                  damaged_message_indexes, index_damage_note)
from dyn_node.errors import STATE_ERROR, DynNodeError


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
    undecodable_messages: int = 0  # on a channel whose schema could not be read (not yielded)
    notes: list[str] = field(default_factory=list)  # damage that lost nothing (rebuilt indexes)
    data_crc: dict[str, str] = field(default_factory=dict)  # file -> ok | mismatch | index_only | absent | unchecked



def bag_files(path: str | Path) -> tuple[list[Path], dict | None]:
    """The MCAP files of a bag in recording order, and its parsed rosbag2 ``metadata.yaml``."""
    p = Path(path)
    if not p.exists():
        raise BagError(f"bag {p} does not exist", code="bag_missing")
    if p.is_file():
        return [p], None
    info = _bag_info(p)
    files: list[Path] = []
    if info and info.get("relative_file_paths"):
        files = [p / f for f in info["relative_file_paths"] if (p / f).is_file()]
    if not files:
        files = sorted(p.glob("*.mcap"), key=lambda f: (len(f.name), f.name))
        # dyn-bag-recover's outputs beside the inputs would read every message twice; a
        # directory holding nothing else is a recovered bag, read as such.
        inputs = [f for f in files if not is_own_output(f)]
        files = inputs or files
    if not files:
        raise BagError(f"{p} holds no .mcap file", code="bag_empty")
    return files, info


def _bag_info(bag_dir: Path) -> dict | None:
    """The ``rosbag2_bagfile_information`` of a bag directory's metadata.yaml, or None."""
    meta = bag_dir / "metadata.yaml"
    if not meta.is_file():
        return None
    try:
        info = (yaml.safe_load(meta.read_text()) or {}).get("rosbag2_bagfile_information")
    except (yaml.YAMLError, OSError, AttributeError):
        return None
    return info if isinstance(info, dict) else None


def _file_span(entry: Any) -> tuple[int | None, int | None, int | None]:
    """(start, end, messages) of one metadata.yaml ``files`` entry (None where not given)."""
    try:
        start = int(entry["starting_time"]["nanoseconds_since_epoch"]) or None
        end = None if start is None else start + int(entry["duration"]["nanoseconds"])
    except (TypeError, KeyError, ValueError):
        start = end = None
    try:
        count = int(entry["message_count"])
    except (TypeError, KeyError, ValueError):
        count = None
    return start, end, count


def missing_files(bag_dir: str | Path, info: dict | None = None) -> list[UnreadableRange]:
    """The files metadata.yaml lists that are not in the bag directory: damage (a deleted split
    file once audited "all feasible"). Each range is the file's span from its ``files`` entry,
    else from its neighbours' (the end of the one before, the start of the one after)."""
    p = Path(bag_dir)
    info = _bag_info(p) if info is None and p.is_dir() else info
    names = (info or {}).get("relative_file_paths") or []
    if not isinstance(names, list):
        return []
    entries = {Path(str(e.get("path", ""))).name: e for e in (info or {}).get("files") or []
               if isinstance(e, dict)}
    spans = [_file_span(entries.get(Path(str(n)).name)) for n in names]
    out = []
    for i, name in enumerate(names):
        name = Path(str(name)).name
        if (p / name).is_file():
            continue
        start, end, count = spans[i]
        if start is None and i > 0:
            start = spans[i - 1][1]
        if end is None and i + 1 < len(spans):
            end = spans[i + 1][0]
        held = f", {count} messages" if count is not None else ""
        out.append(UnreadableRange(start, end, f"{name}: listed in metadata.yaml but missing{held}", name))
    return out


# dyn-bag-recover marks every file it writes: the Header's library field starts with
# OWN_LIBRARY, and its default names end with OWN_SUFFIX.
OWN_LIBRARY = "dyn-bag-recover"
OWN_SUFFIX = ".recovered.mcap"


def is_own_output(path: Path) -> bool:
    """Whether ``path`` was written by dyn-bag-recover: its name ends ``.recovered.mcap``, or its
    Header's library field starts with ``dyn-bag-recover`` (both, for every file it writes)."""
    if path.name.endswith(OWN_SUFFIX):
        return True
    try:
        with path.open("rb") as f:
            head = f.read(len(MAGIC) + 9)
            if len(head) < len(MAGIC) + 9 or head[:8] != MAGIC or head[8] != OP_HEADER:
                return False
            body = memoryview(f.read(min(_U64.unpack_from(head, 9)[0], 1 << 20)))
        _profile, off = _str(body, 0)
        library, _ = _str(body, off)
    except (OSError, ValueError, struct.error):
        return False
    return library.startswith(OWN_LIBRARY)


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

    def metadata_records(self, name: str) -> list[dict[str, str]]:
        """Every MCAP metadata record ``name`` of every file, in file order (a recorder writes
        one per configuration change). Via each file's summary, else by reading its records
        without decompressing chunks (metadata records are never inside one). Never raises for
        damage: what cannot be read is left out."""
        out: list[dict[str, str]] = []
        for f in self.files:
            try:
                found = _all_metadata_from_summary(f, name)
            except (OSError, struct.error, ValueError):
                found = None
            if found is None:
                fr = _FileReader(f, set(), BagStats())
                fr.skip_chunks = True
                for _ in fr.messages():
                    pass
                found = [v for k, v in fr.metadata_all if k == name]
            out.extend(found)
        return out

    def damaged_metadata_records(self, name: str) -> list[tuple[dict[str, str], list[str]]]:
        """The MCAP metadata records ``name`` that :meth:`metadata_records` leaves out because a
        string in them is not UTF-8: (the fields that still decode, the keys that do not), in
        file order. Reading them reports them in :attr:`unreadable` no more than streaming does."""
        out: list[tuple[dict[str, str], list[str]]] = []
        for f in self.files:
            fr = _FileReader(f, set(), BagStats())
            fr.skip_chunks = True
            for _ in fr.messages():
                pass
            out.extend((good, bad) for k, good, bad in fr.metadata_damaged if k == name)
        return out

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
        self.unreadable.extend(missing_files(self.path, self.info) if self.path.is_dir() else [])
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
        # Channels whose (non-zero) schema id no readable Schema record defines: their messages
        # cannot be decoded, so they are counted as lost, per channel [sid, count, first, last].
        self.orphans: dict[int, ChannelInfo] = {}
        self.orphan_lost: dict[int, list] = {}
        self.last_ns: int | None = None  # last log time read from this file
        self.stop_on_metadata: str | None = None
        self.metadata_all: list[tuple[str, dict[str, str]]] = []  # every record, in file order
        self.skip_chunks = False  # a metadata scan: chunks hold no metadata records
        # Metadata records skipped as damaged (a string that is not UTF-8): (name, the fields
        # that still decode, the keys that do not), for a reader that wants to say what was lost.
        self.metadata_damaged: list[tuple[str, dict[str, str], list[str]]] = []

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
            # Records that cannot be parsed are skipped (their length is known), as
            # dyn-bag-recover does; the lost range runs from the last message read before them
            # to the first one read after them: [start, reason, records skipped].
            skipped: list | None = None
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
                    self._data_end(body, crc, skipping=skipped is not None)
                    clean_end = True
                    break
                crc = zlib.crc32(body, zlib.crc32(head, crc))
                at = pos
                pos += 9 + length
                view = memoryview(body)
                if op == OP_CHUNK and self.skip_chunks:
                    continue
                if op == OP_CHUNK:
                    if skipped is not None and length >= 8:
                        self._lost_skipped(skipped, _U64.unpack_from(view, 0)[0])
                        skipped = None
                    yield from self._chunk(view)
                elif op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_METADATA):
                    try:
                        m = self._record(op, view)
                    except (struct.error, UnicodeDecodeError, IndexError, ValueError) as exc:
                        if skipped is None:
                            skipped = [self.last_ns, f"{name}: malformed record (opcode {op:#04x}) "
                                       f"at byte {at} skipped ({exc})", 0]
                        skipped[2] += 1
                        continue
                    if skipped is not None and op == OP_MESSAGE:
                        self._lost_skipped(skipped, _U64.unpack_from(view, 6)[0])
                        skipped = None
                    if m is not None:
                        yield m
                elif op == OP_FOOTER:
                    clean_end = True
                    break
            if skipped is not None:  # nothing readable came after it
                self._lost_skipped(skipped, None)
            self._lost_orphans()
            if not clean_end:
                self._ended_early(cut_start, pos, size)

    def _data_end(self, body: bytes, crc: int, *, skipping: bool) -> None:
        """Check the data section's CRC (``crc``: computed while reading) against Data End's."""
        name = self.path.name
        (want,) = _U32.unpack_from(body, 0) if len(body) >= 4 else (0,)
        state = "absent" if want == 0 else "ok" if want == crc else "mismatch"
        if state == "mismatch" and not self.skip_chunks:
            # Damage only in Message Indexes (the reader never uses them) lost
            # nothing: a note, as dyn-bag-recover gives, not a lost range.
            damaged = damaged_message_indexes(self.path)
            if damaged:
                state = "index_only"
                self.stats.notes.append(index_damage_note(name, damaged))
            elif not self.unreadable and not skipping:
                # Every chunk passed its CRC and every record parsed, so the damage
                # is in a record no CRC of its own covers: what was read from this
                # file cannot be vouched for (dyn-bag-recover: "some data lost").
                self._lost(None, self.last_ns, f"{name}: data section CRC mismatch "
                           "outside every chunk and message index (a record without "
                           "a CRC of its own, e.g. metadata or a message outside a "
                           "chunk, holds damaged bytes)")
        self.stats.data_crc[name] = state

    def _ended_early(self, cut_start: int | None, pos: int, size: int) -> None:
        """The file ended without Data End or Footer: truncated after ``pos``."""
        name = self.path.name
        self.stats.data_crc.setdefault(name, "unchecked")
        start = cut_start if cut_start is not None else self.last_ns
        self._lost(start, None, f"{name}: file ends early at byte {pos} of {size} "
                   "(truncated; no data-end record): nothing after "
                   + ("the last readable message" if start is not None else "the header")
                   + " could be read")

    def _orphan_message(self, cid: int, log_ns: int) -> None:
        """A message on a channel without a readable schema is lost (counted, not yielded);
        one on a channel nothing defines is a malformed record."""
        if cid not in self.orphans:
            raise ValueError(f"message on unknown channel {cid}")
        lost = self.orphan_lost[cid]
        lost[1] += 1
        lost[2] = log_ns if lost[2] is None else min(lost[2], log_ns)
        lost[3] = log_ns if lost[3] is None else max(lost[3], log_ns)
        if self.last_ns is None or log_ns > self.last_ns:
            self.last_ns = log_ns

    def _lost_orphans(self) -> None:
        for cid, (sid, n, first, last) in self.orphan_lost.items():
            if n:
                self._lost(first, last, f"{self.path.name}: {n} message(s) on "
                           f"{self.orphans[cid].topic} undecodable: their schema (id {sid}) "
                           "could not be read")
        self.stats.undecodable_messages += sum(v[1] for v in self.orphan_lost.values())

    def _lost_skipped(self, skipped: list, end_ns: int | None) -> None:
        start, reason, n = skipped
        self._lost(start, end_ns, reason + (f" and {n - 1} more record(s) after it" if n > 1 else ""))

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
                        self._orphan_message(cid, log_ns)
                        if flast is None or log_ns > flast:
                            flast = log_ns
                        off = end
                        continue
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
                self._orphan_message(cid, log_ns)
                return None
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
            info = ChannelInfo(topic, sname, senc, sdata, menc, meta)
            if sid and sid not in self.schemas:
                self.orphans[cid] = info
                self.orphan_lost.setdefault(cid, [sid, 0, None, None])
                self.channels.pop(cid, None)
            else:
                self.channels[cid] = info
                self.orphans.pop(cid, None)
        elif op == OP_METADATA:
            mname, off = _str(body, 0)
            try:
                meta, _ = _map(body, off)
            except UnicodeDecodeError:
                self.metadata_damaged.append((mname, *_salvage_map(body, off)))
                raise
            self.metadata.setdefault(mname, meta)
            self.metadata_all.append((mname, meta))
        return None




def _metadata_by_scan(path: Path, name: str) -> dict[str, str] | None:
    fr = _FileReader(path, set(), BagStats())
    fr.stop_on_metadata = name
    for _ in fr.messages():
        if name in fr.metadata:
            break
    return fr.metadata.get(name)


# mcap_ros2 (0.6) takes only [A-Z][A-Za-z0-9]* as a type name, so not a service's request,
# response or event type (pkg/srv/Name_Request ...): renamed without the underscore for decoding
# (CDR carries no names, so the decoded message is the same)
_SERVICE_TYPE = re.compile(r"\b([A-Z][A-Za-z0-9]*)_(Request|Response|Event)\b")


def _without_service_underscores(name: str, text: str) -> tuple[str, str]:
    return _SERVICE_TYPE.sub(r"\1\2", name), _SERVICE_TYPE.sub(r"\1\2", text)


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
            name, text = _without_service_underscores(channel.schema_name, channel.schema_data.decode())
            dec = self._decoders[key] = generate_dynamic(name, text)[name]
        return dec(data)
