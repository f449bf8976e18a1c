"""ROS side of recording: parameters, raw subscriptions, start/stop services, recorder status.

``RecordingBridge(node)`` subscribes raw to every configured topic and hands the bytes to a
:class:`dyn_node.bag.recorder.Recorder`; the callback does no disk I/O. The node's own endpoints
are recorded from its calls instead of a subscription to itself (which are, and why:
docs/BAGS.md).
"""
from __future__ import annotations

import threading
import time
from typing import Any, Callable

import yaml
from rcl_interfaces.msg import ParameterType
from rclpy.clock import ClockType
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                       ReliabilityPolicy)
from std_srvs.srv import Trigger

from dyn_node.errors import EVALUATION_ERROR, RecordingError
from dyn_node.bag.metadata import TopicInfo, qos_profile_dict
from dyn_node.bag.writer import COMPRESSIONS
from dyn_node.bag.msgdefs import has_header_first
from dyn_node.bag.recorder import HEADER_STAMP, Recorder, RecorderConfig, RecorderStats
from dyn_node.ros.params import parameter_descriptor
from dyn_node.core.robot.status import ERROR, NAME_PREFIX, OK, WARN, Status

STATUS_NAME = NAME_PREFIX + "recorder"
# the question services' introspection events: each request and response with contents
SERVICE_EVENT_TOPICS = ["~/check_trajectory/_service_event", "~/compute_inverse_dynamics/_service_event",
                        "~/retime_trajectory/_service_event"]
DEFAULT_TOPICS = ["joint_states", "joint_trajectory", *SERVICE_EVENT_TOPICS,
                  "robot_description", "/diagnostics",
                  "~/gravity_torque", "~/inverse_dynamics", "~/trajectory_effort",
                  "~/feasibility", "~/controller_status",
                  "~/external_torque", "~/external_wrench", "~/observer_events", "~/gate_decisions"]
# Subscriber history: deep enough that a busy executor does not lose 1 kHz messages in DDS.
SUBSCRIBER_DEPTH = 1000

_RELIABILITY = {ReliabilityPolicy.RELIABLE: "reliable",
                ReliabilityPolicy.BEST_EFFORT: "best_effort"}
_DURABILITY = {DurabilityPolicy.TRANSIENT_LOCAL: "transient_local",
               DurabilityPolicy.VOLATILE: "volatile"}
_HISTORY = {HistoryPolicy.KEEP_LAST: "keep_last", HistoryPolicy.KEEP_ALL: "keep_all"}
_LIVELINESS = {LivelinessPolicy.AUTOMATIC: "automatic",
               LivelinessPolicy.MANUAL_BY_TOPIC: "manual_by_topic"}


