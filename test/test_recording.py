"""The pure bag writer, read back by independent readers (rosbags, mcap) with exact counts."""
from __future__ import annotations

import errno
import io
import struct
import threading
import zlib
import time
from pathlib import Path

import pytest
import yaml
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import (Channel, Chunk, ChunkIndex, Message, MessageIndex, Metadata,
                          MetadataIndex, Statistics, SummaryOffset)
from mcap.stream_reader import StreamReader, get_chunk_data_stream
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader as Rosbag2Reader
from rosbags.typesys import Stores, get_typestore, get_types_from_msg
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from conftest import FullDisk
from dyn_node import __version__
from dyn_node.bag.recover import recover_file
from dyn_node.errors import RecordingError
from dyn_node.bag.recorder import (Recorder, RecorderConfig, RecorderStats, TopicInfo, cdr_string,
                                header_stamp_ns, message_definition, qos_profile_dict)

URDF = "<robot name='r'><link name='base'/></robot>"
JS = "/joint_states"
DESC = "/robot_description"


def joint_state(seq: int) -> bytes:
    """Serialized JointState carrying ``seq``. rclpy leaves CDR padding bytes uninitialised, so
    two serializations of one message may differ: compare against the bytes actually sent."""
    m = JointState()
    m.header.stamp.sec, m.header.stamp.nanosec = 1000 + seq // 1000, (seq % 1000) * 1_000_000
    m.header.frame_id = str(seq)
    m.name = ["j1", "j2", "j3", "j4", "j5", "j6", "j7"]
    m.position = [seq * 1e-3 + k for k in range(7)]
    m.velocity = [0.1 * k for k in range(7)]
    m.effort = [float(seq % 7)] * 7
    return serialize_message(m)


def make_recorder(tmp_path: Path, **kw) -> Recorder:
    opts = {k: kw.pop(k) for k in list(kw) if k in RecorderConfig.__dataclass_fields__}
    rec = Recorder(RecorderConfig(directory=str(tmp_path), **opts), robot_description=URDF,
                   parameters_yaml="/dyn_node:\n  ros__parameters:\n    a: 1\n", **kw)
    rec.add_topic(TopicInfo(JS, "sensor_msgs/msg/JointState", (qos_profile_dict(depth=100),)))
    rec.add_topic(TopicInfo("/chatter", "std_msgs/msg/String", (qos_profile_dict(),)))
    return rec


