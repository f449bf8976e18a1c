"""Conversions between ROS messages and dyn_node's plain values (the only place that knows both).

Stamps become float seconds; sequences stay as the message's ``array.array('d')`` (NumPy reads them
without copying element by element); :class:`~dyn_node.core.robot.status.Status` maps one-to-one onto
``diagnostic_msgs/DiagnosticStatus`` (level as the byte diagnostic_msgs defines).
"""
from __future__ import annotations

import array
import struct
from dataclasses import dataclass
from typing import Any, Iterable, Sequence

import numpy as np
from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from dyn_node.bag.cdr import decode_joint_state
from dyn_node.core.robot.status import Status


def stamp_to_s(stamp: Time) -> float:
    """builtin_interfaces/Time → seconds (float)."""
    return stamp.sec + stamp.nanosec * 1e-9


def _sec_nanosec(t: float) -> tuple[int, int]:
    """The one rounding rule of seconds → (sec, nanosec): floor, nanoseconds rounded to nearest,
    a carry when they round to 10⁹ (so 0.9999999999 s is 1 s 0 ns, never 0 s 10⁹ ns)."""
    sec = int(t // 1)
    nanosec = int(round((t - sec) * 1e9))
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return sec, nanosec


def s_to_stamp(t: float) -> Time:
    sec, nanosec = _sec_nanosec(t)
    return Time(sec=sec, nanosec=nanosec)


def s_to_duration(t: float) -> Duration:
    """Seconds → builtin_interfaces/Duration (time_from_start), by :func:`s_to_stamp`'s rule."""
    sec, nanosec = _sec_nanosec(t)
    return Duration(sec=sec, nanosec=nanosec)


def duration_to_s(d: Duration) -> float:
    return d.sec + d.nanosec * 1e-9


def to_byte(value: int | bool) -> bytes:
    """The one-byte ``bytes`` a rosidl ``byte`` field needs (diagnostic_msgs' ``level``,
    SelfTest's ``passed``). Every byte field the node and dyn_sim write goes through here: rclpy
    does not convert other values (a ``bool`` assigned to ``byte passed`` is serialised as a
    garbage byte), so anything but an integer 0..255 (``bool``: 0/1) raises TypeError/ValueError."""
    if isinstance(value, (bool, np.bool_)):
        return b"\x01" if value else b"\x00"
    if not isinstance(value, (int, np.integer)):
        raise TypeError(f"a byte field needs an integer 0..255, not {type(value).__name__}")
    if not 0 <= int(value) <= 255:
        raise ValueError(f"a byte field holds 0..255, not {int(value)}")
    return bytes([int(value)])


def status_to_msg(status: Status) -> DiagnosticStatus:
    return DiagnosticStatus(level=to_byte(status.level), name=status.name, message=status.message,
                            hardware_id=status.hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in status.key_values()])


def diagnostic_array(statuses: Iterable[Status], stamp: Time) -> DiagnosticArray:
    out = DiagnosticArray()
    out.header.stamp = stamp
    out.status = [status_to_msg(s) for s in statuses]
    return out


class JointStateOut:
    """An outgoing JointState for one model's joint names (set once), encoded per message."""

    def __init__(self, names: Sequence[str]):
        self.names = list(names)
        self._segments: tuple[bytes, bytes, bytes, bytes] | None = None

    def encode(self, sec: int, nanosec: int, q: np.ndarray, v: np.ndarray, effort: np.ndarray) -> bytes:
        """The CDR bytes (little endian) of the JointState with these names, the stamp (sec,
        nanosec) and the arrays as position, velocity and effort, for ``publish(bytes)``.

        rclpy's ``publish(msg)`` converts the Python message to C and serialises it on every
        call; the names never change, so everything but the stamp and the three arrays is laid
        out once here. Each array must have one float64 per name (the model's order). Padding
        bytes are zero (Fast DDS leaves them unspecified); deserialising gives the same message.
        """
        segs = self._segments
        if segs is None:
            segs = self._segments = _joint_state_segments(self.names)
        return b"".join((segs[0], _TIME.pack(sec, nanosec), segs[1],
                         np.asarray(q, dtype="<f8").tobytes(), segs[2],
                         np.asarray(v, dtype="<f8").tobytes(), segs[3],
                         np.asarray(effort, dtype="<f8").tobytes()))


