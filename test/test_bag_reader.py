"""bag_reader: streaming, CRC-checked reading of MCAP files and rosbag2 dirs; damage as time ranges.

Bags are written here with mcap + mcap_ros2 (independent of the reader under test) and messages
are serialized with rclpy's own CDR serializer, the oracle for the hand-written JointState decoder.
The helpers at the top are shared with test_audit.py and test_report.py.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from dyn_node.bag.reader import (BagError, BagReader, MessageDecoder, decode_joint_state,
                                 decode_joint_state_batch)

SHARE = Path(sys.prefix) / "share"
PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
              "int32", "uint32", "int64", "uint64", "string", "wstring"}


def msgdef(full_type: str) -> str:
    """The full ros2msg definition text (main type + every dependency), as rosbag2 writes it."""
    pkg, name = full_type.split("/msg/") if "/msg/" in full_type else full_type.split("/")

    def text(p: str, n: str) -> str:
        return (SHARE / p / "msg" / f"{n}.msg").read_text()

    def deps(p: str, body: str) -> list[tuple[str, str]]:
        out = []
        for line in body.splitlines():
            line = line.split("#")[0].strip()
            if not line or "=" in line.split()[1 if len(line.split()) > 1 else 0]:
                continue
            t = re.sub(r"\[.*\]", "", line.split()[0])
            t = re.sub(r"<=\d+", "", t)
            if t in PRIMITIVES:
                continue
            if "/" in t:
                dp, dn = t.split("/")[0], t.split("/")[-1]
            elif t == "Header":
                dp, dn = "std_msgs", "Header"
            else:
                dp, dn = p, t
            out.append((dp, dn))
        return out

    seen: list[tuple[str, str]] = []
    todo = deps(pkg, text(pkg, name))
    while todo:
        d = todo.pop(0)
        if d in seen:
            continue
        seen.append(d)
        todo.extend(deps(d[0], text(*d)))
    parts = [text(pkg, name)]
    for dp, dn in seen:
        parts.append("=" * 80 + f"\nMSG: {dp}/{dn}\n" + text(dp, dn))
    return "\n".join(parts)


class BagWriter:
    """Writes a rosbag2-layout directory (metadata.yaml + name_0.mcap) from rclpy messages."""

    TYPES = {"sensor_msgs/msg/JointState", "trajectory_msgs/msg/JointTrajectory",
             "diagnostic_msgs/msg/DiagnosticArray", "diagnostic_msgs/msg/DiagnosticStatus",
             "std_msgs/msg/String"}

    def __init__(self, path: Path, name: str = "bag", chunk_size: int = 64 * 1024,
                 metadata: dict[str, str] | None = None, compression: str = "zstd",
                 single_file: bool = False, index: int = 0):
        from mcap.writer import CompressionType, Writer

        self.dir = path
        path.mkdir(parents=True, exist_ok=True)
        self.file = path / f"{name}_{index}.mcap" if not single_file else path / f"{name}.mcap"
        self._fh = open(self.file, "wb")
        self.w = Writer(self._fh, chunk_size=chunk_size,
                        compression={"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                                     "none": CompressionType.NONE}[compression],
                        enable_crcs=True, enable_data_crcs=True)
        self.w.start(profile="ros2", library="test")
        self.single = single_file
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, tuple[int, str]] = {}
        self.counts: dict[str, int] = {}
        self.first = self.last = None
        if metadata is not None:
            self.w.add_metadata("dyn_node", metadata)

    def write(self, topic: str, msg, log_ns: int, type_name: str | None = None) -> None:
        from rclpy.serialization import serialize_message

        t = type_name or f"{type(msg).__module__.split('.')[0]}/msg/{type(msg).__name__}"
        if topic not in self.channels:
            if t not in self.schemas:
                self.schemas[t] = self.w.register_schema(t, "ros2msg", msgdef(t).encode())
            cid = self.w.register_channel(topic, "cdr", self.schemas[t])
            self.channels[topic] = (cid, t)
        cid, _ = self.channels[topic]
        self.w.add_message(cid, log_time=log_ns, data=serialize_message(msg), publish_time=log_ns,
                           sequence=self.counts.get(topic, 0))
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.first = log_ns if self.first is None else min(self.first, log_ns)
        self.last = log_ns if self.last is None else max(self.last, log_ns)

    def close(self) -> Path:
        self.w.finish()
        self._fh.close()
        if self.single:
            return self.file
        info = {"rosbag2_bagfile_information": {
            "version": 8, "storage_identifier": "mcap",
            "duration": {"nanoseconds": (self.last or 0) - (self.first or 0)},
            "starting_time": {"nanoseconds_since_epoch": self.first or 0},
            "message_count": sum(self.counts.values()),
            "topics_with_message_count": [
                {"topic_metadata": {"name": tp, "type": t, "serialization_format": "cdr",
                                    "offered_qos_profiles": ""}, "message_count": self.counts[tp]}
                for tp, (_, t) in self.channels.items()],
            "compression_format": "", "compression_mode": "",
            "relative_file_paths": [self.file.name],
            "files": [{"path": self.file.name, "starting_time": {"nanoseconds_since_epoch": self.first},
                       "duration": {"nanoseconds": (self.last or 0) - (self.first or 0)},
                       "message_count": sum(self.counts.values())}],
        }}
        (self.dir / "metadata.yaml").write_text(yaml.safe_dump(info))
        return self.dir


def joint_state(names, q, v=(), e=(), stamp_ns=0):
    from sensor_msgs.msg import JointState

    m = JointState()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    m.header.frame_id = "base"
    m.name = list(names)
    m.position = [float(x) for x in q]
    m.velocity = [float(x) for x in v]
    m.effort = [float(x) for x in e]
    return m


T0 = 1_700_000_000_000_000_000


def simple_bag(path: Path, n: int = 2000, chunk_size: int = 16 * 1024, **kw) -> Path:
    """n JointStates at 1 kHz (3 joints) and a String every 100 messages."""
    from std_msgs.msg import String

    w = BagWriter(path, chunk_size=chunk_size, **kw)
    for i in range(n):
        t = T0 + i * 1_000_000
        w.write("/joint_states", joint_state(["a", "b", "c"], [i * 1e-3, 1.0, -1.0], [1, 0, 0],
                                             [0.5, 0.25, i], stamp_ns=t), t)
        if i % 100 == 0:
            w.write("/chatter", String(data=f"s{i}"), t + 1)
    return w.close()


# --- tests -----------------------------------------------------------------------------------
def test_joint_state_decoder_matches_rclpy_serializer():
    from rclpy.serialization import serialize_message

    rng = np.random.default_rng(0)
    cases = [(["a"], [1.0], [], [2.0]), (["ab", "c"], [1, 2], [3, 4], [5, 6]), (["x"] * 0, [], [], []),
             (["joint_with_long_name_7"], [0.1], [0.2], []), (["q"], [np.nan], [], [np.nan])]
    for k in range(20):
        nj = int(rng.integers(1, 9))
        cases.append(([f"j{i}" * int(rng.integers(1, 4)) for i in range(nj)], rng.normal(size=nj),
                      rng.normal(size=nj) if k % 2 else [], rng.normal(size=nj) if k % 3 else []))
    for names, q, v, e in cases:
        stamp = int(rng.integers(0, 2 ** 31 * 10 ** 9))
        d = decode_joint_state(serialize_message(joint_state(names, q, v, e, stamp_ns=stamp)))
        assert d.names == tuple(names) and d.frame_id == "base" and d.stamp_ns == stamp
        np.testing.assert_array_equal(d.position, np.asarray(q, float))
        np.testing.assert_array_equal(d.velocity, np.asarray(v, float))
        np.testing.assert_array_equal(d.effort, np.asarray(e, float))
    with pytest.raises(ValueError):
        decode_joint_state(serialize_message(joint_state(["a", "b"], [1, 2], [3, 4], [5, 6]))[:30])


def test_batch_decoder_equals_the_message_decoder_and_declines_irregular_runs():
    """decode_joint_state_batch: row k is decode_joint_state of message k (rclpy's serializer
    as the oracle for the bytes); a run whose bytes differ outside stamps and values (other
    names, frame, sizes, big-endian) is declined, so the caller decodes it message by message."""
    from rclpy.serialization import serialize_message

    rng = np.random.default_rng(5)
    for names, nv, ne in ((["a", "bb", "ccc"], 3, 3), (["j1", "j2"], 0, 2), (["x"] * 1, 1, 0),
                          ([f"panda_joint{i}" for i in range(1, 10)], 9, 9)):
        n = len(names)
        datas, want = [], []
        for k in range(40):
            stamp = int(rng.integers(0, 2 ** 31 * 10 ** 9))
            e = rng.normal(size=ne)
            if ne and k % 7 == 0:
                e[0] = np.nan
            d = serialize_message(joint_state(names, rng.normal(size=n), rng.normal(size=nv), e,
                                              stamp_ns=stamp))
            datas.append(d)
            want.append(decode_joint_state(d))
        b = decode_joint_state_batch(datas)
        assert b is not None and b.names == tuple(names)
        assert b.stamp_ns.tolist() == [w.stamp_ns for w in want]
        assert b.sec.tolist() == [w.sec for w in want]
        assert b.nanosec.tolist() == [w.nanosec for w in want]
        for field in ("position", "velocity", "effort"):
            got = getattr(b, field)
            rows = [getattr(w, field) for w in want]
            if len(rows[0]) == 0:
                assert got is None
            else:
                np.testing.assert_array_equal(got, np.array(rows))
                assert np.array_equal(np.signbit(got), np.signbit(np.array(rows)))
    base = serialize_message(joint_state(["a", "b"], [1, 2], [3, 4], [5, 6]))
    other_name = serialize_message(joint_state(["a", "c"], [1, 2], [3, 4], [5, 6]))
    other_frame = bytearray(base)
    other_frame[16] ^= 1  # first byte of the frame id
    shorter = serialize_message(joint_state(["a", "b"], [1, 2], [], [5, 6]))
    for bad in (other_name, bytes(other_frame), shorter, base[:30]):
        assert decode_joint_state_batch([base, base, bad]) is None
    big_endian = bytearray(base)
    big_endian[1] = 0
    assert decode_joint_state_batch([bytes(big_endian)] * 2) is None
    assert decode_joint_state_batch([]) is None


def test_batch_decoder_ignores_what_alignment_padding_holds():
    """CDR leaves alignment padding unspecified and Fast CDR serialises whatever its buffer held
    there (seen in a CI run: garbage after strings and before the first double). Messages equal
    but for their padding are one run, decoded as each decodes alone; a changed byte that is not
    padding still splits the run."""
    from rclpy.serialization import serialize_message

    from dyn_node.bag.reader import _array_spans

    names = ["panda_joint1", "j2", "abc"]  # NUL-terminated lengths 13, 3, 4: padding after each
    rng = np.random.default_rng(11)
    datas = [serialize_message(joint_state(names, rng.normal(size=3), rng.normal(size=3),
                                           rng.normal(size=3), stamp_ns=k * 1_000_000 + 7))
             for k in range(30)]
    spans, pads = _array_spans(datas[0])
    assert pads and sum(n for _, n in pads) >= 6
    padded = []
    for d in datas:
        b = bytearray(d)
        for off, n in pads:
            b[off:off + n] = rng.integers(1, 256, n, dtype=np.uint8).tobytes()
        padded.append(bytes(b))
    got = decode_joint_state_batch(padded)
    assert got is not None and got.names == tuple(names)
    for field, (_off, count) in zip(("position", "velocity", "effort"), spans):
        assert count == 3
        np.testing.assert_array_equal(getattr(got, field),
                                      np.array([getattr(decode_joint_state(d), field) for d in padded]))
    not_padding = bytearray(padded[5])
    not_padding[pads[0][0] - 2] ^= 0x20  # the frame id's last letter ("base"): a real difference
    assert decode_joint_state_batch(padded[:5] + [bytes(not_padding)]) is None


def test_reads_rosbag2_dir_single_file_and_agrees_with_mcap_reader(tmp_path):
    from mcap.reader import make_reader

    bag = simple_bag(tmp_path / "bag")
    r = BagReader(bag)
    msgs = list(r.messages())
    assert r.stats.message_counts == {"/joint_states": 2000, "/chatter": 20}
    assert not r.unreadable and r.stats.data_crc == {"bag_0.mcap": "ok"}
    assert r.stats.crc_checked_chunks == r.stats.chunks > 1
    with open(bag / "bag_0.mcap", "rb") as fh:
        ref = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(fh).iter_messages(
            log_time_order=False)]
    assert [(m.topic, m.log_time_ns, m.data) for m in msgs] == ref
    # topic filter yields only those topics but counts all
    r2 = BagReader(bag / "bag_0.mcap", topics=["/chatter"])
    got = list(r2.messages())
    assert [m.topic for m in got] == ["/chatter"] * 20
    assert r2.stats.message_counts["/joint_states"] == 2000
    assert MessageDecoder().decode(got[3].channel, got[3].data).data == "s300"
    assert decode_joint_state([m for m in msgs if m.topic == "/joint_states"][5].data).effort[2] == 5.0


def test_metadata_record_found_via_summary_and_by_scan(tmp_path):
    bag = simple_bag(tmp_path / "bag", n=50, metadata={"robot_description": "<robot/>", "version": "1"})
    r = BagReader(bag)
    assert r.peek_metadata("dyn_node") == {"robot_description": "<robot/>", "version": "1"}
    assert r.peek_metadata("other") is None
    # without the summary (file cut before the footer) the record is found by scanning
    f = bag / "bag_0.mcap"
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    assert BagReader(bag).peek_metadata("dyn_node")["version"] == "1"


def test_lz4_and_uncompressed_chunks(tmp_path):
    for comp in ("lz4", "none"):
        r = BagReader(simple_bag(tmp_path / comp, n=300, compression=comp))
        assert sum(1 for _ in r.messages()) == 303 and not r.unreadable


@pytest.mark.parametrize("fraction", [0.05, 0.3, 0.5, 0.77, 0.97, 0.999])
def test_truncation_reports_the_lost_range(tmp_path, fraction):
    bag = simple_bag(tmp_path / "bag")
    f = bag / "bag_0.mcap"
    full = f.read_bytes()
    f.write_bytes(full[: int(len(full) * fraction)])
    r = BagReader(bag)
    msgs = [m for m in r.messages() if m.topic == "/joint_states"]
    if len(msgs) == 2000:
        # cut inside the summary section, after the data-end record: nothing is lost
        assert not r.unreadable and r.stats.data_crc["bag_0.mcap"] == "ok"
        return
    assert r.unreadable, "a truncated file must be reported"
    lost = r.unreadable[-1]
    assert "truncated" in lost.reason
    # what was read is a prefix; the lost range starts at or before the first missing message
    # and (bounded by metadata.yaml) ends at the recording's end
    times = [m.log_time_ns for m in msgs]
    assert times == [T0 + i * 1_000_000 for i in range(len(times))]
    first_missing = T0 + len(times) * 1_000_000
    if times:  # the range starts inside what was read (the last chunk header, at the latest)
        assert lost.start_ns is not None
        assert times[-1] - 100 * 1_000_000 <= lost.start_ns <= first_missing
    else:  # nothing read: the range starts at the first chunk's start, or is unknown
        assert lost.start_ns in (None, T0)
    assert lost.end_ns == T0 + 1999 * 1_000_000  # metadata.yaml's end of the recording


def test_corrupt_byte_inside_a_chunk_loses_exactly_that_chunk(tmp_path):
    from mcap.reader import make_reader

    bag = simple_bag(tmp_path / "bag", compression="none")
    f = bag / "bag_0.mcap"
    with open(f, "rb") as fh:
        chunks = list(make_reader(fh).get_summary().chunk_indexes)
    victim = chunks[len(chunks) // 2]
    data = bytearray(f.read_bytes())
    data[victim.chunk_start_offset + victim.chunk_length - 20] ^= 0xFF
    f.write_bytes(bytes(data))
    r = BagReader(bag)
    msgs = list(r.messages())
    assert len(r.unreadable) >= 1
    bad = [u for u in r.unreadable if "chunk" in u.reason]
    assert len(bad) == 1 and "CRC" in bad[0].reason
    assert (bad[0].start_ns, bad[0].end_ns) == (victim.message_start_time, victim.message_end_time)
    lost = [m for m in msgs if victim.message_start_time <= m.log_time_ns <= victim.message_end_time]
    assert not lost
    expected_lost = sum(1 for i in range(2000) if victim.message_start_time <= T0 + i * 1_000_000
                        <= victim.message_end_time) + sum(
        1 for i in range(0, 2000, 100) if victim.message_start_time <= T0 + i * 1_000_000 + 1
        <= victim.message_end_time)
    assert len(msgs) == 2020 - expected_lost


def test_compressed_chunk_corruption_and_garbage_files(tmp_path):
    from mcap.reader import make_reader

    bag = simple_bag(tmp_path / "bag")
    f = bag / "bag_0.mcap"
    with open(f, "rb") as fh:
        victim = list(make_reader(fh).get_summary().chunk_indexes)[1]
    data = bytearray(f.read_bytes())
    for off in (victim.chunk_start_offset + victim.chunk_length // 2,):
        data[off] ^= 0x55
    f.write_bytes(bytes(data))
    r = BagReader(bag)
    n = sum(1 for _ in r.messages())  # never raises
    assert [(u.start_ns, u.end_ns) for u in r.unreadable] == [
        (victim.message_start_time, victim.message_end_time)]
    assert n < 2020 and r.stats.data_crc["bag_0.mcap"] == "mismatch"
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap at all")
    r = BagReader(tmp_path / "junk.mcap")
    assert list(r.messages()) == [] and "not an MCAP" in r.unreadable[0].reason
    with pytest.raises(BagError):
        BagReader(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError):
        BagReader(tmp_path / "empty")


def test_split_bag_reads_files_in_metadata_order(tmp_path):
    """A split bag: files are read in metadata.yaml order (not name order), metadata from either."""
    from std_msgs.msg import String

    d = tmp_path / "split"
    # the k-th file of the recording is named bag_{index}: name order (0, 1, 2) would read the
    # recording's files 1, 2, 0 and give the first metadata record of file 1
    order = []
    for k, index in enumerate((2, 0, 1)):
        w = BagWriter(d, index=index, metadata={"version": str(k)})
        for i in range(100):
            t = T0 + (k * 100 + i) * 1_000_000
            w.write("/joint_states", joint_state(["a"], [k * 100 + i]), t)
        w.write("/robot_description", String(data="<robot/>"), T0 + k * 100 * 1_000_000)
        w.w.finish()
        w._fh.close()
        order.append(w.file.name)
    assert order == ["bag_2.mcap", "bag_0.mcap", "bag_1.mcap"]
    (d / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": {
        "relative_file_paths": order, "starting_time": {"nanoseconds_since_epoch": T0},
        "duration": {"nanoseconds": 299 * 1_000_000}}}))
    r = BagReader(d)
    pos = [decode_joint_state(m.data).position[0] for m in r.messages() if m.topic == "/joint_states"]
    assert pos == list(range(300)) and r.stats.message_counts["/robot_description"] == 3
    assert r.peek_metadata("dyn_node") == {"version": "0"}
    assert r.metadata_records("dyn_node") == [{"version": "0"}, {"version": "1"}, {"version": "2"}]
    assert r.known_topics() == {"/joint_states", "/robot_description"}  # from the summaries


def _unchunked_bag(path: Path, n: int = 30) -> Path:
    """n JointStates written as Message records outside any chunk (mcap's unchunked mode)."""
    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh, use_chunking=False, enable_crcs=True)
        w.start(profile="ros2", library="test")
        t = "sensor_msgs/msg/JointState"
        sid = w.register_schema(t, "ros2msg", msgdef(t).encode())
        cid = w.register_channel("/joint_states", "cdr", sid)
        from rclpy.serialization import serialize_message
        for i in range(n):
            ts = T0 + i * 1_000_000
            w.add_message(cid, log_time=ts, publish_time=ts, sequence=i,
                          data=serialize_message(joint_state(["a"], [float(i)], stamp_ns=ts)))
        w.finish()
    return path


