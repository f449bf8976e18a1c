"""``dyn-bag-recover INPUT [-o OUTPUT]``: rewrite a truncated or damaged MCAP into a valid, indexed one.

The file is read record by record from the start, never trusting the summary for data; damaged
chunks are skipped and reading goes on. Exit status 0 nothing lost, 3 something lost, 1 nothing
recoverable, 4 no space for the output (nothing written). Outputs appear whole or not at all
(written beside, then renamed). Usage: docs/recording.md "Recovering a crashed or damaged bag"; the rules: docs/BAGS.md.
"""
from __future__ import annotations

import argparse
import errno
import os
import re
import struct
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Sequence

import yaml
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Metadata, Message, Schema
from mcap.writer import CompressionType, Writer

from dyn_node import __version__
from dyn_node.bag.reader import (OWN_LIBRARY, OWN_SUFFIX, damaged_message_indexes, index_damage_note,  # and
                                 is_own_output, missing_files, _decompress as decompress)  # the reader's decompressor
from dyn_node.errors import RecoverError
from dyn_node.bag.metadata import FileInfo, TopicInfo, bag_metadata, write_metadata_yaml

MAGIC = b"\x89MCAP0\r\n"
EXIT_OK, EXIT_NOTHING, EXIT_LOST, EXIT_NO_SPACE = 0, 1, 3, 4


class NoSpaceError(RecoverError):
    """The output's file system is full (or over quota): nothing was written."""


def _write_error(dst: Path, exc: OSError) -> RecoverError:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return NoSpaceError(f"no space left on the device for {dst}: nothing written (free "
                            "some space, or give -o OUTPUT on another file system)")
    return RecoverError(f"cannot recover into {dst}: {exc.strerror or exc}")
# Guards against absurd sizes in a damaged header (never allocate more than this per record).
MAX_RECORD = 4 << 30
# Every file we write says so in its Header's library field (OWN_LIBRARY), and the default
# names end with OWN_SUFFIX: either marks a file as our output (bag_reader.is_own_output, which
# dyn-audit uses too), never to be taken as an input of a directory.
# Footer: opcode, length 20 (the spec never extends it), three fields; then the magic.
FOOTER_LEN = 9 + 20
# A summary is indexes and definitions (about 100 bytes per chunk); a larger one is taken for
# a damaged Footer rather than read into memory.
MAX_SUMMARY = 1 << 28


@dataclass
class Recovery:
    """What one file yielded: per-topic kept counts and why anything was lost."""

    path: str
    output: str
    kept: dict[str, int] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    lost: bool = False
    expected: int | None = None  # the file's own Statistics message count, when readable
    topics: list[TopicInfo] = field(default_factory=list)
    start_ns: int = 0
    end_ns: int = 0
    metadata: int = 0  # metadata records kept
    attachments: int = 0  # attachments kept
    expected_metadata: int | None = None
    expected_attachments: int | None = None
    notes: list[str] = field(default_factory=list)  # reported, nothing lost (e.g. bad summary)

    @property
    def total(self) -> int:
        return sum(self.kept.values())

    @property
    def anything(self) -> bool:
        return bool(self.total or self.metadata or self.attachments)


class _Fields:
    """One record's content, read field by field as the spec lays it out. A field that runs
    past the content is an error; bytes after the last known field are fields of a later
    version of the spec, which readers must ignore."""

    __slots__ = ("buf", "pos")

    def __init__(self, buf: bytes) -> None:
        self.buf, self.pos = buf, 0

    def take(self, n: int) -> bytes:
        end = self.pos + n
        if end > len(self.buf):
            raise ValueError("a field runs past the end of its record")
        out, self.pos = self.buf[self.pos:end], end
        return out

    def _int(self, fmt: str) -> int:
        return struct.unpack(fmt, self.take(struct.calcsize(fmt)))[0]

    def u16(self) -> int:
        return self._int("<H")

    def u32(self) -> int:
        return self._int("<I")

    def u64(self) -> int:
        return self._int("<Q")

    def string(self) -> str:
        return self.take(self.u32()).decode("utf-8")

    def str_map(self) -> dict[str, str]:
        length = self.u32()
        end = self.pos + length
        if end > len(self.buf):
            raise ValueError("a map runs past the end of its record")
        out: dict[str, str] = {}
        while self.pos < end:
            key = self.string()
            out[key] = self.string()
        if self.pos != end:
            raise ValueError("a map's entries overrun its length")
        return out


