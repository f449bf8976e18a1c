"""Section "libraries": dyn_node's hand-written MCAP writer, reader and plots beside the libraries.

    .venv/bin/python -m benchmarks.libraries_bench                 # every part
    .venv/bin/python -m benchmarks.libraries_bench --part writer   # writer | layout | reader | report
    .venv/bin/python -m benchmarks.run --only libraries            # the same, as a bench section
                                                                   # (opt-in; in bench.json only)
    .venv/bin/python -m benchmarks.libraries_bench --quick         # fewer repeats, smaller bags

What each part measures: docs/BENCHMARK_METHODS.md; the figures: docs/LIBRARIES.md.
"""
from __future__ import annotations

import argparse
import io
import json
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

from .common import REPO, NotAvailable, progress

JS = "sensor_msgs/msg/JointState"
DIAG = "diagnostic_msgs/msg/DiagnosticArray"
TOPICS = (("/joint_states", JS), ("/dyn_node/inverse_dynamics", JS),
          ("/dyn_node/gravity_torque", JS), ("/diagnostics", DIAG))
FLUSH_PERIOD_S = 0.5


def _median(xs: list[float]) -> float:
    return statistics.median(xs)


# ================================================================= writer
def _workload(seconds: float) -> list[tuple[int, int, bytes]]:
    """(topic index, log ns, CDR bytes) in arrival order for ``seconds`` of the node at 1 kHz."""
    from .recording_bench import _stamp_patched, joint_state_bytes

    t0 = 1_700_000_000 * 1_000_000_000
    cycle, _ = joint_state_bytes(1000, t0)
    n = int(seconds * 1000)
    diag = bytes(b"\x00\x01\x00\x00" + (b"dyn_node: trajectory feasibility OK key value " * 40))
    out = []
    for k, (data, stamp) in enumerate(_stamp_patched(cycle, n, t0, 1000.0)):
        out.append((0, stamp, data))
        out.append((1, stamp + 200_000, data))  # outputs: same size and shape as the input
        out.append((2, stamp + 210_000, data))
        if k % 1000 == 0:
            out.append((3, stamp + 300_000, diag))
    return out


def _channel_meta(type_name: str) -> dict[str, str]:
    from dyn_node.bag.recorder import qos_profile_dict, qos_yaml, type_description_hash

    meta = {"offered_qos_profiles": qos_yaml([qos_profile_dict()])}
    h = type_description_hash(type_name)
    if h:
        meta["topic_type_hash"] = h
    return meta


class _Ours:
    name = "dyn_node McapFile"

    def __init__(self, stream, chunk_size: int):
        from dyn_node.bag.recorder import McapFile

        self.f = McapFile(stream, "zstd", "ros2", "bench")
        self.chunk_size = chunk_size

    def schema(self, name, data):
        return self.f.add_schema(name, "ros2msg", data)

    def channel(self, topic, sid, meta):
        return self.f.add_channel(topic, "cdr", sid, meta)

    def metadata(self, name, values):
        self.f.add_metadata(name, values)

    def message(self, cid, log_ns, data):
        self.f.add_message(cid, log_ns, log_ns, data)
        if self.f.size >= self.chunk_size:
            self.f.close_chunk()

    def flush(self):
        self.f.close_chunk()

    def finish(self):
        self.f.finish()


class _Library:
    name = "mcap.writer.Writer"

    def __init__(self, stream, chunk_size: int):
        from mcap.writer import CompressionType, Writer

        self.w = Writer(stream, chunk_size=chunk_size, compression=CompressionType.ZSTD,
                        enable_crcs=True, enable_data_crcs=True)
        self.w.start(profile="ros2", library="bench")

    def schema(self, name, data):
        return self.w.register_schema(name, "ros2msg", data)

    def channel(self, topic, sid, meta):
        return self.w.register_channel(topic, "cdr", sid, meta)

    def metadata(self, name, values):
        self.w.add_metadata(name, values)

    def message(self, cid, log_ns, data):
        self.w.add_message(cid, log_ns, data, log_ns)

    def flush(self):
        self.w.flush()  # closes the chunk and flushes the stream (no fsync: done by the caller)

    def finish(self):
        self.w.finish()


class _zstd_level:
    """Make mcap.writer compress with zstd level ``level`` (1.6.0 calls zstandard.compress(data))."""

    def __init__(self, level: int | None):
        self.level = level

    def __enter__(self):
        import mcap.writer as mw
        import zstandard

        self.saved = mw.zstandard
        if self.level is not None:
            mw.zstandard = SimpleNamespace(compress=zstandard.ZstdCompressor(level=self.level).compress)

    def __exit__(self, *exc):
        import mcap.writer as mw

        mw.zstandard = self.saved