def _message_record_offsets(data: bytes) -> list[int]:
    """Byte offsets of the Message records (opcode 0x05) of an unchunked file's data section."""
    import struct

    out, off = [], 8
    while off + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, off)
        if op == 0x0F:  # data end
            break
        if op == 0x05:
            out.append(off)
        off += 9 + length
    return out


def test_a_malformed_record_outside_a_chunk_is_skipped_and_reading_goes_on(tmp_path):
    """One unreadable Message record outside a chunk (channel id no Channel record defines) and
    one cut short: both skipped and reported, every other message still read (as dyn-bag-recover
    does), the lost range from the message before them to the message after them."""
    import struct

    f = _unchunked_bag(tmp_path / "u.mcap")
    data = bytearray(f.read_bytes())
    offs = _message_record_offsets(bytes(data))
    assert len(offs) == 30
    struct.pack_into("<H", data, offs[10] + 9, 0xFFFF)      # message 10: unknown channel
    struct.pack_into("<Q", data, offs[20] + 1, 10)          # message 20: 10 bytes, header cut
    # the bytes after message 20's shortened body are not a record: keep the file parseable by
    # giving them a record of their own (an unknown opcode, which readers must skip)
    rest = struct.unpack_from("<Q", bytes(f.read_bytes()), offs[20] + 1)[0] - 10
    struct.pack_into("<BQ", data, offs[20] + 9 + 10, 0x80, rest - 9)
    f.write_bytes(bytes(data))
    r = BagReader(f)
    got = [decode_joint_state(m.data).position[0] for m in r.messages()]
    assert got == [float(i) for i in range(30) if i not in (10, 20)]
    assert [(u.start_ns, u.end_ns) for u in r.unreadable] == [
        (T0 + 9 * 1_000_000, T0 + 11 * 1_000_000), (T0 + 19 * 1_000_000, T0 + 21 * 1_000_000)]
    assert all("malformed record (opcode 0x05)" in u.reason for u in r.unreadable)
    assert f"at byte {offs[10]} skipped" in r.unreadable[0].reason
    assert r.stats.message_counts == {"/joint_states": 28}


