"""dyn_sim: the ROS 2 adapter around :class:`dyn_node.sim.simulator.Simulator` (MuJoCo, 1 ms step).

Publishes ``joint_states`` (sensor_msgs/JointState: positions, velocities and measured effort =
the applied, saturated actuator torque) at ``publish_rate_hz`` and the URDF on
``robot_description`` (std_msgs/String, reliable, transient-local, depth 1, as
robot_state_publisher does); executes trajectories as ros2_control's joint_trajectory_controller
would, with its interfaces: ``/<controller_name>/joint_trajectory``, the FollowJointTrajectory
action ``/<controller_name>/follow_joint_trajectory`` and ``/<controller_name>/controller_state``
(:mod:`dyn_node.ros.sim.action`). Bad trajectories are rejected with a logged
reason and the current motion continues. ``~/apply_wrench`` (geometry_msgs/WrenchStamped: the
wrench on the robot at the origin of the link named by frame_id, in that link's axes) pushes the
robot from the next step on for ``apply_wrench_hold`` s, unless a newer message replaces it; a
zero wrench ends the push; an unknown frame_id or a non-finite value is logged and counted
(:meth:`dyn_node.sim.simulator.Simulator.apply_wrench` does the math). ``~/applied_wrench`` says
what the simulation actually applied, in its own stamps: the push when it starts acting and a
zero wrench when it ends, so an estimate can be compared with the truth on a loaded machine too.

Timing: the simulation runs in a thread of its own. With ``real_time`` true it is paced against
the wall clock in batches (every wake-up steps as many 1 ms steps as are due, publishing at each
publish boundary inside the batch), so a late wake-up on a loaded machine is caught up instead
of slowing the simulation; header stamps are start-time + simulation time, so they are evenly
spaced. With ``real_time`` false it runs as fast as it can and publishes ``/clock`` (simulation
time from 0) for nodes started with ``use_sim_time``.

Run: ``ros2 run dyn_node dyn_sim`` or ``python -m dyn_node.ros.sim_node [--ros-args ...]``.
"""
from __future__ import annotations

import sys
import threading
import time
from typing import Any

import rclpy
from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import WrenchStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from dyn_node.errors import DynNodeError
from dyn_node.core.robot.model import DEFAULT_MODEL, model_from_source
from dyn_node.sim.simulator import DEFAULT_DAMPING_RATIO, DEFAULT_NATURAL_FREQUENCY, DEFAULT_TIMESTEP, SimConfig, Simulator
from dyn_node.ros.main import spin_until_signalled
from dyn_node.core.robot.settings import ParamSpec
from dyn_node.ros.params import KINDS, parameter_descriptor
from dyn_node.ros.qos import LATCHED_HISTORY
from dyn_node.ros.sim.physics import SCENE_PARAMETERS, SimPhysics, sim_config_extras
from dyn_node.sim.scene import SceneError
from dyn_node.ros.sim.action import JTC_PARAMETERS, JtcFace, joint_tolerance_parameters

#: Largest backlog (s) a real-time run catches up. When the process was starved of CPU (a loaded
#: machine), the steps that were due are computed in a burst with their own evenly spaced stamps,
#: so every subscriber still sees the motion exactly as it happened in stamp time, only delivered
#: late. Beyond this backlog it is dropped (logged): the simulation pauses for that long and its
#: stamps jump with the wall clock.
MAX_CATCH_UP_S = 5.0
#: joint_states publisher history: a catch-up burst must not overwrite samples a reliable
#: subscriber has not acknowledged yet (2 s at 500 Hz).
JOINT_STATES_DEPTH = 1000


_D, _B, _S, _DA = "double", "bool", "string", "double_array"

