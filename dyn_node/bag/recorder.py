"""Record raw CDR messages into a rosbag2-layout MCAP bag, off the caller's thread.

Pure (no rclpy): the ROS adapter (:mod:`dyn_node.ros.recording`) hands it the bytes it received,
never re-serialized. :meth:`Recorder.write` never blocks on disk and never raises (a full queue
counts a drop), and per topic ``received == written + dropped`` once closed. Guarantees and the
bag layout: docs/recording.md and docs/BAGS.md. Message definitions, metadata.yaml and the MCAP
writer are :mod:`~dyn_node.bag.msgdefs`, :mod:`~dyn_node.bag.metadata`, :mod:`~dyn_node.bag.writer`.
"""
from __future__ import annotations

import atexit
import errno
import os
import threading
import time
import weakref
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Callable, Mapping

from dyn_node import __version__
from dyn_node.bag.metadata import (METADATA_RECORD, FileInfo, TopicInfo, bag_metadata, limits_record,
                                   new_bag_directory,
                           qos_profile_dict, qos_yaml, write_metadata_yaml)
from dyn_node.bag.cdr import cdr_string, cdr_string_value, header_stamp_ns
from dyn_node.errors import RecordingError
from dyn_node.bag.writer import COMPRESSIONS, PROFILE, CountingFile, McapFile
from dyn_node.bag.msgdefs import is_service_type, message_definition, type_description_hash

__all__ = [  # the recorder, and what its callers pass it or read from it
    "COMPRESSIONS", "HEADER_STAMP", "METADATA_RECORD", "Recorder", "RecorderConfig",
    "RecorderStats", "RecordingError", "TopicCounts", "TopicInfo", "cdr_string",
    "header_stamp_ns", "message_definition", "qos_profile_dict", "type_description_hash"]

SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
DESCRIPTION_TYPE = "std_msgs/msg/String"
STATES = ("idle", "recording", "error", "closed")


# --------------------------------------------------------------------------- the recorder

@dataclass(frozen=True)
class RecorderConfig:
    """Recorder settings. Sizes in MB (10^6 bytes), durations in seconds; 0 disables a split."""

    directory: str = "bags"
    compression: str = "zstd"
    max_bag_size_mb: float = 0.0
    max_bag_duration_s: float = 0.0
    prefix: str = "dyn_node"
    queue_size: int = 20_000
    queue_bytes: int = 256 * 1024 * 1024
    flush_period_s: float = 0.5
    chunk_size: int = 1024 * 1024
    fsync: bool = True
    description_topic: str = "/robot_description"

    def validate(self) -> None:
        if self.compression not in COMPRESSIONS:
            raise RecordingError(f"record.compression must be one of {sorted(COMPRESSIONS)}, "
                                 f"got {self.compression!r}")
        for key in ("max_bag_size_mb", "max_bag_duration_s"):
            v = getattr(self, key)
            if not (v >= 0 and v < float("inf")):
                raise RecordingError(f"record.{key} must be finite and >= 0 (0 = off), got {v!r}")
        if not (0 < self.flush_period_s <= 1.0):
            raise RecordingError("flush_period_s must be in (0, 1] s: at most 1 s may be lost")
        if self.queue_size < 1 or self.queue_bytes < 1 or self.chunk_size < 1:
            raise RecordingError("queue_size, queue_bytes and chunk_size must be positive")


@dataclass(frozen=True)
class TopicCounts:
    received: int = 0
    written: int = 0
    dropped: int = 0


@dataclass(frozen=True)
class RecorderStats:
    """Snapshot of the recorder: state in STATES, error text ("" if none), bag directory,
    files so far, per-topic counts, messages waiting in the queue, injected description copies."""

    state: str
    error: str
    path: str
    files: tuple[str, ...]
    topics: Mapping[str, TopicCounts]
    queued: int
    description_copies: int

    @property
    def dropped(self) -> int:
        return sum(c.dropped for c in self.topics.values())


# Recorder.write's publish time "the header stamp of the message" (parsed on the writer thread).
HEADER_STAMP = -1

