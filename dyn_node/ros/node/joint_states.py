"""The joint_states thread: a helper node holding only that subscription and the controller-status
timer, waited on by a minimal wait set; each message is recorded, checked by the monitor and
answered (~/inverse_dynamics, ~/gravity_torque, the contact observer's outputs)."""
from __future__ import annotations

import threading
import time
from typing import Any, TYPE_CHECKING

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
from sensor_msgs.msg import JointState

from dyn_node.core.contacts.contact_monitor import RESET_RECORDING, Observed
from dyn_node.errors import InputError
from dyn_node.ros.convert import parse_joint_state_cdr, s_to_stamp, status_to_msg

if TYPE_CHECKING:  # annotations only: the package's __init__ composes these parts
    from dyn_node.ros.node.model import NodeCore


JOINT_STATES_QOS_RELIABILITY = ReliabilityPolicy.BEST_EFFORT  # matches reliable and best-effort publishers
_DRAIN = 256  # most queued joint_states handled per executor wake-up


class JointStatesIO:
    """DynNode's joint_states part (a mixin: DynNode composes it)."""

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
        return info

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

    def _contact_observe(self, core: NodeCore, r: Any, sec: int, nsec: int, stamp_ns: int,
                         receipt_ns: int) -> Observed:
        """The observer on the message whose ~/inverse_dynamics just went out, and
        ~/external_torque when there is an estimate (none is ever published from bad input);
        the wrench and the episodes follow in :meth:`_contact_finish`, off this output's latency."""
        observed = core.contact.observe(receipt_ns, stamp_ns, *core.monitor.last_inputs)
        tau = observed.estimate.tau_ext
        if tau is not None:
            self._publish(self._pub_external_torque, core.out_external.encode(sec, nsec, r.q, r.v, tau))
        return observed

    def _contact_finish(self, core: NodeCore, observed: Observed, sec: int, nsec: int) -> None:
        """~/external_wrench (none while the frame is singular), the controller's contact state
        and ~/observer_events on a reset."""
        contact = core.contact
        cs = contact.finish(observed)
        core.tracker.note_contact(cs.state, contact.detector.episode)
        if cs.reset is not None:
            self._publish_events(core)
        if cs.wrench is not None:
            self._publish(self._pub_external_wrench, core.out_wrench.encode(sec, nsec, cs.wrench.wrench))

    def _publish_events(self, core: NodeCore) -> None:
        for ev in core.contact.pop_events():
            self._publish(self._pub_observer_events, status_to_msg(ev.status(core.model.name)))

    def _on_recording_start(self) -> None:
        """Under the io lock, before the new bag's first message (RecordingBridge.on_start)."""
        core = self._core
        if core is not None:
            core.contact.reset(RESET_RECORDING, "recording started")


def _run_coroutine(coro: Any) -> None:
    """Run a coroutine that never suspends (rclpy's QoS event handlers with plain callbacks)."""
    try:
        coro.send(None)
    except StopIteration:
        pass
    else:  # pragma: no cover - a handler that awaits something: not ours to drive
        coro.close()