def _schema(b: bytes) -> Schema:
    r = _Fields(b)
    sid, name, encoding = r.u16(), r.string(), r.string()
    return Schema(id=sid, name=name, encoding=encoding, data=r.take(r.u32()))


def _channel(b: bytes) -> Channel:
    r = _Fields(b)
    cid, sid, topic, encoding = r.u16(), r.u16(), r.string(), r.string()
    return Channel(id=cid, schema_id=sid, topic=topic, message_encoding=encoding,
                   metadata=r.str_map())


def _message(b: bytes) -> Message:
    # Never extended: the data runs to the end of the record.
    r = _Fields(b)
    cid, seq, log, pub = r.u16(), r.u32(), r.u64(), r.u64()
    return Message(channel_id=cid, sequence=seq, log_time=log, publish_time=pub, data=b[r.pos:])


def _chunk(b: bytes) -> Chunk:
    r = _Fields(b)
    start, end, size, crc, compression = r.u64(), r.u64(), r.u64(), r.u32(), r.string()
    return Chunk(message_start_time=start, message_end_time=end, uncompressed_size=size,
                 uncompressed_crc=crc, compression=compression, data=r.take(r.u64()))


def _metadata(b: bytes) -> Metadata:
    r = _Fields(b)
    name = r.string()
    return Metadata(name=name, metadata=r.str_map())


def _attachment(b: bytes) -> Attachment:
    r = _Fields(b)
    log, create, name, media_type = r.u64(), r.u64(), r.string(), r.string()
    data = r.take(r.u64())
    fields_end = r.pos
    crc = r.u32()  # of the fields before it; 0: not computed
    if crc and zlib.crc32(b[:fields_end]) != crc:
        raise ValueError(f"attachment {name!r} CRC mismatch")
    return Attachment(log_time=log, create_time=create, name=name, media_type=media_type,
                      data=data)


def _statistics(b: bytes) -> tuple[int, int, int]:
    """(messages, attachments, metadata records) of a Statistics record."""
    r = _Fields(b)
    messages, _schemas, _channels = r.u64(), r.u16(), r.u32()
    attachments, metadata = r.u32(), r.u32()
    return messages, attachments, metadata


def _header(b: bytes) -> tuple[str, str]:
    r = _Fields(b)
    return r.string(), r.string()


def _chunk_payload(chunk: Chunk) -> bytes:
    """The chunk's records, checked against its declared size and CRC (ValueError if not)."""
    size = chunk.uncompressed_size
    if size > MAX_RECORD:
        raise ValueError("declared uncompressed size is implausible")
    data = decompress(chunk.compression, chunk.data, size)
    if len(data) != size:
        raise ValueError("chunk decompresses to a different size than declared")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("chunk CRC mismatch")
    return data


def _records(buf: bytes):
    """(opcode, content) of every record in ``buf``: a chunk's decompressed payload (already
    CRC-checked) or the summary section. A record that overruns ``buf`` is an error."""
    pos = 0
    while pos < len(buf):
        if pos + 9 > len(buf):
            raise ValueError("truncated record inside chunk")
        op, n = struct.unpack_from("<BQ", buf, pos)
        if pos + 9 + n > len(buf):
            raise ValueError("record overruns its chunk")
        yield op, buf[pos + 9:pos + 9 + n]
        pos += 9 + n


