"""dyn_sim's joint_trajectory_controller face: the controller's topics and action, as ros2_control
serves them (Jazzy), on a node named ``controller_name`` (default ``joint_trajectory_controller``).

- ``/<controller_name>/follow_joint_trajectory`` — control_msgs/action/FollowJointTrajectory. An
  invalid goal (unknown or missing joints, bad lengths or times, a non-zero last velocity, an end
  in the past) is rejected at the goal response, as the controller does. An accepted goal
  pre-empts the running one, which ends CANCELED with ``INVALID_GOAL`` and the controller's
  string (ros2_controllers since 4.x; backports after June 2026 end it ABORTED instead). A
  cancel request ends the goal CANCELED and holds the current position. Path tolerance violated
  while the trajectory plays → ABORTED ``PATH_TOLERANCE_VIOLATED``; outside the goal tolerance
  ``goal_time_tolerance`` after the end → ABORTED ``GOAL_TOLERANCE_VIOLATED``; inside it after
  the end → SUCCEEDED ``SUCCESSFUL`` (rules in :mod:`dyn_node.sim.jtc`). The physics diverging
  (the simulator's fault) → ABORTED ``PATH_TOLERANCE_VIOLATED`` with the fault's line. Feedback (desired,
  actual, error) at ``action_monitor_rate`` Hz (default 20, the controller's).
- ``/<controller_name>/joint_trajectory`` — trajectory_msgs/JointTrajectory, executed as before.
- ``/<controller_name>/controller_state`` — control_msgs/msg/JointTrajectoryControllerState at
  ``state_publish_rate`` Hz: reference, feedback, error and output (the applied torque: dyn_sim's
  command interface is effort), ``speed_scaling_factor`` 1.

dyn_sim limits effort only (no velocity or acceleration limits), so a goal too fast for the robot
really runs too fast. Tolerances come from the ``constraints.*`` parameters (one value for all
joints) overridden by the goal's. The controller node is spun by an executor of its own: an
action's execute callback waits for its goal's end.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from control_msgs.action import FollowJointTrajectory
from control_msgs.msg import JointTrajectoryControllerState
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from dyn_node.core.robot.settings import ParamSpec
from dyn_node.core.check.execution import Timing, refusals
from dyn_node.core.check.trajectory import validate_trajectory
from dyn_node.errors import DynNodeError, TrajectoryError
from dyn_node.ros.actions import end_canceled
from dyn_node.ros.convert import stamp_to_s
from dyn_node.sim import jtc

#: dyn_sim parameters of the controller face (declared with the others, read at start-up)
JTC_PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("controller_name", "string", "joint_trajectory_controller",
              "name of the emulated joint_trajectory_controller: its node and the prefix of its "
              "follow_joint_trajectory, joint_trajectory and controller_state"),
    ParamSpec("action_monitor_rate", "double", 20.0,
              "FollowJointTrajectory feedback rate (Hz), as the controller's parameter", 0.1, 1000.0),
    ParamSpec("state_publish_rate", "double", 50.0, "controller_state rate (Hz)", 1.0, 1000.0),
    ParamSpec("constraints.goal_time", "double", 0.0,
              "default goal_time_tolerance (s); 0: wait for the goal tolerance for ever", 0.0, 3600.0),
    ParamSpec("constraints.stopped_velocity_tolerance", "double", 0.01,
              "largest |velocity| (rad/s) counted as stopped at the goal", 0.0, 1e6),
    ParamSpec("constraints.trajectory", "double", 0.0,
              "default path position tolerance of every joint (rad); 0: not checked; "
              "constraints.<joint>.trajectory wins", 0.0, 1e6),
    ParamSpec("constraints.goal", "double", 0.0,
              "default goal position tolerance of every joint (rad); 0: not checked; "
              "constraints.<joint>.goal wins", 0.0, 1e6),
)


def joint_tolerance_parameters(joints: list[str] | tuple[str, ...]) -> tuple[ParamSpec, ...]:
    """JTC's per-joint ``constraints.<joint>.trajectory`` and ``.goal`` (its parameter yaml,
    ``constraints: __map_joints``), declared by dyn_sim once the model's joints are known. Unset
    (default -1 here, not a tolerance): the ``constraints.trajectory``/``.goal`` value above."""
    out = []
    for j in joints:
        for kind, what in (("trajectory", "path"), ("goal", "goal")):
            out.append(ParamSpec(f"constraints.{j}.{kind}", "double", -1.0,
                                 f"{what} position tolerance of {j} (rad), as JTC's; 0: not checked; "
                                 f"-1: constraints.{kind}", -1.0, 1e6))
    return tuple(out)


def joint_tolerances(params: dict[str, Any], joints: list[str], kind: str) -> list[float]:
    """Per joint: ``constraints.<joint>.<kind>`` when set (≥ 0), else ``constraints.<kind>``."""
    return [params[f"constraints.{j}.{kind}"] if params.get(f"constraints.{j}.{kind}", -1.0) >= 0.0
            else params[f"constraints.{kind}"] for j in joints]

Result = FollowJointTrajectory.Result


@dataclass
class _Goal:
    """One accepted goal, shared by its execute callback and the simulation thread."""

    handle: Any
    msg: JointTrajectory
    tol: jtc.SegmentTolerances
    done: threading.Event = field(default_factory=threading.Event)
    outcome: jtc.Outcome | None = None
    preempted: bool = False
    act: Any = None  # the simulator's ActiveTrajectory, once started
    feedback: Any = None  # (stamp, q_ref, v_ref, q, v) of the last update


def _point(q: np.ndarray, v: np.ndarray | None = None, effort: np.ndarray | None = None) -> JointTrajectoryPoint:
    p = JointTrajectoryPoint()
    p.positions = q.tolist()
    if v is not None:
        p.velocities = v.tolist()
    if effort is not None:
        p.effort = effort.tolist()
    return p


class JtcFace:
    """The controller node beside dyn_sim. ``submit`` hands a JointTrajectory to the simulation
    thread (dyn_sim's inbox); ``hold`` asks it to hold the current position. The simulation thread
    calls :meth:`started` when it takes a trajectory and :meth:`update` at each publish."""

    def __init__(self, sim_node: Node, params: dict[str, Any], submit: Callable[[JointTrajectory], None],
                 clock_now_s: Callable[[], float]):
        self.sim_node = sim_node
        self.model = sim_node.model
        self.joints = list(self.model.joint_names)
        self._submit = submit
        self._now_s = clock_now_s
        self.monitor_period = 1.0 / float(params["action_monitor_rate"])
        self.state_period = 1.0 / float(params["state_publish_rate"])
        self.defaults = jtc.default_tolerances(
            len(self.joints), trajectory=joint_tolerances(params, self.joints, "trajectory"),
            goal=joint_tolerances(params, self.joints, "goal"),
            stopped_velocity=params["constraints.stopped_velocity_tolerance"],
            goal_time=params["constraints.goal_time"])
        self._lock = threading.Lock()
        self._active: _Goal | None = None
        self._pending: dict[int, _Goal] = {}  # id(goal msg) → goal not yet started
        self._by_handle: dict[int, _Goal] = {}  # id(goal handle) → its goal, until it ends
        self._hold_requested = False
        self._last_state_t = -1e9
        self.node = Node(params["controller_name"], context=sim_node.context,
                         namespace=sim_node.get_namespace(), start_parameter_services=False)
        group = ReentrantCallbackGroup()
        self.state_pub = self.node.create_publisher(JointTrajectoryControllerState, "~/controller_state", 10)
        self.node.create_subscription(JointTrajectory, "~/joint_trajectory", submit, 10, callback_group=group)
        self.server = ActionServer(self.node, FollowJointTrajectory, "~/follow_joint_trajectory",
                                   execute_callback=self._execute, goal_callback=self._on_goal,
                                   handle_accepted_callback=self._on_accepted,
                                   cancel_callback=lambda _h: CancelResponse.ACCEPT,
                                   # its own group: an action waitable run by two threads at once
                                   # loses requests (shared ready flags)
                                   callback_group=MutuallyExclusiveCallbackGroup())
        self.executor = MultiThreadedExecutor(num_threads=4, context=sim_node.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="dyn_sim controller", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        # spin_once with a stop flag: shutting an executor down while a thread is inside spin()
        # can destroy the guard condition that thread is about to trigger
        while not self._stop.is_set() and self.executor.context.ok():
            self.executor.spin_once(timeout_sec=0.1)

    # --- goal life cycle (executor threads) -----------------------------------------------------
    def _validate(self, goal: Any) -> None:
        tr = goal.trajectory
        pts = tr.points
        times = [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts]
        traj = validate_trajectory(self.joints, list(tr.joint_names), times, [list(p.positions) for p in pts],
                                   [list(p.velocities) for p in pts], [list(p.accelerations) for p in pts],
                                   min_points=1, ignored_joints=tuple(self.model.locked_joints))
        # the controller's refusals from the one execution model (the check judges the same)
        refused = refusals(traj, Timing(stamp_s=stamp_to_s(tr.header.stamp), receipt_s=self._now_s()))
        if refused:
            code, text = refused[0]
            raise TrajectoryError(text, code=code)

    def _on_goal(self, goal: Any) -> GoalResponse:
        try:
            self._validate(goal)
        except DynNodeError as exc:
            self.node.get_logger().error(f"goal rejected ({exc.code}): {exc}")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _on_accepted(self, handle: Any) -> None:
        g = handle.request
        tol, why = jtc.goal_tolerances(
            self.defaults, self.joints,
            [(t.name, t.position, t.velocity, t.acceleration) for t in g.path_tolerance],
            [(t.name, t.position, t.velocity, t.acceleration) for t in g.goal_tolerance],
            g.goal_time_tolerance.sec + g.goal_time_tolerance.nanosec * 1e-9)
        if why:
            self.node.get_logger().error(f"goal tolerances: {why}")
        goal = _Goal(handle=handle, msg=g.trajectory, tol=tol)
        with self._lock:
            old, self._active = self._active, None
            for p in self._pending.values():
                p.preempted = True
                p.done.set()
            self._pending = {id(goal.msg): goal}
            self._by_handle[id(handle)] = goal
        if old is not None:
            old.preempted = True
            old.done.set()
        self._submit(goal.msg)
        handle.execute()

    def _execute(self, handle: Any) -> Any:
        try:
            return self._run(handle, self._by_handle[id(handle)])
        finally:
            with self._lock:
                self._by_handle.pop(id(handle), None)

    def _run(self, handle: Any, goal: _Goal) -> Any:
        fb = FollowJointTrajectory.Feedback()
        fb.joint_names = self.joints
        while not goal.done.wait(self.monitor_period):
            if handle.is_cancel_requested:
                return self._cancel(goal)
            if goal.feedback is not None:
                stamp, q_ref, v_ref, q, v = goal.feedback
                fb.header.stamp = stamp
                fb.desired, fb.actual = _point(q_ref, v_ref), _point(q, v)
                fb.error = _point(q_ref - q, v_ref - v)
                handle.publish_feedback(fb)
        if goal.preempted:
            end_canceled(handle)
            return Result(error_code=Result.INVALID_GOAL, error_string=jtc.PREEMPTED_TEXT)
        out = goal.outcome
        if out.code == jtc.SUCCESSFUL:
            handle.succeed()
        else:
            handle.abort()
        return Result(error_code=out.code, error_string=out.text)

    def _cancel(self, goal: _Goal) -> Any:
        with self._lock:
            if self._active is goal or self._pending.get(id(goal.msg)) is goal:
                self._active = None
                self._pending.pop(id(goal.msg), None)
                self._hold_requested = True
        goal.handle.canceled()
        return Result()

    # --- simulation thread ----------------------------------------------------------------------
    def started(self, msg: JointTrajectory, act: Any) -> None:
        """dyn_sim took ``msg`` (a goal's trajectory or a topic's) and runs ``act``."""
        with self._lock:
            goal = self._pending.pop(id(msg), None)
            if goal is not None and goal.msg is msg:
                goal.act = act
                self._active = goal

    def rejected(self, msg: JointTrajectory, exc: DynNodeError) -> None:
        """dyn_sim could not start ``msg`` (validated at the goal response, so only a start time
        that became invalid): its goal ends ABORTED with the reason."""
        with self._lock:
            goal = self._pending.pop(id(msg), None)
        if goal is not None:
            goal.outcome = jtc.Outcome(jtc.INVALID_GOAL, str(exc))
            goal.done.set()

    def update(self, sim: Any, stamp: Any, st: Any) -> None:
        """One controller update at a publish boundary: pending hold, goal monitoring, state."""
        with self._lock:
            hold, self._hold_requested = self._hold_requested, False
            goal = self._active
        if hold:
            sim.hold()
        if goal is not None and goal.outcome is None and not goal.preempted and sim.fault is not None:
            # the physics diverged: the goal cannot be executed (issue 37), said with the cause
            with self._lock:
                if self._active is goal:
                    self._active = None
            goal.outcome = jtc.Outcome(jtc.PATH_TOLERANCE_VIOLATED, f"dyn_sim: {sim.fault.text}")
            goal.done.set()
        elif goal is not None and goal.outcome is None and not goal.preempted:
            act = sim.active if sim.active is not None else goal.act
            goal.feedback = (stamp, st.q_ref, st.v_ref, st.q, st.v)
            out = jtc.monitor(st.t, act.end_time, st.q_ref - st.q, st.v_ref - st.v, goal.tol, self.joints)
            if out is not None:
                if out.code != jtc.SUCCESSFUL:
                    sim.hold()  # the controller holds the current position after an abort
                with self._lock:
                    if self._active is goal:
                        self._active = None
                goal.outcome = out
                goal.done.set()
        if st.t - self._last_state_t >= self.state_period - 1e-9:
            self._last_state_t = st.t
            self._publish_state(stamp, st)

    def _publish_state(self, stamp: Any, st: Any) -> None:
        msg = JointTrajectoryControllerState()
        msg.header.stamp = stamp
        msg.joint_names = self.joints
        msg.reference = _point(st.q_ref, st.v_ref)
        msg.feedback = _point(st.q, st.v)
        msg.error = _point(st.q_ref - st.q, st.v_ref - st.v)
        msg.output = _point(np.zeros(0), None, st.effort)
        msg.speed_scaling_factor = 1.0
        self.state_pub.publish(msg)

    def close(self) -> None:
        with self._lock:
            goals = [g for g in (self._active, *self._pending.values()) if g is not None]
            self._active, self._pending = None, {}
        for g in goals:  # no execute callback left waiting
            g.outcome = g.outcome or jtc.Outcome(jtc.INVALID_GOAL, "dyn_sim is shutting down")
            g.done.set()
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.server.destroy()
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
