"""``dyn-bag-recover INPUT [-o OUTPUT]``: rewrite a truncated or damaged MCAP into a valid, indexed one.

INPUT is either one ``.mcap`` file or a bag directory (every ``*.mcap`` in it, in split order;
a fresh ``metadata.yaml`` is written for the output directory). OUTPUT defaults to
``<name>.recovered.mcap`` beside a file, or ``<dir>.recovered/`` beside a directory.

How: the file is read record by record from the start, never trusting the summary. Each record's
length must fit in the file; each chunk must decompress to its declared size and match its CRC.
A record cut short by the end of the file ends recovery (everything after a truncation is gone);
a chunk that fails its CRC or cannot be decompressed is skipped and counted as a lost region, and
reading continues at the next record (its length field is outside the chunk's payload).
Schemas, channels, messages (in file order), metadata records and attachments are kept.

Exit status: 0 nothing lost, 3 something lost (truncation, bad chunk, data-section CRC mismatch,
or fewer messages than the file's own statistics), 1 nothing recoverable (or unusable input).
Because a cut only removes records at the end, the number of messages recovered never
decreases as the cut point moves later in the file.
"""
from __future__ import annotations

import argparse
import io
import re
import struct
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Sequence

import yaml
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Metadata, Message, Schema, Statistics
from mcap.writer import CompressionType, Writer

from .recording import FileInfo, TopicInfo, bag_metadata, write_metadata_yaml

MAGIC = b"\x89MCAP0\r\n"
EXIT_OK, EXIT_NOTHING, EXIT_LOST = 0, 1, 3
# Guards against absurd sizes in a damaged header (never allocate more than this per record).
MAX_RECORD = 4 << 30


class RecoverError(Exception):
    """A clear, user-facing failure (bad input path, not an MCAP file, unwritable output)."""


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

    @property
    def total(self) -> int:
        return sum(self.kept.values())


def _parse(record_cls, content: bytes, *extra):
    """Parse one record's content strictly: it must consume exactly the bytes it was given."""
    stream = ReadDataStream(io.BytesIO(content))
    rec = record_cls.read(stream, *extra)
    if stream.count != len(content):
        raise ValueError(f"{record_cls.__name__} record length mismatch")
    return rec


def _decompress(chunk: Chunk) -> bytes:
    size = chunk.uncompressed_size
    if size > MAX_RECORD:
        raise ValueError("declared uncompressed size is implausible")
    if chunk.compression == "":
        data = chunk.data
    elif chunk.compression == "zstd":
        import zstandard
        data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=size)
    elif chunk.compression == "lz4":
        import lz4.frame
        data = lz4.frame.decompress(chunk.data)
    else:
        raise ValueError(f"unknown chunk compression {chunk.compression!r}")
    if len(data) != size:
        raise ValueError("chunk decompresses to a different size than declared")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("chunk CRC mismatch")
    return data


def _records(buf: bytes):
    """(opcode, content) of every record in a chunk's decompressed payload (already CRC-checked)."""
    pos = 0
    while pos < len(buf):
        if pos + 9 > len(buf):
            raise ValueError("truncated record inside chunk")
        op, n = struct.unpack_from("<BQ", buf, pos)
        if pos + 9 + n > len(buf):
            raise ValueError("record overruns its chunk")
        yield op, buf[pos + 9:pos + 9 + n]
        pos += 9 + n


class _Rewriter:
    """Re-emits kept records through mcap's Writer, remapping schema/channel ids."""

    def __init__(self, out: BinaryIO, profile: str, library: str):
        self.w = Writer(out, compression=CompressionType.ZSTD, enable_crcs=True,
                        enable_data_crcs=True)
        self.w.start(profile=profile, library=library)
        self.schemas: dict[int, Schema] = {}
        self.schema_ids: dict[int, int] = {}
        self.channels: dict[int, Channel] = {}
        self.channel_ids: dict[int, int] = {}
        self.unknown_channel = 0

    def schema(self, s: Schema) -> None:
        if s.id not in self.schemas:
            self.schemas[s.id] = s

    def channel(self, c: Channel) -> None:
        if c.id in self.channels:
            return
        self.channels[c.id] = c

    def _out_channel(self, cid: int) -> int | None:
        if cid in self.channel_ids:
            return self.channel_ids[cid]
        c = self.channels.get(cid)
        if c is None:
            return None
        sid = 0
        if c.schema_id:
            s = self.schemas.get(c.schema_id)
            if s is None:
                return None
            if s.id not in self.schema_ids:
                self.schema_ids[s.id] = self.w.register_schema(s.name, s.encoding, s.data)
            sid = self.schema_ids[s.id]
        self.channel_ids[cid] = self.w.register_channel(c.topic, c.message_encoding, sid,
                                                        dict(c.metadata))
        return self.channel_ids[cid]

    def message(self, m: Message, rec: Recovery) -> None:
        cid = self._out_channel(m.channel_id)
        if cid is None:
            self.unknown_channel += 1
            return
        self.w.add_message(cid, log_time=m.log_time, data=m.data, publish_time=m.publish_time,
                           sequence=m.sequence)
        topic = self.channels[m.channel_id].topic
        rec.kept[topic] = rec.kept.get(topic, 0) + 1
        rec.start_ns = m.log_time if rec.total == 1 else min(rec.start_ns, m.log_time)
        rec.end_ns = max(rec.end_ns, m.log_time)


