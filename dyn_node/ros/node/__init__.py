"""The dyn_node ROS 2 node: a thin adapter around :mod:`dyn_node.core.live.monitor` and the feasibility check.

Run it with ``ros2 run dyn_node dyn_node`` or ``python -m dyn_node.ros.node``; parameters, topics and
diagnostics are listed in docs/node.md. Everything numeric happens in the pure core; this package only
converts messages, owns timers, publishers and parameters, and swaps immutable pieces atomically.

Parts (mixins that :class:`DynNode` composes; this module wires them, publishes and shuts down):
``joint_states`` (the I/O thread and the hot path), ``model`` (model and settings, (re)loading),
``trajectories`` (the feasibility worker), ``diagnostics`` (periodic outputs and ~/self_test);
the question services are :mod:`dyn_node.ros.services`, the gate :mod:`dyn_node.ros.gate`, the
recording :mod:`dyn_node.ros.recording`.

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

import gc
import queue
import sys
import threading
import traceback
from typing import Any, Callable, NoReturn

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from diagnostic_msgs.srv import SelfTest
from geometry_msgs.msg import WrenchStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.serialization import serialize_message
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from dyn_node.core.live.allocator import retain_freed_memory
from dyn_node.core.live.drops import DropCounter
from dyn_node.errors import DynNodeError, SettingsError
from dyn_node.core.robot.model import RobotModel
from dyn_node.core.robot.model_source import build_model, limits_text
from dyn_node.core.robot.model_status import model_error_status
from dyn_node.core.live.monitor_results import Counts
from dyn_node.ros.main import end_process, spin_until_signalled
from dyn_node.ros.params import KINDS, parameter_descriptor
from dyn_node.ros.qos import LATCHED_HISTORY
from dyn_node.ros.startup_log import FirstStateAnnouncer
from dyn_node.ros.services import QuestionServices
from dyn_node.core.robot.settings import PARAMETERS, ParamSpec, settings_from_mapping
from dyn_node.core.robot.status import Status
from dyn_node.ros.node.diagnostics import PeriodicOutputs
from dyn_node.ros.node.joint_states import JointStatesIO
from dyn_node.ros.node.model import ModelState, NodeCore
from dyn_node.ros.node.trajectories import TrajectoryWorker


# ~/feasibility keeps the last 10: with depth 1 a burst of answers (a full request queue's
# 'rejected: busy', several clients' requests) overwrote verdicts a reader had not acknowledged yet
FEASIBILITY_QOS = LATCHED_HISTORY


def _descriptor(spec: ParamSpec) -> ParameterDescriptor:
    start_only = spec.name == "qos_depth"
    return parameter_descriptor(spec.name, KINDS[spec.kind], spec.description, low=spec.low,
                                high=spec.high, read_only=start_only,
                                constraints="read at start-up only" if start_only else "")


class DynNode(JointStatesIO, ModelState, PeriodicOutputs, TrajectoryWorker, Node):
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
        self._core: NodeCore | None = None
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
        self._worker_dyn = threading.local()  # each worker thread's Dynamics (_worker_dynamics)
        # The worker may still be checking when the node is destroyed (destroy_node waits only
        # briefly for it): it publishes under this lock, and not at all once closed is set.
        self._worker_pub_lock = threading.Lock()
        self._worker_closed = False
        self._worker = threading.Thread(target=self._feasibility_loop, name="dyn_node_feasibility", daemon=True)
        self._worker.start()
        # questions (check, inverse dynamics, retime): services with a worker per kind, apart
        # from joint_trajectory's, so a planner's questions never delay a command's verdict
        # (computed in a worker process of their own: dyn_node.core.live.question_process)
        self.questions = QuestionServices(self, core=lambda: self._core, start_state=self._start_state_now,
                                          failed=self._callback_failed)

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

    def _callback_failed(self, what: str) -> None:
        """Count and log an exception caught in a callback. During shutdown (SIGINT/SIGTERM
        invalidate the context while a callback may be publishing) it is expected and silent."""
        if not self.context.ok():
            return
        self._callback_errors += 1
        self.get_logger().error(f"{what} failed:\n{traceback.format_exc()}", throttle_duration_sec=5.0)

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


#: how long a thread holding the GIL keeps a thread that waits for it (s; CPython's default is
#: 5 ms): the joint_states thread then waits at most about this long for a timer or service
#: callback running Python on the executor thread (docs/INTERNALS.md)
GIL_SWITCH_INTERVAL_S = 2e-4


#: full (generation 2) garbage collections only after this many generation-1 ones (CPython: 10)
GC_FULL_COLLECTION_THRESHOLD = 1000


def _started_node() -> DynNode:
    """DynNode, with the cyclic garbage collector kept off the joint_states path.

    A full collection holds the GIL while it scans every tracked object: at start ~135,000
    (modules, model, kernels) and, while a large service request is answered, its messages'
    (~7 per point). Collections triggered by a 20,000-point request paused joint_states for
    60-120 ms. What exists at start lives as long as the process: frozen out of the scans. Full
    collections become rare (every ~7 M allocations instead of ~70 k); the young generations,
    a few thousand objects each, still collect reference cycles as before."""
    node = DynNode()
    gc.freeze()
    g0, g1, _ = gc.get_threshold()
    gc.set_threshold(g0, g1, GC_FULL_COLLECTION_THRESHOLD)
    return node


def main(args: list[str] | None = None) -> NoReturn:
    """Entry point of ``ros2 run dyn_node dyn_node``: spin until SIGINT/SIGTERM, then clean up
    and exit (without the interpreter's finalization: :func:`dyn_node.ros.main.end_process`).

    The bag is finalised in ``destroy_node`` before the context goes. A parameter that cannot be
    used at start-up (rclpy refuses its type or range, or the settings reject it) ends the process
    with exit code 2 and a one-line error instead of a traceback.
    """
    retain_freed_memory()     # each trajectory check then reuses the last one's pages
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)  # the process's, so here and not in DynNode
    end_process(spin_until_signalled(_started_node, args, "dyn_node", fatal=(
        InvalidParameterValueException, InvalidParameterTypeException, SettingsError)))


if __name__ == "__main__":
    main()