@dataclass
class _Summary:
    """What an intact summary section offers: Schema and Channel records (the spec's copies of
    the data section's) and the Statistics counts (messages, attachments, metadata)."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    counts: tuple[int, int, int] | None = None


class _Rewriter:
    """Re-emits kept records through mcap's Writer, remapping schema/channel ids."""

    def __init__(self, out: BinaryIO, profile: str, library: str, summary: _Summary):
        self.w = Writer(out, compression=CompressionType.ZSTD, enable_crcs=True,
                        enable_data_crcs=True)
        self.w.start(profile=profile, library=library)
        self.summary = summary
        self.schemas: dict[int, Schema] = {}  # as the data section defines them (first wins)
        self.schema_ids: dict[int, int] = {}
        self.channels: dict[int, Channel] = {}
        self.channel_ids: dict[int, int] = {}
        self.written: dict[int, Channel] = {}  # input channel id -> the channel kept
        self.unknown_channel = 0
        self.conflicts: list[str] = []

    def schema(self, s: Schema) -> None:
        if s.id == 0:  # invalid by the spec; readers ignore it
            return
        if self.schemas.setdefault(s.id, s) != s:
            self._conflict(f"schema {s.id}")

    def channel(self, c: Channel) -> None:
        if self.channels.setdefault(c.id, c) != c:
            self._conflict(f"channel {c.id}")

    def _conflict(self, what: str) -> None:
        # The spec requires records sharing an id to be identical; which one a message meant
        # is then unknown, so it is reported (the first definition is kept).
        text = f"{what} is defined twice, differently (the first definition was kept)"
        if text not in self.conflicts:
            self.conflicts.append(text)

    def _channel_of(self, cid: int) -> Channel | None:
        return self.channels.get(cid) or self.summary.channels.get(cid)

    def _out_channel(self, cid: int) -> int | None:
        if cid in self.channel_ids:
            return self.channel_ids[cid]
        c = self._channel_of(cid)
        if c is None:
            return None
        sid = 0  # a schema id of 0: the channel has no schema
        if c.schema_id:
            s = self.schemas.get(c.schema_id) or self.summary.schemas.get(c.schema_id)
            if s is None:
                return None
            if s.id not in self.schema_ids:
                self.schema_ids[s.id] = self.w.register_schema(s.name, s.encoding, s.data)
            sid = self.schema_ids[s.id]
        self.channel_ids[cid] = self.w.register_channel(c.topic, c.message_encoding, sid,
                                                        dict(c.metadata))
        self.written[cid] = c
        return self.channel_ids[cid]

    def message(self, m: Message, rec: Recovery) -> None:
        cid = self._out_channel(m.channel_id)
        if cid is None:
            self.unknown_channel += 1
            return
        self.w.add_message(cid, log_time=m.log_time, data=m.data, publish_time=m.publish_time,
                           sequence=m.sequence)
        topic = self.written[m.channel_id].topic
        rec.kept[topic] = rec.kept.get(topic, 0) + 1
        rec.start_ns = m.log_time if rec.total == 1 else min(rec.start_ns, m.log_time)
        rec.end_ns = max(rec.end_ns, m.log_time)

    def metadata(self, m: Metadata, rec: Recovery) -> None:
        self.w.add_metadata(m.name, m.metadata)
        rec.metadata += 1

    def attachment(self, a: Attachment, rec: Recovery) -> None:
        self.w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        rec.attachments += 1

    def finish(self, rec: Recovery) -> None:
        """Keep the channels that carried no message too (a topic recorded without traffic),
        then write the summary."""
        for cid in [*self.channels, *(c for c in self.summary.channels if c not in self.channels)]:
            if self._out_channel(cid) is None:
                c = self._channel_of(cid)
                rec.problems.append(f"channel {cid} ({c.topic if c else '?'}) dropped: its "
                                    "schema was lost")
        if self.unknown_channel:
            rec.problems.append(f"{self.unknown_channel} messages on channels whose "
                                "definition was lost")
        rec.problems.extend(self.conflicts)
        self.w.finish()


def _read_exact(f: BinaryIO, n: int) -> bytes | None:
    data = f.read(n)
    return data if len(data) == n else None


