"""What an MCAP file's summary section and index records tell without reading its data: the
metadata records through their indexes, and whether a data-section CRC mismatch is explained by
damaged Message Index records alone."""
from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path
from typing import Sequence

from dyn_node.bag.records import (_CHUNK_HEAD, _U8_U64, _U32, _U64, MAGIC, OP_CHUNK, OP_DATA_END, OP_FOOTER,
                                  OP_MESSAGE, OP_MESSAGE_INDEX, OP_METADATA, OP_METADATA_INDEX, _decompress,
                                  _map, _str)


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


def _all_metadata_from_summary(path: Path, name: str) -> list[dict[str, str]] | None:
    """Every metadata record ``name`` the summary's metadata indexes point to, in their order;
    None when the file has no summary (or an index points at something else)."""
    recs = _summary_records(path)
    if recs is None:
        return None
    out = []
    with open(path, "rb") as fh:
        for op, body in recs:
            if op != OP_METADATA_INDEX or _str(body, 16)[0] != name:
                continue
            moff, mlen = struct.unpack_from("<QQ", body, 0)
            fh.seek(moff)
            rec = memoryview(fh.read(mlen))
            if len(rec) < 9 or rec[0] != OP_METADATA:
                return None
            _rname, o = _str(rec, 9)
            out.append(_map(rec, o)[0])
    return out


def _canonical_indexes(records: bytes) -> bytes:
    """The Message Index records of one decompressed chunk as both our recorder and mcap's
    writer lay them out: one per channel, in the order each channel first appears, entries
    (log time, record offset) in message order."""
    index: dict[int, list[int]] = {}
    off, n = 0, len(records)
    while off + 9 <= n:
        op, length = _U8_U64.unpack_from(records, off)
        if op == OP_MESSAGE and length >= 22:
            cid, _seq, log_ns = struct.unpack_from("<HIQ", records, off + 9)
            index.setdefault(cid, []).extend((log_ns, off))
        off += 9 + length
    return b"".join(_U8_U64.pack(OP_MESSAGE_INDEX, 6 + 8 * len(e))
                    + struct.pack(f"<HI{len(e)}Q", cid, 8 * len(e), *e) for cid, e in index.items())


def damaged_message_indexes(path: Path) -> list[int] | None:
    """For a file whose data-section CRC does not match: the byte offsets of the Message Index
    records whose damage alone explains it, i.e. with each chunk's index records rebuilt from
    the chunk the data-section CRC matches the one in Data End. Then every message, metadata
    record and attachment is intact and nothing was lost (both tools rebuild indexes). None
    when that is not so: the damage lies elsewhere, or cannot be placed."""
    try:
        with open(path, "rb") as fh:
            return _damaged_message_indexes(fh, os.fstat(fh.fileno()).st_size)
    except Exception:  # noqa: BLE001 - any decoder error on damaged bytes: cannot be placed
        return None


def _damaged_message_indexes(fh, size: int) -> list[int] | None:
    if fh.read(8) != MAGIC:
        return None
    crc, pos = zlib.crc32(MAGIC), 8
    canonical: bytes | None = None  # the index records the last chunk should be followed by
    run: list[tuple[int, bytes]] = []  # (offset, bytes) of the index records that follow it
    damaged: list[int] = []
    while True:
        head = fh.read(9)
        if len(head) < 9:
            return None
        op, length = _U8_U64.unpack(head)
        if length > size - pos - 9:
            return None
        body = fh.read(length)
        if op == OP_MESSAGE_INDEX and canonical is not None:
            run.append((pos, head + body))
            pos += 9 + length
            continue
        if run:
            actual = b"".join(r for _, r in run)
            if actual != canonical:
                damaged += [at for at, r in run if r not in canonical]
            crc = zlib.crc32(canonical, crc)
            run, canonical = [], None
        if op == OP_DATA_END:
            want = _U32.unpack_from(body, 0)[0] if length >= 4 else 0
            return damaged if damaged and want == crc else None
        crc = zlib.crc32(body, zlib.crc32(head, crc))
        pos += 9 + length
        canonical = None
        if op == OP_CHUNK:
            view = memoryview(body)
            _start, _end, usize, ucrc = _CHUNK_HEAD.unpack_from(view, 0)
            comp, off = _str(view, 28)
            (rlen,) = _U64.unpack_from(view, off)
            data = _decompress(comp, bytes(view[off + 8:off + 8 + rlen]), usize)
            if not ucrc or zlib.crc32(data) != ucrc:
                return None  # a chunk no CRC vouches for: the damage cannot be placed
            canonical = _canonical_indexes(data)


def index_damage_note(file: str, offsets: Sequence[int]) -> str:
    """What both tools say of a data-section CRC mismatch that only Message Indexes explain."""
    return (f"{file}: data section CRC mismatch, all of it in the message index record(s) at "
            f"byte {', '.join(map(str, offsets))} (rebuilt from their chunks, the CRC then "
            "matches): nothing lost")