class RecordingBridge:
    """Owns the recorder of a node. ``robot_description`` is a callable returning the URDF in
    use (or ""); without one, the node's ``robot_description`` parameter is used if declared."""

    _PARAMETERS_REFRESH = 10  # discovery ticks between parameter snapshots without a set

    def __init__(self, node: Node, robot_description: Callable[[], str] | None = None, *,
                 discovery_period_s: float = 1.0, flush_period_s: float = 0.5,
                 opener: Callable[[str], Any] | None = None, autostart: bool = True,
                 configuration_since: Callable[[], int | None] | None = None,
                 limits_yaml: Callable[[], str | None] | None = None):
        """``configuration_since() -> ns``: the log time from which the owner's current
        configuration applies (written as ``effective_log_time_ns`` in each metadata record).
        ``limits_yaml() -> text``: the limits file text the owner's model was built from (None:
        none), recorded with its sha256 beside each parameter snapshot."""
        self.node = node
        self._configuration_since = configuration_since
        self._limits_fn = limits_yaml
        self._clock = node.get_clock()
        self._clock_handle = self._clock.handle
        self._ros_clock = self._clock.clock_type == ClockType.ROS_TIME
        # Held while the recorder is swapped in or out. An owner that records from another
        # thread (the node's joint_states thread) sets its own lock here and holds it around
        # each message, so a message and its outputs are recorded together or not at all.
        self.guard: Any = threading.Lock()
        #: called under ``guard`` as a recording starts, before its first message (the node
        #: resets its momentum observer there, so a bag replays from its own first sample)
        self.on_start: Callable[[], None] | None = None
        self._description_fn = robot_description
        self._flush_period_s = flush_period_s
        self._opener = opener  # tests inject a failing file here
        self._recorder: Recorder | None = None
        self._last_stats: RecorderStats | None = None
        self._subs: dict[str, Any] = {}
        self._topics: list[str] = []
        self._description = ""
        self._unknown: set[str] = set()
        self._outgoing: dict[str, TopicInfo] = {}  # this node's publishers, recorded directly
        self._direct: set[str] = set()
        # publisher or subscription object -> (topic, stamped): topic_name is a call into rcl
        self._endpoints: dict[Any, tuple[str, bool]] = {}
        self._live: dict[Any, tuple[str, bool]] = {}  # the endpoints recorded right now
        self._declare_parameters()
        self._start_srv = node.create_service(Trigger, "~/start_recording", self._on_start)
        self._stop_srv = node.create_service(Trigger, "~/stop_recording", self._on_stop)
        self._timer = node.create_timer(discovery_period_s, self._discover)
        self._ticks = 0
        self._parameters_changed = False
        node.add_post_set_parameters_callback(self._on_parameters_set)
        if autostart:
            self.start_if_enabled()

    def _declare_parameters(self) -> None:
        T = ParameterType

        def declare(name: str, default: Any, ptype: int, description: str, **kw: Any) -> None:
            self.node.declare_parameter(name, default, parameter_descriptor(name, ptype, description, **kw))

        declare("record.enabled", False, T.PARAMETER_BOOL,
                "Start recording at startup (services ~/start_recording, ~/stop_recording toggle it).")
        declare("record.directory", "bags", T.PARAMETER_STRING,
                "Parent directory; each recording gets a new timestamped sub-directory.")
        declare("record.topics", DEFAULT_TOPICS, T.PARAMETER_STRING_ARRAY,
                "Topics to record; relative and ~/ names resolve against this node.")
        declare("record.compression", "zstd", T.PARAMETER_STRING, "MCAP chunk compression: zstd | lz4 | none.",
                constraints="one of: zstd, lz4, none")
        declare("record.max_bag_size_mb", 0.0, T.PARAMETER_DOUBLE,
                "Split into a new file beyond this size in MB (10^6 bytes); 0 = off.", low=0.0, high=1e9)
        declare("record.max_bag_duration_s", 0.0, T.PARAMETER_DOUBLE,
                "Split into a new file after this many seconds of log time; 0 = off.", low=0.0, high=1e9)

    def start_if_enabled(self) -> None:
        """Start recording when ``record.enabled`` is set (an owner that registers its own
        endpoints with :meth:`add_publisher` first passes ``autostart=False`` and calls this)."""
        if self.node.get_parameter("record.enabled").value:
            ok, msg = self.start()
            if not ok:
                self.node.get_logger().error(f"recording not started: {msg}")

    # ------------------------------------------------------------------ public API
    @property
    def recording(self) -> bool:
        return self._recorder is not None

    @property
    def recorder(self) -> Recorder | None:
        return self._recorder

    def add_publisher(self, publisher: Any) -> None:
        """Record this node's own publisher (or subscription) directly instead of subscribing to
        it: the node hands the serialized bytes it publishes or takes to :meth:`record`. Saves one
        subscription callback per message (the dominant recording cost in rclpy) and records
        exactly what the node saw and said.

        A subscription sees every publisher of its topic, so recording what it takes is the
        whole topic. A publisher is the whole topic only under the node's private namespace
        (``~/`` names): on a shared topic such as ``/diagnostics`` other nodes publish too, so
        such a publisher is left to a raw subscription like any input (which also receives the
        node's own samples, each exactly once) and :meth:`records` is False for it."""
        if isinstance(publisher, Publisher) and not self.is_private(publisher.topic_name):
            return  # a shared topic: _discover subscribes to it
        cls = publisher.msg_type
        type_name = f"{cls.__module__.split('.')[0]}/msg/{cls.__name__}"
        self._endpoints[publisher] = (publisher.topic_name, has_header_first(type_name))
        q = publisher.qos_profile
        self._outgoing[publisher.topic_name] = TopicInfo(publisher.topic_name, type_name, (
            qos_profile_dict(reliability=_RELIABILITY.get(q.reliability, "unknown"),
                             durability=_DURABILITY.get(q.durability, "unknown"),
                             history=_HISTORY.get(q.history, "unknown"), depth=q.depth,
                             liveliness=_LIVELINESS.get(q.liveliness, "unknown")),))
        if self._recorder is not None and publisher.topic_name in self._topics:
            self._recorder.add_topic(self._outgoing[publisher.topic_name])
            self._direct = self._direct | {publisher.topic_name}
        self._update_live()

    def is_private(self, topic: str) -> bool:
        """Whether a resolved topic name lies under this node's private namespace (``~/``),
        where only this node publishes."""
        return topic.startswith(self.node.get_fully_qualified_name().rstrip("/") + "/")

    def records(self, publisher: Any) -> bool:
        """Whether bytes published on ``publisher`` are being recorded right now."""
        return publisher in self._live

    def record(self, publisher: Any, data: bytes, now_ns: int | None = None) -> None:
        """Record serialized bytes this node just published (or took) on ``publisher`` (see
        :meth:`add_publisher`); a no-op when not recording or the topic is not recorded.
        ``now_ns``: the log time if the caller already read the node's clock (else read here)."""
        # Runs up to 3 times per joint state on the node's hot thread: the header stamp is read
        # on the recorder's thread (HEADER_STAMP), the clock inline (see now_ns).
        entry = self._live.get(publisher)
        rec = self._recorder
        if entry is None or rec is None:
            return
        if now_ns is None:
            if self._ros_clock and not self._clock_handle.get_ros_time_override_is_enabled():
                now_ns = time.time_ns()
            else:
                now_ns = self.now_ns()
        rec.write(entry[0], data, now_ns, HEADER_STAMP if entry[1] else None)

    def now_ns(self) -> int:
        """The node's clock (ROS time) in ns. Without a /clock override ROS time is the system
        time, read here with ``time.time_ns``: rclpy's clock handle costs far more and this is
        paid per recorded output."""
        h = self._clock_handle
        # No ``with h``: the node keeps its clock (and handle) for its whole life, and the
        # bridge stops recording before the node is destroyed.
        if self._ros_clock and not h.get_ros_time_override_is_enabled():
            return time.time_ns()
        with h:
            return h.get_now().nanoseconds

    def _update_live(self) -> None:
        """Endpoints recorded from the node's own calls right now (read without a lock by
        :meth:`record`: the dict is replaced, never mutated)."""
        direct = self._direct if self._recorder is not None else set()
        self._live = {ep: entry for ep, entry in self._endpoints.items() if entry[0] in direct}

    def set_robot_description(self, urdf: str) -> None:
        """Description to embed in every file (repeated on /robot_description + metadata)."""
        self._description = urdf
        if self._recorder is not None:
            self._recorder.set_robot_description(urdf)

    def start(self) -> tuple[bool, str]:
        """Start a new recording; returns (success, bag path or error text)."""
        if self._recorder is not None:
            return True, str(self._recorder.path)
        p = self.node.get_parameter
        try:
            config = RecorderConfig(
                directory=str(p("record.directory").value),
                compression=str(p("record.compression").value),
                max_bag_size_mb=float(p("record.max_bag_size_mb").value),
                max_bag_duration_s=float(p("record.max_bag_duration_s").value),
                flush_period_s=self._flush_period_s,
                description_topic=self.node.resolve_topic_name("robot_description"))
            rec = Recorder(config, robot_description=self._current_description(),
                           parameters_yaml=self.parameters_yaml(),
                           effective_log_time_ns=self._since(), limits_yaml=self._limits(),
                           opener=self._opener, on_state=self._on_state)
        except (RecordingError, OSError) as exc:
            return False, str(exc)
        topics = self._resolved_topics()
        direct = {t for t in topics if t in self._outgoing}
        for t in direct:
            rec.add_topic(self._outgoing[t])
        with self.guard:  # between two messages of the owner's recording thread
            self._topics, self._direct, self._recorder = topics, direct, rec
            self._update_live()
            if self.on_start is not None:
                self.on_start()
        self._discover()
        self.node.get_logger().info(f"recording to {self._recorder.path}")
        return True, str(self._recorder.path)

    def stop(self) -> tuple[bool, str]:
        """Stop and close the current recording; returns (success, bag path or reason)."""
        rec = self._recorder
        if rec is None:
            return False, "not recording"
        for sub in self._subs.values():
            self.node.destroy_subscription(sub)
        self._subs.clear()
        with self.guard:  # no message of the owner's recording thread is half recorded
            self._direct = set()
            self._recorder = None
            self._update_live()
        self._last_stats = rec.close()
        return self._last_stats.state != "error", str(rec.path)

    def close(self) -> None:
        """Clean close (node shutdown, SIGINT/SIGTERM): summaries and metadata.yaml written."""
        if self._recorder is not None:
            self.stop()

    def status(self) -> Status:
        """``dyn_node: recorder``: OK, WARN on any drop, ERROR when writing failed."""
        rec = self._recorder
        stats = rec.stats() if rec is not None else self._last_stats
        if stats is None:
            return Status(STATUS_NAME, OK, "not recording", values={"recording": False})
        values: dict[str, Any] = {"recording": rec is not None, "bag": stats.path,
                                  "state": stats.state, "files": len(stats.files),
                                  "queued": stats.queued}
        for topic, c in sorted(stats.topics.items()):
            values[f"{topic} received"] = c.received
            values[f"{topic} written"] = c.written
            values[f"{topic} dropped"] = c.dropped
        values["dropped_messages"] = stats.dropped
        if stats.state == "error":
            values["failure_label"] = EVALUATION_ERROR
            return Status(STATUS_NAME, ERROR, f"recording failed: {stats.error}; "
                          f"{stats.dropped} messages dropped", values=values)
        if stats.dropped:
            values["failure_label"] = EVALUATION_ERROR
            return Status(STATUS_NAME, WARN, f"{stats.dropped} messages dropped (writer queue "
                          "full)", values=values)
        return Status(STATUS_NAME, OK, "recording" if rec is not None else "stopped",
                      values=values)

    def parameters_yaml(self) -> str:
        """All declared parameters of the node, as a --params-file YAML document."""
        params = self.node.get_parameters_by_prefix("")
        tree: dict[str, Any] = {}
        for name in sorted(params):
            value = params[name].value
            if isinstance(value, (list, tuple)) or hasattr(value, "tolist"):
                value = list(value.tolist() if hasattr(value, "tolist") else value)
            node = tree
            parts = name.split(".")
            for part in parts[:-1]:
                nxt = node.setdefault(part, {})
                if not isinstance(nxt, dict):  # "a" and "a.b" both set: keep the dotted name
                    node = None
                    break
                node = nxt
            if node is None:
                tree[name] = value
            else:
                node[parts[-1]] = value
        return yaml.safe_dump({self.node.get_fully_qualified_name(): {"ros__parameters": tree}},
                              sort_keys=False)

    # ------------------------------------------------------------------ internals
    def _current_description(self) -> str:
        if self._description_fn is not None:
            try:
                text = self._description_fn() or ""
            except Exception:  # noqa: BLE001 - a failing getter must not stop recording
                text = ""
            if text:
                return text
        if self._description:
            return self._description
        if self.node.has_parameter("robot_description"):
            v = self.node.get_parameter("robot_description").value
            if isinstance(v, str):
                return v
        return ""

    def _resolved_topics(self) -> list[str]:
        out = []
        for t in self.node.get_parameter("record.topics").value or []:
            try:
                name = self.node.resolve_topic_name(str(t))
            except Exception:  # noqa: BLE001 - invalid names are logged and skipped
                self.node.get_logger().warning(f"record.topics: invalid topic name {t!r}")
                continue
            if name not in out:
                out.append(name)
        return out

    def _discover(self) -> None:
        rec = self._recorder
        if rec is None:
            return
        desc = self._current_description()
        if desc:
            rec.set_robot_description(desc)
        # Dumping every parameter to YAML is too slow for every tick: done after a parameter was
        # set, and every _PARAMETERS_REFRESH ticks for parameters declared later (written only
        # when changed).
        self._ticks += 1
        if self._parameters_changed or self._ticks % self._PARAMETERS_REFRESH == 0:
            self._parameters_changed = False
            self._snapshot(rec)
        missing = [t for t in self._topics if t not in self._subs and t not in self._direct]
        if not missing:
            return
        types = dict(self.node.get_topic_names_and_types())
        for topic in missing:
            if not types.get(topic):
                continue
            msg_type = types[topic][0]
            pubs = self.node.get_publishers_info_by_topic(topic)
            if not pubs:
                continue
            try:
                cls = _import_type(msg_type)
            except (ImportError, AttributeError, ValueError):
                if topic not in self._unknown:
                    self._unknown.add(topic)
                    self.node.get_logger().warning(
                        f"cannot record {topic}: message type {msg_type} is not installed")
                continue
            reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs)
            latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                          for p in pubs)
            qos = QoSProfile(
                depth=SUBSCRIBER_DEPTH, history=HistoryPolicy.KEEP_LAST,
                reliability=(ReliabilityPolicy.RELIABLE if reliable
                             else ReliabilityPolicy.BEST_EFFORT),
                durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                            else DurabilityPolicy.VOLATILE))
            offered = tuple(qos_profile_dict(
                reliability=_RELIABILITY.get(p.qos_profile.reliability, "unknown"),
                durability=_DURABILITY.get(p.qos_profile.durability, "unknown"),
                history=_HISTORY.get(p.qos_profile.history, "unknown"),
                depth=p.qos_profile.depth,
                liveliness=_LIVELINESS.get(p.qos_profile.liveliness, "unknown")) for p in pubs)
            rec.add_topic(TopicInfo(topic, msg_type, offered))
            self._subs[topic] = self.node.create_subscription(
                cls, topic, self._callback(rec, topic, has_header_first(msg_type)), qos, raw=True)

    def _since(self) -> int | None:
        return self._configuration_since() if self._configuration_since is not None else None

    def _limits(self) -> str | None:
        return self._limits_fn() if self._limits_fn is not None else None

    def _snapshot(self, rec: Recorder) -> None:
        rec.set_parameters_yaml(self.parameters_yaml(), effective_log_time_ns=self._since(),
                                limits_yaml=self._limits())

    def _on_parameters_set(self, _parameters: list) -> None:
        # Snapshot now, not at the next discovery tick: two changes within one tick would
        # otherwise leave the first configuration unrecorded, and the audit could not replay it.
        rec = self._recorder
        if rec is not None and self._configuration_since is not None:
            self._snapshot(rec)
        else:
            self._parameters_changed = True

    def _callback(self, rec: Recorder, topic: str, stamped: bool) -> Callable[[bytes], None]:
        clock = self._clock_handle

        pub = HEADER_STAMP if stamped else None

        def on_message(data: bytes) -> None:
            with clock:
                now = clock.get_now().nanoseconds
            rec.write(topic, data, now, pub)
        return on_message

    def _on_state(self, stats: RecorderStats) -> None:
        # Runs on the writer thread the moment writing fails (the logger is thread-safe), so
        # the failure is visible before the next /diagnostics period.
        if stats.state == "error":
            self.node.get_logger().error(f"recording to {stats.path} failed: {stats.error}; "
                                         "further messages are dropped (counted)")

    def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = self.start()
        return response

    def _on_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = self.stop()
        return response


def _import_type(type_name: str):
    """'pkg/msg/Type' -> the generated Python class."""
    import importlib
    pkg, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


__all__ = ["RecordingBridge", "DEFAULT_TOPICS", "STATUS_NAME", "COMPRESSIONS"]