def _own_library(source_library: str) -> str:
    """The Header library field of a file we write: our marker, then the input's own."""
    return f"{OWN_LIBRARY} {__version__}" + (f" (from {source_library})" if source_library
                                              else "")


def _read_header(f: BinaryIO, size: int) -> tuple[str, str] | None:
    """(profile, library) of the Header record right after the magic, or None if unreadable."""
    f.seek(len(MAGIC))
    head = _read_exact(f, 9)
    if head is None or head[0] != Opcode.HEADER:
        return None
    n = struct.unpack_from("<Q", head, 1)[0]
    content = _read_exact(f, n) if n <= size else None
    if content is None:
        return None
    try:
        return _header(content)
    except ValueError:
        return None


def _read_summary(f: BinaryIO, size: int, rec: Recovery) -> _Summary:
    """The summary section found through an intact Footer (nothing if the file was cut or its
    summary CRC is wrong): definitions the data section may lack, and the Statistics counts."""
    out = _Summary()
    if size < len(MAGIC) + FOOTER_LEN + len(MAGIC):
        return out
    footer_at = size - FOOTER_LEN - len(MAGIC)
    f.seek(footer_at)
    tail = f.read(FOOTER_LEN + len(MAGIC))
    if (tail[FOOTER_LEN:] != MAGIC or tail[0] != Opcode.FOOTER
            or struct.unpack_from("<Q", tail, 1)[0] != 20):
        return out  # no Footer: a cut file (the walk reports it)
    start, _offsets, crc = struct.unpack_from("<QQI", tail, 9)
    if start == 0:
        return out
    if not len(MAGIC) < start <= footer_at:
        rec.notes.append("the Footer points outside the file: summary ignored")
        return out
    if footer_at - start > MAX_SUMMARY:
        rec.notes.append(f"the summary would be {footer_at - start} bytes: summary ignored")
        return out
    f.seek(start)
    region = f.read(footer_at - start)
    if crc and zlib.crc32(tail[:FOOTER_LEN - 4], zlib.crc32(region)) != crc:
        rec.notes.append("summary CRC mismatch: summary ignored")
        return out
    try:
        for op, body in _records(region):
            try:
                if op == Opcode.SCHEMA:
                    s = _schema(body)
                    if s.id:
                        out.schemas.setdefault(s.id, s)
                elif op == Opcode.CHANNEL:
                    c = _channel(body)
                    out.channels.setdefault(c.id, c)
                elif op == Opcode.STATISTICS:
                    out.counts = _statistics(body)
            except ValueError:
                continue  # one unreadable summary record: the rest still counts
    except ValueError:
        pass  # a record overruns the summary: keep what came before it
    return out


def recover_file(src: Path, dst: Path) -> Recovery:
    """Recover one MCAP file into ``dst`` (overwritten if it exists, never equal to ``src``)."""
    rec = Recovery(str(src), str(dst))
    try:
        size = src.stat().st_size
        f = src.open("rb")
    except OSError as exc:
        raise RecoverError(f"cannot read {src}: {exc.strerror or exc}") from None
    with f:
        rw, summary, complete = _rewrite(f, size, src, dst, rec)
    rec.lost = bool(rec.problems) or not complete
    if summary.counts is not None:
        _compare_statistics(rec, summary.counts)
    if not rec.lost:
        rec.problems = []
    rec.topics = _topics(rw)
    return rec