#: Every dyn_sim parameter (all read at start-up; change them by restarting the node).
PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("robot_model", _S, DEFAULT_MODEL,
             "built-in robot (panda, ur5, planar_2link); used when robot_description and "
             "robot_description_file are empty"),
    ParamSpec("robot_description", _S, "", "URDF XML of the robot (wins over the other sources)"),
    ParamSpec("robot_description_file", _S, "", "path to a URDF file"),
    ParamSpec("timestep", _D, DEFAULT_TIMESTEP, "MuJoCo integration step (s)", 1e-4, 0.01),
    ParamSpec("publish_rate_hz", _D, 500.0,
             "joint_states rate (Hz); rounded to a whole number of steps", 1.0, 1000.0),
    ParamSpec("real_time", _B, True,
             "true: paced by the wall clock; false: as fast as possible, publishing /clock"),
    ParamSpec("kp", _DA, None,
             "PD stiffness per joint (N·m/rad, model order); unset: M_ii(q0)·natural_frequency²"),
    ParamSpec("kd", _DA, None,
             "PD damping per joint (N·m·s/rad); unset: 2·damping_ratio·M_ii(q0)·natural_frequency"),
    ParamSpec("natural_frequency", _D, DEFAULT_NATURAL_FREQUENCY,
             "closed-loop bandwidth for automatic gains (rad/s)", 1.0, 500.0),
    ParamSpec("damping_ratio", _D, DEFAULT_DAMPING_RATIO, "damping ratio for automatic gains",
             0.05, 10.0),
    ParamSpec("feedforward", _B, True,
             "add MuJoCo inverse dynamics of the reference to the PD torque"),
    ParamSpec("initial_positions", _DA, None,
             "start pose per joint (rad|m, model order); unset: middle of each joint's range "
             "(Panda: the 'ready' pose of the demo is passed explicitly)"),
    ParamSpec("publish_locked_joints", _B, True,
             "also publish locked joints (Panda fingers) at their locked position, as "
             "joint_state_broadcaster does for every joint of the robot"),
    ParamSpec("apply_wrench_hold", _D, 0.5,
             "how long (s) each ~/apply_wrench message pushes the robot, unless a newer one "
             "replaces it", 0.001, 3600.0),
) + SCENE_PARAMETERS + JTC_PARAMETERS


def _descriptor(p: ParamSpec) -> ParameterDescriptor:
    return parameter_descriptor(p.name, KINDS[p.kind], p.description, low=p.low, high=p.high,
                                read_only=True)


