"""The MCAP record primitives the reader, the summary scans and dyn-bag-recover share: magic,
opcodes, fixed-size heads, strict strings and maps, chunk decompression."""
from __future__ import annotations

import struct

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_METADATA, OP_METADATA_INDEX, OP_DATA_END = 0x0C, 0x0D, 0x0F
OP_MESSAGE_INDEX = 0x07

_U8_U64 = struct.Struct("<BQ")
_MSG_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed crc
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")



def _str(buf: memoryview, off: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(buf, off)
    off += 4
    if off + n > len(buf):
        raise ValueError("string runs past the end of its record")
    # Strict: a string that is not UTF-8 is damage (dyn-bag-recover skips such a record too),
    # never a value with U+FFFD in it that a reader would take as what was written.
    return bytes(buf[off:off + n]).decode("utf-8"), off + n


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


def _salvage_map(buf: memoryview, off: int) -> tuple[dict[str, str], list[str]]:
    """The fields of a map whose framing holds but some strings are not UTF-8: (the pairs that
    decode, the keys (or ``#i``) of those that do not). Never raises."""
    good: dict[str, str] = {}
    bad: list[str] = []
    try:
        (n,) = _U32.unpack_from(buf, off)
        off += 4
        end = min(off + n, len(buf))
        while off < end:
            raw = []
            for _ in range(2):
                (ln,) = _U32.unpack_from(buf, off)
                raw.append(bytes(buf[off + 4:off + 4 + ln]))
                off += 4 + ln
            try:
                good[raw[0].decode("utf-8")] = raw[1].decode("utf-8")
            except UnicodeDecodeError:
                bad.append(raw[0].decode("utf-8", "backslashreplace"))
    except struct.error:
        pass
    return good, bad


def _decompress(kind: str, data: bytes, size: int) -> bytes:
    """A chunk's records from its compressed bytes (``size``: the uncompressed size declared)."""
    if kind == "":
        return data
    if kind == "zstd":
        import zstandard
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if kind == "lz4":
        import lz4.frame
        return lz4.frame.decompress(data)
    raise ValueError(f"unsupported chunk compression '{kind}'")