def _rewrite(f: BinaryIO, size: int, src: Path, dst: Path,
             rec: Recovery) -> tuple[_Rewriter, _Summary, bool]:
    """The readable records of ``f`` written to ``dst``: the writer, the summary section found,
    and whether the data section ended as the spec says."""
    if _read_exact(f, 8) != MAGIC:
        raise RecoverError(f"{src} is not an MCAP file (bad magic)")
    # Header record: the profile carries over (the walk below reads the Header again).
    header = _read_header(f, size)
    if header is None:
        rec.problems.append("header record unreadable")
    profile, library = header or ("", "")
    summary = _read_summary(f, size, rec)
    f.seek(len(MAGIC))
    # Written beside and renamed when whole: a failure (a full disk) leaves no half file.
    part = dst.with_name(f".{dst.name}.part")
    try:
        with part.open("wb") as out:
            rw = _Rewriter(out, profile, _own_library(library), summary)
            complete = _walk(f, size, rw, rec)
            rw.finish(rec)
        os.replace(part, dst)
    except BaseException as exc:
        part.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise _write_error(dst, exc) from None
        raise
    return rw, summary, complete


def _compare_statistics(rec: Recovery, counts: tuple[int, int, int]) -> None:
    """Something was lost when the file's Statistics record lists more than was kept."""
    rec.expected, rec.expected_attachments, rec.expected_metadata = counts
    for what, listed, kept in (("messages", rec.expected, rec.total),
                               ("attachments", rec.expected_attachments, rec.attachments),
                               ("metadata records", rec.expected_metadata, rec.metadata)):
        if listed > kept:
            rec.lost = True
            rec.problems.append(f"the file's statistics list {listed} {what}")


def _walk(f: BinaryIO, size: int, rw: _Rewriter, rec: Recovery) -> bool:
    """Read the data section record by record into ``rw``; True if it ended as the spec says
    (Data End, or a Footer in a file without one), False if it was cut short."""
    data_crc = zlib.crc32(MAGIC)
    while True:
        start = f.tell()
        hdr = _read_exact(f, 9)
        if hdr is None:
            if f.tell() != start or start < size:
                rec.problems.append(f"file truncated at byte {start}")
            else:
                rec.problems.append(f"file ends at byte {start} without a footer")
            return False
        op, n = struct.unpack_from("<BQ", hdr)
        if n > min(size - start - 9, MAX_RECORD):
            rec.problems.append(f"record at byte {start} runs past the end of the file "
                                "(truncated)")
            return False
        body = _read_exact(f, n)
        if body is None:
            rec.problems.append(f"file truncated at byte {start}")
            return False
        if op == Opcode.DATA_END:
            (crc,) = struct.unpack_from("<I", body) if n >= 4 else (0,)
            if crc and crc != data_crc:
                # Damage only in Message Indexes (rebuilt by the writer) loses nothing.
                damaged = damaged_message_indexes(Path(f.name)) if isinstance(f.name, str) else None
                if damaged:
                    rec.notes.append(index_damage_note(Path(f.name).name, damaged))
                else:
                    rec.problems.append("data section CRC mismatch")
            return True
        data_crc = zlib.crc32(body, zlib.crc32(hdr, data_crc))
        try:
            _handle(op, body, rw, rec)
        except ValueError as exc:
            what = "chunk" if op == Opcode.CHUNK else f"record (opcode {op:#x})"
            rec.problems.append(f"{what} at byte {start} skipped: {exc}")
        except Exception as exc:  # noqa: BLE001 - parsing junk can fail in many ways
            rec.problems.append(f"record (opcode {op:#x}) at byte {start} skipped: "
                                f"{type(exc).__name__}")
        if op == Opcode.FOOTER:
            return True


def _handle(op: int, body: bytes, rw: _Rewriter, rec: Recovery) -> None:
    if op == Opcode.SCHEMA:
        rw.schema(_schema(body))
    elif op == Opcode.CHANNEL:
        rw.channel(_channel(body))
    elif op == Opcode.MESSAGE:
        rw.message(_message(body), rec)
    elif op == Opcode.CHUNK:
        payload = _chunk_payload(_chunk(body))
        # Parse the whole chunk before emitting anything, so a bad chunk is all-or-nothing.
        inner: list[tuple[int, Schema | Channel | Message]] = []
        for iop, ibody in _records(payload):
            if iop == Opcode.SCHEMA:
                inner.append((iop, _schema(ibody)))
            elif iop == Opcode.CHANNEL:
                inner.append((iop, _channel(ibody)))
            elif iop == Opcode.MESSAGE:
                inner.append((iop, _message(ibody)))
            # Other opcodes (application extensions) are skipped, as the spec says.
        for iop, r in inner:
            if iop == Opcode.SCHEMA:
                rw.schema(r)
            elif iop == Opcode.CHANNEL:
                rw.channel(r)
            else:
                rw.message(r, rec)
    elif op == Opcode.METADATA:
        rw.metadata(_metadata(body), rec)
    elif op == Opcode.ATTACHMENT:
        rw.attachment(_attachment(body), rec)
    # Indexes, statistics, summary offsets, unknown opcodes: rebuilt by the writer or skipped.