def _write_layer(cls, work, path: Path, chunk_size: int, fsync: bool) -> dict:
    """Write ``work`` through one writer: chunks closed every 0.5 s of log time (or at
    chunk_size), each flushed and fsynced. Returns CPU s, wall s, file bytes."""
    from dyn_node.bag.recorder import METADATA_RECORD, message_definition
    from dyn_node.bag.writer import CountingFile

    raw = open(path, "xb", buffering=0)
    stream = CountingFile(raw)
    c0, w0 = time.process_time(), time.perf_counter()
    wr = cls(stream, chunk_size)
    sids = {t: wr.schema(t, message_definition(t).encode()) for t in (JS, DIAG)}
    cids = [wr.channel(topic, sids[t], _channel_meta(t)) for topic, t in TOPICS]
    wr.metadata(METADATA_RECORD, {"robot_description": "<robot name='panda'/>", "parameters": "",
                                  "version": "bench"})
    next_flush = work[0][1] + int(FLUSH_PERIOD_S * 1e9)
    for ti, log_ns, data in work:
        if log_ns >= next_flush:
            wr.flush()
            if fsync:
                os.fsync(raw.fileno())
            next_flush += int(FLUSH_PERIOD_S * 1e9)
        wr.message(cids[ti], log_ns, data)
    wr.finish()
    if fsync:
        os.fsync(raw.fileno())
    raw.close()
    return dict(cpu_s=time.process_time() - c0, wall_s=time.perf_counter() - w0,
                bytes=path.stat().st_size)


def _count_messages(path: Path) -> tuple[int, int]:
    """(messages by mcap's reader with CRCs checked, messages by dyn_node's BagReader)."""
    from mcap.reader import make_reader

    from dyn_node.bag.reader import BagReader

    with open(path, "rb") as fh:
        n_lib = sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages())
    r = BagReader(path)
    n_ours = sum(1 for _ in r.messages())
    if r.unreadable:
        raise RuntimeError(f"{path.name}: BagReader found damage: {r.unreadable}")
    return n_lib, n_ours


def _library_mcapfile():
    """An adapter with McapFile's interface over mcap.writer.Writer, for the Recorder (bench only).

    The recorder decides when a chunk closes (size, flush period) and counts a chunk's messages
    as written once it reached the stream, so the adapter keeps the per-channel log times the
    recorder's accounting reads (``index``) and closes chunks only when asked."""
    from mcap.writer import CompressionType, Writer

    class LibraryMcapFile:
        def __init__(self, stream, compression="zstd", profile="ros2", library=""):
            comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}.get(
                compression, CompressionType.NONE)
            self._w = Writer(stream, chunk_size=1 << 62, compression=comp, enable_crcs=True,
                             enable_data_crcs=True)
            self._w.start(profile=profile, library=library)
            self.parts: list = []
            self.size = 0
            self.index: dict[int, list[int]] = {}
            self.lo = None
            self.hi = 0

        def add_schema(self, name, encoding, data):
            return self._w.register_schema(name, encoding, data)

        def add_channel(self, topic, message_encoding, schema_id, metadata):
            return self._w.register_channel(topic, message_encoding, schema_id, dict(metadata))

        def add_metadata(self, name, values):
            self._w.add_metadata(name, dict(values))

        def add_message(self, channel_id, log_ns, pub_ns, data):
            self._w.add_message(channel_id, log_ns, data, pub_ns)
            self.size += 31 + len(data)
            idx = self.index.get(channel_id)
            if idx is None:
                idx = self.index[channel_id] = []
            idx += (log_ns, 0)
            if self.lo is None or log_ns < self.lo:
                self.lo = log_ns
            if log_ns > self.hi:
                self.hi = log_ns
            self.parts = True  # "the open chunk holds a message" (the recorder's _fail resets it)

        def close_chunk(self, on_written=None):
            if not self.parts:
                return False
            self._w.flush()
            index, lo, hi = self.index, self.lo or 0, self.hi
            self.parts, self.size, self.index, self.lo, self.hi = [], 0, {}, None, 0
            if on_written is not None:
                on_written(index, lo, hi)
            return True

        def finish(self, on_written=None):
            self.close_chunk(on_written)
            self._w.finish()

    return LibraryMcapFile


def _paced_recording(seconds: float, work, variant: str, tmp: Path) -> dict:
    """Feed ``work`` at its log-time pace (every 10 ms, what arrived in it) into a Recorder with
    fsync on, or into nothing (``variant='none'``); process CPU over the whole run incl. close."""
    import dyn_node.bag.recorder as rec_mod
    from dyn_node.bag.recorder import Recorder, RecorderConfig, TopicInfo

    saved = rec_mod.McapFile
    if variant == "library":
        rec_mod.McapFile = _library_mcapfile()
    try:
        topics = [t for t, _ in TOPICS]
        d = tmp / f"paced_{variant}_{time.perf_counter_ns()}"
        d.mkdir()
        c0, w0 = time.process_time(), time.perf_counter()
        rec = None
        if variant != "none":
            rec = Recorder(RecorderConfig(directory=str(d)), robot_description="<robot name='panda'/>")
            for topic, t in TOPICS:
                rec.add_topic(TopicInfo(topic, t))
        write = rec.write if rec is not None else (lambda *a: True)
        t_start = time.perf_counter()
        base_ns = work[0][1]
        i, n = 0, len(work)
        tick = 0
        while i < n:
            tick += 1
            until_ns = base_ns + tick * 10_000_000
            while i < n and work[i][1] < until_ns:
                ti, log_ns, data = work[i]
                write(topics[ti], data, log_ns, log_ns)
                i += 1
            delay = t_start + tick * 0.010 - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        stats = rec.close(timeout=60.0) if rec is not None else None
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        if stats is not None:
            written = sum(c.written for c in stats.topics.values())
            if written != n or stats.state != "closed":
                raise RuntimeError(f"{variant}: recorder wrote {written} of {n} ({stats.error})")
            files = [Path(f) for f in stats.files]
            n_lib = sum(_count_messages(f)[0] for f in files)
            if n_lib != n + stats.description_copies:
                raise RuntimeError(f"{variant}: mcap reads {n_lib} messages, expected "
                                   f"{n + stats.description_copies}")
        return dict(cpu_s=cpu, wall_s=wall)
    finally:
        rec_mod.McapFile = saved


