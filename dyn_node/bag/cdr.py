"""CDR without rclpy: sensor_msgs/JointState (one decoder for the audit's bag reader and the
live node, which reads its subscription's raw bytes with ``strict=True``), a Header's stamp and
std_msgs/String.

The JointState decoder is written by hand because it is the hot path of both (1 kHz for hours);
the tests check it against rclpy's serializer.
"""
from __future__ import annotations

import struct
import sys
from typing import TYPE_CHECKING, NamedTuple, Sequence

if TYPE_CHECKING:
    import numpy as np

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
_LITTLE = sys.byteorder == "little"
# names by their raw CDR bytes, with whether every one is exact (non-empty length, NUL-terminated,
# no NUL inside): senders repeat the same names in almost every message
_name_cache: dict[bytes, tuple[tuple[str, ...], bool]] = {}
_last_names: list = [b"", (), True]  # the last little-endian message's raw names, names, exact


def decode_joint_state(data: bytes, *, strict: bool = False) -> JointStateData:
    """Decode the CDR bytes of a sensor_msgs/JointState (little- or big-endian XCDR1). Raises
    ValueError on bytes that do not parse.

    ``strict``: also refuse what rclpy might read otherwise (big-endian data or host; a name
    that is empty, unterminated or holds a NUL), and leave the frame id unread (""); the live
    node then lets rclpy's deserialisation judge the message.
    """
    import numpy as np

    if len(data) < 12 or data[0] != 0 or data[1] not in (0, 1):
        raise ValueError("not a CDR encapsulation header")
    if strict and (data[1] != 1 or not _LITTLE):
        raise ValueError("not little-endian CDR on a little-endian host")
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
        frame = bytes(buf[12:off - 1]).decode("utf-8") if ln and not strict else ""
        off = (off + 3) & ~3
        start = off
        last_raw, last_names, exact = _last_names
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
            cached = _name_cache.get(raw)
            if cached is None:
                cached = _parse_names(raw, u32)
                if len(_name_cache) < 64:
                    _name_cache[raw] = cached
            names, exact = cached
            if le:
                _last_names[:] = [raw, names, exact]
        if strict and not exact:
            raise ValueError("a name that rclpy may read otherwise (empty, unterminated or with a NUL)")
        layout = _layouts.get((off, n)) if le else None
        if layout is not None and layout[0].unpack_from(buf, off) == layout[1]:
            # Same array sizes where the last such message had them: one view, three slices.
            _, _, first, span, parts = layout
            whole = np.frombuffer(buf, dtype="<f8", count=span, offset=first) if span else _EMPTY
            arrays = [whole[i:j] if j else _EMPTY for i, j in parts]
        else:
            arrays = _read_arrays(buf, off, le, u32)
    except struct.error as exc:
        raise ValueError(f"JointState CDR ends early ({exc})") from None
    return JointStateData(sec, nsec, sec * 1_000_000_000 + nsec, frame, names, *arrays)


def _read_arrays(buf: memoryview, off: int, le: bool, u32) -> list:
    """position, velocity and effort from ``off`` on, as read-only float64 arrays; a
    little-endian layout is remembered for the next message of the same shape."""
    import numpy as np

    n = len(buf)
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
    return arrays


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


def _parse_names(raw: bytes, u32) -> tuple[tuple[str, ...], bool]:
    """The names of a JointState's raw name sequence, and whether each is exact CDR (a length
    counting its terminating NUL, and no NUL before it)."""
    count = u32(raw, 0)[0]
    off = 4
    out = []
    exact = True
    for _ in range(count):
        off = (off + 3) & ~3
        ln = u32(raw, off)[0]
        off += 4
        text = raw[off:off + ln - 1 if ln else off]
        exact = exact and ln != 0 and raw[off + ln - 1] == 0 and b"\0" not in text
        out.append(text.decode("utf-8"))
        off += ln
    return tuple(out), exact


# --- other CDR: a Header's stamp, std_msgs/String ------------------------------------------
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