def read_mcap(path: str | Path) -> tuple[list, list]:
    """(messages as (topic, log, publish, data), metadata records) via mcap's reader, CRCs on."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        msgs = [(ch.topic, m.log_time, m.publish_time, m.data)
                for _s, ch, m in reader.iter_messages(log_time_order=False)]
        meta = [(r.name, dict(r.metadata)) for r in reader.iter_metadata()]
    return msgs, meta


def test_message_definition_is_complete_and_parseable():
    text = message_definition("trajectory_msgs/msg/JointTrajectory")
    for dep in ("std_msgs/Header", "builtin_interfaces/Time",
                "trajectory_msgs/JointTrajectoryPoint", "builtin_interfaces/Duration"):
        assert f"MSG: {dep}\n" in text
    # rosbags parses the concatenated definition independently.
    types = get_types_from_msg(text, "trajectory_msgs/msg/JointTrajectory")
    assert "trajectory_msgs/msg/JointTrajectory" in types
    assert message_definition("no_such_pkg/msg/Nothing") == ""


def test_header_stamp_from_raw_cdr():
    data = joint_state(1234)
    assert header_stamp_ns(data) == 1001 * 10**9 + 234 * 10**6
    assert header_stamp_ns(b"\x00\x01") is None


def test_bag_read_back_by_independent_readers(tmp_path):
    rec = make_recorder(tmp_path, chunk_size=4096)
    sent, sent_js = [], []
    for seq in range(3000):
        data = joint_state(seq)
        sent_js.append(data)
        log = 1_700_000_000 * 10**9 + seq * 1_000_000
        assert rec.write(JS, data, log, header_stamp_ns(data))
        sent.append((JS, log, header_stamp_ns(data), data))
        if seq % 100 == 0:
            s = serialize_message(String(data=f"hello {seq}"))
            rec.write("/chatter", s, log, None)
            sent.append(("/chatter", log, log, s))
    stats = rec.close()
    assert stats.state == "closed" and stats.error == ""
    assert stats.topics[JS].received == stats.topics[JS].written == 3000
    assert stats.topics["/chatter"].written == 30 and stats.dropped == 0
    bag = Path(stats.path)
    assert [p.name for p in sorted(bag.iterdir())] == [f"{bag.name}_0.mcap", "metadata.yaml"]

    # mcap's own reader: payloads byte-equal, times as given, description first, metadata record.
    msgs, meta = read_mcap(bag / f"{bag.name}_0.mcap")
    assert msgs[0][0] == DESC and msgs[0][3] == cdr_string(URDF)
    assert sorted(msgs[1:]) == sorted(sent)
    assert meta == [("dyn_node", {"robot_description": URDF, "parameters":
                                  "/dyn_node:\n  ros__parameters:\n    a: 1\n",
                                  "version": __version__})]

    # rosbags' rosbag2 reader on the directory, and its typestore decoding our schema text.
    with Rosbag2Reader(bag) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts == {DESC: 1, JS: 3000, "/chatter": 30}
        store = get_typestore(Stores.EMPTY)
        js_conn = next(c for c in reader.connections if c.topic == JS)
        store.register(get_types_from_msg(js_conn.msgdef.data, js_conn.msgtype))
        seen = 0
        for conn, ts, raw in reader.messages():
            if conn.topic != JS:
                continue
            m = store.deserialize_cdr(raw, conn.msgtype)
            seq = int(m.header.frame_id)
            assert raw == sent_js[seq] and ts == 1_700_000_000 * 10**9 + seq * 1_000_000
            seen += 1
        assert seen == 3000
    meta_yaml = yaml.safe_load((bag / "metadata.yaml").read_text())
    info = meta_yaml["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["message_count"] == 3031 and info["files"][0]["message_count"] == 3031
    assert meta_yaml["dyn_node"]["topics"][JS] == {"received": 3000, "written": 3000, "dropped": 0}


def _records_at(data: bytes, start: int, end: int) -> list[tuple[int, int, bytes]]:
    """Top-level MCAP records in data[start:end] as (offset, opcode, body); they must tile it."""
    out, pos = [], start
    while pos < end:
        op, n = struct.unpack_from("<BQ", data, pos)
        assert pos + 9 + n <= end, f"record at {pos} overruns"
        out.append((pos, op, data[pos + 9:pos + 9 + n]))
        pos += 9 + n
    assert pos == end
    return out


def _parse(cls, body: bytes, *extra):
    stream = ReadDataStream(io.BytesIO(body))
    rec = cls.read(stream, *extra)
    assert stream.count == len(body), cls.__name__
    return rec


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_mcap_layout_follows_the_spec(tmp_path, compression):
    """The recorder writes MCAP itself: every index, offset, count and CRC is checked here
    against the bytes, record by record (mcap's reader is used only to parse record bodies
    and, as a second opinion, to stream the file with CRC validation)."""
    rec = make_recorder(tmp_path, chunk_size=3000, compression=compression)
    logs: dict[str, list[int]] = {JS: [], "/chatter": []}
    for seq in range(700):
        log = 10**18 + seq * 1_000_000 - (seq % 3) * 1_500_000  # not monotone within a chunk
        rec.write(JS, joint_state(seq), log)
        logs[JS].append(log)
        if seq % 50 == 0:
            rec.write("/chatter", cdr_string(f"m{seq}"), log + 7)
            logs["/chatter"].append(log + 7)
        if seq == 350:
            rec.set_parameters_yaml("/dyn_node:\n  ros__parameters:\n    a: 2\n")
    stats = rec.close()
    assert stats.state == "closed" and stats.dropped == 0
    path = Path(stats.files[0])
    data = path.read_bytes()

    # Second opinion: mcap's stream reader validates the data-section and chunk CRCs.
    n_stream = sum(isinstance(r, Message) for r in
                   StreamReader(io.BytesIO(data), validate_crcs=True).records)
    assert n_stream == 700 + 14 + 1  # + the description copy

    magic = b"\x89MCAP0\r\n"
    assert data[:8] == magic and data[-8:] == magic
    footer_at = len(data) - 8 - 29
    op, n = struct.unpack_from("<BQ", data, footer_at)
    assert (op, n) == (0x02, 20)
    summary_start, offsets_start, summary_crc = struct.unpack_from("<QQI", data, footer_at + 9)
    assert summary_crc == zlib.crc32(data[summary_start:footer_at + 9 + 16])

    # Data section: Header, then records up to Data End, whose CRC covers magic..last record.
    data_recs = _records_at(data, 8, summary_start)
    assert data_recs[0][1] == 0x01 and data_recs[-1][1] == 0x0F
    data_end_at = data_recs[-1][0]
    assert struct.unpack("<I", data_recs[-1][2]) == (zlib.crc32(data[:data_end_at]),)
    by_offset = {off: (op, body) for off, op, body in data_recs}
    chunks = [(off, body) for off, op, body in data_recs if op == 0x06]
    metas = [(off, body) for off, op, body in data_recs if op == 0x0C]
    channels = {c.id: c for c in (_parse(Channel, b) for _o, op, b in data_recs if op == 0x04)}
    topic_of = {cid: c.topic for cid, c in channels.items()}

    # Summary: groups tile [summary_start, offsets_start), each of one opcode; then the offsets.
    summary = _records_at(data, summary_start, footer_at)
    groups = [_parse(SummaryOffset, b) for off, op, b in summary if off >= offsets_start]
    assert all(op == 0x0E for off, op, _b in summary if off >= offsets_start)
    pos = summary_start
    grouped: dict[int, list[bytes]] = {}
    for g in groups:
        assert g.group_start == pos
        recs = _records_at(data, pos, pos + g.group_length)
        assert {op for _o, op, _b in recs} == {g.group_opcode}
        grouped[g.group_opcode] = [b for _o, _op, b in recs]
        pos += g.group_length
    assert pos == offsets_start
    assert set(grouped) == {0x03, 0x04, 0x0B, 0x08, 0x0D}
    assert {c.id: c for c in map(lambda b: _parse(Channel, b), grouped[0x04])} == channels

    # Chunk indexes: each points at its chunk; message indexes point at each message.
    seen: dict[int, list[int]] = {}
    indexes = [_parse(ChunkIndex, b) for b in grouped[0x08]]
    assert [ci.chunk_start_offset for ci in indexes] == [off for off, _b in chunks]
    for ci, (off, body) in zip(indexes, chunks):
        chunk = _parse(Chunk, body)
        assert ci.chunk_length == 9 + len(body)
        assert (ci.compression, ci.compressed_size, ci.uncompressed_size) == (
            chunk.compression, len(chunk.data), chunk.uncompressed_size)
        assert chunk.compression == {"none": ""}.get(compression, compression)
        records = get_chunk_data_stream(chunk, validate_crc=True)[0].read(chunk.uncompressed_size)
        inner = _records_at(records, 0, len(records))
        messages = {o: _parse(Message, b, len(b)) for o, op, b in inner if op == 0x05}
        assert {op for _o, op, _b in inner} == {0x05}
        times = [m.log_time for m in messages.values()]
        assert (ci.message_start_time, ci.message_end_time) == (min(times), max(times))
        assert (chunk.message_start_time, chunk.message_end_time) == (min(times), max(times))
        idx_at = off + ci.chunk_length
        assert sum(by_offset[o][0] == 0x07 and 1 for o in ci.message_index_offsets.values()) \
            == len(ci.message_index_offsets)
        covered = 0
        for cid, mi_off in sorted(ci.message_index_offsets.items(), key=lambda kv: kv[1]):
            assert mi_off == idx_at
            mi = _parse(MessageIndex, by_offset[mi_off][1])
            assert mi.channel_id == cid
            for log, moff in mi.records:
                assert messages[moff].channel_id == cid and messages[moff].log_time == log
                seen.setdefault(cid, []).append(log)
            covered += len(mi.records)
            idx_at += 9 + len(by_offset[mi_off][1])
        assert covered == len(messages)
        assert idx_at - off - ci.chunk_length == ci.message_index_length
    assert sorted(seen[next(c for c, t in topic_of.items() if t == JS)]) == sorted(logs[JS])
    assert sorted(seen[next(c for c, t in topic_of.items() if t == "/chatter")]) == \
        sorted(logs["/chatter"])

    # Statistics from the bytes above; metadata indexes point at their records.
    st = _parse(Statistics, grouped[0x0B][0])
    all_logs = [t for v in seen.values() for t in v]
    assert st.message_count == len(all_logs) == 715
    assert dict(st.channel_message_counts) == {cid: len(v) for cid, v in seen.items()}
    assert (st.message_start_time, st.message_end_time) == (min(all_logs), max(all_logs))
    assert (st.chunk_count, st.metadata_count, st.channel_count, st.schema_count,
            st.attachment_count) == (len(chunks), len(metas), len(channels), 2, 0)
    assert len(grouped[0x03]) == sum(op == 0x03 for _o, op, _b in data_recs) == 2
    assert len(metas) == 2
    mindex = [_parse(MetadataIndex, b) for b in grouped[0x0D]]
    assert [(m.offset, m.length, m.name) for m in mindex] == [
        (off, 9 + len(body), "dyn_node") for off, body in metas]
    assert _parse(Metadata, metas[1][1]).metadata["parameters"].endswith("a: 2\n")


@pytest.mark.parametrize("split", ["size", "duration"])
def test_split_files_each_valid_and_union_exact(tmp_path, split):
    kw = {"max_bag_size_mb": 0.05} if split == "size" else {"max_bag_duration_s": 0.5}
    rec = make_recorder(tmp_path, compression="lz4" if split == "size" else "none", **kw)
    n = 2500
    for seq in range(n):  # 2.5 s of log time at 1 kHz
        rec.write(JS, joint_state(seq), 10**18 + seq * 1_000_000)
    stats = rec.close()
    assert stats.state == "closed" and stats.topics[JS].written == n
    bag = Path(stats.path)
    files = sorted(bag.glob("*.mcap"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    assert len(files) >= 3 and len(files) == len(stats.files)
    union = []
    for f in files:
        msgs, meta = read_mcap(f)  # each file alone, with its summary and CRCs
        assert msgs[0][0] == DESC and msgs[0][3] == cdr_string(URDF)
        assert [m for m in msgs if m[0] == DESC] == [msgs[0]]
        assert meta and meta[0][1]["robot_description"] == URDF
        union += [m[1] for m in msgs if m[0] == JS]
        if split == "duration":
            times = [m[1] for m in msgs if m[0] == JS]
            assert max(times) - min(times) < 0.5e9
        else:
            assert f.stat().st_size < 0.05e6 * 1.3  # open chunk counted uncompressed: bounded
    assert union == [10**18 + s * 1_000_000 for s in range(n)]  # every message exactly once
    with Rosbag2Reader(bag) as reader:
        assert {c.topic: c.msgcount for c in reader.connections}[JS] == n
        assert sum(1 for c, _, _ in reader.messages() if c.topic == JS) == n


def test_disk_full_reports_error_and_counts_exactly(tmp_path):
    failed = threading.Event()
    disks: list[FullDisk] = []
    error_at: list[float] = []

    def on_state(stats: RecorderStats) -> None:
        if stats.state == "error":
            error_at.append(time.monotonic())
            failed.set()

    def opener(path: str) -> FullDisk:
        disks.append(FullDisk(path, 60_000))
        return disks[-1]

    rec = make_recorder(tmp_path, chunk_size=2048, opener=opener, on_state=on_state)
    n, t_fail, worst_call = 0, None, 0.0
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        t0 = time.perf_counter()
        rec.write(JS, joint_state(n), 10**18 + n * 1_000_000)  # never raises
        worst_call = max(worst_call, time.perf_counter() - t0)
        n += 1
        if failed.is_set():
            t_fail = t_fail or time.monotonic()
            if n % 500 == 0:
                break
    assert failed.is_set(), "ENOSPC not detected"
    assert error_at[0] - disks[0].full_at <= 1.0  # reported within a second of the disk filling
    stats = rec.close()
    assert stats.state == "error" and "ENOSPC" in stats.error
    c = stats.topics[JS]
    assert c.received == n and c.written + c.dropped == n and c.dropped > 0
    # "written" means on disk: the partial file, recovered, holds exactly that many messages.
    bag = Path(stats.path)
    r = recover_file(bag / f"{bag.name}_0.mcap", tmp_path / "out.mcap")
    assert r.kept.get(JS, 0) == c.written and r.lost
    assert worst_call < 0.5  # the caller never waits on the disk


def test_queue_full_drops_are_counted(tmp_path):
    release = threading.Event()

    class SlowDisk(FullDisk):
        def write(self, data: bytes) -> int:
            release.wait(10.0)  # the disk hangs until released
            return super().write(data)

    rec = make_recorder(tmp_path, queue_size=100, opener=lambda p: SlowDisk(p, 10**9))
    results = [rec.write(JS, joint_state(i), 10**18 + i) for i in range(300)]
    release.set()
    stats = rec.close()
    c = stats.topics[JS]
    assert c.received == 300 and c.dropped == results.count(False) >= 200
    assert c.written == results.count(True) and stats.state == "closed"


def test_concurrent_writers_and_close_counted_exactly(tmp_path):
    """write() takes no lock on its fast path: threads writing one topic at once, a small queue
    (drops), and a close() in the middle of it all still give received == calls and
    written + dropped == received, with exactly the written messages in the file."""
    rec = make_recorder(tmp_path, queue_size=64, chunk_size=2048)
    payloads = [joint_state(i) for i in range(50)]
    calls = {JS: 0, "/chatter": 0}
    accepted = {JS: 0, "/chatter": 0}
    lock = threading.Lock()
    start = threading.Barrier(5)

    def writer(k: int) -> None:
        topic = JS if k % 2 else "/chatter"
        start.wait()
        n = ok = 0
        for i in range(3000):
            ok += rec.write(topic, payloads[i % 50], 10**18 + i)
            n += 1
        with lock:
            calls[topic] += n
            accepted[topic] += ok

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    start.wait()
    while rec.stats().topics[JS].received < 2000:  # close while the writers are busy
        threading.Event().wait(0.001)
    stats = rec.close()
    for t in threads:
        t.join()
    final = rec.stats()
    assert final.queued == 0 and final.state == "closed" and stats.state == "closed"
    msgs, _meta = read_mcap(Path(final.files[0]))
    for topic in (JS, "/chatter"):
        c = final.topics[topic]
        assert c.received == calls[topic] == 6000
        assert c.written + c.dropped == c.received and c.written <= accepted[topic]
        assert c.dropped > 0  # the queue of 64 overflowed, or the writes came after close()
        assert sum(1 for m in msgs if m[0] == topic) == c.written
    meta = yaml.safe_load((Path(final.path) / "metadata.yaml").read_text())["dyn_node"]["topics"]
    for topic in (JS, "/chatter"):  # the file's counts are final for everything before close
        assert meta[topic]["written"] == final.topics[topic].written


def test_never_overwrites_and_rejects_bad_config(tmp_path):
    a, b = make_recorder(tmp_path), make_recorder(tmp_path)
    assert a.path != b.path and a.path.parent == b.path.parent == tmp_path
    a.close(), b.close()
    assert a.close().state == "closed"  # idempotent
    with pytest.raises(RecordingError, match="compression"):
        Recorder(RecorderConfig(directory=str(tmp_path), compression="gzip"))
    with pytest.raises(RecordingError, match="max_bag_size_mb"):
        Recorder(RecorderConfig(directory=str(tmp_path), max_bag_size_mb=-1))


def _thread_cpu_s(thread: threading.Thread, window_s: float) -> float:
    """CPU seconds ``thread`` used over ``window_s`` of wall time (its own POSIX CPU clock)."""
    clock = time.pthread_getcpuclockid(thread.ident)
    c0 = time.clock_gettime(clock)
    threading.Event().wait(window_s)
    return time.clock_gettime(clock) - c0


def test_failed_recorder_costs_nothing(tmp_path):
    """After ENOSPC the writer thread sleeps until close(): it used to spin on a flush deadline
    that no longer advanced, a whole core taken from the node's live path (issue 27)."""
    failed = threading.Event()
    rec = make_recorder(tmp_path, chunk_size=2048, flush_period_s=0.1,
                        opener=lambda p: FullDisk(p, 20_000), on_state=lambda s: failed.set() if s.state == "error" else None)
    n = 0
    while not failed.is_set() and n < 100_000:
        rec.write(JS, joint_state(n % 50), 10**18 + n)
        n += 1
        if n % 200 == 0:
            failed.wait(0.01)
    assert failed.is_set(), "ENOSPC not detected"
    writer = rec._thread
    assert writer.is_alive()
    cpu = _thread_cpu_s(writer, 1.0)  # idle: blocked until close(), no wake-up at all
    assert cpu < 0.01, f"failed writer used {cpu:.3f} s of CPU in 1 s"
    assert all(rec.write(JS, joint_state(1), 2 * 10**18 + k) is False for k in range(100))
    stats = rec.close()
    assert not writer.is_alive() and stats.state == "error"
    assert stats.topics[JS].received == n + 100
    assert stats.topics[JS].written + stats.topics[JS].dropped == n + 100


