"""Trajectories on joint_trajectory: recorded with the robot's state, checked on a worker thread
with its own Dynamics, the verdict and the per-waypoint effort published."""
from __future__ import annotations

import math
import queue
import struct
import threading
from typing import Any, TYPE_CHECKING

from rclpy.serialization import deserialize_message
from trajectory_msgs.msg import JointTrajectory

# at start, not at the first trajectory: loading the compiled kernels holds the GIL for about
# 0.7 s, which then stalled joint_states handling by up to 170 ms (seen in make demo)
from dyn_node.core.check import feasibility, on_demand
from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
from dyn_node.errors import TrajectoryError
from dyn_node.ros.convert import (RawTrajectory, encode_joint_trajectory_cdr, fill_trajectory_effort,
                                  parse_joint_trajectory_cdr, stamp_to_s, trajectory_arrays, verdict_array)
from dyn_node.core.check.trajectory import validate_trajectory

if TYPE_CHECKING:  # annotations only: the package's __init__ composes these parts
    from dyn_node.ros.node.model import NodeCore


class TrajectoryWorker:
    """DynNode's trajectory part (a mixin: DynNode composes it)."""

    def _record_with_state(self, sub: Any, data: bytes) -> tuple[int, NodeCore | None,
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

    def execution_state(self) -> tuple[NodeCore | None, feasibility.StartState | None]:
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

    def _worker_dynamics(self, core: NodeCore) -> Dynamics:
        """The calling thread's Dynamics for ``core`` (built on its first use there).

        One instance per worker thread (a Dynamics holds Pinocchio's scratch data), kept in a
        thread-local slot: a shared cache cleared on each miss made the workers evict each
        other's instance on every alternation. A replaced model replaces the slot's instance."""
        slot = self._worker_dyn
        key = (id(core.model), core.settings.include_friction)
        cached = getattr(slot, "dynamics", None)
        if cached is None or cached[0] != key or cached[1].model is not core.model:
            dyn = Dynamics(core.model, DynamicsOptions(include_friction=core.settings.include_friction))
            cached = slot.dynamics = (key, dyn)
        return cached[1]

    def _check_trajectory(self, data: bytes, receipt_s: float, core: NodeCore,
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
        error: TrajectoryError | None = None
        traj = None
        try:
            traj = validate_trajectory(model.joint_names, names, times, P, V, A, min_points=1,
                                       efforts=E)
            current = self._core
            if (request == on_demand.REQUEST_EXECUTE and current is not None
                    and current.model.joint_names == model.joint_names):
                current.tracker.follow(traj, timing=feasibility.Timing(stamp_s, receipt_s),
                                       start=start_state, lock=self._io_lock,
                                       options=on_demand.options_for(settings).execution)
            if traj.n_points < 2:
                validate_trajectory(model.joint_names, names, times, P, V, A, min_points=2)
        except TrajectoryError as exc:
            error = exc
        hid = model.name
        duration = float(times[-1]) if times and all(map(math.isfinite, times)) else 0.0
        if error is not None:
            statuses = feasibility.rejected_statuses(error, hid, len(times), duration)
        else:
            options = on_demand.options_for(settings)
            try:
                # judged as the controller executes it: from its header stamp, received now,
                # by the robot in the last joint_states state
                result = feasibility.check_trajectory(self._worker_dynamics(core), traj, options,
                                                      start=start_state,
                                                      start_unknown=feasibility.NO_CURRENT_STATE,
                                                      timing=feasibility.Timing(stamp_s, receipt_s))
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

    def _start_state_now(self, core: NodeCore) -> feasibility.StartState | None:
        """The robot's state a question received now starts from (None: none within stale_timeout)."""
        clock = self._clock_handle
        with self._io_lock:
            with clock:
                now_ns = clock.get_now().nanoseconds
            last = self._last_state
        if last is None or last[0].joint_names != core.model.joint_names:
            return None
        return feasibility.current_state(last[1:], now_ns, core.settings.stale_timeout)