def run_writer(quick: bool) -> dict:
    from dyn_node.bag.recorder import RecorderConfig

    repeats = 5
    seconds = 10.0 if quick else 30.0
    work = _workload(seconds)
    n = len(work)
    chunk = RecorderConfig().chunk_size
    variants = [("ours", _Ours, None), ("library_as_shipped_zstd3", _Library, None),
                ("library_zstd_level_-1", _Library, -1)]
    out: dict = dict(messages=n, seconds=seconds, chunk_size=chunk, flush_period_s=FLUSH_PERIOD_S,
                     repeats=repeats, layer={}, paced={})
    with tempfile.TemporaryDirectory(prefix="dyn_libbench_") as tn:
        tmp = Path(tn)
        progress("libraries", f"writer layer: {n} messages ({seconds:g} s at 1 kHz) × {repeats}")
        res: dict[str, list[dict]] = {k: [] for k, _, _ in variants}
        for rep in range(repeats):  # interleaved: drift and load hit every variant alike
            for key, cls, level in variants:
                p = tmp / f"{key}_{rep}.mcap"
                with _zstd_level(level):
                    res[key].append(_write_layer(cls, work, p, chunk, fsync=True))
                if rep == 0:
                    n_lib, n_ours = _count_messages(p)
                    if n_lib != n or n_ours != n:
                        raise RuntimeError(f"{key}: read back {n_lib} (mcap) / {n_ours} (ours) of {n}")
                p.unlink()
        for key in res:
            cpu = _median([r["cpu_s"] for r in res[key]])
            out["layer"][key] = dict(cpu_us_per_msg=cpu / n * 1e6,
                                     cpu_ms_per_s_at_1khz=cpu / seconds * 1e3,
                                     wall_s=_median([r["wall_s"] for r in res[key]]),
                                     mib=res[key][0]["bytes"] / 2**20,
                                     cpu_s_all=[r["cpu_s"] for r in res[key]])
        base = out["layer"]["ours"]["cpu_us_per_msg"]
        for key in res:
            out["layer"][key]["ratio_to_ours"] = out["layer"][key]["cpu_us_per_msg"] / base

        p_seconds = 5.0 if quick else 8.0
        pw = _workload(p_seconds)
        progress("libraries", f"paced Recorder: {len(pw)} messages over {p_seconds:g} s × {repeats}, "
                              "none / ours / library")
        pres: dict[str, list[dict]] = {"none": [], "ours": [], "library": []}
        for _ in range(repeats):
            for key in pres:
                pres[key].append(_paced_recording(p_seconds, pw, key, tmp))
        none = _median([r["cpu_s"] for r in pres["none"]])
        for key in ("ours", "library"):
            extra = [r["cpu_s"] - b["cpu_s"] for r, b in zip(pres[key], pres["none"])]
            out["paced"][key] = dict(cpu_ms_per_s=_median(extra) / p_seconds * 1e3,
                                     cpu_us_per_msg=_median(extra) / len(pw) * 1e6,
                                     extra_cpu_s_all=extra)
        out["paced"]["pacing_loop_cpu_ms_per_s"] = none / p_seconds * 1e3
        out["paced"]["messages"] = len(pw)
        out["paced"]["seconds"] = p_seconds
        out["paced"]["ratio_library_to_ours"] = (out["paced"]["library"]["cpu_ms_per_s"]
                                                 / out["paced"]["ours"]["cpu_ms_per_s"])
    return out


def _records_outside_chunks(path: Path) -> dict[str, int]:
    """Schema and Channel records in the data section (outside chunks) and inside chunks."""
    from mcap.records import Channel, Chunk, Schema
    from mcap.stream_reader import StreamReader, breakup_chunk

    out = {"outside": 0, "inside": 0}
    with open(path, "rb") as fh:
        for r in StreamReader(fh, emit_chunks=True).records:
            if isinstance(r, (Schema, Channel)):
                out["outside"] += 1
            elif isinstance(r, Chunk):
                out["inside"] += sum(isinstance(x, (Schema, Channel)) for x in breakup_chunk(r))
            if r.__class__.__name__ == "DataEnd":
                break  # the summary repeats them; only the data section matters after a crash
    return out