def test_malformed_records_at_the_end_run_to_the_end_of_the_recording(tmp_path):
    import struct

    f = _unchunked_bag(tmp_path / "u.mcap", n=10)
    data = bytearray(f.read_bytes())
    offs = _message_record_offsets(bytes(data))
    for k in (8, 9):
        struct.pack_into("<H", data, offs[k] + 9, 0xFFFF)
    f.write_bytes(bytes(data))
    r = BagReader(f)
    assert len(list(r.messages())) == 8
    assert [(u.start_ns, u.end_ns) for u in r.unreadable] == [(T0 + 7 * 1_000_000, None)]
    assert "and 1 more record(s) after it" in r.unreadable[0].reason


def test_every_metadata_record_in_file_order_via_summary_and_by_scan(tmp_path, monkeypatch):
    """A recorder writes one dyn_node record per configuration; all are found, in order, also
    when the file has no summary (cut short: read without decompressing any chunk)."""
    from std_msgs.msg import String

    w = BagWriter(tmp_path / "bag", chunk_size=1024, metadata={"version": "a"})
    for i in range(300):
        w.write("/chatter", String(data=f"s{i}"), T0 + i * 1_000_000)
        if i in (100, 200):
            w.w.add_metadata("other", {"k": str(i)})
            w.w.add_metadata("dyn_node", {"version": str(i)})
    bag = w.close()
    want = [{"version": "a"}, {"version": "100"}, {"version": "200"}]
    assert BagReader(bag).metadata_records("dyn_node") == want
    f = bag / "bag_0.mcap"
    data = f.read_bytes()
    f.write_bytes(data[: int(len(data) * 0.9)])
    import dyn_node.bag.reader as br

    calls = []
    real = br._decompress
    monkeypatch.setattr(br, "_decompress", lambda *a: calls.append(1) or real(*a))
    r = BagReader(bag)
    assert r.metadata_records("dyn_node") == want
    assert r.metadata_records("other") == [{"k": "100"}, {"k": "200"}]
    assert calls == []  # the scan skipped every chunk
    assert len(list(r.messages())) > 0 and calls  # (and reading messages does decompress)


