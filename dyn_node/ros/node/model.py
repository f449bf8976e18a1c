"""The node's model and settings: the immutable core a message reads once, built aside and
swapped in one reference; the model from parameters or ~/robot_description; parameter changes."""
from __future__ import annotations

from dataclasses import dataclass

from rcl_interfaces.msg import SetParametersResult
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
from std_msgs.msg import String

from dyn_node.core.contacts.contact_monitor import RESET_MODEL, RESET_PARAMETERS, ContactMonitor, contact_settings
from dyn_node.errors import DynNodeError, SettingsError
from dyn_node.core.robot.model import RobotModel
from dyn_node.core.robot.model_source import build_model, limits_text
from dyn_node.core.robot.model_status import model_error_status
from dyn_node.core.live.monitor import Monitor
from dyn_node.ros.convert import JointStateOut, WrenchStampedOut
from dyn_node.ros.startup_log import model_ready_line
from dyn_node.core.robot.settings import MODEL_PARAMETERS, SPECS, Settings, settings_from_mapping
from dyn_node.core.live.tracker import ControllerTracker


LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)


@dataclass(frozen=True)
class NodeCore:
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


class ModelState:
    """DynNode's model part (a mixin: DynNode composes it, the attributes are the node's)."""

    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _make_core(self, settings: Settings, model: RobotModel) -> NodeCore:
        tracker = ControllerTracker(model, settings)
        monitor = Monitor(model, settings, self._counts)
        try:
            # the Monitor's Dynamics: both run on the joint_states thread, statuses under its lock
            contact = ContactMonitor(monitor.dynamics, contact_settings(settings), history_limit=100)
        except ValueError as exc:  # a gain list of the wrong length, an unknown contact frame
            raise SettingsError(f"contact monitor: {exc}", code="bad_parameter") from exc
        core = NodeCore(model, settings, monitor, tracker,
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

    def _swap_core(self, core: NodeCore | None) -> None:
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