def run_layout(quick: bool) -> dict:
    """Where each writer puts Schema and Channel records, and what that means after a crash that
    also damaged the first chunk: 5 s of the node's topics in chunks closed at 64 KiB or every
    0.5 s of data (no fsync: only the layout matters here), the file cut at 60 % (no summary)
    and one byte flipped in chunk 1."""
    from mcap.reader import make_reader

    from dyn_node.bag.reader import BagReader

    work = _workload(5.0)
    out: dict = {}
    with tempfile.TemporaryDirectory(prefix="dyn_libbench_") as tn:
        tmp = Path(tn)
        for key, cls in (("ours", _Ours), ("library", _Library)):
            p = tmp / f"{key}.mcap"
            _write_layer(cls, work, p, 64 * 1024, fsync=False)
            where = _records_outside_chunks(p)
            with open(p, "rb") as fh:
                chunks = sorted(make_reader(fh).get_summary().chunk_indexes,
                                key=lambda c: c.chunk_start_offset)
            data = bytearray(p.read_bytes())
            c0 = chunks[0]
            data[c0.chunk_start_offset + c0.chunk_length // 2] ^= 0xFF
            cut = bytes(data[: int(len(data) * 0.6)])
            d = tmp / f"{key}_crashed.mcap"
            d.write_bytes(cut)
            r = BagReader(d)
            n_ours = sum(1 for _ in r.messages())
            dmg: list[str] = []
            n_hybrid = sum(1 for _ in hybrid_messages(d, dmg))
            out[key] = dict(schema_channel_records=where, chunks=len(chunks),
                            crashed_bagreader_messages=n_ours, crashed_hybrid_messages=n_hybrid,
                            crashed_bagreader_unreadable=[u.reason for u in r.unreadable][:3],
                            crashed_hybrid_damage=sorted(set(x.split(" at ")[0] for x in dmg))[:4],
                            undecodable=r.stats.undecodable_messages,
                            messages_written=len(work))
    return out


# ================================================================= reader
def _lib_seeking(path: Path, crc: bool) -> Callable[[], int]:
    def read() -> int:
        from mcap.reader import make_reader

        with open(path, "rb") as fh:
            return sum(1 for _ in make_reader(fh, validate_crcs=crc).iter_messages())
    return read


def _lib_seeking_unordered(path: Path) -> Callable[[], int]:
    def read() -> int:
        from mcap.reader import make_reader

        with open(path, "rb") as fh:
            return sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages(
                log_time_order=False))
    return read


def _hybrid(path: Path) -> Callable[[], int]:
    return lambda: sum(1 for _ in hybrid_messages(path))


def _lib_stream(path: Path, crc: bool) -> Callable[[], int]:
    def read() -> int:
        from mcap.reader import NonSeekingReader

        with open(path, "rb") as fh:
            return sum(1 for _ in NonSeekingReader(fh, validate_crcs=crc).iter_messages(
                log_time_order=False))
    return read


def _ours_read(path: Path) -> Callable[[], int]:
    def read() -> int:
        from dyn_node.bag.reader import BagReader

        return sum(1 for _ in BagReader(path).messages())
    return read


def hybrid_messages(path: Path, damage: list[str] | None = None):
    """(channel, message) of an MCAP file: mcap's record classes and chunk decompression under a
    record loop of our own (bench only). The loop knows each top-level record's extent before
    parsing it, so a record that fails to parse (bad CRC, bad string, bad compression) is skipped
    and reading resumes at the next one; a record running past the end of the file ends the file.
    Inside a chunk, bytes past a record's known fields are skipped (mcap 1.6.0's breakup_chunk
    does not). ``damage`` collects what was skipped."""
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Chunk, Message, Schema
    from mcap.stream_reader import get_chunk_data_stream

    damage = [] if damage is None else damage
    size = path.stat().st_size
    channels: dict[int, Channel] = {}
    schemas: dict[int, Schema] = {}

    def inner(stream, end: int):
        while stream.count < end:
            op, length = stream.read1(), stream.read8()
            at = stream.count
            if op == Opcode.MESSAGE:
                m = Message.read(stream, length)
                ch = channels.get(m.channel_id)
                if ch is None:
                    damage.append(f"message on unknown channel {m.channel_id}")
                else:
                    yield ch, m
            elif op == Opcode.CHANNEL:
                c = Channel.read(stream)
                channels[c.id] = c
            elif op == Opcode.SCHEMA:
                sc = Schema.read(stream)
                if sc.id:
                    schemas[sc.id] = sc
            pad = length - (stream.count - at)
            if pad > 0:
                stream.read(pad)

    with open(path, "rb") as fh:
        if fh.read(8) != b"\x89MCAP0\r\n":
            damage.append("not MCAP")
            return
        pos = 8
        while pos + 9 <= size:
            fh.seek(pos)
            head = fh.read(9)
            op, length = head[0], int.from_bytes(head[1:], "little")
            end = pos + 9 + length
            if end > size:
                damage.append(f"record at {pos} runs past the end of the file (truncated)")
                return
            if op == Opcode.FOOTER:
                return
            try:
                rs = ReadDataStream(fh)
                if op == Opcode.CHUNK:
                    stream, n = get_chunk_data_stream(Chunk.read(rs), validate_crc=True)
                    msgs = list(inner(stream, n))  # a chunk is all or nothing
                    yield from msgs
                elif op in (Opcode.MESSAGE, Opcode.CHANNEL, Opcode.SCHEMA):
                    fh.seek(pos + 9)
                    # re-frame the one record for inner(): it reads opcode and length itself
                    yield from inner(ReadDataStream(io.BytesIO(head + fh.read(length))), 9 + length)
            except Exception as exc:  # noqa: BLE001 - a damaged record is skipped, not fatal
                damage.append(f"record 0x{op:02x} at {pos} skipped: {type(exc).__name__}")
            pos = end
        if pos < size:
            damage.append("file ends inside a record header (truncated)")