# Queue items: a message is (topic, data, log_ns, publish_ns); anything else is
# (None, kind, payload) with kind one of these.
_TOPIC, _DESC, _META, _STOP = range(4)

_LIVE: "weakref.WeakSet[Recorder]" = weakref.WeakSet()


@atexit.register
def _close_live_recorders() -> None:
    # Interpreter exit (e.g. an unhandled KeyboardInterrupt) still writes summaries.
    for rec in list(_LIVE):
        rec.close(timeout=5.0)


class Recorder:
    """One recording: a bag directory written by a background thread.

    ``opener(path) -> binary file`` is injectable (tests simulate ENOSPC with it);
    ``on_state(stats)`` is called from the writer thread when the state changes."""

    # The writer takes messages in batches: it wakes every _BATCH_S or once _BATCH_N messages
    # wait, not per message. A wake-up per message (a thread switch and a trip through the
    # lock at 3 kHz: joint_states plus two outputs) cost the recording node more CPU than
    # writing the messages.
    _BATCH_S = 0.1
    _BATCH_N = 1024

    def __init__(self, config: RecorderConfig = RecorderConfig(), *,
                 robot_description: str = "", parameters_yaml: str = "",
                 effective_log_time_ns: int | None = None, limits_yaml: str | None = None,
                 opener: Callable[[str], BinaryIO] | None = None,
                 on_state: Callable[[RecorderStats], None] | None = None,
                 clock_ns: Callable[[], int] = time.time_ns):
        config.validate()
        self.config = config
        # Unbuffered: McapFile writes whole records (a chunk in one call), and a full disk then
        # surfaces at the write that failed rather than at some later buffer flush.
        self._opener = opener or (lambda p: open(p, "xb", buffering=0))
        self._on_state = on_state
        self._clock_ns = clock_ns
        self.path = new_bag_directory(config.directory, config.prefix, fsync=config.fsync)
        # Re-entrant: the on_state observer runs under the lock and may call stats().
        self._lock = threading.RLock()
        self._wake = threading.Condition(self._lock)
        # Callers append without the lock (see write); only the writer thread (or a drain under
        # the lock) takes items out. A message counts as received once it leaves the queue;
        # stats() adds the ones still in it.
        self._queue: deque[tuple] = deque()
        self._bytes_in = 0  # payload bytes ever queued (callers) ...
        self._bytes_out = 0  # ... and taken out (under the lock)
        self._queue_size, self._queue_bytes = config.queue_size, config.queue_bytes
        self._counts: dict[str, list[int]] = {}  # topic -> [received, written, dropped]
        self._declared: set[str] = set()
        self._accepting = True  # recording and not closing (read by write() under the lock)
        self._state = "recording"
        self._error = ""
        self._closing = False
        self._topics: dict[str, TopicInfo] = {}
        self._description = robot_description
        self._description_raw: bytes | None = None
        self._parameters_yaml = parameters_yaml
        self._effective_ns = effective_log_time_ns
        self._limits_yaml = limits_yaml
        # the configuration the writer has reached in queue order (what each file's record says)
        self._w_parameters = (parameters_yaml, effective_log_time_ns, limits_yaml)
        self._description_copies = 0
        self._files: list[FileInfo] = []
        # Writer-thread state.
        self._mcap: McapFile | None = None
        self._stream: CountingFile | None = None
        self._channels: dict[str, int] = {}
        self._channel_topics: dict[int, str] = {}
        self._channelled: set[str] = set()  # topics given a channel in some file
        self._schemas: dict[str, int] = {}
        self._file_index = -1
        self._file_start = 0
        self._file_end = 0
        self._file_counts: dict[str, int] = {}
        self._pending_copies = 0  # description copies in the open chunk
        self._file_first_ns: int | None = None  # first recorded (not copied) message of the file
        self._current: str | None = None
        self._meta_desc: str | None = None
        self._chunk_limit = config.chunk_size
        self._file_written_desc = ""
        self._thread = threading.Thread(target=self._run, name="dyn_node recorder", daemon=True)
        self._closed = threading.Event()
        _LIVE.add(self)
        self._thread.start()

    # ---------------------------------------------------------------- caller side (any thread)
    def add_topic(self, topic: TopicInfo) -> None:
        """Declare a topic before its first message (the channel carries its QoS)."""
        with self._lock:
            self._counts.setdefault(topic.name, [0, 0, 0])
            self._declared.add(topic.name)
            if not self._accepting:
                return
            self._queue.append((None, _TOPIC, topic))
            self._wake.notify()

    def write(self, topic: str, data: bytes, log_time_ns: int,
              publish_time_ns: int | None = None) -> bool:
        """Queue one serialized message; True if queued, False if dropped (counted). Never raises
        for I/O, never blocks on disk. Unknown topics must be added first with add_topic().

        ``publish_time_ns``: None = the log time; :data:`HEADER_STAMP` = the message's header
        stamp (:func:`header_stamp_ns`, the log time if unusable), read on the writer thread so
        the caller's thread does not pay for it."""
        # No lock on this path: it runs on the node's hot thread up to 3 times per joint state,
        # and deque.append is atomic. The byte bound is approximate: the counters are updated
        # without a lock, and a lost update only ever errs towards accepting a message.
        q = self._queue
        n = len(data)
        if (self._accepting and topic in self._declared and len(q) < self._queue_size
                and self._bytes_in - self._bytes_out + n <= self._queue_bytes):
            self._bytes_in += n
            q.append((topic, data, log_time_ns,
                      log_time_ns if publish_time_ns is None else publish_time_ns))
            if len(q) == self._BATCH_N:
                with self._lock:
                    self._wake.notify()
            return True
        with self._lock:
            c = self._counts.get(topic)
            if c is None:
                c = self._counts[topic] = [0, 0, 0]
            c[0] += 1
            c[2] += 1
        return False

    def set_robot_description(self, urdf: str) -> None:
        """The description to repeat at the start of every file and in the metadata record."""
        with self._lock:
            if urdf == self._description or not self._accepting:
                self._description = urdf
                return
            self._description = urdf
            self._queue.append((None, _DESC, urdf))
            self._wake.notify()

    def set_parameters_yaml(self, text: str, *, effective_log_time_ns: int | None = None,
                            limits_yaml: str | None = None) -> None:
        """New parameter snapshot: a new ``dyn_node`` metadata record is written if it (or the
        log time from which it applies, ``effective_log_time_ns``, or the limits file text the
        model was built from, ``limits_yaml``; None: no limits file) changed. The record follows
        the messages queued before this call, so every file's record is the configuration in
        force at that point of the recording."""
        with self._lock:
            if effective_log_time_ns is None:
                effective_log_time_ns = self._effective_ns
            new = (text, effective_log_time_ns, limits_yaml)
            if new == (self._parameters_yaml, self._effective_ns, self._limits_yaml):
                return
            self._parameters_yaml, self._effective_ns, self._limits_yaml = new
            if self._accepting:
                self._queue.append((None, _META, new))
                self._wake.notify()

    def stats(self) -> RecorderStats:
        with self._lock:
            return self._stats_locked()

    def _stats_locked(self) -> RecorderStats:
        # Messages still in the queue are received (not yet counted); once the writer has
        # finished, nothing will take them out: they are dropped.
        queued: dict[str, int] = {}
        for item in list(self._queue):  # list(): one atomic copy while callers append
            if item[0] is not None:
                queued[item[0]] = queued.get(item[0], 0) + 1
        gone = self._closed.is_set()
        return RecorderStats(
            state=self._state, error=self._error, path=str(self.path),
            files=tuple(f.path for f in self._files) + (
                (str(self._file_path(self._file_index)),) if self._mcap is not None else ()),
            topics={t: TopicCounts(c[0] + queued.get(t, 0), c[1],
                                   c[2] + (queued.get(t, 0) if gone else 0))
                    for t, c in self._counts.items()},
            queued=sum(queued.values()), description_copies=self._description_copies)

    def close(self, timeout: float = 10.0) -> RecorderStats:
        """Drain the queue, write summaries and metadata.yaml; idempotent. Messages still queued
        when ``timeout`` expires are counted as dropped."""
        with self._lock:
            if not self._closing:
                self._closing = True
                self._accepting = False
                self._queue.append((None, _STOP, None))
                self._wake.notify()
        self._closed.wait(timeout)
        with self._lock:
            if not self._closed.is_set():
                # The writer is stuck (e.g. a hung disk): account for what it will never write.
                self._drop_locked(self._queue, taken=False)
                self._set_state_locked("error", self._error or "writer did not finish in time")
            return self._stats_locked()

    # ---------------------------------------------------------------- writer thread
    def _file_path(self, index: int) -> Path:
        return self.path / f"{self.path.name}_{index}.mcap"

    def _set_state_locked(self, state: str, error: str = "") -> None:
        changed = state != self._state
        self._state = state
        if state != "recording":
            self._accepting = False
        if error:
            self._error = error
        if changed and self._on_state is not None:
            stats = self._stats_locked()
            try:
                self._on_state(stats)
            except Exception:  # a faulty observer must not kill the writer
                pass

    def _drop_locked(self, items: "deque[tuple]", taken: bool) -> None:
        """Count the messages among ``items`` as dropped (and as received unless ``taken``, i.e.
        already taken from the queue) and remove them."""
        counts = self._counts
        pop = items.popleft
        while items:  # popleft, not iteration: callers may append to the queue meanwhile
            item = pop()
            if item[0] is not None:
                c = counts[item[0]]
                c[2] += 1
                if not taken:
                    c[0] += 1
                    self._bytes_out += len(item[1])

    def _take_locked(self) -> "deque[tuple]":
        """Take what is in the queue now; its messages count as received from here on."""
        q = self._queue
        pop = q.popleft
        batch = deque([pop() for _ in range(len(q))])
        counts = self._counts
        n_bytes = 0
        for item in batch:
            if item[0] is not None:
                counts[item[0]][0] += 1
                n_bytes += len(item[1])
        self._bytes_out += n_bytes
        return batch

    def _run(self) -> None:
        next_flush = time.monotonic() + self.config.flush_period_s
        try:
            self._open_file()
            self._write_metadata_yaml()
            self._reserve(True)
        except Exception as exc:  # noqa: BLE001 - any I/O failure becomes the error state
            self._fail(exc)
        stop = False
        while not stop:
            with self._lock:
                q = self._queue
                if self._state != "recording":
                    # Failed: nothing is queued any more (write() counts its drops), so sleep
                    # until close(). Waiting on the flush deadline here, which no longer
                    # advances, spun a whole core and starved the node's live path.
                    while not self._closing:
                        self._wake.wait()
                elif len(q) < self._BATCH_N and not self._urgent():
                    self._wake.wait(max(0.0, min(next_flush - time.monotonic(), self._BATCH_S)))
                batch = self._take_locked()
            try:
                stop = self._write_batch(batch)
            except Exception as exc:  # noqa: BLE001
                self._fail(exc)
                stop = self._drain_failed(batch)
            if self._state == "recording" and (stop or time.monotonic() >= next_flush):
                try:
                    self._flush()
                except Exception as exc:  # noqa: BLE001
                    self._fail(exc)
                next_flush = time.monotonic() + self.config.flush_period_s
        self._finish()

    def _urgent(self) -> bool:
        """Whether the queue holds anything but messages (stop, a topic, a new description)."""
        q = self._queue
        return bool(q) and (q[-1][0] is None or q[0][0] is None or self._closing)

    def _drain_failed(self, batch: "deque[tuple]") -> bool:
        """After a failure: count the rest of the batch as dropped; True if it held the stop."""
        stop = any(item[0] is None and item[1] == _STOP for item in batch)
        with self._lock:
            self._drop_locked(batch, taken=True)
        return stop

    def _write_batch(self, batch: "deque[tuple]") -> bool:
        """Write a batch of queue items in order; True once the stop item was reached. On an
        exception, the items not yet consumed stay in ``batch``."""
        if self._state != "recording":
            return self._drain_failed(batch)
        cfg = self.config
        split = cfg.max_bag_size_mb > 0 or cfg.max_bag_duration_s > 0
        desc_topic = cfg.description_topic
        pop = batch.popleft
        while batch:
            item = pop()
            topic = item[0]
            if topic is None:
                if item[1] == _STOP:
                    with self._lock:  # nothing follows the stop item, but be exact
                        self._drop_locked(batch, taken=True)
                    return True
                self._control(item)
                continue
            mcap = self._mcap
            if split:
                self._current = topic  # not in a chunk yet: _fail must count it if we fail now
                self._maybe_split(item[2], len(item[1]))
                self._current = None
                mcap = self._mcap
            cid = self._channels.get(topic)
            if cid is None:  # writes Schema and Channel records: may fail like any write
                self._current = topic
                cid = self._channel(self._topics[topic])
                self._current = None
            if topic == desc_topic:
                self._record_description(cid, item)
                continue
            pub = item[3]
            if pub == HEADER_STAMP:
                pub = header_stamp_ns(item[1]) or item[2]
            mcap.add_message(cid, item[2], pub, item[1])
            if self._file_first_ns is None:
                self._file_first_ns = item[2]
            if mcap.size >= self._chunk_limit:
                self._flush_chunk()
        return False

    def _record_description(self, cid: int, item: tuple) -> None:
        _topic, data, log_ns, pub_ns = item
        if pub_ns == HEADER_STAMP:
            pub_ns = header_stamp_ns(data) or log_ns
        text = cdr_string_value(data)
        if text is not None:
            self._description_raw = bytes(data)
            with self._lock:
                self._description = text
            self._file_written_desc = text
        assert self._mcap is not None
        self._mcap.add_message(cid, log_ns, pub_ns, data)
        if self._file_first_ns is None:
            self._file_first_ns = log_ns
        if self._meta_desc != self._description:
            self._write_metadata_record()  # the record follows the description in use
        if self._mcap.size >= self._chunk_limit:
            self._flush_chunk()

    def _control(self, item: tuple) -> None:
        kind = item[1]
        if kind == _TOPIC:
            topic: TopicInfo = item[2]
            # The first registration of a name wins for the whole recording: a channel cannot
            # change once written, and metadata.yaml must describe the channels in the files
            # (readers such as rosbags match them by QoS too). The injected description copy
            # registers /robot_description as reliable + transient local.
            if topic.name not in self._topics:
                self._topics[topic.name] = topic
                if self._mcap is not None and not is_service_type(topic.type):
                    self._channel(topic)
        elif kind == _DESC:
            if item[2] != self._file_written_desc:
                self._description_raw = None
                self._write_description(self._clock_ns())
                self._write_metadata_record()
        elif kind == _META:
            self._w_parameters = item[2]
            self._write_metadata_record()

    def _channel(self, info: TopicInfo) -> int:
        assert self._mcap is not None
        cid = self._channels.get(info.name)
        if cid is not None:
            return cid
        sid = self._schemas.get(info.type)
        if sid is None:
            definition = message_definition(info.type)
            sid = self._mcap.add_schema(info.type, SCHEMA_ENCODING, definition.encode())
            self._schemas[info.type] = sid
        meta = {"offered_qos_profiles": qos_yaml(info.offered_qos_profiles)}
        h = type_description_hash(info.type)
        if h:
            meta["topic_type_hash"] = h
        cid = self._mcap.add_channel(info.name, MESSAGE_ENCODING, sid, meta)
        self._channels[info.name] = cid
        self._channel_topics[cid] = info.name
        self._channelled.add(info.name)
        return cid

    def _open_file(self, log_ns: int | None = None) -> None:
        self._file_index += 1
        path = self._file_path(self._file_index)
        self._stream = CountingFile(self._opener(str(path)))
        chunk = self.config.chunk_size
        if self.config.max_bag_size_mb > 0:
            chunk = max(4096, min(chunk, int(self.config.max_bag_size_mb * 1e6 / 4)))
        self._chunk_limit = chunk
        self._mcap = McapFile(self._stream, self.config.compression, PROFILE,
                              f"dyn_node/{__version__}")
        self._channels, self._channel_topics, self._schemas = {}, {}, {}
        self._file_counts = {}
        self._file_start = self._file_end = 0
        self._file_first_ns = None
        for info in list(self._topics.values()):
            # a service's event channel is made by its first event: readers that cannot read
            # srv types (rosbags, mcap_ros2) then open every bag without calls
            if not is_service_type(info.type) or info.name in self._channelled:
                self._channel(info)
        # The copy of a split file takes the log time of the message that caused the split, so
        # it lies inside the file's time range.
        self._write_description(self._clock_ns() if log_ns is None else log_ns)
        self._write_metadata_record()
        self._flush()

    def _write_description(self, log_ns: int) -> None:
        with self._lock:
            text = self._description
        if not text and self._description_raw is None:
            return
        raw = self._description_raw if self._description_raw is not None else cdr_string(text)
        topic = self.config.description_topic
        if topic not in self._topics:
            self._topics[topic] = TopicInfo(topic, DESCRIPTION_TYPE, (qos_profile_dict(
                durability="transient_local", depth=1),))
        assert self._mcap is not None
        self._mcap.add_message(self._channel(self._topics[topic]), log_ns, log_ns, raw)
        self._pending_copies += 1
        self._file_written_desc = text

    def _write_metadata_record(self) -> None:
        assert self._mcap is not None
        with self._lock:
            desc = self._description
        params, effective_ns, limits = self._w_parameters
        self._meta_desc = desc
        values = {"robot_description": desc, "parameters": params, "version": __version__}
        if effective_ns is not None:
            values["effective_log_time_ns"] = str(effective_ns)
        if limits is not None:  # the bag alone then rebuilds the limits (dyn-audit)
            values.update(limits_record(limits))
        self._mcap.add_metadata(METADATA_RECORD, values)

    def _maybe_split(self, log_ns: int, size: int) -> None:
        # Only split a file that holds a recorded message: a file with just the description
        # copy cannot get smaller, and splitting it again would loop.
        cfg = self.config
        first = self._file_first_ns
        if first is None or self._stream is None or self._mcap is None:
            return
        too_long = cfg.max_bag_duration_s > 0 and log_ns - first >= cfg.max_bag_duration_s * 1e9
        # Compressed size is known only for closed chunks; the open chunk counts uncompressed.
        too_big = cfg.max_bag_size_mb > 0 and \
            self._stream.tell() + self._mcap.size + size >= cfg.max_bag_size_mb * 1e6
        if too_long or too_big:
            self._close_file()
            self._open_file(log_ns)
            self._write_metadata_yaml()

    def _flush_chunk(self, final: bool = False) -> None:
        """Close the open chunk and hand it to the OS; its messages then count as written
        (also when writing its message indexes fails afterwards: they are in the file)."""
        assert self._mcap is not None
        if final:
            self._mcap.finish(self._commit)
        else:
            self._mcap.close_chunk(self._commit)

    def _flush(self) -> None:
        """Close the open chunk, flush it to the OS and fsync (the periodic durability point)."""
        if self._mcap is None or self._stream is None:
            return
        self._flush_chunk()
        self._stream.flush()
        if self.config.fsync:
            self._stream.fsync()

    def _commit(self, index: dict[int, list[int]], lo: int, hi: int) -> None:
        """A chunk reached the file: its messages (from its message index) count as written."""
        topics = self._channel_topics
        desc_topic = self.config.description_topic
        copies, self._pending_copies = self._pending_copies, 0
        with self._lock:
            for cid, entries in index.items():
                topic = topics[cid]
                n = len(entries) // 2
                self._file_counts[topic] = self._file_counts.get(topic, 0) + n
                if topic == desc_topic:
                    n -= copies
                if n:
                    self._counts.setdefault(topic, [0, 0, 0])[1] += n
            self._description_copies += copies
        self._file_start = lo if self._file_start == 0 else min(lo, self._file_start)
        self._file_end = max(hi, self._file_end)

    def _close_file(self) -> None:
        assert self._mcap is not None and self._stream is not None
        self._flush_chunk(final=True)
        self._stream.flush()
        if self.config.fsync:
            self._stream.fsync()
        self._stream.close()
        self._files.append(self._file_info())
        self._mcap, self._stream = None, None

    def _file_info(self) -> FileInfo:
        return FileInfo(str(self._file_path(self._file_index)), self._file_start,
                        self._file_end, sum(self._file_counts.values()), dict(self._file_counts))

    def _fail(self, exc: BaseException) -> None:
        name = errno.errorcode.get(getattr(exc, "errno", None) or -1, type(exc).__name__)
        with self._lock:
            # Messages in the chunk that did not reach the disk are lost: count them.
            if self._mcap is not None:
                desc_topic = self.config.description_topic
                for cid, entries in self._mcap.index.items():
                    topic = self._channel_topics[cid]
                    n = len(entries) // 2 - (self._pending_copies if topic == desc_topic else 0)
                    if n:
                        self._counts.setdefault(topic, [0, 0, 0])[2] += n
                self._mcap.index = {}
                self._mcap.parts = []
            self._pending_copies = 0
            if self._current is not None:
                self._counts[self._current][2] += 1
                self._current = None
            self._drop_locked(self._queue, taken=False)
            self._set_state_locked("error", f"write failed ({name}): {exc}")
            # What was flushed stays on disk; keep the partial file for dyn-bag-recover.
            if self._mcap is not None and self._stream is not None:
                self._files.append(self._file_info())
        if self._stream is not None:
            try:
                self._stream.close()
            except Exception:  # noqa: BLE001 - the file is already broken
                pass
        self._mcap, self._stream = None, None

    # Room kept for the final metadata.yaml (about 1 kB per topic, 0.2 kB per file): a disk
    # that fills up during the recording still gets its counts and error written at close.
    _RESERVE_BYTES = 64 * 1024

    def _reserve(self, hold: bool) -> None:
        """Hold (or release, before the final metadata.yaml) the reserved space in the bag."""
        path = self.path / ".metadata.yaml.reserve"
        if not hold:
            path.unlink(missing_ok=True)
            return
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        except OSError:
            return
        try:
            os.posix_fallocate(fd, 0, self._RESERVE_BYTES)
        except OSError:  # no room even for that: go on without it
            path.unlink(missing_ok=True)
        finally:
            os.close(fd)

    def _write_metadata_yaml(self) -> None:
        with self._lock:
            files = list(self._files)
            counts = {t: {"received": c[0], "written": c[1], "dropped": c[2]}
                      for t, c in self._counts.items()}
            extra = {"version": __version__, "state": self._state, "error": self._error,
                     "description_copies": self._description_copies, "topics": counts}
        if self._mcap is not None:
            files.append(self._file_info())
        topics = [t for t in self._topics.values()
                  if not is_service_type(t.type) or t.name in self._channelled]
        write_metadata_yaml(self.path, bag_metadata(topics, files, extra),
                            fsync=self.config.fsync)

    def _finish(self) -> None:
        if self._state == "recording" and self._mcap is not None:
            try:
                self._close_file()
            except Exception as exc:  # noqa: BLE001
                self._fail(exc)
        with self._lock:
            if self._state == "recording":
                self._set_state_locked("closed")
            # A caller that passed write()'s check just before close() may have queued after
            # the stop item; a message queued later still shows as dropped in stats().
            self._drop_locked(self._queue, taken=False)
        try:
            self._reserve(False)
            self._write_metadata_yaml()
        except Exception as exc:  # noqa: BLE001 - e.g. the disk is still full
            note = f"metadata.yaml not written: {exc}"
            with self._lock:  # the bag then has no metadata.yaml (never a stale one)
                self._set_state_locked("error", f"{self._error}; {note}" if self._error else note)
        _LIVE.discard(self)
        self._closed.set()