def test_real_full_tmpfs(tmp_path):
    """A real 128 kB tmpfs (needs root to mount): ENOSPC from the kernel, not from a fake. The
    writer then idles, and close() leaves the final metadata.yaml (state error, the counts)
    and no temp file: never the start's "recording" beside a 0-byte metadata.yaml.tmp."""
    import os
    from tmpfs import tiny_tmpfs

    with tiny_tmpfs(tmp_path / "tiny", 128) as mnt:
        failed = threading.Event()
        rec = Recorder(RecorderConfig(directory=str(mnt), chunk_size=8192, flush_period_s=0.1),
                       robot_description=URDF,
                       on_state=lambda s: failed.set() if s.state == "error" else None)
        rec.add_topic(TopicInfo("/noise", "std_msgs/msg/String"))
        sent = []
        deadline = time.monotonic() + 20.0
        while not failed.is_set() and time.monotonic() < deadline:
            payload = len(sent).to_bytes(4, "little") + os.urandom(1000)  # incompressible
            rec.write("/noise", payload, 10**18 + len(sent) * 1000)
            sent.append(payload)
        assert failed.is_set(), "the tmpfs never filled"
        assert _thread_cpu_s(rec._thread, 1.0) < 0.01  # the failed writer sleeps
        for k in range(100):  # after the error: counted as dropped, never raised
            assert rec.write("/noise", b"late", 2 * 10**18 + k) is False
        stats = rec.close()
        c = stats.topics["/noise"]
        assert stats.state == "error" and "ENOSPC" in stats.error
        assert c.received == len(sent) + 100 and c.written + c.dropped == c.received
        bag = Path(stats.path)
        assert sorted(p.name for p in bag.iterdir()) == [f"{bag.name}_0.mcap", "metadata.yaml"]
        meta = yaml.safe_load((bag / "metadata.yaml").read_text())
        assert meta["dyn_node"]["state"] == "error" and "ENOSPC" in meta["dyn_node"]["error"]
        assert meta["dyn_node"]["topics"]["/noise"] == {
            "received": c.received, "written": c.written, "dropped": c.dropped}
        # The half-written record was cut off: the file ends exactly on a record (MCAP spec:
        # magic, then records of opcode u8, length u64, body).
        raw = (bag / f"{bag.name}_0.mcap").read_bytes()
        pos = 8
        while pos < len(raw):
            pos += 9 + struct.unpack_from("<Q", raw, pos + 1)[0]
        assert raw[:8] == b"\x89MCAP0\r\n" and pos == len(raw)
        recovered = recover_file(bag / f"{bag.name}_0.mcap", tmp_path / "out.mcap")
        assert recovered.kept.get("/noise", 0) == c.written > 0
        msgs, _ = read_mcap(tmp_path / "out.mcap")
        assert [m[3] for m in msgs if m[0] == "/noise"] == sent[:c.written]


