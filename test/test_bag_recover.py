"""dyn-bag-recover: truncated and damaged files, exit codes, monotone recovery in the cut point;
every valid file the MCAP specification allows (a corpus written byte by byte from it), read back
with the official ``mcap`` readers; never our own outputs as inputs."""
from __future__ import annotations

import random
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Channel
from mcap.stream_reader import StreamReader
from rosbags.rosbag2 import Reader as Rosbag2Reader

from dyn_node.bag.recover import main
from dyn_node.bag.recorder import Recorder, RecorderConfig, TopicInfo, qos_profile_dict
from mcap_corpus import CORPUS, OFFICIAL_READER_MISREADS, Expected, McapBuilder

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
    r = subprocess.run([sys.executable, "-m", "dyn_node.bag.recover", str(src)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 3, r.stderr
    assert "Traceback" not in r.stderr and "some data was lost" in r.stdout
    assert (tmp_path / "t.recovered.mcap").is_file()


# ------------------------------------------------------------ valid files from the specification


def _official(path: Path, *, seeking: bool) -> Expected:
    """Everything the official ``mcap`` reader finds in a file (messages in file order):
    through the summary and indexes (``make_reader`` on a file), or reading the file from the
    start (``NonSeekingReader``, which also sees messages outside chunks in an indexed file)."""
    def reader(f):
        return make_reader(f, validate_crcs=True) if seeking else \
            NonSeekingReader(f, validate_crcs=True)

    with open(path, "rb") as f:
        messages = [(ch.topic, ch.message_encoding, dict(ch.metadata),
                     (s.name, s.encoding, s.data) if s is not None else None,
                     m.log_time, m.publish_time, m.sequence, m.data)
                    for s, ch, m in reader(f).iter_messages(log_time_order=False)]
    with open(path, "rb") as f:
        metadata = [(m.name, dict(m.metadata)) for m in reader(f).iter_metadata()]
    with open(path, "rb") as f:
        attachments = [(a.name, a.media_type, a.log_time, a.create_time, a.data)
                       for a in reader(f).iter_attachments()]
    with open(path, "rb") as f:
        if seeking:
            channels = {c.id: c.topic for c in make_reader(f).get_summary().channels.values()}
        else:  # the Channel records of the data section
            channels = {r.id: r.topic for r in StreamReader(f).records
                        if isinstance(r, Channel)}
    return Expected(messages, metadata, attachments, sorted(channels.values()))


@pytest.mark.parametrize("case", sorted(CORPUS))
def test_valid_file_from_the_spec_is_kept_whole(case, tmp_path, capsys):
    data, expected = CORPUS[case]()
    expected.topics = sorted(expected.topics)
    src, out = tmp_path / f"{case}.mcap", tmp_path / f"{case}.out.mcap"
    src.write_bytes(data)
    if case not in OFFICIAL_READER_MISREADS:
        # The corpus is what the official reader reads in it.
        assert _official(src, seeking=False) == expected
    assert main([str(src), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    # Nothing lost, and no note either: the summary CRC and every other CRC checked out.
    assert "nothing lost" in text and "lost:" not in text and "note:" not in text
    assert _official(out, seeking=True) == expected
    assert _official(out, seeking=False) == expected
    for name in {m[0] for m in expected.messages}:
        n = sum(m[0] == name for m in expected.messages)
        assert f"  {name}: {n} messages kept" in text
    assert f"{len(expected.metadata)} metadata records kept" in text
    assert f"{len(expected.attachments)} attachments kept" in text


def test_directory_never_rereads_our_own_outputs(bag, tmp_path, capsys):
    """Recover a file beside its bag (default output), then the directory: each message once.
    Our output renamed to look like a split is still recognised (its MCAP Header), and so is
    a file whose name alone says it was recovered."""
    d = tmp_path / "bag"
    d.mkdir()
    src = d / _mcap_of(bag).name
    src.write_bytes(_mcap_of(bag).read_bytes())
    assert main([str(src)]) == 0
    beside = d / (src.name[:-len(".mcap")] + ".recovered.mcap")
    assert beside.is_file()
    renamed = d / "copy_7.mcap"  # our output under a split's name: only the marker says so
    renamed.write_bytes(beside.read_bytes())
    older = d / "older.recovered.mcap"  # only the name says so (e.g. an earlier version's)
    older.write_bytes(src.read_bytes())
    capsys.readouterr()
    out = tmp_path / "out"
    assert main([str(d), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    with Rosbag2Reader(out) as reader:
        assert {c.topic: c.msgcount for c in reader.connections}[JS] == N
    assert sorted(p.name for p in out.glob("*.mcap")) == [src.name]
    assert _read(out / src.name) == [_payload(s) for s in range(N)]
    assert f"{beside}: skipped (written by dyn-bag-recover)" in text
    assert f"{renamed}: skipped (written by dyn-bag-recover)" in text
    assert f"{older}: skipped (written by dyn-bag-recover)" in text
    with open(beside, "rb") as f:
        assert make_reader(f).get_header().library.startswith("dyn-bag-recover ")
    # A directory holding nothing but our outputs: a clear error, and the way out.
    only = tmp_path / "only"
    only.mkdir()
    (only / beside.name).write_bytes(beside.read_bytes())
    assert main([str(only)]) == 1
    assert "written by dyn-bag-recover" in capsys.readouterr().err
    # Given explicitly, one of our outputs is recovered again (the user asked for it).
    assert main([str(only / beside.name), "-o", str(tmp_path / "again.mcap")]) == 0
    assert _read(tmp_path / "again.mcap") == [_payload(s) for s in range(N)]


def test_damaged_attachment_skipped_rest_kept(tmp_path, capsys):
    b = McapBuilder()
    b.add_attachment("good", "text/plain", 1, 1, b"intact")
    b.add_attachment("bad", "text/plain", 2, 2, b"will be flipped")
    b.add_metadata("m", {"k": "v"})
    data = bytearray(b.finish())
    data[data.index(b"will be flipped")] ^= 0x01  # inside the data its CRC covers
    src, out = tmp_path / "a.mcap", tmp_path / "a.out.mcap"
    src.write_bytes(bytes(data))
    assert main([str(src), "-o", str(out)]) == 3
    text = capsys.readouterr().out
    assert "lost: record (opcode 0x9)" in text and "'bad' CRC mismatch" in text
    assert "the file's statistics list 2 attachments" in text
    got = _official(out, seeking=True)
    assert [a[0] for a in got.attachments] == ["good"] and got.metadata == [("m", {"k": "v"})]


def test_summary_supplies_definitions_of_a_damaged_chunk(tmp_path, capsys):
    """The chunk that defined the channel is damaged; the intact summary still has the
    channel (the spec's copy), so the next chunk's messages are kept."""
    b = McapBuilder(profile="ros2")
    b.add_chunk([b.schema(1, "std_msgs/msg/String", "ros2msg", b"string data\n"),
                 b.channel(1, 1, "/chatter", "cdr"), b.message(1, 0, 1, 1, b"first")])
    b.add_chunk([b.message(1, 1, 2, 2, b"second"), b.message(1, 2, 3, 3, b"third")])
    data = bytearray(b.finish())
    data[data.index(b"first")] ^= 0x01  # the first chunk fails its CRC
    src, out = tmp_path / "c.mcap", tmp_path / "c.out.mcap"
    src.write_bytes(bytes(data))
    assert main([str(src), "-o", str(out)]) == 3
    text = capsys.readouterr().out
    assert "chunk at byte" in text and "the file's statistics list 3 messages" in text
    got = _official(out, seeking=True)
    assert [(m[0], m[3], m[7]) for m in got.messages] == [
        ("/chatter", ("std_msgs/msg/String", "ros2msg", b"string data\n"), b"second"),
        ("/chatter", ("std_msgs/msg/String", "ros2msg", b"string data\n"), b"third")]


def test_cut_file_with_only_metadata_keeps_what_came_before(tmp_path, capsys):
    data, expected = CORPUS["metadata_only"]()
    second = data.index(b"empty") - 9 - 4  # the second Metadata record's opcode
    src, out = tmp_path / "m.mcap", tmp_path / "m.out.mcap"
    src.write_bytes(data[:second + 12])
    assert main([str(src), "-o", str(out)]) == 3  # something kept, something lost: not 1
    text = capsys.readouterr().out
    assert "1 metadata records kept" in text and "some data was lost" in text
    assert _official(out, seeking=True).metadata == expected.metadata[:1]


def test_damaged_summary_is_ignored_and_noted(tmp_path, capsys):
    data, expected = CORPUS["chunked_zstd"]()
    expected.topics = sorted(expected.topics)
    summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 20)[0]
    damaged = bytearray(data)
    damaged[summary_start + 20] ^= 0xFF  # inside the summary's first record
    src, out = tmp_path / "s.mcap", tmp_path / "s.out.mcap"
    src.write_bytes(bytes(damaged))
    assert main([str(src), "-o", str(out)]) == 0  # the data section is whole
    assert "note: summary CRC mismatch: summary ignored" in capsys.readouterr().out
    assert _official(out, seeking=True) == expected


def test_conflicting_channel_definitions_reported(tmp_path, capsys):
    b = McapBuilder()
    b.add(b.channel(1, 0, "/a", "json"), b.message(1, 0, 1, 1, b"{}"),
          b.channel(1, 0, "/b", "json"), b.message(1, 1, 2, 2, b"[]"))
    src, out = tmp_path / "c.mcap", tmp_path / "c.out.mcap"
    src.write_bytes(b.finish(summary=False))
    assert main([str(src), "-o", str(out)]) == 3
    assert "lost: channel 1 is defined twice, differently" in capsys.readouterr().out
    assert [(m[0], m[7]) for m in _official(out, seeking=True).messages] == [("/a", b"{}"),
                                                                             ("/a", b"[]")]


def _listing(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*"))


def test_full_disk_says_no_space_and_leaves_nothing(bag, tmp_path, capsys):
    """A real full tmpfs (root needed to mount): the default outputs beside the input fail with
    exit 4 and one "no space" line, and leave no file or directory behind; the old
    ``unexpected failure: OSError`` left a 0-byte file and exit 1."""
    import shutil
    from tmpfs import fill, tiny_tmpfs

    with tiny_tmpfs(tmp_path / "tiny", 512) as mnt:
        src = mnt / bag.name
        shutil.copytree(bag, src)
        fill(mnt)
        before = _listing(mnt)
        for target in (_mcap_of(src), src):  # one file, then the whole bag directory
            assert main([str(target)]) == 4
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and "no space left on the device" in err
            assert "Traceback" not in err and "unexpected" not in err
            assert _listing(mnt) == before
        (mnt / "filler").unlink()  # with room again, the same command recovers everything
        assert main([str(src)]) == 0
        capsys.readouterr()
        assert _read(mnt / f"{bag.name}.recovered" / _mcap_of(bag).name) == [
            _payload(s) for s in range(N)]


def test_injected_enospc_mid_file_leaves_no_half_output(bag, tmp_path, capsys, monkeypatch):
    """ENOSPC after some bytes of the output (injected at the file layer, no mount needed):
    exit 4, nothing at the output path, no temporary file, in file and directory mode."""
    import errno
    import shutil

    real_open = Path.open

    class Full:
        def __init__(self, f):
            self.f, self.budget = f, 3000

        def write(self, data):
            if len(data) > self.budget:
                raise OSError(errno.ENOSPC, "No space left on device")
            self.budget -= len(data)
            return self.f.write(data)

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    def fake_open(self, mode="r", *args, **kwargs):
        f = real_open(self, mode, *args, **kwargs)
        return Full(f) if "w" in mode and self.suffix == ".part" else f

    src = tmp_path / "in"
    shutil.copytree(bag, src)
    monkeypatch.setattr(Path, "open", fake_open)
    before = _listing(tmp_path)
    for target in (src / _mcap_of(bag).name, src):
        assert main([str(target)]) == 4
        assert "no space left on the device" in capsys.readouterr().err
        assert _listing(tmp_path) == before


def test_a_deleted_split_file_is_data_lost(tmp_path, capsys):
    """dyn-bag-recover on a bag whose metadata.yaml lists a file that is gone: exit 3, the file
    named as lost (it once said "nothing lost")."""
    from fleet_bags import write_split_bag

    bag = write_split_bag(tmp_path, "split", seconds=3.0)
    gone = sorted(bag.glob("*_1.mcap"))
    assert len(gone) == 1
    gone[0].unlink()
    code = main([str(bag), "-o", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert code == 3
    assert f"  lost: {gone[0].name}: listed in metadata.yaml but missing, " in out
    assert out.rstrip().endswith("some data was lost")
    # the same bag whole: nothing lost
    whole = write_split_bag(tmp_path, "whole", seconds=3.0)
    assert main([str(whole), "-o", str(tmp_path / "out2")]) == 0
    assert capsys.readouterr().out.rstrip().endswith("nothing lost")
