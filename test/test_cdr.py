"""The one JointState CDR decoder (dyn_node.bag.cdr), as the audit uses it and as the live node uses
it (strict: whatever rclpy might read otherwise is refused, and the node lets rclpy judge it).
The bytes are built here by hand from the XCDR1 layout, and checked against rclpy's reading."""
from __future__ import annotations

import array
import struct

import numpy as np
import pytest

from dyn_node.bag.cdr import decode_joint_state


def _cdr(names_raw: list[bytes], pos: list[float], *, big: bool = False, sec: int = 7,
         nsec: int = 9, frame: bytes = b"f") -> bytes:
    """A sensor_msgs/JointState in XCDR1; ``names_raw``: each name's bytes as sent (the length
    field counts them all, so a name may lack its NUL or hold one inside)."""
    e = ">" if big else "<"
    body = bytearray(struct.pack(e + "iI", sec, nsec))
    body += struct.pack(e + "I", len(frame) + 1) + frame + b"\0"

    def align(n: int) -> None:
        body.extend(b"\0" * (-len(body) % n))

    align(4)
    body += struct.pack(e + "I", len(names_raw))
    for raw in names_raw:
        align(4)
        body += struct.pack(e + "I", len(raw)) + raw
    for values in (pos, [], pos):
        align(4)
        body += struct.pack(e + "I", len(values))
        if values:
            align(8)
            body += struct.pack(e + "%dd" % len(values), *values)
    return (b"\x00\x00" if big else b"\x00\x01") + b"\x00\x00" + bytes(body)


GOOD = [b"j1\0", b"joint_2\0"]


def test_strict_and_lax_read_a_plain_message_as_rclpy_does():
    rclpy_ser = pytest.importorskip("rclpy.serialization")
    from sensor_msgs.msg import JointState

    data = _cdr(GOOD, [0.5, -1.25])
    ref = rclpy_ser.deserialize_message(data, JointState)
    for strict in (False, True):
        js = decode_joint_state(data, strict=strict)
        assert (js.sec, js.nanosec, js.stamp_ns) == (7, 9, 7_000_000_009)
        assert list(js.names) == list(ref.name) == ["j1", "joint_2"]
        assert js.position.tolist() == list(ref.position) == [0.5, -1.25]
        assert js.velocity.size == len(ref.velocity) == 0
        assert js.effort.tolist() == list(ref.effort)
    assert decode_joint_state(data).frame_id == ref.header.frame_id == "f"
    assert decode_joint_state(data, strict=True).frame_id == ""  # the node does not read it


def test_the_nodes_parser_gives_rclpys_types_from_the_same_decoder():
    pytest.importorskip("rclpy")
    from dyn_node.ros.convert import parse_joint_state_cdr

    sec, nsec, names, p, v, e = parse_joint_state_cdr(_cdr(GOOD, [0.5, -1.25]))
    assert (sec, nsec, names) == (7, 9, ["j1", "joint_2"])
    assert isinstance(names, list)
    for a in (p, v, e):
        assert isinstance(a, array.array) and a.typecode == "d"
    assert (p.tolist(), v.tolist(), e.tolist()) == ([0.5, -1.25], [], [0.5, -1.25])


@pytest.mark.parametrize("bad", [[b"j1\0", b"ab"],          # no terminating NUL
                                 [b"j1\0", b""],            # a length of 0
                                 [b"j\0x\0", b"joint_2\0"]])  # a NUL inside
def test_strict_refuses_names_rclpy_may_read_otherwise(bad):
    data = _cdr(bad, [0.5, -1.25])
    js = decode_joint_state(data)  # the audit reads them as they are
    assert len(js.names) == 2 and js.position.tolist() == [0.5, -1.25]
    with pytest.raises(ValueError):
        decode_joint_state(data, strict=True)
    decode_joint_state(_cdr(GOOD, [1.0, 2.0]), strict=True)  # the cache does not carry it over
    with pytest.raises(ValueError):
        decode_joint_state(data, strict=True)


def test_big_endian_is_read_by_the_audit_and_left_to_rclpy_by_the_node():
    le, be = _cdr(GOOD, [0.5, -1.25]), _cdr(GOOD, [0.5, -1.25], big=True)
    a, b = decode_joint_state(le), decode_joint_state(be)
    assert (a.stamp_ns, a.names) == (b.stamp_ns, b.names)
    assert np.array_equal(a.position, b.position) and np.array_equal(a.effort, b.effort)
    with pytest.raises(ValueError):
        decode_joint_state(be, strict=True)


def test_every_cut_of_a_message_is_refused():
    data = _cdr(GOOD, [0.5, -1.25])
    for cut in range(len(data) - 1, 0, -1):
        for strict in (False, True):
            with pytest.raises(ValueError):
                decode_joint_state(data[:cut], strict=strict)