def test_metadata_yaml_on_a_full_disk_is_new_or_absent_never_stale(tmp_path):
    """write_metadata_yaml on a full file system: the old file is given up for the new one
    (written whole) or, when even that does not fit, removed; no temp file is ever left."""
    from tmpfs import fill, tiny_tmpfs
    from dyn_node.bag.metadata import write_metadata_yaml

    with tiny_tmpfs(tmp_path / "tiny", 64) as mnt:
        write_metadata_yaml(mnt, {"state": "recording"})
        fill(mnt)
        write_metadata_yaml(mnt, {"state": "error", "pad": "x" * 3000})  # fits in the old one's page
        assert sorted(p.name for p in mnt.iterdir()) == ["filler", "metadata.yaml"]
        assert yaml.safe_load((mnt / "metadata.yaml").read_text())["state"] == "error"
        with pytest.raises(OSError) as err:  # larger than what removing the old one frees
            write_metadata_yaml(mnt, {"state": "closed", "pad": "x" * 20_000})
        assert err.value.errno == errno.ENOSPC
        assert sorted(p.name for p in mnt.iterdir()) == ["filler"]


def _log_durability_calls(monkeypatch) -> list[tuple[str, ...]]:
    """Patch os.fsync and os.replace to log, in call order, ("fsync", the fd's path) and
    ("replace", src, dst), then do the real call."""
    import os
    calls: list[tuple[str, ...]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        calls.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        return real_fsync(fd)

    def replace(src, dst, *args, **kwargs):
        calls.append(("replace", str(Path(src).resolve()), str(Path(dst).resolve())))
        return real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    return calls


def _durable_replaces(calls: list[tuple[str, ...]], bag: Path) -> int:
    """How many times metadata.yaml was replaced; each one must be: fsync of the new file, the
    rename, fsync of the directory (else a power loss can leave an empty metadata.yaml)."""
    bag = bag.resolve()
    tmp, meta = str(bag / "metadata.yaml.tmp"), str(bag / "metadata.yaml")
    at = [i for i, c in enumerate(calls) if c == ("replace", tmp, meta)]
    for i in at:
        assert calls[i - 1] == ("fsync", tmp), calls[max(0, i - 2):i + 2]
        assert calls[i + 1:i + 2] == [("fsync", str(bag))], calls[max(0, i - 2):i + 2]
    return len(at)


def test_metadata_yaml_fsynced_before_and_after_rename(tmp_path, monkeypatch):
    from dyn_node.bag.recorder import write_metadata_yaml
    calls = _log_durability_calls(monkeypatch)
    write_metadata_yaml(tmp_path, {"a": 1})
    assert _durable_replaces(calls, tmp_path) == 1 and len(calls) == 3
    assert yaml.safe_load((tmp_path / "metadata.yaml").read_text()) == {"a": 1}
    # The recorder writes it at the start, at every split and at the end: each one durable.
    rec = make_recorder(tmp_path / "rec", max_bag_size_mb=0.05, compression="lz4")
    for seq in range(1000):
        rec.write(JS, joint_state(seq), 10**18 + seq * 1_000_000)
    stats = rec.close()
    assert stats.state == "closed" and len(stats.files) >= 2
    assert _durable_replaces(calls, Path(stats.path)) >= len(stats.files) + 1


def test_new_bag_directory_fsyncs_the_directories_that_hold_new_names(tmp_path, monkeypatch):
    """mkdir alone can be lost in a power loss (the entry lives in the parent's data): the bag
    directory's parent, and the parent of every directory created on the way, are fsynced
    after the mkdir; the recorder does it before writing anything into the bag."""
    from dyn_node.bag.recorder import new_bag_directory

    calls = _log_durability_calls(monkeypatch)
    d = new_bag_directory(tmp_path / "a" / "b", now=0.0)
    assert d == tmp_path / "a" / "b" / "dyn_node_19700101_000000"
    assert calls == [("fsync", str(tmp_path / "a" / "b")), ("fsync", str(tmp_path / "a")),
                     ("fsync", str(tmp_path))]
    calls.clear()
    assert new_bag_directory(tmp_path / "a" / "b", now=0.0, fsync=False).name.endswith("_1")
    assert calls == []
    rec = make_recorder(tmp_path / "rec")
    parent = ("fsync", str((tmp_path / "rec").resolve()))
    assert calls[:1] == [parent], calls  # before anything is written into the bag
    rec.close()