def _topics(rw: _Rewriter) -> list[TopicInfo]:
    topics = []
    for c in rw.written.values():
        s = rw.schemas.get(c.schema_id) or rw.summary.schemas.get(c.schema_id)
        try:
            qos = yaml.safe_load(c.metadata.get("offered_qos_profiles", "")) or []
            qos = tuple(q for q in qos if isinstance(q, dict))
        except yaml.YAMLError:
            qos = ()
        topics.append(TopicInfo(c.topic, s.name if s else "", qos))
    return topics


def _split_index(p: Path) -> tuple[int, str]:
    m = re.search(r"_(\d+)\.mcap$", p.name)
    return (int(m.group(1)) if m else 1 << 30, p.name)


@dataclass
class DirRecovery:
    """A bag directory's recovery: one result per input file, and our own earlier outputs
    found there (never read, or recovering a file and then its directory would duplicate)."""

    results: list[Recovery]
    skipped: list[Path]


def recover_dir(src: Path, dst: Path) -> DirRecovery:
    """Recover every MCAP file of a bag directory into ``dst`` and write its metadata.yaml."""
    candidates = sorted((p for p in src.iterdir() if p.suffix == ".mcap" and p.is_file()),
                        key=_split_index)
    skipped = [p for p in candidates if is_own_output(p)]
    files = [p for p in candidates if p not in skipped]
    if not files:
        raise RecoverError(f"{src} holds no .mcap files" + (
            f" but {len(skipped)} written by dyn-bag-recover (give one as INPUT to recover it "
            "again)" if skipped else ""))
    created = not dst.exists()
    try:
        dst.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _write_error(dst, exc) from None
    results: list[Recovery] = []
    try:
        _recover_files(files, dst, results)
    except NoSpaceError:
        _remove_outputs(results, dst, created)
        raise
    results += [Recovery(str(src / m.file), "", lost=True, problems=[m.reason])  # listed, deleted: lost
                for m in missing_files(src)]
    topics: dict[str, TopicInfo] = {}
    infos = []
    for r in results:
        if not r.output:
            continue
        for t in r.topics:
            topics.setdefault(t.name, t)
        infos.append(FileInfo(r.output, r.start_ns, r.end_ns, r.total, dict(r.kept)))
    try:
        write_metadata_yaml(dst, bag_metadata(list(topics.values()), infos,
                                              {"recovered_from": str(src)}))
    except OSError as exc:
        err = _write_error(dst / "metadata.yaml", exc)
        if isinstance(err, NoSpaceError):
            _remove_outputs(results, dst, created)
        raise err from None
    return DirRecovery(results, skipped)


def _recover_files(files: Sequence[Path], dst: Path, results: list[Recovery]) -> None:
    """Recover each file into ``dst``, appending to ``results``; a full disk stops it all."""
    for p in files:
        try:
            results.append(recover_file(p, dst / p.name))
        except NoSpaceError:
            raise
        except RecoverError as exc:
            results.append(Recovery(str(p), "", lost=True, problems=[str(exc)]))


def _remove_outputs(results: Sequence[Recovery], dst: Path, created: bool) -> None:
    """Undo a directory recovery the disk had no room for: our outputs, and ``dst`` if new."""
    for r in results:
        if r.output:
            Path(r.output).unlink(missing_ok=True)
    (dst / "metadata.yaml").unlink(missing_ok=True)
    if created:
        try:
            dst.rmdir()
        except OSError:
            pass  # something else was put there meanwhile: leave it