def _record_offsets(data: bytes, opcode: int) -> list[int]:
    """Byte offsets of the records ``opcode`` in a file's data section (outside chunks)."""
    import struct

    out, off = [], 8
    while off + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, off)
        if op == 0x0F:
            break
        if op == opcode:
            out.append(off)
        off += 9 + length
    return out


def test_messages_whose_schema_record_is_unreadable_are_counted_as_lost(tmp_path):
    """The Schema record skipped as malformed: its channel's 30 messages cannot be decoded, so
    they are not handed out with an empty schema (where a reader ignores them uncounted) but
    counted and reported over their log-time range."""
    import struct

    f = _unchunked_bag(tmp_path / "u.mcap")
    data = bytearray(f.read_bytes())
    (at,) = _record_offsets(bytes(data), 0x03)
    struct.pack_into("<I", data, at + 9 + 2, 0xFFFFFF)  # the schema name runs past its record
    f.write_bytes(bytes(data))
    r = BagReader(f)
    assert list(r.messages()) == []
    lost = [u for u in r.unreadable if "undecodable" in u.reason]
    assert [(u.start_ns, u.end_ns) for u in lost] == [(T0, T0 + 29 * 1_000_000)]
    assert "30 message(s) on /joint_states" in lost[0].reason and "schema (id 1)" in lost[0].reason
    assert r.stats.undecodable_messages == 30