class SimNode(Node):
    """The dyn_sim node: a Simulator stepped in a pacing thread, ROS I/O around it."""

    def __init__(self, **kwargs: Any):
        super().__init__("dyn_sim", **kwargs)
        self.p: dict[str, Any] = {}
        self._declare(PARAMETERS)
        arr = lambda k: tuple(float(x) for x in (self.p[k] or ()))  # noqa: E731
        self.model = model_from_source(self.p["robot_description"], self.p["robot_description_file"],
                                       self.p["robot_model"])
        self._declare(joint_tolerance_parameters(self.model.joint_names))
        self.sim = Simulator(self.model, SimConfig(
            timestep=self.p["timestep"], kp=arr("kp"), kd=arr("kd"),
            natural_frequency=self.p["natural_frequency"], damping_ratio=self.p["damping_ratio"],
            feedforward=self.p["feedforward"], initial_positions=arr("initial_positions"),
            **sim_config_extras(self.p, self.model)))
        self.steps_per_publish = max(1, int(round(1.0 / (self.p["publish_rate_hz"] * self.p["timestep"]))))
        self.real_time = bool(self.p["real_time"])
        # Stamps: wall-clock start + simulation time (real time), or simulation time (/clock).
        self.epoch_ns = self.get_clock().now().nanoseconds if self.real_time else 0

        names = list(self.model.joint_names)
        self._locked = ([(n, float(v)) for n, v in self.model.locked_joints.items()]
                        if self.p["publish_locked_joints"] else [])
        self._names = names + [n for n, _ in self._locked]
        self._locked_q = [v for _, v in self._locked]
        self._locked_zero = [0.0] * len(self._locked)

        self.js_pub = self.create_publisher(JointState, "joint_states", JOINT_STATES_DEPTH)
        latched = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.desc_pub = self.create_publisher(String, "robot_description", latched)
        self.desc_pub.publish(String(data=self.model.urdf))
        self.clock_pub = None if self.real_time else self.create_publisher(Clock, "/clock", 10)
        self.create_subscription(WrenchStamped, "~/apply_wrench", self._on_wrench, 10)
        self.applied_pub = self.create_publisher(WrenchStamped, "~/applied_wrench", LATCHED_HISTORY)
        self._announced: Any = None  # the AppliedWrench last said on ~/applied_wrench
        self.physics = SimPhysics(self, self.sim, self._stamp, period_s=self.p["physics_diagnostics_period"])

        self._wrench_inbox: list[WrenchStamped] = []
        #: ~/apply_wrench messages rejected (unknown frame_id, non-finite values)
        self.rejected_wrenches = 0
        self._inbox: list[JointTrajectory] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.published = 0
        self.lag_events = 0
        self.catch_ups = 0
        self._last_catch_up_log = -1e9
        self._thread = threading.Thread(target=self._run, name="dyn_sim_loop", daemon=True)
        # the controller's topics and action (/<controller_name>/...), on a node of its own
        # "now" on the stamps' clock (epoch + simulation time): goal stamps are compared with it
        self.jtc = JtcFace(self, self.p, self._on_trajectory, lambda: self.epoch_ns * 1e-9 + self.sim.time)
        self._reset_requested = threading.Event()
        self.create_service(Trigger, "~/reset", self._on_reset)
        self._lag_said = False
        for note in (self.sim.integrator_note, self.sim.gain_warning):
            if note:
                self.get_logger().warning(note)
        self.get_logger().info(
            f"simulating {self.model.name} ({self.model.nv} DoF) with MuJoCo at "
            f"{self.p['timestep'] * 1e3:g} ms, joint_states every {self.steps_per_publish} steps, "
            f"{'real time' if self.real_time else 'as fast as possible with /clock'}")
        self._thread.start()

    def _declare(self, specs: tuple[ParamSpec, ...]) -> None:
        for spec in specs:
            default = spec.default if spec.default is not None else Parameter.Type.DOUBLE_ARRAY
            self.declare_parameter(spec.name, default, _descriptor(spec))
            try:
                value = self.get_parameter(spec.name).value
            except rclpy.exceptions.ParameterUninitializedException:
                value = None
            self.p[spec.name] = value

    # --- ROS callbacks ---------------------------------------------------------------------------
    def _on_trajectory(self, msg: JointTrajectory) -> None:
        with self._lock:
            self._inbox.append(msg)

    def _on_reset(self, _req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        """Clear a physics fault: the robot held at rest where it is (the last good state)."""
        fault = self.sim.fault
        self._reset_requested.set()
        res.success = True
        res.message = f"reset (was: {fault.text})" if fault is not None else "reset (no fault)"
        return res

    def _on_wrench(self, msg: WrenchStamped) -> None:
        with self._lock:
            self._wrench_inbox.append(msg)

    def _take_wrenches(self) -> None:
        """Apply the pushes received since the last step (in order: the newest wins)."""
        with self._lock:
            msgs, self._wrench_inbox = self._wrench_inbox, []
        for msg in msgs:
            f, m = msg.wrench.force, msg.wrench.torque
            try:
                push = self.sim.apply_wrench(msg.header.frame_id, (f.x, f.y, f.z), (m.x, m.y, m.z),
                                             hold_s=self.p["apply_wrench_hold"])
            except DynNodeError as exc:
                self.rejected_wrenches += 1
                # throttled: a publisher streaming bad pushes must not flood the log; the count says all
                self.get_logger().error(f"apply_wrench rejected ({exc.failure_label}, {exc.code}): {exc} "
                                        f"({self.rejected_wrenches} rejected so far)", throttle_duration_sec=1.0)
                continue
            # said now: a push shorter than a publish period is over by the next joint_states
            self._announce_push()
            if push is None:
                self.get_logger().info("apply_wrench: zero wrench, push ended", throttle_duration_sec=1.0)
            else:
                self.get_logger().info(
                    f"apply_wrench: {push.force_n:.3g} N, {push.moment_nm:.3g} N·m at {push.mount.link} "
                    f"(MuJoCo body {push.mount.body}) for {self.p['apply_wrench_hold']:g} s",
                    throttle_duration_sec=1.0)

    def _take_trajectories(self) -> None:
        if self._reset_requested.is_set():
            self._reset_requested.clear()
            self.sim.reset(self.sim.q)
        with self._lock:
            msgs, self._inbox = self._inbox, []
        for msg in msgs:
            stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            # the stamp on the simulation clock (stamps are epoch + simulation time)
            start = None if stamp_ns == 0 else (stamp_ns - self.epoch_ns) * 1e-9
            if start is not None:
                self._say_lag()
            pts = msg.points
            try:
                act = self.sim.execute(
                    list(msg.joint_names),
                    [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts],
                    [list(p.positions) for p in pts],
                    [list(p.velocities) for p in pts],
                    [list(p.accelerations) for p in pts],
                    start_time=start)
            except DynNodeError as exc:
                self.get_logger().error(
                    f"trajectory rejected ({exc.failure_label}, {exc.code}): {exc}")
                self.jtc.rejected(msg, exc)
                continue
            self.jtc.started(msg, act)
            self.get_logger().info(
                f"executing trajectory: {act.trajectory.n_points} points, "
                f"{act.trajectory.duration:.3f} s, {act.mode} interpolation, starts in "
                f"{max(0.0, act.start_time - self.sim.time):.3f} s")

    def _say_lag(self) -> None:
        """Once: the simulation clock runs behind the wall clock (CPU starvation), so a goal
        stamped by the wall clock starts at its stamp on the simulation clock, late in wall time."""
        lag = (self.get_clock().now().nanoseconds - self.epoch_ns) * 1e-9 - self.sim.time
        if self.real_time and lag > 0.05 and not self._lag_said:
            self._lag_said = True
            self.get_logger().warning(
                f"the simulation clock is {lag:.3f} s behind the wall clock (the process is starved of "
                "CPU): stamped goals start at their stamp on the simulation clock, later in wall time "
                "(said once)")

    # --- simulation loop -------------------------------------------------------------------------
    def _stamp(self, steps: int) -> TimeMsg:
        ns = self.epoch_ns + int(round(steps * self.sim.config.timestep * 1e9))
        return TimeMsg(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    def _announce_push(self) -> None:
        """~/applied_wrench on a change of push (when one is applied, and at each publish for
        one whose hold ran out): the new one stamped with the step it starts acting on, or a
        zero wrench stamped with the step the last one stopped acting on."""
        cur, old = self.sim.wrench, self._announced
        if cur is old:
            return
        msg = WrenchStamped()
        if cur is not None:
            msg.header.stamp = self._stamp(cur.start_step)
            msg.header.frame_id = cur.mount.link
            f, m = cur.wrench[:3], cur.wrench[3:]
            msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = (float(x) for x in f)
            msg.wrench.torque.x, msg.wrench.torque.y, msg.wrench.torque.z = (float(x) for x in m)
        else:
            msg.header.stamp = self._stamp(min(old.end_step, self.sim.steps))
            msg.header.frame_id = old.mount.link
        self.applied_pub.publish(msg)
        self._announced = cur

    def _publish(self) -> None:
        self._announce_push()
        st = self.sim.state()
        stamp = self._stamp(self.sim.steps)
        msg = JointState()
        msg.header.stamp = stamp
        msg.name = self._names
        msg.position = st.q.tolist() + self._locked_q
        msg.velocity = st.v.tolist() + self._locked_zero
        msg.effort = st.effort.tolist() + self._locked_zero
        if self.clock_pub is not None:
            self.clock_pub.publish(Clock(clock=stamp))
        self.js_pub.publish(msg)
        self.published += 1
        self.physics.on_publish()
        self.jtc.update(self.sim, stamp, st)

    def _run(self) -> None:
        dt = self.sim.config.timestep
        n = self.steps_per_publish
        if self.real_time:
            # Stamp = this instant + simulation time: taken together with wall0 so they agree.
            self.epoch_ns = self.get_clock().now().nanoseconds
        wall0 = time.monotonic()
        skipped = 0
        done = 0
        try:
            self._publish()
            while not self._stop.is_set():
                self._take_trajectories()
                self._take_wrenches()
                if self.real_time:
                    due = int((time.monotonic() - wall0) / dt) - skipped - done
                    if due * dt > MAX_CATCH_UP_S:
                        # Too far behind (machine overloaded): drop the backlog, keep going.
                        self.lag_events += 1
                        if self.lag_events in (1, 10, 100) or self.lag_events % 1000 == 0:
                            self.get_logger().warning(
                                f"simulation fell {due * dt:.3f} s behind the wall clock; "
                                f"dropping the backlog ({self.lag_events} time(s) so far)")
                        dropped = due - n
                        skipped += dropped
                        self.epoch_ns += int(round(dropped * dt * 1e9))
                        due = n
                    if due < n:
                        self._stop.wait((n - due) * dt)
                        continue
                    chunks = due // n
                    if due * dt > 0.05:
                        self.catch_ups += 1
                        now = time.monotonic()
                        if now - self._last_catch_up_log > 5.0:
                            self._last_catch_up_log = now
                            self.get_logger().info(
                                f"catching up {due * dt * 1e3:.0f} ms of simulation (the process "
                                f"was starved of CPU; {self.catch_ups} catch-up(s) so far); "
                                "stamps stay exact, delivery is late")
                else:
                    chunks = 1
                for i in range(chunks):
                    if i:
                        self._take_trajectories()  # a trajectory that arrived mid-burst
                        self._take_wrenches()
                    self.sim.step(n)
                    done += n
                    self._publish()
        except Exception as exc:  # a dead sim thread must be visible, not silent
            if not self._stop.is_set():
                self.get_logger().fatal(f"simulation loop failed: {exc!r}")
                raise

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)

    def destroy_node(self) -> None:
        self.stop()
        self.jtc.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Jazzy main(): spin until SIGINT/SIGTERM, then stop the sim thread and shut down cleanly
    (signal handling in :mod:`dyn_node.ros.main`). A model that cannot be loaded exits with 1, a
    scene file or solver setting that cannot be used with 2 (bad input), each with one line.
    ``--check-physics`` runs the simulator's physics checks instead (no ROS graph)."""
    argv = list(sys.argv if args is None else args)
    if "--check-physics" in argv:
        from dyn_node.sim.physics_check import main as check_physics
        return check_physics(argv[argv.index("--check-physics") + 1:])
    return spin_until_signalled(SimNode, args, "dyn_sim", fatal=(DynNodeError,),
                                describe=lambda exc: f"{exc.failure_label}: {exc}",
                                fatal_code=lambda exc: 2 if isinstance(exc, SceneError) else 1)


if __name__ == "__main__":
    raise SystemExit(main())