class WrenchStampedOut:
    """An outgoing geometry_msgs/WrenchStamped in one frame (set once), encoded per message as
    :class:`JointStateOut` does: header stamp, frame_id, force (N) then torque (N·m)."""

    def __init__(self, frame_id: str):
        self.frame_id = frame_id
        body = bytearray(8)  # the stamp's place
        name = frame_id.encode() + b"\0"
        body += _U32.pack(len(name)) + name
        body += b"\0" * ((-len(body)) % 8)  # the first double is 8-aligned
        self._head = b"\x00\x01\x00\x00"
        self._frame = bytes(body[8:])

    def encode(self, sec: int, nanosec: int, wrench: np.ndarray) -> bytes:
        """The CDR bytes (little endian) for ``publish(bytes)``; ``wrench`` = [fx, fy, fz, mx, my, mz]."""
        return b"".join((self._head, _TIME.pack(sec, nanosec), self._frame,
                         np.asarray(wrench, dtype="<f8").tobytes()))


def _joint_state_segments(names: list[str]) -> tuple[bytes, bytes, bytes, bytes]:
    """Constant parts of a JointState's CDR with ``names`` and len(names) values per array:
    (encapsulation header, stamp → first double, between arrays 1 and 2, between 2 and 3).
    Offsets count from the end of the 4-byte encapsulation header, as CDR alignment does."""
    body = bytearray(8)  # the stamp's place

    def pad(to: int) -> None:
        body.extend(b"\0" * ((-len(body)) % to))

    body += _U32.pack(1) + b"\0"  # frame_id ""
    pad(4)
    body += _U32.pack(len(names))
    for name in names:
        b = name.encode() + b"\0"
        pad(4)
        body += _U32.pack(len(b)) + b
    marks = []
    for _ in range(3):
        marks.append(len(body))
        pad(4)
        body += _U32.pack(len(names))
        if names:  # CDR aligns the first element; an empty sequence has none
            pad(8)
        marks.append(len(body))
        body += bytes(8 * len(names))  # the array's place
    b = bytes(body)
    return (b"\x00\x01\x00\x00", b[8:marks[1]], b[marks[2]:marks[3]], b[marks[4]:marks[5]])


def parse_joint_state_cdr(data: bytes) -> tuple[int, int, list, array.array, array.array, array.array]:
    """(stamp sec, stamp nanosec, names, position, velocity, effort) of a little-endian CDR
    sensor_msgs/JointState (what Fast DDS sends on x86 and ARM), with the types rclpy's
    deserialisation gives, without building rclpy's message object
    (:func:`dyn_node.bag.cdr.decode_joint_state`, strict). Raises ValueError on anything else;
    callers then fall back to ``deserialize_message``, which decides what is malformed."""
    js = decode_joint_state(data, strict=True)
    return (js.sec, js.nanosec, list(js.names), array.array("d", js.position.tobytes()),
            array.array("d", js.velocity.tobytes()), array.array("d", js.effort.tobytes()))


def _rows(seqs: list) -> np.ndarray | list:
    """Per-point ``array('d')`` fields as one N×k array when every point has the same length k
    (built from the raw bytes: the per-point loop stays in Python, so other threads keep the GIL
    in turns, and the copy is one memcpy), else the list itself so validation reports the odd one."""
    if not seqs:
        return seqs
    k = len(seqs[0])
    if any(len(r) != k for r in seqs):
        return seqs
    if k == 0:
        return np.zeros((len(seqs), 0))
    return np.frombuffer(b"".join([r.tobytes() if isinstance(r, array.array)
                                   else np.asarray(r, dtype=float).tobytes() for r in seqs]),
                         dtype=float).reshape(len(seqs), k)


def trajectory_arrays(msg: JointTrajectory) -> tuple[list[str], list[float], Any, Any, Any]:
    """(names, times s, positions, velocities, accelerations): N×k arrays (lists of per-point
    sequences when the points disagree in length)."""
    pts = msg.points
    times = [duration_to_s(p.time_from_start) for p in pts]
    return (list(msg.joint_names), times, _rows([p.positions for p in pts]),
            _rows([p.velocities for p in pts]), _rows([p.accelerations for p in pts]))