def _report(results: Sequence[Recovery], out=None, *, skipped: Sequence[Path] = ()) -> int:
    out = out or sys.stdout
    total = sum(r.total for r in results)
    lost = any(r.lost for r in results)
    kept: dict[str, int] = {}
    for p in skipped:
        print(f"{p}: skipped (written by dyn-bag-recover)", file=out)
    for r in results:
        print(f"{r.path} -> {r.output or '(nothing written)'}", file=out)
        for topic, n in sorted(r.kept.items()):
            kept[topic] = kept.get(topic, 0) + n
            print(f"  {topic}: {n} messages kept", file=out)
        if r.output:
            print(f"  {r.metadata} metadata records kept", file=out)
            print(f"  {r.attachments} attachments kept", file=out)
        for p in r.problems:
            print(f"  lost: {p}", file=out)
        for n in r.notes:
            print(f"  note: {n}", file=out)
    metadata, attachments = sum(r.metadata for r in results), sum(r.attachments for r in results)
    if len(results) > 1:
        print("total:", file=out)
        for topic, n in sorted(kept.items()):
            print(f"  {topic}: {n} messages kept", file=out)
        print(f"  {metadata} metadata records kept", file=out)
        print(f"  {attachments} attachments kept", file=out)
    if lost and not any(r.anything for r in results):
        print("result: nothing recoverable", file=out)
        return EXIT_NOTHING
    print(f"result: {total} messages, {metadata} metadata records, {attachments} attachments "
          "kept; " + ("some data was lost" if lost else "nothing lost"), file=out)
    return EXIT_LOST if lost else EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="dyn-bag-recover",
        description="Rewrite a truncated or damaged MCAP file (or every file of a bag "
                    "directory) into a valid, indexed one. Exit 0: nothing lost, "
                    "3: some data lost, 1: nothing recoverable, 4: no space for the output "
                    "(nothing written).")
    parser.add_argument("input", help="an .mcap file or a bag directory")
    parser.add_argument("-o", "--output", help="output file (or directory for a bag directory); "
                        "default: <input>.recovered.mcap, or <dir>.recovered")
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse already printed the usage error
        return EXIT_NOTHING if exc.code else EXIT_OK
    src = Path(args.input)
    try:
        if src.is_dir():
            dst = Path(args.output) if args.output else src.with_name(src.name + ".recovered")
            if dst.resolve() == src.resolve():
                raise RecoverError("output directory must differ from the input directory")
            bag = recover_dir(src, dst)
            results, skipped = bag.results, bag.skipped
        elif src.is_file():
            dst = Path(args.output) if args.output else src.with_name(
                src.name[:-5] + OWN_SUFFIX if src.name.endswith(".mcap")
                else src.name + OWN_SUFFIX)
            if dst.exists() and dst.resolve() == src.resolve():
                raise RecoverError("output file must differ from the input file")
            results, skipped = [recover_file(src, dst)], []
        else:
            raise RecoverError(f"{src}: no such file or directory")
    except NoSpaceError as exc:
        print(f"dyn-bag-recover: error: {exc}", file=sys.stderr)
        return EXIT_NO_SPACE
    except RecoverError as exc:
        print(f"dyn-bag-recover: error: {exc}", file=sys.stderr)
        return EXIT_NOTHING
    except KeyboardInterrupt:
        print("dyn-bag-recover: interrupted", file=sys.stderr)
        return EXIT_NOTHING
    except Exception as exc:  # noqa: BLE001 - the contract is: never a traceback
        print(f"dyn-bag-recover: error: unexpected failure: {type(exc).__name__}: {exc}",
              file=sys.stderr)
        return EXIT_NOTHING
    return _report(results, skipped=skipped)


if __name__ == "__main__":
    sys.exit(main())