def test_strings_that_are_not_utf8_are_damage_not_replacement_characters(tmp_path):
    """A topic name with a byte that is not UTF-8: the Channel record is skipped and reported
    (never a topic named with U+FFFD), and a JointState whose joint name is not UTF-8 does not
    decode (rclpy cannot deserialise it either)."""
    from rclpy.serialization import serialize_message

    f = _unchunked_bag(tmp_path / "u.mcap")
    data = bytearray(f.read_bytes())
    (at,) = _record_offsets(bytes(data), 0x04)
    data[data.index(b"/joint_states", at) + 1] = 0xE9
    f.write_bytes(bytes(data))
    r = BagReader(f)
    assert list(r.messages()) == [] and r.stats.message_counts == {}
    assert any("opcode 0x04" in u.reason for u in r.unreadable), r.unreadable
    raw = bytearray(serialize_message(joint_state(["joint_a"], [1.0])))
    raw[raw.index(b"joint_a")] = 0xE9
    with pytest.raises(ValueError):
        decode_joint_state(bytes(raw))


def test_a_directory_without_metadata_yaml_never_reads_dyn_bag_recover_outputs(tmp_path, capsys):
    """dyn-bag-recover's outputs beside the input (named *.recovered.mcap, or renamed: told by
    their Header) are not inputs of the bag, or every message would be read twice; a directory
    of nothing but such files is a recovered bag and is read."""
    import shutil

    from dyn_node.bag.recover import main as recover

    d = tmp_path / "bag"
    d.mkdir()
    f = _unchunked_bag(d / "u.mcap")
    assert recover([str(f)]) == 0
    shutil.copy(d / "u.recovered.mcap", d / "renamed.mcap")
    r = BagReader(d)
    assert r.files == [f]
    assert len(list(r.messages())) == 30
    only = tmp_path / "only"
    only.mkdir()
    shutil.copy(d / "u.recovered.mcap", only / "u.recovered.mcap")
    assert len(list(BagReader(only).messages())) == 30