def _read_exact(f: BinaryIO, n: int) -> bytes | None:
    data = f.read(n)
    return data if len(data) == n else None


def recover_file(src: Path, dst: Path) -> Recovery:
    """Recover one MCAP file into ``dst`` (overwritten if it exists, never equal to ``src``)."""
    rec = Recovery(str(src), str(dst))
    try:
        size = src.stat().st_size
        f = src.open("rb")
    except OSError as exc:
        raise RecoverError(f"cannot read {src}: {exc.strerror or exc}") from None
    with f:
        if _read_exact(f, 8) != MAGIC:
            raise RecoverError(f"{src} is not an MCAP file (bad magic)")
        # Header record: profile and library, to carry over (read again in the loop below).
        profile, library = "", "dyn-bag-recover"
        head = _read_exact(f, 9)
        if head is not None and head[0] == Opcode.HEADER:
            n = struct.unpack_from("<Q", head, 1)[0]
            content = _read_exact(f, n) if n <= size else None
            if content is not None:
                try:
                    s = ReadDataStream(io.BytesIO(content))
                    profile, library = s.read_prefixed_string(), s.read_prefixed_string()
                except Exception:  # noqa: BLE001 - a damaged header only loses the labels
                    rec.problems.append("header record unreadable")
        f.seek(8)
        try:
            out = dst.open("wb")
        except OSError as exc:
            raise RecoverError(f"cannot write {dst}: {exc.strerror or exc}") from None
        with out:
            rw = _Rewriter(out, profile, library)
            data_crc = zlib.crc32(MAGIC)
            complete = False
            while True:
                start = f.tell()
                hdr = _read_exact(f, 9)
                if hdr is None:
                    if f.tell() != start or start < size:
                        rec.problems.append(f"file truncated at byte {start}")
                    else:
                        rec.problems.append(f"file ends at byte {start} without a footer")
                    break
                op, n = struct.unpack_from("<BQ", hdr)
                if n > min(size - start - 9, MAX_RECORD):
                    rec.problems.append(f"record at byte {start} runs past the end of the file "
                                        "(truncated)")
                    break
                body = _read_exact(f, n)
                if body is None:
                    rec.problems.append(f"file truncated at byte {start}")
                    break
                if op == Opcode.DATA_END:
                    (crc,) = struct.unpack_from("<I", body) if n >= 4 else (0,)
                    if crc and crc != data_crc:
                        rec.problems.append("data section CRC mismatch")
                    complete = True
                    _scan_summary(f, size, rec)
                    break
                data_crc = zlib.crc32(body, zlib.crc32(hdr, data_crc))
                try:
                    _handle(op, body, rw, rec)
                except ValueError as exc:
                    if op == Opcode.CHUNK:
                        rec.problems.append(f"chunk at byte {start} skipped: {exc}")
                    else:
                        rec.problems.append(f"record (opcode {op:#x}) at byte {start} "
                                            f"skipped: {exc}")
                except Exception as exc:  # noqa: BLE001 - parsing junk can fail in many ways
                    rec.problems.append(f"record (opcode {op:#x}) at byte {start} skipped: "
                                        f"{type(exc).__name__}")
                if op == Opcode.FOOTER:
                    complete = True
                    break
            if rw.unknown_channel:
                rec.problems.append(f"{rw.unknown_channel} messages on channels whose "
                                    "definition was lost")
            try:
                rw.w.finish()
            except OSError as exc:
                raise RecoverError(f"cannot write {dst}: {exc.strerror or exc}") from None
    rec.lost = bool(rec.problems) or not complete
    if rec.expected is not None and rec.expected > rec.total:
        rec.lost = True
        rec.problems.append(f"the file's statistics list {rec.expected} messages")
    if not rec.lost:
        rec.problems = []
    rec.topics = _topics(rw)
    return rec