def _outcome(fn: Callable[[], "object"]) -> dict:
    """Run a reader to its end: messages yielded, and the exception that stopped it, if any."""
    n = 0
    try:
        for _ in fn():
            n += 1
        return dict(messages=n, stopped_by="")
    except Exception as exc:  # noqa: BLE001 - the point is to see what each reader raises
        text = str(exc).splitlines()[0][:90] if str(exc) else ""
        return dict(messages=n, stopped_by=f"{type(exc).__name__}: {text}")


def _readers(path: Path) -> tuple[dict[str, Callable[[], "object"]], dict]:
    """The four readers of the damage table, by name, and a holder for what each reported."""
    from mcap.reader import NonSeekingReader, make_reader

    from dyn_node.bag.reader import BagReader

    holder: dict = {}

    def ours():
        r = BagReader(path)
        holder["ours"] = r
        yield from r.messages()

    def seeking():
        with open(path, "rb") as fh:
            yield from make_reader(fh, validate_crcs=True).iter_messages()

    def stream():
        with open(path, "rb") as fh:
            yield from NonSeekingReader(fh, validate_crcs=True).iter_messages(log_time_order=False)

    def hybrid():
        holder["hybrid"] = []
        yield from hybrid_messages(path, holder["hybrid"])

    return {"BagReader": ours, "make_reader (seeking, CRCs on)": seeking,
            "NonSeekingReader (CRCs on, file order)": stream,
            "hybrid (mcap records, our loop)": hybrid}, holder


def _small_chunk_bag(directory: Path, seconds: float) -> Path:
    """A dyn_node bag (Recorder) of 1 kHz joint_states in 64 KiB chunks: many chunks to damage."""
    from dyn_node.bag.recorder import Recorder, RecorderConfig, TopicInfo

    from .recording_bench import _stamp_patched, joint_state_bytes

    t0 = 1_700_000_000 * 1_000_000_000
    rec = Recorder(RecorderConfig(directory=str(directory), fsync=False, chunk_size=64 * 1024,
                                  queue_size=100_000), robot_description="<robot name='panda'/>",
                   clock_ns=lambda: t0)
    rec.add_topic(TopicInfo("/joint_states", JS))
    cycle, _ = joint_state_bytes(1000, t0)
    for data, stamp in _stamp_patched(cycle, int(seconds * 1000), t0, 1000.0):
        rec.write("/joint_states", data, stamp, stamp)
    stats = rec.close(timeout=60.0)
    return Path(stats.files[0])


