"""The dyn_node ROS 2 node: a thin adapter around :mod:`dyn_node.core.live.monitor` and the feasibility check.

Run it with ``ros2 run dyn_node dyn_node`` or ``python -m dyn_node.ros.node``; parameters, topics and
diagnostics are listed in docs/node.md. Everything numeric happens in the pure core; this module only
converts messages, owns timers, publishers and parameters, and swaps immutable pieces atomically.

Threads: joint_states are taken on a thread of their own (a hidden helper node ``_dyn_node_io``
holding only that subscription and the controller-status timer, waited on by a minimal wait
set: rclpy's executor would rebuild its wait set over all ~30 entities of this node on every
wake-up); the diagnostics timer, services, parameters and the other subscriptions run on the
executor that spins this node. A callback never sees a
half-applied model or settings: a new model is built aside and one reference, ``self._core``, is
replaced, and each message reads it once. ``_io_lock`` serialises each message's work with the
timers and the workers that read or feed the same monitor, tracker and recorder. Trajectory
feasibility runs on a worker thread with its own :class:`~dyn_node.core.robot.dynamics.Dynamics` so
joint_states keep flowing while a long trajectory is checked. Both outputs are published as CDR
bytes laid out once per model (:meth:`~dyn_node.ros.convert.JointStateOut.encode`) and the input
is read from its CDR bytes (:func:`~dyn_node.ros.convert.parse_joint_state_cdr`, rclpy's
deserialisation as the fallback), so the recorder gets exactly the bytes taken and sent.
"""
from __future__ import annotations

import math
import queue
import struct
import sys
import threading
import time
import traceback
from dataclasses import dataclass, replace
from typing import Any, Callable, NoReturn

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from diagnostic_msgs.srv import SelfTest
from geometry_msgs.msg import WrenchStamped
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectory

# at start, not at the first trajectory: loading the compiled kernels holds the GIL for about
# 0.7 s, which then stalled joint_states handling by up to 170 ms (seen in make demo)
from dyn_node.core.check import feasibility, on_demand
from dyn_node.core.live.allocator import retain_freed_memory
from dyn_node.core.contacts.contact_monitor import (RESET_MODEL, RESET_PARAMETERS, RESET_RECORDING, ContactMonitor,
                                                    Observed, contact_settings)
from dyn_node.core.live.drops import DropCounter
from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.errors import DynNodeError, InputError, STATE_ERROR, SettingsError, TrajectoryError
from dyn_node.core.robot.model import RobotModel
from dyn_node.core.robot.model_source import build_model, limits_text
from dyn_node.core.robot.model_status import model_error_status, model_status, waiting_model_status
from dyn_node.core.live.monitor import JOINT_STATES, Monitor
from dyn_node.core.live.monitor_results import Counts
from dyn_node.ros.main import end_process, spin_until_signalled
from dyn_node.ros.convert import (JointStateOut, RawTrajectory, WrenchStampedOut, diagnostic_array,
                          encode_joint_trajectory_cdr,
                          fill_trajectory_effort, parse_joint_state_cdr, parse_joint_trajectory_cdr,
                          s_to_stamp, status_to_msg, stamp_to_s, to_byte, trajectory_arrays,
                          verdict_array)
from dyn_node.ros.params import KINDS, parameter_descriptor
from dyn_node.ros.qos import LATCHED_HISTORY
from dyn_node.ros.startup_log import FirstStateAnnouncer, model_ready_line
from dyn_node.ros.services import QuestionServices
from dyn_node.core.robot.selftest import run_self_test
from dyn_node.core.robot.settings import MODEL_PARAMETERS, PARAMETERS, SPECS, ParamSpec, Settings, settings_from_mapping
from dyn_node.core.robot.status import STALE, Status
from dyn_node.core.live.tracker import ControllerTracker
from dyn_node.core.check.trajectory import validate_trajectory

JOINT_STATES_QOS_RELIABILITY = ReliabilityPolicy.BEST_EFFORT  # matches reliable and best-effort publishers
_DRAIN = 256  # most queued joint_states handled per executor wake-up
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)
# ~/feasibility keeps the last 10: with depth 1 a burst of answers (a full request queue's
# 'rejected: busy', several clients' requests) overwrote verdicts a reader had not acknowledged yet
FEASIBILITY_QOS = LATCHED_HISTORY


def _descriptor(spec: ParamSpec) -> ParameterDescriptor:
    start_only = spec.name == "qos_depth"
    return parameter_descriptor(spec.name, KINDS[spec.kind], spec.description, low=spec.low,
                                high=spec.high, read_only=start_only,
                                constraints="read at start-up only" if start_only else "")


@dataclass(frozen=True)
class _Core:
    """Everything the joint_states path needs, replaced as one reference."""

    model: RobotModel
    settings: Settings
    monitor: Monitor
    tracker: ControllerTracker
    out_gravity: JointStateOut
    out_inverse: JointStateOut
    contact: ContactMonitor
    out_external: JointStateOut
    out_wrench: WrenchStampedOut