def _handle(op: int, body: bytes, rw: _Rewriter, rec: Recovery) -> None:
    if op == Opcode.SCHEMA:
        rw.schema(_parse(Schema, body))
    elif op == Opcode.CHANNEL:
        rw.channel(_parse(Channel, body))
    elif op == Opcode.MESSAGE:
        rw.message(_parse(Message, body, len(body)), rec)
    elif op == Opcode.CHUNK:
        payload = _decompress(_parse(Chunk, body))
        # Parse the whole chunk before emitting anything, so a bad chunk is all-or-nothing.
        inner = []
        for iop, ibody in _records(payload):
            if iop == Opcode.SCHEMA:
                inner.append((iop, _parse(Schema, ibody)))
            elif iop == Opcode.CHANNEL:
                inner.append((iop, _parse(Channel, ibody)))
            elif iop == Opcode.MESSAGE:
                inner.append((iop, _parse(Message, ibody, len(ibody))))
        for iop, r in inner:
            if iop == Opcode.SCHEMA:
                rw.schema(r)
            elif iop == Opcode.CHANNEL:
                rw.channel(r)
            else:
                rw.message(r, rec)
    elif op == Opcode.METADATA:
        m = _parse(Metadata, body)
        rw.w.add_metadata(m.name, m.metadata)
    elif op == Opcode.ATTACHMENT:
        a = _parse(Attachment, body)
        rw.w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
    # Indexes, statistics, summary offsets: rebuilt by the writer.


def _scan_summary(f: BinaryIO, size: int, rec: Recovery) -> None:
    """Read the Statistics record of an intact summary, to compare message counts."""
    while True:
        start = f.tell()
        hdr = _read_exact(f, 9)
        if hdr is None:
            return
        op, n = struct.unpack_from("<BQ", hdr)
        if n > size - start - 9:
            return
        body = _read_exact(f, n)
        if body is None or op == Opcode.FOOTER:
            return
        if op == Opcode.STATISTICS:
            try:
                rec.expected = _parse(Statistics, body).message_count
            except Exception:  # noqa: BLE001 - a damaged summary is ignored
                pass
            return


def _topics(rw: _Rewriter) -> list[TopicInfo]:
    topics = []
    for c in rw.channels.values():
        s = rw.schemas.get(c.schema_id)
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


def recover_dir(src: Path, dst: Path) -> list[Recovery]:
    """Recover every MCAP file of a bag directory into ``dst`` and write its metadata.yaml."""
    files = sorted((p for p in src.iterdir() if p.suffix == ".mcap"), key=_split_index)
    if not files:
        raise RecoverError(f"{src} holds no .mcap files")
    try:
        dst.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RecoverError(f"cannot create {dst}: {exc.strerror or exc}") from None
    results = []
    for p in files:
        try:
            results.append(recover_file(p, dst / p.name))
        except RecoverError as exc:
            r = Recovery(str(p), "", lost=True, problems=[str(exc)])
            results.append(r)
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
        raise RecoverError(f"cannot write {dst / 'metadata.yaml'}: {exc.strerror or exc}") from None
    return results


def _report(results: Sequence[Recovery], out=None) -> int:
    out = out or sys.stdout
    total = sum(r.total for r in results)
    lost = any(r.lost for r in results)
    kept: dict[str, int] = {}
    for r in results:
        print(f"{r.path} -> {r.output or '(nothing written)'}", file=out)
        for topic, n in sorted(r.kept.items()):
            kept[topic] = kept.get(topic, 0) + n
            print(f"  {topic}: {n} messages kept", file=out)
        for p in r.problems:
            print(f"  lost: {p}", file=out)
    if len(results) > 1:
        print("total:", file=out)
        for topic, n in sorted(kept.items()):
            print(f"  {topic}: {n} messages kept", file=out)
    if total == 0 and lost:
        print("result: nothing recoverable", file=out)
        return EXIT_NOTHING
    print(f"result: {total} messages kept; "
          + ("some data was lost" if lost else "nothing lost"), file=out)
    return EXIT_LOST if lost else EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="dyn-bag-recover",
        description="Rewrite a truncated or damaged MCAP file (or every file of a bag "
                    "directory) into a valid, indexed one. Exit 0: nothing lost, "
                    "3: some data lost, 1: nothing recoverable.")
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
            results = recover_dir(src, dst)
        elif src.is_file():
            dst = Path(args.output) if args.output else src.with_name(
                src.name[:-5] + ".recovered.mcap" if src.name.endswith(".mcap")
                else src.name + ".recovered.mcap")
            if dst.exists() and dst.resolve() == src.resolve():
                raise RecoverError("output file must differ from the input file")
            results = [recover_file(src, dst)]
        else:
            raise RecoverError(f"{src}: no such file or directory")
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
    return _report(results)


if __name__ == "__main__":
    sys.exit(main())
