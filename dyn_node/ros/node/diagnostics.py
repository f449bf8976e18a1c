"""The node's periodic outputs (/diagnostics, ~/controller_status) and ~/self_test."""
from __future__ import annotations

import time
from dataclasses import replace

from diagnostic_msgs.srv import SelfTest

from dyn_node.errors import STATE_ERROR
from dyn_node.core.robot.model_status import model_error_status, model_status, waiting_model_status
from dyn_node.core.live.monitor import JOINT_STATES
from dyn_node.ros.convert import diagnostic_array, status_to_msg, to_byte
from dyn_node.core.robot.selftest import run_self_test
from dyn_node.core.robot.status import STALE, Status



class PeriodicOutputs:
    """DynNode's diagnostics part (a mixin: DynNode composes it)."""

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
