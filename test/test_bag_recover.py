"""dyn-bag-recover: truncated and damaged files, exit codes, monotone recovery in the cut point."""
from __future__ import annotations

import random
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader as Rosbag2Reader

from dyn_node.bag_recover import main
from dyn_node.recording import Recorder, RecorderConfig, TopicInfo, qos_profile_dict

JS = "/joint_states"
N = 2000


def _payload(seq: int) -> bytes:
    # A CDR std_msgs/String-like payload that carries its sequence number (content is opaque
    # to the recorder and the recovery; only bytes and counts matter here).
    text = f"{seq:06d}" + "x" * (seq % 37)
    b = text.encode()
    return b"\x00\x01\x00\x00" + len(b + b"\x00").to_bytes(4, "little") + b + b"\x00"


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    """A small bag: many zstd chunks of one topic, sequence numbers in the payloads."""
    d = tmp_path_factory.mktemp("recover")
    rec = Recorder(RecorderConfig(directory=str(d), chunk_size=2048),
                   robot_description="<robot name='r'/>")
    rec.add_topic(TopicInfo(JS, "std_msgs/msg/String", (qos_profile_dict(),)))
    for seq in range(N):
        rec.write(JS, _payload(seq), 10**18 + seq * 1_000_000)
    stats = rec.close()
    assert stats.topics[JS].written == N
    return Path(stats.path)


def _mcap_of(bag: Path) -> Path:
    return bag / f"{bag.name}_0.mcap"


def _read(path: Path) -> list[bytes]:
    with open(path, "rb") as f:
        return [m.data for _s, ch, m in make_reader(f, validate_crcs=True).iter_messages(
            log_time_order=False) if ch.topic == JS]


def test_intact_file_nothing_lost(bag, tmp_path, capsys):
    out = tmp_path / "out.mcap"
    assert main([str(_mcap_of(bag)), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"{JS}: {N} messages kept" in text and "nothing lost" in text
    assert _read(out) == [_payload(s) for s in range(N)]


def test_cut_at_random_offsets_monotone_prefix(bag, tmp_path, capsys):
    data = _mcap_of(bag).read_bytes()
    rng = random.Random(5)
    cuts = sorted(rng.sample(range(len(data)), 80)) + [len(data)]
    # The footer says where the summary starts; the data section (DataEnd included) ends there.
    summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 29 + 9)[0]
    prev, codes = -1, set()
    for cut in cuts:
        src, out = tmp_path / "cut.mcap", tmp_path / "cut_out.mcap"
        src.write_bytes(data[:cut])
        rc = main([str(src), "-o", str(out)])
        capsys.readouterr()
        codes.add(rc)
        assert rc in (0, 1, 3)
        kept = _read(out) if rc != 1 else []
        assert kept == [_payload(s) for s in range(len(kept))]  # a contiguous prefix
        assert len(kept) >= prev, f"recovered count decreased at cut {cut}"
        prev = len(kept)
        # Nothing lost exactly when the whole data section survived the cut.
        assert (rc == 0) == (cut >= summary_start)
    assert prev == N and {1, 3, 0} <= codes


def test_corrupt_chunk_is_skipped_and_reported(bag, tmp_path, capsys):
    data = bytearray(_mcap_of(bag).read_bytes())
    with open(_mcap_of(bag), "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    victim = chunks[len(chunks) // 2]
    data[victim.chunk_start_offset + victim.chunk_length - 3] ^= 0xFF  # in its compressed data
    src, out = tmp_path / "bad.mcap", tmp_path / "bad_out.mcap"
    src.write_bytes(bytes(data))
    assert main([str(src), "-o", str(out)]) == 3
    assert "lost:" in capsys.readouterr().out
    kept = _read(out)
    # Exactly the damaged chunk's messages are missing: a contiguous run, the rest intact.
    all_msgs = [_payload(s) for s in range(N)]
    first_missing = next(i for i, (a, b) in enumerate(zip(kept, all_msgs)) if a != b)
    gap = N - len(kept)
    assert 0 < gap < N / 4
    assert kept == all_msgs[:first_missing] + all_msgs[first_missing + gap:]


def test_bag_directory_and_errors(bag, tmp_path, capsys):
    out = tmp_path / "bag.recovered"
    assert main([str(bag), "-o", str(out)]) == 0
    capsys.readouterr()
    with Rosbag2Reader(out) as reader:
        assert {c.topic: c.msgcount for c in reader.connections}[JS] == N
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap at all" * 10)
    assert main([str(garbage)]) == 1
    assert "not an MCAP file" in capsys.readouterr().err
    assert main([str(tmp_path / "missing.mcap")]) == 1
    assert "no such file" in capsys.readouterr().err
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert main([str(empty)]) == 1


@pytest.mark.timeout(60)
def test_runs_as_module_without_traceback(bag, tmp_path):
    src = tmp_path / "t.mcap"
    data = _mcap_of(bag).read_bytes()
    # The Footer's fields (summary start u64, summary offset start u64, CRC u32) end 8 bytes
    # (the magic) before the end of the file. Cut 1000 bytes into the data section.
    (summary_start,) = struct.unpack_from("<Q", data, len(data) - 8 - 20)
    src.write_bytes(data[:summary_start - 1000])
    r = subprocess.run([sys.executable, "-m", "dyn_node.bag_recover", str(src)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 3, r.stderr
    assert "Traceback" not in r.stderr and "some data was lost" in r.stdout
    assert (tmp_path / "t.recovered.mcap").is_file()