def _damage_cases(tmp: Path) -> dict[str, tuple[Path, int, str]]:
    """name -> (file, messages a reader should get, what was done)."""
    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    sys.path.insert(0, str(REPO / "test"))
    import mcap_corpus

    src = _small_chunk_bag(tmp / "dmg_src", 5.0)
    data = src.read_bytes()
    with open(src, "rb") as fh:
        summ = make_reader(fh).get_summary()
    chunks = sorted(summ.chunk_indexes, key=lambda c: c.chunk_start_offset)
    total = sum(summ.statistics.channel_message_counts.values())
    with open(src, "rb") as fh:
        per_chunk = [sum(isinstance(r, Message) for r in breakup_chunk(c))
                     for c in StreamReader(fh, emit_chunks=True).records if isinstance(c, Chunk)]
    cases: dict[str, tuple[Path, int, str]] = {}

    def put(name: str, blob: bytes, expect: int, what: str) -> None:
        p = tmp / f"{name}.mcap"
        p.write_bytes(blob)
        cases[name] = (p, expect, what)

    put("healthy", data, total, f"dyn_node bag, 5 s at 1 kHz, {len(chunks)} chunks "
        "(64 KiB), summary")
    half = chunks[len(chunks) // 2]
    cut = half.chunk_start_offset + half.chunk_length // 2
    before = sum(per_chunk[:len(chunks) // 2])
    put("truncated_mid_chunk", data[:cut], before,
        f"cut in the middle of chunk {len(chunks) // 2 + 1} of {len(chunks)} (a crash: no summary)")
    flip = bytearray(data)
    c1 = chunks[1]
    flip[c1.chunk_start_offset + c1.chunk_length // 2] ^= 0xFF
    put("flipped_byte_chunk2", bytes(flip), total - per_chunk[1],
        "one byte flipped inside chunk 2 (its CRC fails); summary intact")
    put("flipped_byte_chunk2_truncated", bytes(flip[:cut]), before - per_chunk[1],
        "chunk 2 damaged as above and the file cut as in truncated_mid_chunk")
    meta = bytearray(data)
    # the dyn_node Metadata record (opcode 0x0C, then its u64 length, then the name "dyn_node")
    at = data.find(b"\x08\x00\x00\x00dyn_node")
    if at >= 9 and data[at - 9] == 0x0C:
        meta[at + 12:at + 16] = (0xFFFFFF00).to_bytes(4, "little")
        put("malformed_metadata_record", bytes(meta), total,
            "the dyn_node Metadata record (outside chunks) has a map length past its record")
    mi = bytearray(data)
    mi_at = c1.chunk_start_offset + c1.chunk_length  # the first Message Index after chunk 2
    mi[mi_at + 1:mi_at + 9] = (1 << 40).to_bytes(8, "little")
    put("message_index_length_garbled", bytes(mi), total,
        "the record length of the Message Index after chunk 2 set past the end of the file")
    for name in ("extra_bytes_zstd", "outside_chunks"):
        blob, expected = mcap_corpus.CORPUS[name]()
        put(f"corpus_{name}", blob, len(expected.messages),
            {"extra_bytes_zstd": "spec corpus: unknown trailing fields on every extensible record, "
                                 "one message outside chunks, indexed (summary)",
             "outside_chunks": "spec corpus: no chunks, messages in the data section, no summary"}[name])
    return cases


def run_reader(quick: bool) -> dict:
    from .recording_bench import write_bag

    repeats = 5
    seconds = 20.0 if quick else 60.0
    out: dict = dict(repeats=repeats, speed={}, damage={})
    with tempfile.TemporaryDirectory(prefix="dyn_libbench_") as tn:
        tmp = Path(tn)
        progress("libraries", f"reader: writing a {seconds:g} s 1 kHz bag")
        bag = write_bag(tmp / "big", seconds)
        f = sorted(bag.glob("*.mcap"))[0]
        readers = {"BagReader (CRCs always)": _ours_read(f),
                   "make_reader seeking, CRCs off": _lib_seeking(f, False),
                   "make_reader seeking, CRCs on": _lib_seeking(f, True),
                   "NonSeekingReader file order, CRCs off": _lib_stream(f, False),
                   "NonSeekingReader file order, CRCs on": _lib_stream(f, True),
                   "make_reader seeking, file order, CRCs on": _lib_seeking_unordered(f),
                   "hybrid: mcap records + our record loop, CRCs on": _hybrid(f)}
        times: dict[str, list[float]] = {k: [] for k in readers}
        counts: dict[str, int] = {}
        progress("libraries", f"reader speed × {repeats}")
        for _ in range(repeats):
            for k, fn in readers.items():
                t0 = time.perf_counter()
                counts[k] = fn()
                times[k].append(time.perf_counter() - t0)
        base = _median(times["BagReader (CRCs always)"])
        for k in readers:
            t = _median(times[k])
            out["speed"][k] = dict(s=t, msgs_per_s=counts[k] / t, messages=counts[k],
                                   time_ratio_to_ours=t / base)
        out["speed_bag"] = dict(seconds=seconds, mib=f.stat().st_size / 2**20)

        progress("libraries", "reader: damaged files")
        for name, (path, expect, what) in _damage_cases(tmp).items():
            fns, holder = _readers(path)
            row: dict = dict(what=what, expected_messages=expect, readers={})
            for rname, fn in fns.items():
                o = _outcome(fn)
                if rname == "BagReader" and "ours" in holder:
                    o["reported"] = [f"{u.reason}" for u in holder["ours"].unreadable][:3]
                if rname.startswith("hybrid"):
                    o["reported"] = holder.get("hybrid", [])[:3]
                row["readers"][rname] = o
            out["damage"][name] = row
    return out


# ================================================================= report
_MPL_SCRIPT = r'''
import pickle, sys, time
t0, c0 = time.perf_counter(), time.process_time()
mode = sys.argv[2]
if mode == "ours":
    from dyn_node.audit import report
else:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from benchmarks import libraries_bench as lb
t_import, c_import = time.perf_counter() - t0, time.process_time() - c0
record, series, names = pickle.loads(open(sys.argv[1], "rb").read())
out = sys.argv[3]
def render():
    if mode == "ours":
        from dyn_node.audit.report import write_report
        write_report(record, series, None, out)
    else:
        lb.mpl_write_report(record, series, out, fmt=mode)
t1, c1 = time.perf_counter(), time.process_time(); render()
t_first, c_first = time.perf_counter() - t1, time.process_time() - c1
warm = []
for _ in range(int(sys.argv[4])):
    t1 = time.perf_counter(); render(); warm.append(time.perf_counter() - t1)
warm.sort()
print(f"{t_import} {t_first} {warm[len(warm) // 2]} {c_import} {c_first}")
'''


def _mpl_effort(plt, series, names, start_ns, violations):
    import numpy as np

    from dyn_node.audit.report import _BLUE, _DARK_BLUE, _ORANGE, _RED, _centres

    n, nv = series.n, len(names)
    t = _centres(series, start_ns)
    w_s = series.width * 1e-9
    have = series.count[:n] > 0
    fig, axes = plt.subplots(nv, 1, sharex=True, figsize=(11.0, (62 + nv * 150 + 40) / 100), dpi=100)
    fig.suptitle("Effort vs limit over time (shaded red: effort violations)", fontsize=11)
    for j, ax in enumerate(np.atleast_1d(axes)):
        lo = np.where(have, series.tau_min[:n, j], np.nan)
        hi = np.where(have, series.tau_max[:n, j], np.nan)
        lim = series.limit[:n, j]
        meas = series.meas_max[:n, j]  # the report draws min and max; one is enough to time
        env = np.where(have & np.isfinite(lim), lim, np.nan)
        for v in violations:
            if v["joint"] == names[j] and v["kind"] == "effort":
                ax.axvspan(v["start_s"], max(v["end_s"], v["start_s"] + w_s), color=_RED, alpha=0.18, lw=0)
        ax.fill_between(t, lo, hi, step="mid", color=_BLUE, alpha=0.55, lw=0,
                        label="model torque (min–max per bin)")
        ax.plot(t, (lo + hi) / 2, color=_DARK_BLUE, lw=0.7)
        if np.isfinite(meas).any():
            ax.step(t, meas, where="mid", color=_ORANGE, lw=1.0, label="measured effort (max per bin)")
        if np.isfinite(env).any():
            ax.step(t, env, where="mid", color=_RED, lw=1.3, label="±effort limit")
            ax.step(t, -env, where="mid", color=_RED, lw=1.3)
        ax.set_ylabel(f"{names[j]}\nN·m", fontsize=8)
        ax.grid(True, color="#e2e5ea", lw=0.6)
        ax.tick_params(labelsize=7)
        if j == 0:
            ax.legend(loc="lower left", bbox_to_anchor=(0, 1.0), ncol=3, fontsize=8, frameon=False)
    np.atleast_1d(axes)[-1].set_xlabel("time since bag start (s)", fontsize=9)
    return fig


def _mpl_utilisation(plt, series, names, start_ns):
    import numpy as np

    from dyn_node.audit.report import _centres

    n, nv = series.n, len(names)
    u = np.where(series.count[:n, None] > 0, series.util[:n], np.nan).T
    t = _centres(series, start_ns)
    w_s = series.width * 1e-9
    vmax = max(1.2, float(np.nanmax(u)) if np.isfinite(u).any() else 1.2)
    fig, ax = plt.subplots(figsize=(11.0, (34 + nv * 30 + 48) / 100), dpi=100)
    im = ax.imshow(u, aspect="auto", cmap="RdYlGn_r", vmin=0, vmax=vmax, interpolation="nearest",
                   extent=(float(t[0] - w_s / 2), float(t[-1] + w_s / 2), nv - 0.5, -0.5))
    ax.set_yticks(range(nv), [str(x) for x in names], fontsize=8)
    ax.set_title("Effort utilisation, joint × time (max per bin)", fontsize=11)
    ax.set_xlabel("time since bag start (s)", fontsize=9)
    cb = fig.colorbar(im, ax=ax, pad=0.01)
    cb.ax.axhline(1.0, color="k", lw=1.2)
    cb.set_label("utilisation (1 = at the limit)", fontsize=8)
    return fig


def _mpl_trajectories(plt, trajs):
    from dyn_node.audit.report import _GREEN, _RED, _finite

    idx = [t["index"] for t in trajs]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11.0, 3.2), dpi=100)
    ks = [_finite(t.get("time_scale")) or 0.0 for t in trajs]
    pm = [_finite(t.get("payload_margin_kg")) or 0.0 for t in trajs]
    a.bar(idx, ks, color=[_GREEN if t["feasible"] else _RED for t in trajs])
    a.axhline(1.0, color="k", ls="--", lw=1)
    a.set_title("Time scale (≤ 1: feasible)", fontsize=10)
    a.set_ylabel("time scale k", fontsize=8)
    b.bar(idx, pm, color=[_GREEN if p >= 0 else _RED for p in pm])
    b.axhline(0.0, color="k", lw=1)
    b.set_title("Payload margin", fontsize=10)
    b.set_ylabel("kg", fontsize=8)
    for ax in (a, b):
        ax.set_xlabel("trajectory #", fontsize=9)
        ax.grid(True, axis="y", color="#e2e5ea", lw=0.6)
    return fig


def mpl_write_report(record: dict, series, out_dir: str, *, fmt: str = "png") -> None:
    """report.write_report with the three plots drawn by matplotlib (bench only): same data, same
    pixel sizes (dpi 100), saved as PNG or SVG and embedded by report.render_html."""
    import io

    import matplotlib.pyplot as plt

    from dyn_node.audit.report import render_html

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    start_ns = record["inputs"]["time_span"]["start_ns"] or 0
    names = record["configuration"]["model"]["joint_names"]
    figs = {}
    if series is not None and series.n:
        figs["effort"] = _mpl_effort(plt, series, names, start_ns, record["outputs"]["violations"])
        figs["utilisation"] = _mpl_utilisation(plt, series, names, start_ns)
    if record["outputs"]["trajectories"]:
        figs["trajectories"] = _mpl_trajectories(plt, record["outputs"]["trajectories"])
    images = {}
    for name, fig in figs.items():
        buf = io.BytesIO()
        fig.savefig(buf, format=fmt, dpi=100)
        plt.close(fig)
        images[f"{name}.png"] = buf.getvalue()  # render_html embeds the bytes as they are
        (out / f"{name}.{fmt}").write_bytes(buf.getvalue())
    (out / "report.html").write_text(render_html(record, images), encoding="utf-8")


def _audit_inputs(bag: Path, tmp: Path, label: str) -> tuple[Path, dict]:
    from dyn_node.audit.bag_audit import Audit, AuditOptions

    t0 = time.perf_counter()
    record, _code, series = Audit(AuditOptions(bag=str(bag), out=str(tmp / f"a_{label}"),
                                               report=False, progress=False)).run()
    audit_s = time.perf_counter() - t0
    names = record["configuration"]["model"]["joint_names"]
    p = tmp / f"{label}.pkl"
    p.write_bytes(pickle.dumps((record, series, names)))
    return p, dict(bins=int(series.n) if series is not None else 0,
                   trajectories=len(record["outputs"]["trajectories"]),
                   violations=len(record["outputs"]["violations"]),
                   messages=record["inputs"].get("message_counts"), audit_run_s=audit_s)


_IMPORTS = {"Pillow (Image, ImageDraw, ImageFont)": "from PIL import Image, ImageDraw, ImageFont",
            "matplotlib + pyplot, Agg": "import matplotlib; matplotlib.use('Agg'); import matplotlib.pyplot",
            "dyn_node.audit.report": "import dyn_node.audit.report"}


def _import_times(repeats: int, env: dict) -> dict[str, float]:
    """Median import time of each plotting stack in a fresh interpreter with numpy already in."""
    out = {}
    for name, stmt in _IMPORTS.items():
        code = (f"import numpy, time; t = time.perf_counter(); {stmt}; "
                "print(time.perf_counter() - t)")
        runs = [float(subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, check=True,
                                     capture_output=True, text=True).stdout)
                for _ in range(repeats)]
        out[name] = _median(runs)
    return out


def run_report(quick: bool) -> dict:
    sys.path.insert(0, str(REPO / "test"))
    try:
        import rclpy  # noqa: F401 - fleet_bags serializes with rclpy
        from fleet_bags import BagSpec, write_bag
    except ImportError as exc:
        raise NotAvailable(f"needs rclpy for the bag generator: {exc}")
    repeats = 5
    out: dict = dict(repeats=repeats, bags={})
    sizes = {"demo": BagSpec("demo", seconds=20.0, rate_hz=1000.0, spike=(8.0, 8.4),
                             trajectories=(False, True, False)),
             "large": BagSpec("large", seconds=60.0 if quick else 120.0, rate_hz=1000.0,
                              spike=(30.0, 30.5), trajectories=(False, True) * 10)}
    env = dict(os.environ, PYTHONPATH=str(REPO))
    out["import_s"] = _import_times(repeats, env)
    with tempfile.TemporaryDirectory(prefix="dyn_libbench_") as tn:
        tmp = Path(tn)
        for label, spec in sizes.items():
            progress("libraries", f"report: writing and auditing the {label} bag ({spec.seconds:g} s)")
            bag = write_bag(tmp, spec)
            pkl, info = _audit_inputs(bag, tmp, label)
            row: dict = dict(info, bag_seconds=spec.seconds, modes={})
            for mode in ("ours", "png", "svg"):
                runs = []
                for k in range(repeats):
                    p = subprocess.run([sys.executable, "-c", _MPL_SCRIPT, str(pkl), mode,
                                        str(tmp / f"r_{label}_{mode}_{k}"), "5"],
                                       cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
                    if p.returncode:
                        raise RuntimeError(f"{mode}: {p.stderr.strip().splitlines()[-1:]}")
                    runs.append([float(x) for x in p.stdout.split()])
                imp, first, warm, c_imp, c_first = (_median([r[i] for r in runs]) for i in range(5))
                sizes_b = sum(f.stat().st_size for f in (tmp / f"r_{label}_{mode}_0").iterdir()
                              if f.suffix in (".png", ".svg"))
                html_b = (tmp / f"r_{label}_{mode}_0" / "report.html").stat().st_size
                row["modes"][mode] = dict(import_s=imp, first_render_s=first, warm_render_s=warm,
                                          per_process_s=imp + first,
                                          per_process_cpu_s=c_imp + c_first, images_kib=sizes_b / 1024,
                                          html_kib=html_b / 1024)
            base = row["modes"]["ours"]["per_process_s"]
            cbase = row["modes"]["ours"]["per_process_cpu_s"]
            for mode in row["modes"]:
                m = row["modes"][mode]
                m["per_process_ratio_to_ours"] = m["per_process_s"] / base
                m["per_process_cpu_ratio_to_ours"] = m["per_process_cpu_s"] / cbase
            out["bags"][label] = row
    return out


# ================================================================= entry
PARTS = {"writer": run_writer, "layout": run_layout, "reader": run_reader, "report": run_report}


def run(quick: bool = False, smoke: bool = False, parts: tuple[str, ...] = tuple(PARTS)) -> dict:
    out: dict = dict(loadavg_start=os.getloadavg())
    for name in parts:
        t0 = time.perf_counter()
        la = os.getloadavg()
        try:
            out[name] = PARTS[name](quick or smoke)
        except NotAvailable as exc:
            out[name] = dict(status=f"not available: {exc}")
        out[name]["wall_s"] = time.perf_counter() - t0
        out[name]["loadavg_start"] = la
        out[name]["loadavg_end"] = os.getloadavg()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.libraries_bench", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", default=",".join(PARTS), help=f"comma-separated: {','.join(PARTS)}")
    ap.add_argument("--quick", action="store_true", help="smaller bags and workloads")
    ap.add_argument("--json", default=str(REPO / "bench_out" / "libraries.json"),
                    help="where the raw figures go")
    args = ap.parse_args(argv)
    parts = tuple(p.strip() for p in args.part.split(",") if p.strip())
    for p in parts:
        if p not in PARTS:
            raise SystemExit(f"unknown part {p!r}; choose from {', '.join(PARTS)}")
    res = run(quick=args.quick, parts=parts)
    res["measured_at"] = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = json.loads(path.read_text()) if path.exists() else {}
    doc.update(res)
    path.write_text(json.dumps(doc, indent=1, default=str))
    print(json.dumps(res, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