def trajectory_message(traj: Any, joint_names: Sequence[str], header: Any) -> JointTrajectory:
    """A model-order core Trajectory as a JointTrajectory under ``header`` (velocities and
    accelerations when it has them; times by :func:`s_to_duration`)."""
    points = []
    for i, t in enumerate(np.asarray(traj.times, dtype=float)):
        p = JointTrajectoryPoint(positions=traj.positions[i].tolist(), time_from_start=s_to_duration(float(t)))
        if traj.velocities is not None:
            p.velocities = traj.velocities[i].tolist()
        if traj.accelerations is not None:
            p.accelerations = traj.accelerations[i].tolist()
        points.append(p)
    return JointTrajectory(header=header, joint_names=list(joint_names), points=points)


def goal_trajectory_message(template: JointTrajectory, traj: Any, joint_names: Sequence[str]) -> JointTrajectory:
    """``template`` (a goal's JointTrajectory, header kept) with ``traj``'s points (model order)."""
    return trajectory_message(traj, joint_names, template.header)


def fill_trajectory_effort(msg: JointTrajectory, effort_model_order: np.ndarray,
                           model_joints: Sequence[str]) -> JointTrajectory:
    """``msg`` with every point's effort set from an N×nv model-order array, in the message's joint
    order (modified in place and returned)."""
    order = np.array([list(model_joints).index(n) for n in msg.joint_names])
    eff = np.ascontiguousarray(effort_model_order[:, order], dtype=float)
    for p, row in zip(msg.points, eff):
        p.effort = array.array("d", row.tobytes())
    return msg


# --- JointTrajectory CDR without a Python message ------------------------------------------
# rclpy builds a Python object per waypoint when it deserialises a JointTrajectory, in one C call
# that holds the GIL for seconds on a long trajectory, during which no joint_states callback can
# run (docs/INTERNALS.md).
# Reading the CDR bytes here keeps the per-point loop in Python (the interpreter hands the GIL to
# the executor thread every few milliseconds) and gathers the numbers with NumPy.
# Layout (XCDR1, little endian, offsets aligned relative to the byte after the 4-byte
# encapsulation header): Header{Time{int32 sec, uint32 nanosec}, string frame_id},
# sequence<string> joint_names, sequence<JointTrajectoryPoint{sequence<double> positions,
# velocities, accelerations, effort; Duration{int32 sec, uint32 nanosec}}>. A string is uint32
# length (NUL included) then the bytes; an empty double sequence has no alignment padding.

_U32 = struct.Struct("<I")
_TIME = struct.Struct("<iI")


@dataclass(frozen=True)
class RawTrajectory:
    """A JointTrajectory read from CDR: stamp, frame_id, names and per-point N×k arrays
    (``None`` for a field whose points disagree in length: ``lists`` then has the rows)."""

    stamp: Time
    frame_id: bytes
    names: list[str]
    times: list[float]
    durations: list[tuple[int, int]]
    fields: tuple[Any, Any, Any, Any]  # positions, velocities, accelerations, effort


def _align(off: int, n: int) -> int:
    return (off + n - 1) & ~(n - 1)


