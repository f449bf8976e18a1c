"""Valid MCAP files written byte by byte from the specification's record layouts.

Each record is ``<opcode u8><content length u64><content>`` with little-endian integers, String =
``u32 length + UTF-8``, Map = ``u32 byte length + entries``, Bytes fields prefixed as the
specification says per record (https://mcap.dev/spec). Nothing here uses the ``mcap`` package or
dyn_node's writers, so a reader is checked against files neither of them produced.

The specification lets every record except Message and Footer grow new fields at its end
("readers should ignore any unknown fields"): every builder takes ``extra`` bytes that stand for
such fields. Opcodes 0x80-0xFF are application extensions a reader must skip.

:class:`McapBuilder` records, as records are added, what a reader must find: the messages (with
their channel and schema), metadata records, attachments and every channel's topic.
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

MAGIC = b"\x89MCAP0\r\n"
HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK, MESSAGE_INDEX, CHUNK_INDEX = range(1, 9)
ATTACHMENT, ATTACHMENT_INDEX, STATISTICS, METADATA, METADATA_INDEX, SUMMARY_OFFSET, DATA_END = \
    range(9, 16)
USER_OPCODE = 0x80  # the first opcode reserved for application extensions


def u8(v: int) -> bytes:
    return struct.pack("<B", v)


def u16(v: int) -> bytes:
    return struct.pack("<H", v)


def u32(v: int) -> bytes:
    return struct.pack("<I", v)


def u64(v: int) -> bytes:
    return struct.pack("<Q", v)


def string(s: str) -> bytes:
    b = s.encode("utf-8")
    return u32(len(b)) + b


def str_map(d: dict[str, str]) -> bytes:
    body = b"".join(string(k) + string(v) for k, v in d.items())
    return u32(len(body)) + body


def record(op: int, content: bytes) -> bytes:
    return u8(op) + u64(len(content)) + content


def compress(data: bytes, compression: str) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard
        return zstandard.ZstdCompressor().compress(data)
    if compression == "lz4":
        import lz4.frame
        return lz4.frame.compress(data)
    raise ValueError(compression)


@dataclass
class Expected:
    """What a reader of the file must find (in file order)."""

    # (topic, message_encoding, channel metadata, schema (name, encoding, data) or None,
    #  log_time, publish_time, sequence, data)
    messages: list[tuple] = field(default_factory=list)
    metadata: list[tuple[str, dict[str, str]]] = field(default_factory=list)
    # (name, media_type, log_time, create_time, data)
    attachments: list[tuple[str, str, int, int, bytes]] = field(default_factory=list)
    topics: list[str] = field(default_factory=list)  # every channel, with or without messages


class McapBuilder:
    """Appends records to a file in the order they are added; :meth:`finish` closes it."""

    def __init__(self, *, profile: str = "", library: str = "mcap_corpus", extra: bytes = b""):
        self.buf = bytearray(MAGIC + record(HEADER, string(profile) + string(library) + extra))
        self.expected = Expected()
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.schema_records: dict[int, bytes] = {}
        self.channels: dict[int, tuple[str, str, int, dict[str, str]]] = {}
        self.channel_records: dict[int, bytes] = {}
        self.channel_counts: dict[int, int] = {}
        self.chunk_indexes: list[bytes] = []
        self.attachment_indexes: list[bytes] = []
        self.metadata_indexes: list[bytes] = []
        self.times: list[int] = []
        self.n_chunks = self.n_attachments = self.n_metadata = 0

    # ------------------------------------------------------------------ records (bytes only)
    def schema(self, sid: int, name: str, encoding: str, data: bytes, *,
               extra: bytes = b"") -> bytes:
        """A Schema record; id 0 is invalid and readers ignore it (not registered here)."""
        rec = record(SCHEMA, u16(sid) + string(name) + string(encoding) + u32(len(data)) + data
                     + extra)
        if sid:
            self.schemas[sid] = (name, encoding, data)
            self.schema_records.setdefault(sid, rec)
        return rec

    def channel(self, cid: int, schema_id: int, topic: str, encoding: str,
                metadata: dict[str, str] | None = None, *, extra: bytes = b"") -> bytes:
        metadata = dict(metadata or {})
        rec = record(CHANNEL, u16(cid) + u16(schema_id) + string(topic) + string(encoding)
                     + str_map(metadata) + extra)
        if cid not in self.channels:
            self.expected.topics.append(topic)
        self.channels[cid] = (topic, encoding, schema_id, metadata)
        self.channel_records.setdefault(cid, rec)
        return rec

    def message(self, cid: int, sequence: int, log_time: int, publish_time: int,
                data: bytes) -> bytes:
        """A Message record (never extended: its data runs to the end of the record)."""
        topic, encoding, sid, metadata = self.channels[cid]
        self.expected.messages.append((topic, encoding, metadata, self.schemas.get(sid),
                                       log_time, publish_time, sequence, data))
        self.channel_counts[cid] = self.channel_counts.get(cid, 0) + 1
        self.times.append(log_time)
        return record(MESSAGE, u16(cid) + u32(sequence) + u64(log_time) + u64(publish_time)
                      + data)

    @staticmethod
    def user_record(payload: bytes = b"opaque") -> bytes:
        return record(USER_OPCODE, payload)

    # ------------------------------------------------------------------ appended to the file
    def add(self, *records: bytes) -> None:
        """Records outside any chunk, in the data section."""
        for r in records:
            self.buf += r

    def add_chunk(self, records: list[bytes], *, compression: str = "", extra: bytes = b"",
                  crc: bool = True, message_indexes: bool = True,
                  index_extra: bytes = b"") -> None:
        """A Chunk of ``records`` (Schema, Channel, Message or others), then its Message
        Index records (one per channel with messages, offsets into the uncompressed data)."""
        payload = b"".join(records)
        entries: dict[int, list[tuple[int, int]]] = {}
        times, pos = [], 0
        for r in records:
            if r[0] == MESSAGE:
                cid = struct.unpack_from("<H", r, 9)[0]
                log = struct.unpack_from("<Q", r, 9 + 6)[0]
                entries.setdefault(cid, []).append((log, pos))
                times.append(log)
            pos += len(r)
        data = compress(payload, compression)
        content = (u64(min(times, default=0)) + u64(max(times, default=0)) + u64(len(payload))
                   + u32(zlib.crc32(payload) if crc else 0) + string(compression)
                   + u64(len(data)) + data + extra)
        start = len(self.buf)
        self.buf += record(CHUNK, content)
        chunk_length = len(self.buf) - start
        offsets: dict[int, int] = {}
        index_start = len(self.buf)
        if message_indexes:
            for cid, es in entries.items():
                offsets[cid] = len(self.buf)
                arr = b"".join(u64(t) + u64(o) for t, o in es)
                self.buf += record(MESSAGE_INDEX, u16(cid) + u32(len(arr)) + arr + index_extra)
        offs = b"".join(u16(c) + u64(o) for c, o in offsets.items())
        self.chunk_indexes.append(record(
            CHUNK_INDEX, u64(min(times, default=0)) + u64(max(times, default=0)) + u64(start)
            + u64(chunk_length) + u32(len(offs)) + offs + u64(len(self.buf) - index_start)
            + string(compression) + u64(len(data)) + u64(len(payload)) + index_extra))
        self.n_chunks += 1

    def add_attachment(self, name: str, media_type: str, log_time: int, create_time: int,
                       data: bytes, *, crc: bool = True, extra: bytes = b"") -> None:
        fields = (u64(log_time) + u64(create_time) + string(name) + string(media_type)
                  + u64(len(data)) + data)
        offset = len(self.buf)
        self.buf += record(ATTACHMENT, fields + u32(zlib.crc32(fields) if crc else 0) + extra)
        self.attachment_indexes.append(record(
            ATTACHMENT_INDEX, u64(offset) + u64(len(self.buf) - offset) + u64(log_time)
            + u64(create_time) + u64(len(data)) + string(name) + string(media_type) + extra))
        self.expected.attachments.append((name, media_type, log_time, create_time, data))
        self.n_attachments += 1

    def add_metadata(self, name: str, metadata: dict[str, str], *, extra: bytes = b"") -> None:
        offset = len(self.buf)
        self.buf += record(METADATA, string(name) + str_map(metadata) + extra)
        self.metadata_indexes.append(record(
            METADATA_INDEX, u64(offset) + u64(len(self.buf) - offset) + string(name) + extra))
        self.expected.metadata.append((name, dict(metadata)))
        self.n_metadata += 1

    def statistics(self, *, extra: bytes = b"") -> bytes:
        counts = b"".join(u16(c) + u64(n) for c, n in self.channel_counts.items())
        return record(STATISTICS, u64(len(self.times)) + u16(len(self.schemas))
                      + u32(len(self.channels)) + u32(self.n_attachments)
                      + u32(self.n_metadata) + u32(self.n_chunks)
                      + u64(min(self.times, default=0)) + u64(max(self.times, default=0))
                      + u32(len(counts)) + counts + extra)

    def finish(self, *, data_end: bool = True, summary: bool = True, data_crc: bool = True,
               summary_crc: bool = True, summary_offsets: bool = True, extra: bytes = b"",
               summary_repeats: int = 1) -> bytes:
        """Data End (with the CRC of every byte before it), then optionally the summary
        (every Schema and Channel ``summary_repeats`` times, Chunk, Attachment and Metadata
        indexes, Statistics; grouped by opcode), Summary Offsets, Footer and magic."""
        if data_end:
            self.buf += record(DATA_END, u32(zlib.crc32(self.buf) if data_crc else 0) + extra)
        summary_start = len(self.buf) if summary else 0
        groups: list[tuple[int, int, int]] = []
        if summary:
            for op, recs in (
                    (SCHEMA, list(self.schema_records.values()) * summary_repeats),
                    (CHANNEL, list(self.channel_records.values()) * summary_repeats),
                    (CHUNK_INDEX, self.chunk_indexes),
                    (ATTACHMENT_INDEX, self.attachment_indexes),
                    (METADATA_INDEX, self.metadata_indexes),
                    (STATISTICS, [self.statistics(extra=extra)])):
                if recs:
                    start = len(self.buf)
                    self.buf += b"".join(recs)
                    groups.append((op, start, len(self.buf) - start))
        offset_start = 0
        if summary and summary_offsets:
            offset_start = len(self.buf)
            for op, start, length in groups:
                self.buf += record(SUMMARY_OFFSET, u8(op) + u64(start) + u64(length) + extra)
        footer_head = u8(FOOTER) + u64(20) + u64(summary_start) + u64(offset_start)
        crc = zlib.crc32(footer_head, zlib.crc32(self.buf[summary_start:])) \
            if summary and summary_crc else 0
        self.buf += footer_head + u32(crc) + MAGIC
        return bytes(self.buf)


# ---------------------------------------------------------------------- the corpus
X = b"\xa5future-field\x00\x01"  # stands for fields a later version of the spec adds

JOINT = ("sensor_msgs/msg/JointState", "ros2msg", b"float64[] position\n")
TEXT = ("std_msgs/msg/String", "ros2msg", b"string data\n")


def _cdr(n: int) -> bytes:
    return b"\x00\x01\x00\x00" + bytes([n % 251]) * (n % 7)


def extra_bytes_everywhere(compression: str = "zstd") -> tuple[bytes, Expected]:
    """Every extensible record (Header, Schema, Channel, Chunk, Message Index, Attachment,
    Metadata, Data End, every summary record) carries bytes beyond the fields it defines,
    inside chunks and outside; user-opcode records in the data section and inside a chunk."""
    b = McapBuilder(profile="ros2", extra=X)
    b.add(b.schema(1, *JOINT, extra=X), b.channel(1, 1, "/joint_states", "cdr",
                                                   {"offered_qos_profiles": "- {depth: 1}"},
                                                   extra=X))
    b.add(b.user_record())
    b.add(b.message(1, 0, 1_000, 990, _cdr(0)))  # outside a chunk
    b.add_chunk([b.schema(2, *TEXT, extra=X), b.channel(2, 2, "/chatter", "cdr", extra=X),
                 b.message(2, 7, 2_000, 2_000, _cdr(1)), b.user_record(b"in a chunk"),
                 b.message(1, 1, 3_000, 2_990, _cdr(2))],
                compression=compression, extra=X, index_extra=X)
    b.add_metadata("dyn_node", {"robot_description": "<robot name='r'/>", "version": "0"},
                   extra=X)
    b.add_attachment("calib.yaml", "application/yaml", 2_500, 2_400, b"k: 1\n", extra=X)
    b.add_chunk([b.message(2, 8, 4_000, 4_000, _cdr(3)), b.message(1, 2, 5_000, 4_990, b"")],
                compression=compression, extra=X, index_extra=X)
    return b.finish(extra=X), b.expected


def outside_chunks() -> tuple[bytes, Expected]:
    """No chunk at all: schemas, channels, messages, metadata and attachments interleaved in
    the data section, no summary (the Footer's offsets are 0)."""
    b = McapBuilder(profile="ros2")
    b.add(b.schema(1, *JOINT), b.channel(3, 1, "/joint_states", "cdr"))
    for k in range(5):
        b.add(b.message(3, k, 10 + k, 5 + k, _cdr(k)))
        if k == 1:
            b.add_attachment("log.txt", "text/plain", 11, 0, b"x" * 100)
        if k == 2:
            b.add_metadata("run", {"id": "42", "operator": "ünïcode"})
            b.add(b.schema(2, *TEXT), b.channel(4, 2, "/chatter", "cdr"))
            b.add(b.message(4, 99, 12, 12, _cdr(9)))
    return b.finish(summary=False), b.expected


def chunked(compression: str) -> tuple[bytes, Expected]:
    """Chunks of interleaved channels (two channels on one topic, as two publishers), each
    chunk repeating the Schema and Channel records it uses, an attachment between chunks, a
    full summary with Chunk Indexes, Statistics and Summary Offsets."""
    b = McapBuilder(profile="ros2")
    defs = [b.schema(1, *JOINT), b.channel(1, 1, "/joint_states", "cdr", {"k": "a"}),
            b.channel(2, 1, "/joint_states", "cdr", {"k": "b"})]
    seq = 0
    for c in range(3):
        msgs = []
        for k in range(4):
            msgs.append(b.message(1 + (k % 2), seq, 100 * c + k, 100 * c + k, _cdr(seq)))
            seq += 1
        b.add_chunk(defs + msgs, compression=compression)
        if c == 0:
            b.add_attachment("map.pgm", "image/x-portable-graymap", 50, 40, bytes(range(256)))
    return b.finish(), b.expected


def summary_repeats() -> tuple[bytes, Expected]:
    """Schemas and channels repeated: in the data section outside chunks, again in every
    chunk, and twice in the summary; a channel that carries no message."""
    b = McapBuilder(profile="ros2")
    s1, c1 = b.schema(1, *JOINT), b.channel(1, 1, "/joint_states", "cdr")
    s2, c2 = b.schema(2, *TEXT), b.channel(2, 2, "/idle", "cdr")
    b.add(s1, c1, s2, c2)
    for c in range(3):
        b.add_chunk([s1, c1, s2, c2, b.message(1, c, 10 * c, 10 * c, _cdr(c))],
                    compression="zstd")
        b.add(s1, c1)
    return b.finish(summary_repeats=2), b.expected


def schemaless() -> tuple[bytes, Expected]:
    """Channels with schema id 0 (self-describing JSON and raw bytes), next to a Schema record
    with id 0, which the specification calls invalid and readers ignore."""
    b = McapBuilder(profile="")
    b.add(b.schema(0, "ignored", "jsonschema", b"{}"),
          b.channel(1, 0, "/json", "json"), b.channel(2, 0, "/raw", "x-raw"))
    b.add(b.message(1, 0, 1, 1, b'{"a": 1}'))
    b.add_chunk([b.message(2, 0, 2, 2, b"\x00\x01"), b.message(1, 1, 3, 3, b'{"a": 2}')],
                compression="lz4")
    return b.finish(), b.expected


def attachments_only() -> tuple[bytes, Expected]:
    """No channel, no message: attachments only (one without CRC, one empty)."""
    b = McapBuilder()
    b.add_attachment("a.bin", "application/octet-stream", 5, 4, b"\x00" * 1000)
    b.add_attachment("b.txt", "text/plain", 6, 0, b"hello", crc=False)
    b.add_attachment("empty", "", 7, 7, b"")
    return b.finish(), b.expected


def metadata_only() -> tuple[bytes, Expected]:
    """No channel, no message: metadata records only (one with an empty map)."""
    b = McapBuilder()
    b.add_metadata("first", {"a": "1", "b": ""})
    b.add_metadata("empty", {})
    b.add_metadata("first", {"a": "2"})  # names need not be unique
    return b.finish(summary_offsets=False), b.expected


def no_data_end() -> tuple[bytes, Expected]:
    """The specification's "single message" diagram: Header, Schema, Channel, Message,
    Footer: no Data End, no summary."""
    b = McapBuilder()
    b.add(b.schema(1, *TEXT), b.channel(1, 1, "/chatter", "cdr"), b.message(1, 3, 7, 6, b"m"))
    return b.finish(data_end=False, summary=False), b.expected


def empty() -> tuple[bytes, Expected]:
    """The smallest valid file: Header and Footer."""
    b = McapBuilder()
    return b.finish(data_end=False, summary=False), b.expected


def no_crcs() -> tuple[bytes, Expected]:
    """Every CRC (chunk, data section, summary, attachment) 0, "not available"."""
    b = McapBuilder(profile="ros2")
    b.add_chunk([b.schema(1, *JOINT), b.channel(1, 1, "/joint_states", "cdr"),
                 b.message(1, 0, 1, 1, _cdr(0))], compression="zstd", crc=False)
    b.add_attachment("a", "text/plain", 1, 1, b"a", crc=False)
    return b.finish(data_crc=False, summary_crc=False), b.expected


CORPUS = {
    "extra_bytes_zstd": lambda: extra_bytes_everywhere("zstd"),
    "extra_bytes_lz4": lambda: extra_bytes_everywhere("lz4"),
    "extra_bytes_uncompressed": lambda: extra_bytes_everywhere(""),
    "outside_chunks": outside_chunks,
    "chunked_uncompressed": lambda: chunked(""),
    "chunked_zstd": lambda: chunked("zstd"),
    "chunked_lz4": lambda: chunked("lz4"),
    "summary_repeats": summary_repeats,
    "schemaless": schemaless,
    "attachments_only": attachments_only,
    "metadata_only": metadata_only,
    "no_data_end": no_data_end,
    "empty": empty,
    "no_crcs": no_crcs,
}
# mcap 1.6.0's own reader does not skip unknown trailing fields of records inside a chunk
# (its chunk parser reads the next record where the known fields end), so these files are
# checked against it only after dyn-bag-recover has rewritten them.
OFFICIAL_READER_MISREADS = {"extra_bytes_zstd", "extra_bytes_lz4", "extra_bytes_uncompressed"}
