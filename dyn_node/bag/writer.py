"""A minimal chunked, indexed MCAP writer (spec: https://mcap.dev/spec), used by the recorder.

The MCAP bytes come from :class:`McapFile` rather than ``mcap.writer.Writer``: per message it
costs one ``struct`` pack and list appends instead of a record object and a ``BytesIO`` round
trip, which at 3 records per 1 kHz joint state was most of what recording cost the node.
"""
from __future__ import annotations

import errno
import os
import struct
import sys
import zlib
from array import array
from typing import Any, BinaryIO, Callable, Mapping

from mcap.writer import CompressionType

PROFILE = "ros2"
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}

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
        # Level -1 (zstd's fast mode): compression is the recorder's largest per-message cost
        # and noisy doubles barely compress better at higher levels (docs/BAGS.md).
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

    ``stream`` needs ``write`` and ``tell`` (see :class:`CountingFile`). Nothing is buffered
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


class CountingFile:
    """Wrap the binary file so the MCAP writer's ``tell()`` works on any file-like and we know
    the size without a stat call. Writes loop until done (a raw file may write partially)."""

    def __init__(self, raw: BinaryIO):
        self.raw = raw
        self.pos = 0

    def write(self, data: bytes) -> int:
        if not data:
            return 0
        start = self.pos
        view = memoryview(data)
        try:
            while view:
                n = self.raw.write(view)
                n = len(view) if n is None else n
                if n <= 0:
                    raise OSError(errno.EIO, "write made no progress")
                self.pos += n
                view = view[n:]
        except OSError:
            # Cut the half-written record off: the file then ends on a whole record, and on a
            # full disk its space is what lets the final metadata.yaml be written.
            self._truncate(start)
            raise
        return len(data)

    def _truncate(self, size: int) -> None:
        try:
            os.ftruncate(self.raw.fileno(), size)
        except (AttributeError, OSError, ValueError):
            return  # a file-like without a descriptor: the partial record stays
        self.pos = size

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