def parse_joint_trajectory_cdr(data: bytes) -> RawTrajectory:
    """Read a serialised trajectory_msgs/JointTrajectory; raises ValueError if it is not one."""
    if len(data) < 4 or data[1] != 1:  # only CDR little endian (what every DDS on x86/ARM sends)
        raise ValueError("not little-endian CDR")
    body = memoryview(data)[4:]
    off = 0
    sec, nsec = _TIME.unpack_from(body, off)
    off += 8
    (n,) = _U32.unpack_from(body, off)
    off += 4
    frame_id = bytes(body[off:off + max(n - 1, 0)])
    off += n
    off = _align(off, 4)
    (count,) = _U32.unpack_from(body, off)
    off += 4
    names = []
    for _ in range(count):
        off = _align(off, 4)
        (n,) = _U32.unpack_from(body, off)
        off += 4
        names.append(bytes(body[off:off + n - 1]).decode())
        off += n
    off = _align(off, 4)
    (npts,) = _U32.unpack_from(body, off)
    off += 4
    if npts > len(body):
        raise ValueError("corrupt point count")
    offs = [[0] * npts for _ in range(4)]
    lens = [[0] * npts for _ in range(4)]
    durations = []
    u32, tm = _U32.unpack_from, _TIME.unpack_from
    for i in range(npts):
        for f in range(4):
            off = (off + 3) & ~3
            (n,) = u32(body, off)
            off += 4
            if n:
                off = (off + 7) & ~7
                offs[f][i] = off
                lens[f][i] = n
                off += 8 * n
        off = (off + 3) & ~3
        durations.append(tm(body, off))
        off += 8
    if off > len(body):
        raise ValueError("truncated JointTrajectory")
    D = np.frombuffer(data, dtype="<f8", count=(len(data) - 4) // 8, offset=4)
    fields = []
    for f in range(4):
        ln = np.asarray(lens[f], dtype=np.intp)
        k = int(ln[0]) if npts else 0
        if npts and np.all(ln == k):
            if k == 0:
                fields.append(np.zeros((npts, 0)))
            else:
                idx = np.asarray(offs[f], dtype=np.intp)[:, None] // 8 + np.arange(k)
                fields.append(D[idx])
        else:
            fields.append([D[o // 8:o // 8 + n] for o, n in zip(offs[f], lens[f])])
    return RawTrajectory(Time(sec=sec, nanosec=nsec), frame_id, names,
                         [s + ns * 1e-9 for s, ns in durations], durations, tuple(fields))  # type: ignore[arg-type]


def _seq(out: list, off: int, values: np.ndarray) -> int:
    out_len = len(values)
    pad = _align(off, 4) - off
    out.append(b"\0" * pad + _U32.pack(out_len))
    off += pad + 4
    if out_len:
        pad = _align(off, 8) - off
        out.append(b"\0" * pad + np.ascontiguousarray(values, dtype="<f8").tobytes())
        off += pad + 8 * out_len
    return off


def encode_joint_trajectory_cdr(raw: RawTrajectory, effort: np.ndarray) -> bytes:
    """CDR of the trajectory ``raw`` with every point's effort = the row of ``effort`` (N×k, in
    the message's joint order); rclpy deserialises it to the message it would have serialised
    (padding bytes are zero here, unspecified there). Needs uniform position/velocity/acceleration
    arrays, which a validated trajectory has."""
    out: list[bytes] = [b"\x00\x01\x00\x00", _TIME.pack(raw.stamp.sec, raw.stamp.nanosec)]
    off = 8
    fid = raw.frame_id + b"\0"
    out.append(_U32.pack(len(fid)) + fid)
    off += 4 + len(fid)
    pad = _align(off, 4) - off
    out.append(b"\0" * pad + _U32.pack(len(raw.names)))
    off += pad + 4
    for name in raw.names:
        b = name.encode() + b"\0"
        pad = _align(off, 4) - off
        out.append(b"\0" * pad + _U32.pack(len(b)) + b)
        off += pad + 4 + len(b)
    pad = _align(off, 4) - off
    out.append(b"\0" * pad + _U32.pack(len(raw.times)))
    off += pad + 4
    P, V, A, _ = raw.fields
    for i, (sec, nsec) in enumerate(raw.durations):
        for rows in (P, V, A):
            off = _seq(out, off, rows[i])
        off = _seq(out, off, effort[i])
        pad = _align(off, 4) - off
        out.append(b"\0" * pad + _TIME.pack(sec, nsec))
        off += pad + 8
    return b"".join(out)


def trajectory_header_cdr(data: bytes) -> tuple[Time, str]:
    """(stamp, frame_id) of a serialised trajectory_msgs/JointTrajectory, reading only the header
    (cheap enough for a subscription callback whatever the trajectory's length); big-endian or
    unexpected bytes go through rclpy's deserialisation."""
    try:
        if len(data) < 16 or data[1] != 1:
            raise ValueError("not little-endian CDR")
        sec, nsec = _TIME.unpack_from(data, 4)
        (n,) = _U32.unpack_from(data, 12)
        if n == 0 or 16 + n > len(data):
            raise ValueError("frame_id beyond the data")
        return Time(sec=sec, nanosec=nsec), bytes(data[16:16 + n - 1]).decode()
    except (ValueError, struct.error, UnicodeDecodeError):
        from rclpy.serialization import deserialize_message

        msg = deserialize_message(data, JointTrajectory)
        return msg.header.stamp, msg.header.frame_id


def verdict_array(statuses: Sequence[Status], stamp: Time, frame_id: str, request: str) -> DiagnosticArray:
    """A ``~/feasibility`` verdict: the statuses under the request's whole header (stamp and
    frame_id, so a client can match answers to tagged requests), and the key ``request``
    (``execute``, ``check`` or ``inverse_dynamics``) in the summary status."""
    from dyn_node.core.check.on_demand import with_request

    out = diagnostic_array(with_request(statuses, request), stamp)
    out.header.frame_id = frame_id
    return out