class DynNode(Node):
    """The live node. Construct in-process with ``DynNode(context=ctx, parameter_overrides=[...])``.

    ``status_providers`` are extra callables returning a :class:`Status` appended to every
    /diagnostics array (e.g. the recording bridge's status).
    """

    def __init__(self, node_name: str = "dyn_node", **kwargs: Any):
        super().__init__(node_name, **kwargs)
        self.status_providers: list[Callable[[], Status]] = []
        for spec in PARAMETERS:
            self.declare_parameter(spec.name, spec.default, _descriptor(spec))
        self._init_state()
        values = {spec.name: self.get_parameter(spec.name).value for spec in PARAMETERS}
        # An unusable value at start-up raises SettingsError: better no node than a misconfigured one.
        self.settings = settings_from_mapping(values)
        if self.settings.has_model_source:
            try:
                self._core = self._make_core(self.settings, build_model(self.settings))
            except DynNodeError as exc:
                self.get_logger().error(f"cannot load the robot model: {exc}")
                self._model_problem = model_error_status(exc, self.get_name(), None)
        self._description_sub = None
        self._ensure_description_subscription()
        self._create_publishers()
        self._create_joint_states_io()
        self._create_inputs_and_timers()
        self._start_workers()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        # the FollowJointTrajectory gate, when configured: its parameters declared before the
        # recording's first parameter snapshot, so a bag does not see them appear as a change
        from dyn_node.ros.gate import attach_gate, declare_gate_parameters
        gate_params = declare_gate_parameters(self)
        self._start_recording()
        self.gate = attach_gate(self, gate_params)
        if self._core is not None:
            self._announce_model()
        self._io_thread.start()

    def _init_state(self) -> None:
        self._counts = Counts()
        # Assumes one publisher until the subscription's matched event (or, on an rmw without
        # it, the graph checked each diagnostics period) says otherwise, so gaps from the very
        # first burst are counted.
        self._drops = DropCounter()
        self._matched_event = False
        self._topic_urdf = ""
        self._model_problem: Status | None = None
        self._core: _Core | None = None
        # log time (the recorder's clock) from which the current core applies: recorded with
        # each parameter snapshot, so the audit replays each configuration from that moment
        self._core_since_ns = self.get_clock().now().nanoseconds
        self._last_plan: tuple[Any, float] | None = None
        # (model, receipt ns, q, q̇) of the last accepted joint_states: a trajectory whose first
        # point lies ahead starts from it (feasibility.current_state)
        self._last_state: tuple[RobotModel, int, Any, Any] | None = None
        self._first_state = FirstStateAnnouncer(self.get_logger().info)
        self._callback_errors = 0

    def _create_publishers(self) -> None:
        # Output publishers go without rclpy's default QoS-event handlers: every waitable is rebuilt
        # into the executor's wait set on each iteration, and at 1 kHz that overhead is the budget.
        # Subscriptions keep theirs, so an incompatible publisher is still reported.
        quiet = {"event_callbacks": PublisherEventCallbacks(use_default_callbacks=False)}
        self._pub_inverse = self.create_publisher(JointState, "~/inverse_dynamics", 10, **quiet)
        self._pub_gravity = self.create_publisher(JointState, "~/gravity_torque", 10, **quiet)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10, **quiet)
        self._pub_controller = self.create_publisher(DiagnosticStatus, "~/controller_status", 10, **quiet)
        self._pub_feasibility = self.create_publisher(DiagnosticArray, "~/feasibility", FEASIBILITY_QOS, **quiet)
        self._pub_traj_effort = self.create_publisher(JointTrajectory, "~/trajectory_effort", 10, **quiet)
        self._pub_external_torque = self.create_publisher(JointState, "~/external_torque", 10, **quiet)
        self._pub_external_wrench = self.create_publisher(WrenchStamped, "~/external_wrench", 10, **quiet)
        # reliable, deep: a replay checks every reset and period boundary, none may be lost
        self._pub_observer_events = self.create_publisher(
            DiagnosticStatus, "~/observer_events",
            QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST),
            **quiet)

    def _create_joint_states_io(self) -> None:
        # joint_states run on a node of their own, spun by their own executor on a dedicated
        # thread: rclpy's executor rebuilds its wait set from every entity of its nodes on each
        # wake-up (here ~30: parameter services, self-test, recording services, timers...), in
        # Python, and at 1 kHz that cost more than the message. The outputs still go out on this
        # node's publishers (~/ names unchanged). _io_lock serialises the per-message work with
        # the timers, services and the feasibility worker that read or feed the same monitor,
        # tracker and recorder.
        qos = QoSProfile(depth=self.settings.qos_depth, reliability=JOINT_STATES_QOS_RELIABILITY,
                         history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.VOLATILE)
        self._io_lock = threading.Lock()
        self._clock_handle = self.get_clock().handle
        self._io_node = Node("_dyn_node_io", context=self.context, namespace=self.get_namespace(),
                             use_global_arguments=False, enable_rosout=False,
                             start_parameter_services=False)
        self._sub_js = self._subscribe_joint_states(qos)
        self._io_stop = threading.Event()
        self._io_wake = self._io_node.create_guard_condition(lambda: None)
        self._io_executor: SingleThreadedExecutor | None = None  # only if the wait set fails
        self._io_thread = threading.Thread(target=self._io_loop, name="dyn_node joint_states", daemon=True)

    def _create_inputs_and_timers(self) -> None:
        s = self.settings
        # raw: the CDR bytes are read on the worker (see ros_convert.parse_joint_trajectory_cdr), so
        # a 100,000-point trajectory never holds the executor thread while rclpy builds its objects
        self._sub_traj = self.create_subscription(JointTrajectory, "joint_trajectory", self._on_trajectory, 10,
                                                  raw=True)
        self._srv_self_test = self.create_service(SelfTest, "~/self_test", self._on_self_test)
        self._diag_timer = self.create_timer(s.diagnostics_period, self._on_diagnostics)
        # ~/controller_status ticks on the joint_states thread's wait set, on this node's clock
        # (sim time included): on the executor each 10 Hz tick cost a full wait-set rebuild
        # holding the GIL for ~0.6 ms, 10 times the tick itself (docs/INTERNALS.md)
        self._ctrl_timer = self._io_node.create_timer(s.controller_status_period, self._on_controller_timer,
                                                      clock=self.get_clock())

    def _start_workers(self) -> None:
        self._jobs: queue.Queue = queue.Queue(maxsize=64)
        self._worker_dyn: dict[tuple[int, int, bool], Dynamics] = {}
        # The worker may still be checking when the node is destroyed (destroy_node waits only
        # briefly for it): it publishes under this lock, and not at all once closed is set.
        self._worker_pub_lock = threading.Lock()
        self._worker_closed = False
        self._worker = threading.Thread(target=self._feasibility_loop, name="dyn_node_feasibility", daemon=True)
        self._worker.start()
        # questions (check, inverse dynamics, retime): services with a worker of their own, apart
        # from joint_trajectory's, so a planner's questions never delay a command's verdict
        self.questions = QuestionServices(self, core=lambda: self._core, start_state=self._start_state_now,
                                          dynamics=self._worker_dynamics, failed=self._callback_failed)

    def _start_recording(self) -> None:
        # Imported here: the bridge declares the record.* parameters and owns the recorder thread.
        from dyn_node.ros.recording import RecordingBridge
        self.recording = RecordingBridge(self, lambda: self.model.urdf if self.model else "",
                                         autostart=False,
                                         configuration_since=lambda: self._core_since_ns,
                                         limits_yaml=lambda: limits_text(self.model))
        self.status_providers.append(self.recording.status)
        # Topics the node itself takes or publishes are recorded from their own callbacks and
        # publish calls, with the bytes the node saw and said (subscriptions' QoS is recorded
        # as the offered profile for inputs).
        for endpoint in (self._sub_js, self._sub_traj,
                         self._pub_inverse, self._pub_gravity,
                         self._pub_diag, self._pub_controller, self._pub_feasibility,
                         self._pub_traj_effort, self._pub_external_torque, self._pub_external_wrench,
                         self._pub_observer_events):
            self.recording.add_publisher(endpoint)
        self.recording.guard = self._io_lock
        self.recording.on_start = self._on_recording_start
        self.recording.start_if_enabled()

    # --- model and settings ----------------------------------------------------------------
    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _make_core(self, settings: Settings, model: RobotModel) -> _Core:
        tracker = ControllerTracker(model, settings)
        monitor = Monitor(model, settings, self._counts)
        try:
            # the Monitor's Dynamics: both run on the joint_states thread, statuses under its lock
            contact = ContactMonitor(monitor.dynamics, contact_settings(settings), history_limit=100)
        except ValueError as exc:  # a gain list of the wrong length, an unknown contact frame
            raise SettingsError(f"contact monitor: {exc}", code="bad_parameter") from exc
        core = _Core(model, settings, monitor, tracker,
                     JointStateOut(model.joint_names), JointStateOut(model.joint_names), contact,
                     JointStateOut(model.joint_names), WrenchStampedOut(contact.frame))
        core.monitor.drop_counting = self._drops.method
        old = self._core
        if old is not None:  # the new observer starts from scratch: said so in the bag
            changed = old.model is not model
            contact.reset(RESET_MODEL if changed else RESET_PARAMETERS,
                          "model changed" if changed else "parameters changed")
        if old is not None and old.model.joint_names == model.joint_names and old.tracker._plan is not None:
            tracker._plan = old.tracker._plan
        return core

    def _swap_core(self, core: _Core | None) -> None:
        """Replace the core between two joint_states (under the io lock, which each message
        holds from its receipt time to its outputs) and note the time: every message logged
        before it used the old core, every one logged at or after it the new one."""
        with self._io_lock:
            self._core = core
            with self._clock_handle:
                self._core_since_ns = self._clock_handle.get_now().nanoseconds

    @property
    def model(self) -> RobotModel | None:
        core = self._core
        return core.model if core else None

    @property
    def hardware_id(self) -> str:
        core = self._core
        return core.model.name if core else self.get_name()

    def _ensure_description_subscription(self) -> None:
        if self._description_sub is None and not self.settings.has_model_source:
            self._description_sub = self.create_subscription(String, "robot_description",
                                                             self._on_description, LATCHED)

    def _on_description(self, msg: String) -> None:
        if self.settings.has_model_source:
            return  # a model parameter takes precedence over the topic
        try:
            model = build_model(self.settings, msg.data)
        except DynNodeError as exc:
            self._model_problem = model_error_status(exc, self.hardware_id, self.model)
            self.get_logger().error(f"robot_description rejected, keeping the current model: {exc}")
            return
        except Exception as exc:  # never raise out of a callback
            self._model_problem = model_error_status(exc, self.hardware_id, self.model)
            self.get_logger().error(f"robot_description could not be used: {exc!r}")
            return
        self._topic_urdf = msg.data
        self._swap_core(self._make_core(self.settings, model))
        self._model_problem = None
        self._announce_model()

    def _announce_model(self) -> None:
        """The start-up line of the model in use (startup_log.model_ready_line)."""
        rec = getattr(self, "recording", None)  # not there yet while the constructor runs
        bag = rec.recorder.path if rec is not None and rec.recorder is not None else None
        self.get_logger().info(model_ready_line(
            self.model, limits_file=self.settings.limits_file, limits_text=limits_text(self.model),
            friction=self.settings.include_friction, recording=str(bag) if bag else "off"))

    def _on_set_parameters(self, params: list) -> SetParametersResult:
        values = {p.name: p.value for p in params if p.name in SPECS}
        if not values:
            return SetParametersResult(successful=True)
        try:
            new = settings_from_mapping(values, base=self.settings)
            core = self._core
            if any(n in MODEL_PARAMETERS for n in values) and new.model_key() != self.settings.model_key():
                if new.has_model_source or self._topic_urdf:
                    core = self._make_core(new, build_model(new, self._topic_urdf))
                else:
                    core = None
            elif core is not None:
                core = self._make_core(new, core.model)
        except DynNodeError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        except Exception as exc:  # anything unexpected still leaves the old settings intact
            return SetParametersResult(successful=False, reason=f"{type(exc).__name__}: {exc}")
        old, old_model = self.settings, self.model
        self.settings = new
        self._swap_core(core)
        if core is not None:
            self._model_problem = None
            if core.model is not old_model:
                self._announce_model()
        self._ensure_description_subscription()
        if new.diagnostics_period != old.diagnostics_period:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = self.create_timer(new.diagnostics_period, self._on_diagnostics)
        if new.controller_status_period != old.controller_status_period:
            # in place (the joint_states thread may be waiting on it), restarted at the new period
            self._ctrl_timer.timer_period_ns = int(round(new.controller_status_period * 1e9))
            self._ctrl_timer.reset()
            self._io_wake.trigger()
        return SetParametersResult(successful=True)

    # --- publishing ------------------------------------------------------------------------
    def _publish(self, pub: Any, msg: Any) -> None:
        """Publish, and when this topic is being recorded hand the recorder the same bytes.

        Recording the node's own outputs from the publish path (instead of subscribing to itself)
        saves a subscription callback per message and makes the bag hold exactly what was said.
        """
        rec = self.recording
        if rec.records(pub):
            data = msg if isinstance(msg, bytes) else serialize_message(msg)
            pub.publish(data)
            rec.record(pub, data)
        else:
            pub.publish(msg)

    def _publish_verdict(self, pub: Any, msg: Any) -> None:
        """:meth:`_publish` from the feasibility worker: dropped once the node is being destroyed
        (its publishers are about to go, and a verdict nobody can receive is no loss)."""
        with self._worker_pub_lock:
            if not self._worker_closed:
                self._publish(pub, msg)

    # --- joint_states (hot path) -----------------------------------------------------------
    def _subscribe_joint_states(self, qos: QoSProfile):
        # Resolved (namespace, remappings) by this node: the io node ignores global arguments,
        # so its name cannot be remapped onto this one's.
        topic = self.resolve_topic_name("joint_states")
        io = self._io_node
        try:
            events = SubscriptionEventCallbacks(message_lost=self._on_message_lost,
                                                matched=self._on_matched)
            return io.create_subscription(JointState, topic, self._on_joint_state, qos,
                                          event_callbacks=events, raw=True)
        except Exception:  # an rmw without the message-lost event: drops cannot be counted
            return io.create_subscription(JointState, topic, self._on_joint_state, qos, raw=True)

    def _io_loop(self) -> None:
        """The joint_states thread: a wait set of just the subscription, its QoS events, the
        controller-status timer and a wake-up guard, rebuilt cheaply each time (what rclpy's
        executor does for every entity of a node, generically and at several times the cost).
        Falls back to an executor."""
        sub, wake, ctx, timer = self._sub_js, self._io_wake, self.context, self._ctrl_timer
        handlers = list(getattr(sub, "event_handlers", ()))
        try:
            n_events = sum(h.get_num_entities().num_events for h in handlers)
            with ctx.handle:
                ws = _rclpy.WaitSet(1, 1, 1, 0, 0, n_events, ctx.handle)
        except Exception:  # an rclpy without this internal API
            self._io_spin_executor()
            return
        failures = 0
        while not self._io_stop.is_set():
            try:
                with ctx.handle, sub.handle, wake.handle, timer.handle:
                    ws.clear_entities()
                    ws.add_subscription(sub.handle)
                    ws.add_guard_condition(wake.handle)
                    ws.add_timer(timer.handle)
                    for h in handlers:
                        h.add_to_wait_set(ws)
                    ws.wait(100_000_000)  # 0.1 s: the stop flag is seen even without a wake-up
                if self._io_stop.is_set():
                    return
                for h in handlers:
                    if h.is_ready(ws):
                        _run_coroutine(h.execute(h.take_data()))
                if ws.get_ready_entities("subscription"):
                    first = self._take_pending()
                    if first is not None:
                        self._on_joint_state(first[0], first[1])
                if ws.get_ready_entities("timer"):
                    with timer.handle:
                        timer.handle.call_timer()
                    self._on_controller_timer()
                failures = 0
            except Exception:  # context shut down under us, or a bug: never a dead thread
                if self._io_stop.is_set() or not ctx.ok():
                    return
                failures += 1
                self._callback_failed("joint_states thread")
                if failures > 3:
                    self._io_stop.wait(0.1)  # do not spin hot on a persistent fault

    def _io_spin_executor(self) -> None:
        ex = self._io_executor = SingleThreadedExecutor(context=self.context)
        ex.add_node(self._io_node)
        while not self._io_stop.is_set():
            try:
                ex.spin_once(timeout_sec=0.1)
            except Exception:  # context shut down under us, or the executor was shut down
                if self._io_stop.is_set() or not self.context.ok():
                    return
                self._callback_failed("joint_states executor")

    def _stop_io(self) -> None:
        """Stop the joint_states thread and destroy its node (idempotent)."""
        self._io_stop.set()
        try:
            self._io_wake.trigger()
        except Exception:  # context already gone: the 0.1 s wait timeout ends the loop
            pass
        ex = self._io_executor
        if ex is not None:
            try:
                ex.wake()
            except Exception:
                pass
        if self._io_thread.is_alive() and self._io_thread is not threading.current_thread():
            self._io_thread.join(timeout=5.0)
        if ex is not None:
            try:
                ex.shutdown(timeout_sec=1.0)
            except Exception:
                pass
        try:
            self._io_node.destroy_node()
        except Exception:
            pass

    def _on_message_lost(self, info: Any) -> None:
        with self._io_lock:
            self._drops.lost(int(info.total_count))
            self._report_dropped()

    def _on_matched(self, info: Any) -> None:
        # The moment the publisher set changes, not up to a diagnostics period later: a gap from a
        # second publisher's samples must never be counted as a drop.
        with self._io_lock:
            self._matched_event = True
            if self._drops.publishers(int(info.current_count), time.time_ns()):
                self._report_dropped()

    def _report_dropped(self) -> None:
        core = self._core
        if core is not None:
            core.monitor.note_dropped(self._drops.total, self._drops.method)

    def _on_joint_state(self, data: bytes, info: dict) -> None:
        # Two required arguments: rclpy binds a callback that accepts one argument as
        # message-only, and then no sequence numbers would ever arrive.
        # Taken raw so the recorder gets exactly the bytes the node processed (the audit's
        # re-check then pairs every output with its input); deserialising costs what rclpy's
        # own take would.
        self._take_joint_state(data, info)
        # Drain what is already queued before returning to the executor: rclpy takes one message
        # per subscription per wait-set rebuild, and that rebuild (all timers, services and
        # handlers of the node) costs more than the message itself. Bounded, so timers still run.
        for _ in range(_DRAIN):
            more = self._take_pending()
            if more is None:
                break
            self._take_joint_state(more[0], more[1])

    def _take_joint_state(self, data: bytes, info: dict | None) -> None:
        with self._io_lock:
            if info and self._drops.sequence(info.get("publication_sequence_number"),
                                             info.get("received_timestamp")):
                self._report_dropped()
            clock = self._clock_handle
            with clock:
                receipt_ns = clock.get_now().nanoseconds  # one clock read: receipt and log time
            self.recording.record(self._sub_js, data, receipt_ns)
            try:
                fields = parse_joint_state_cdr(data)
            except Exception:  # not plain little-endian CDR: rclpy reads it (and judges it)
                try:
                    msg = deserialize_message(data, JointState)
                except Exception:  # not a JointState after all: rejected like any malformed message
                    self._handle_joint_state(InputError(
                        f"{len(data)} bytes that rclpy cannot deserialise as a sensor_msgs/JointState",
                        code="undecodable"), receipt_ns)
                    return
                st = msg.header.stamp
                fields = (st.sec, st.nanosec, msg.name, msg.position, msg.velocity, msg.effort)
            self._handle_joint_state(fields, receipt_ns)

    def _take_pending(self) -> tuple[bytes, dict] | None:
        sub = self._sub_js
        try:
            with sub.handle:
                info = sub.handle.take_message(sub.msg_type, sub.raw)
        except Exception:  # subscription being destroyed: leave it to the executor
            return None
        return info if info is not None else None

    def _handle_joint_state(self, fields: tuple | InputError, receipt_ns: int) -> None:
        """``fields`` = (stamp sec, stamp nanosec, names, position, velocity, effort), or the
        InputError of a message that could not be decoded."""
        core = self._core  # read once: a model swap applies from the next message
        receipt = receipt_ns * 1e-9
        if core is None:
            self._counts.received += 1
            self._counts.before_model += 1
            return
        try:
            if isinstance(fields, InputError):
                r = core.monitor.reject_message(fields, receipt)
            else:
                sec, nsec, names, position, velocity, effort = fields
                stamp_ns = sec * 1_000_000_000 + nsec
                r = core.monitor.process(names, position, velocity, effort, sec + nsec * 1e-9, receipt)
            if r.accepted:
                self._last_state = (core.model, receipt_ns, r.q, r.v)
                self._first_state.accepted(core.model, len(fields[2]), r.stamp_s)
                if r.zero_stamp:
                    st = s_to_stamp(r.stamp_s)
                    sec, nsec = st.sec, st.nanosec
                # Published as CDR bytes laid out here (ros_convert.JointStateOut.encode): rclpy's
                # publish(msg) would convert and serialise each message, and the recorder gets
                # the very bytes that went out.
                self._publish(self._pub_inverse, core.out_inverse.encode(sec, nsec, r.q, r.v, r.tau))
                self._publish(self._pub_gravity, core.out_gravity.encode(sec, nsec, r.q, r.v, r.gravity))
                observed = self._contact_observe(core, r, sec, nsec, stamp_ns, receipt_ns)
                self._contact_finish(core, observed, sec, nsec)
            else:
                self.get_logger().warn(f"joint_states rejected: {r.error}", throttle_duration_sec=5.0)
            if core.tracker.update(r, receipt):
                self._publish_controller_status(core.tracker.status(receipt, core.model.name))
        except Exception:  # a bug must not kill the executor; it is counted and logged
            self._callback_failed("joint_states callback")

    def _contact_observe(self, core: _Core, r: Any, sec: int, nsec: int, stamp_ns: int,
                         receipt_ns: int) -> Observed:
        """The observer on the message whose ~/inverse_dynamics just went out, and
        ~/external_torque when there is an estimate (none is ever published from bad input);
        the wrench and the episodes follow in :meth:`_contact_finish`, off this output's latency."""
        observed = core.contact.observe(receipt_ns, stamp_ns, *core.monitor.last_inputs)
        tau = observed.estimate.tau_ext
        if tau is not None:
            self._publish(self._pub_external_torque, core.out_external.encode(sec, nsec, r.q, r.v, tau))
        return observed

    def _contact_finish(self, core: _Core, observed: Observed, sec: int, nsec: int) -> None:
        """~/external_wrench (none while the frame is singular), the controller's contact state
        and ~/observer_events on a reset."""
        contact = core.contact
        cs = contact.finish(observed)
        core.tracker.note_contact(cs.state, contact.detector.episode)
        if cs.reset is not None:
            self._publish_events(core)
        if cs.wrench is not None:
            self._publish(self._pub_external_wrench, core.out_wrench.encode(sec, nsec, cs.wrench.wrench))

    def _publish_events(self, core: _Core) -> None:
        for ev in core.contact.pop_events():
            self._publish(self._pub_observer_events, status_to_msg(ev.status(core.model.name)))

    def _on_recording_start(self) -> None:
        """Under the io lock, before the new bag's first message (RecordingBridge.on_start)."""
        core = self._core
        if core is not None:
            core.contact.reset(RESET_RECORDING, "recording started")

    # --- periodic outputs ----------------------------------------------------------------
    def current_statuses(self, now_s: float | None = None, *, now_ns: int | None = None) -> list[Status]:
        """The statuses of one /diagnostics array (resets the monitor's worst-case window);
        ``now_ns``: the same instant exactly (the array's stamp), for the contact statuses."""
        if now_ns is not None:
            now_s = now_ns * 1e-9
        now = self._now_s() if now_s is None else now_s
        core = self._core
        hid = self.hardware_id
        if self._model_problem is not None:
            out = [self._model_problem]
        elif core is None:
            out = [waiting_model_status(hid)]
        else:
            out = [model_status(core.model, hid)]
        if core is not None:
            if now_ns is None:
                now_ns = int(round(now * 1e9))
            # under the joint_states lock only what the next message changes; the window's fold,
            # the frame kernel and the text are written after it, while messages flow
            with self._io_lock:
                window = core.monitor.close_window(now, hid)
                contact = core.contact.contact_status(now_ns, hid)
                energy = core.contact.close_energy_period(now_ns)
                self._publish_events(core)  # the period just closed
            out += window.statuses()
            out += [contact, energy.status(hid)]
        else:
            out.append(Status(JOINT_STATES, STALE, "no robot model yet: joint_states cannot be used", hid,
                              {"received_messages": self._counts.received,
                               "accepted_messages": self._counts.accepted,
                               "invalid_messages": self._counts.invalid,
                               "before_model_messages": self._counts.before_model,
                               "failure_label": STATE_ERROR}))
        for provider in list(self.status_providers):
            try:
                st = provider()
                out.append(st if st.hardware_id else replace(st, hardware_id=hid))
            except Exception as exc:
                self.get_logger().error(f"status provider {provider!r} failed: {exc!r}",
                                        throttle_duration_sec=10.0)
        return out

    def _on_diagnostics(self) -> None:
        try:
            if not self._matched_event:
                with self._io_lock:
                    if self._drops.publishers(self.count_publishers(self._sub_js.topic_name),
                                              time.time_ns()):
                        self._report_dropped()
            now = self.get_clock().now()
            self._publish(self._pub_diag, diagnostic_array(self.current_statuses(now_ns=now.nanoseconds),
                                                    now.to_msg()))
        except Exception:
            self._callback_failed("diagnostics")

    def _publish_controller_status(self, status: Status) -> None:
        # only ever on the joint_states thread (state changes and the timer in its wait set),
        # so the statuses go out in the order they were made
        self._publish(self._pub_controller, status_to_msg(status))

    def _on_controller_timer(self) -> None:
        core = self._core
        if core is None:
            return
        try:
            with self._io_lock:  # the message conversion and publish after it, outside the lock
                now = self._now_s()
                core.tracker.tick(now)
                status = core.tracker.status(now, core.model.name)
            self._publish_controller_status(status)
        except Exception:
            self._callback_failed("controller status")

    def _callback_failed(self, what: str) -> None:
        """Count and log an exception caught in a callback. During shutdown (SIGINT/SIGTERM
        invalidate the context while a callback may be publishing) it is expected and silent."""
        if not self.context.ok():
            return
        self._callback_errors += 1
        self.get_logger().error(f"{what} failed:\n{traceback.format_exc()}", throttle_duration_sec=5.0)

    # --- self-test -----------------------------------------------------------------------
    def _on_self_test(self, request: SelfTest.Request, response: SelfTest.Response) -> SelfTest.Response:
        core = self._core
        if core is None:
            response.passed = to_byte(False)
            response.id = self.get_name()
            response.status = [status_to_msg(self.current_statuses()[0])]
            return response
        try:
            passed, statuses = run_self_test(core.model, core.settings.include_friction,
                                             hardware_id=core.model.name)
        except Exception as exc:
            passed, statuses = False, [model_error_status(exc, core.model.name, core.model)]
        response.passed = to_byte(passed)  # rclpy sends a bool in a byte field as a garbage byte
        response.id = f"{core.model.name} {core.model.urdf_hash[:12]}"
        response.status = [status_to_msg(s) for s in statuses]
        return response

    # --- trajectories --------------------------------------------------------------------
    def _record_with_state(self, sub: Any, data: bytes) -> tuple[int, _Core | None,
                                                                 feasibility.StartState | None]:
        """Record a trajectory taken on ``sub`` and return (receipt ns, core, the robot's state
        it starts from). Under the joint_states lock, with one clock read for the receipt and
        the log time: the state is the last joint_states recorded before it, as the audit
        replays it, and the core the one of that log time."""
        clock = self._clock_handle
        with self._io_lock:
            with clock:
                receipt_ns = clock.get_now().nanoseconds
            self.recording.record(sub, data, receipt_ns)
            last, core = self._last_state, self._core
        state = None
        if core is not None and last is not None and last[0].joint_names == core.model.joint_names:
            state = feasibility.current_state(last[1:], receipt_ns, core.settings.stale_timeout)
        return receipt_ns, core, state

    def execution_state(self) -> tuple[_Core | None, feasibility.StartState | None]:
        """(core, the robot's state now) to check a goal from, as _record_with_state does."""
        clock = self._clock_handle
        with self._io_lock:
            with clock:
                now_ns = clock.get_now().nanoseconds
            last, core = self._last_state, self._core
        if core is None or last is None or last[0].joint_names != core.model.joint_names:
            return core, None
        return core, feasibility.current_state(last[1:], now_ns, core.settings.stale_timeout)

    def _on_trajectory(self, msg: bytes) -> None:
        receipt_ns, core, state = self._record_with_state(self._sub_traj, msg)
        receipt = receipt_ns * 1e-9
        if core is None:
            self.get_logger().warn("joint_trajectory ignored: no robot model yet", throttle_duration_sec=5.0)
            return
        try:
            self._jobs.put_nowait((msg, receipt, core, on_demand.REQUEST_EXECUTE, state))
        except queue.Full:
            self.get_logger().error("feasibility checker busy: trajectory not checked", throttle_duration_sec=5.0)

    def _feasibility_loop(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                self._check_trajectory(*job)
            except Exception:
                self._callback_failed("trajectory check")

    def _worker_dynamics(self, core: _Core) -> Dynamics:
        # one instance per worker thread: a Dynamics holds Pinocchio's scratch data
        key = (threading.get_ident(), id(core.model), core.settings.include_friction)
        dyn = self._worker_dyn.get(key)
        if dyn is None or dyn.model is not core.model:
            self._worker_dyn.clear()  # one model at a time: drop instances of replaced models
            dyn = Dynamics(core.model, DynamicsOptions(include_friction=core.settings.include_friction))
            self._worker_dyn[key] = dyn
        return dyn

    def _check_trajectory(self, data: bytes, receipt_s: float, core: _Core,
                          request: str = on_demand.REQUEST_EXECUTE,
                          start_state: feasibility.StartState | None = None) -> None:
        """Validate, hand to the controller tracker (``request`` "execute" only: a "check" is
        never tracked), check feasibility and publish the verdict with the request's header."""
        model, settings = core.model, core.settings
        msg: JointTrajectory | None = None
        raw: RawTrajectory | None = None
        try:
            raw = parse_joint_trajectory_cdr(data)
            names, times, (P, V, A, E) = raw.names, raw.times, raw.fields
            stamp, frame_id = raw.stamp, raw.frame_id.decode(errors="replace")
        except (ValueError, IndexError, struct.error, UnicodeDecodeError):
            msg = deserialize_message(data, JointTrajectory)  # big-endian or unexpected: rclpy's way
            names, times, P, V, A = trajectory_arrays(msg)
            E = [p.effort for p in msg.points]
            stamp, frame_id = msg.header.stamp, msg.header.frame_id
        stamp_s = stamp_to_s(stamp)
        start = stamp_s if stamp_s != 0.0 else receipt_s
        error: TrajectoryError | None = None
        traj = None
        try:
            traj = validate_trajectory(model.joint_names, names, times, P, V, A, min_points=1,
                                       efforts=E)
            current = self._core
            if (request == on_demand.REQUEST_EXECUTE and current is not None
                    and current.model.joint_names == model.joint_names):
                with self._io_lock:
                    current.tracker.set_trajectory(traj, start)
            if traj.n_points < 2:
                validate_trajectory(model.joint_names, names, times, P, V, A, min_points=2)
        except TrajectoryError as exc:
            error = exc
        hid = model.name
        duration = float(times[-1]) if times and all(map(math.isfinite, times)) else 0.0
        if error is not None:
            statuses = feasibility.rejected_statuses(error, hid, len(times), duration)
        else:
            options = feasibility.FeasibilityOptions(sample_period=settings.sample_period,
                                                     effort_warn_ratio=settings.effort_warn_ratio)
            try:
                result = feasibility.check_trajectory(self._worker_dynamics(core), traj, options,
                                                      start=start_state,
                                                      start_unknown=feasibility.NO_CURRENT_STATE)
            except TrajectoryError as exc:  # e.g. motion so large the torques overflow
                self._publish_verdict(self._pub_feasibility, verdict_array(
                    feasibility.rejected_statuses(exc, hid, len(times), duration), stamp, frame_id,
                    request))
                return
            statuses = result.statuses(hid)
            if raw is not None:
                order = [model.joint_names.index(n) for n in names]
                self._publish_verdict(self._pub_traj_effort, encode_joint_trajectory_cdr(raw, result.waypoint_effort[:, order]))
            else:
                self._publish_verdict(self._pub_traj_effort, fill_trajectory_effort(msg, result.waypoint_effort,
                                                                     model.joint_names))
        self._publish_verdict(self._pub_feasibility, verdict_array(statuses, stamp, frame_id, request))

    def _start_state_now(self, core: _Core) -> feasibility.StartState | None:
        """The robot's state a question received now starts from (None: none within stale_timeout)."""
        clock = self._clock_handle
        with self._io_lock:
            with clock:
                now_ns = clock.get_now().nanoseconds
            last = self._last_state
        if last is None or last[0].joint_names != core.model.joint_names:
            return None
        return feasibility.current_state(last[1:], now_ns, core.settings.stale_timeout)

    def destroy_node(self) -> None:
        if getattr(self, "gate", None) is not None:
            self.gate.close()  # cancels what it forwarded, before the node's entities go
        if hasattr(self, "_io_thread"):
            self._stop_io()  # no joint_states (nor their recording) after this
        recording = getattr(self, "recording", None)
        if recording is not None:
            recording.close()  # finalise the bag (summary, metadata.yaml) before anything else goes
        self._jobs.queue.clear()
        try:
            self._jobs.put_nowait(None)
        except queue.Full:  # pragma: no cover - cleared just above
            pass
        if self._worker.is_alive() and self._worker is not threading.current_thread():
            self._worker.join(timeout=0.5)  # a check in progress is abandoned (daemon thread)
        self.questions.close()
        with self._worker_pub_lock:
            self._worker_closed = True
        super().destroy_node()


def _run_coroutine(coro: Any) -> None:
    """Run a coroutine that never suspends (rclpy's QoS event handlers with plain callbacks)."""
    try:
        coro.send(None)
    except StopIteration:
        pass
    else:  # pragma: no cover - a handler that awaits something: not ours to drive
        coro.close()


#: how long a thread holding the GIL keeps a thread that waits for it (s; CPython's default is
#: 5 ms): the joint_states thread then waits at most about this long for a timer or service
#: callback running Python on the executor thread (docs/INTERNALS.md)
GIL_SWITCH_INTERVAL_S = 2e-4


def main(args: list[str] | None = None) -> NoReturn:
    """Entry point of ``ros2 run dyn_node dyn_node``: spin until SIGINT/SIGTERM, then clean up
    and exit (without the interpreter's finalization: :func:`dyn_node.ros.main.end_process`).

    The bag is finalised in ``destroy_node`` before the context goes. A parameter that cannot be
    used at start-up (rclpy refuses its type or range, or the settings reject it) ends the process
    with exit code 2 and a one-line error instead of a traceback.
    """
    retain_freed_memory()     # each trajectory check then reuses the last one's pages
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)  # the process's, so here and not in DynNode
    end_process(spin_until_signalled(DynNode, args, "dyn_node", fatal=(
        InvalidParameterValueException, InvalidParameterTypeException, SettingsError)))


if __name__ == "__main__":
    main()