def test_a_deleted_split_file_is_a_partial_audit_naming_the_gap(tmp_path):
    """A 6-file bag with ``_1.mcap`` deleted (metadata.yaml still lists it) once audited exit 0
    "all feasible": the missing file is damage, its time range named from metadata.yaml."""
    from mcap.reader import make_reader

    from dyn_node.audit.bag_audit import AuditOptions, run_audit
    from fleet_bags import write_split_bag

    bag = write_split_bag(tmp_path, "split")
    files = sorted(bag.glob("*.mcap"), key=lambda f: int(f.stem.rsplit("_", 1)[1]))
    assert len(files) == 6
    # the deleted file's own span and count, read by the official reader before it goes
    with open(files[1], "rb") as fh:
        st = make_reader(fh).get_summary().statistics
    with open(files[0], "rb") as fh:
        first = make_reader(fh).get_summary().statistics.message_start_time
    files[1].unlink()
    res = run_audit(AuditOptions(bag=str(bag), out=str(tmp_path / "audit"), robot_model="panda", report=False))
    rec = res.record
    assert res.exit_code == 3 and rec["verdict"]["partial"] is True
    ranges = rec["input_quality"]["unreadable_ranges"]
    assert len(ranges) == 1
    gap = ranges[0]
    assert gap["reason"] == f"{files[1].name}: listed in metadata.yaml but missing, {st.message_count} messages"
    assert gap["start_s"] == pytest.approx((st.message_start_time - first) * 1e-9, abs=1e-9)
    assert gap["end_s"] == pytest.approx((st.message_end_time - first) * 1e-9, abs=1e-9)
    assert 0.9 < gap["end_s"] - gap["start_s"] < 1.0 and st.message_count >= 450
