"""dyn_sim as ros2_control's joint_trajectory_controller: FollowJointTrajectory and
controller_state, talked to from another process with the control_msgs types built here."""
from __future__ import annotations

import signal

import numpy as np
import pytest

from conftest import kv, python_cmd

pytest.importorskip("control_msgs", reason="control_msgs not built into the venv (make)")

READY = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]
ARM = [f"panda_joint{i}" for i in range(1, 8)]
ACTION = "/joint_trajectory_controller/follow_joint_trajectory"


def sim_cmd(*params: str) -> list[str]:
    args = ["--ros-args", "-p", f"initial_positions:={READY}"]
    for p in params:
        args += ["-p", p]
    return python_cmd("dyn_node.ros.sim_node", *args)


def moved(j: int, dq: float) -> list[float]:
    q = list(READY)
    q[j] += dq
    return q


@pytest.fixture
def sim(ros_context, spawn):
    """dyn_sim in a child process and an action client here."""
    from dyn_node.ros.fjt_client import FjtClient

    proc = spawn(sim_cmd("constraints.goal_time:=2.0"))
    client = FjtClient(ros_context, ACTION)
    try:
        client.wait_for_server(60.0)
        yield client, proc
    finally:
        client.close()


@pytest.mark.timeout(120)
def test_goal_succeeds_with_feedback_and_invalid_goals_are_rejected(sim):
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory
    from dyn_node.ros.fjt_client import goal

    client, proc = sim
    Result = FollowJointTrajectory.Result
    # rejected at the goal response, as the controller does: unknown joint, missing joint,
    # times not increasing, non-zero velocity at the end
    bad = [goal([0.5], [READY], names=ARM[:6] + ["elbow"]),
           goal([0.5], [READY[:6]], names=ARM[:6]),
           goal([0.5, 0.4], [READY, READY], names=ARM),
           goal([0.5], [READY], names=ARM, velocities=[[0.1] * 7])]
    for g in bad:
        assert not client.send(g).handle.accepted
    target = moved(0, 0.2)
    sent = client.send(goal([1.0], [target], names=ARM, goal_tolerance=[(n, 0.01) for n in ARM]))
    assert sent.handle.accepted
    status, result = client.result(sent)
    assert (status, result.error_code, result.error_string) == (
        GoalStatus.STATUS_SUCCEEDED, Result.SUCCESSFUL, "Goal successfully reached!")
    # ~20 Hz feedback over a 1 s goal; desired − actual = error, in the controller's joint order
    fb = sent.feedback
    assert len(fb) >= 5
    f = fb[-1]
    assert list(f.joint_names) == ARM
    np.testing.assert_allclose(np.array(f.desired.positions) - np.array(f.actual.positions),
                               np.array(f.error.positions), atol=1e-12)
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in fb]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert np.median(np.diff(stamps)) == pytest.approx(0.05, abs=0.02)  # simulation time, 20 Hz
    rc, out, err = proc.stop(signal.SIGINT)
    assert rc == 0, err
    log = out + err
    for code in ("unknown_joints", "missing_joints", "bad_times", "nonzero_end_velocity"):
        assert f"goal rejected ({code})" in log


@pytest.mark.timeout(120)
def test_path_and_goal_tolerance_violations_abort(sim):
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory
    from dyn_node.ros.fjt_client import goal

    client, _ = sim
    Result = FollowJointTrajectory.Result
    # a fast move tracked within 1 µrad: impossible for the PD loop
    sent = client.send(goal([0.5], [moved(3, 0.3)], names=ARM, path_tolerance=[("panda_joint4", 1e-6)]))
    status, result = client.result(sent)
    assert (status, result.error_code) == (GoalStatus.STATUS_ABORTED, Result.PATH_TOLERANCE_VIOLATED)
    assert result.error_string == "Aborted due to path tolerance violation"
    # a goal tolerance no controller meets (1e-12 rad) with 0.2 s of goal time
    sent = client.send(goal([0.3], [moved(1, 0.05)], names=ARM, goal_tolerance=[("panda_joint2", 1e-12)],
                            goal_time=0.2))
    status, result = client.result(sent)
    assert (status, result.error_code) == (GoalStatus.STATUS_ABORTED, Result.GOAL_TOLERANCE_VIOLATED)
    assert result.error_string.startswith("Aborted due to goal_time_tolerance exceeding by ")
    assert "panda_joint2" in result.error_string


@pytest.mark.timeout(120)
def test_preemption_and_cancel_end_canceled(sim):
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory
    from dyn_node.ros.fjt_client import goal

    client, _ = sim
    Result = FollowJointTrajectory.Result
    first = client.send(goal([5.0], [moved(0, 0.4)], names=ARM))
    assert first.handle.accepted
    assert first.feedback_event.wait(10.0)  # running
    second = client.send(goal([0.5], [READY], names=ARM))
    status, result = client.result(first)
    assert (status, result.error_code, result.error_string) == (
        GoalStatus.STATUS_CANCELED, Result.INVALID_GOAL, "Current goal cancelled due to new incoming action.")
    status, result = client.result(second)
    assert (status, result.error_code) == (GoalStatus.STATUS_SUCCEEDED, Result.SUCCESSFUL)
    # a cancel request ends the running goal CANCELED
    third = client.send(goal([5.0], [moved(0, 0.4)], names=ARM))
    assert third.feedback_event.wait(10.0)
    assert len(client.cancel(third).goals_canceling) == 1
    status, _ = client.result(third)
    assert status == GoalStatus.STATUS_CANCELED


@pytest.mark.timeout(60)
def test_controller_state_published(ros_context, spawn):
    from control_msgs.msg import JointTrajectoryControllerState
    from rclpy.node import Node

    from conftest import Stepper

    spawn(sim_cmd("state_publish_rate:=50.0", "controller_name:=arm_controller"))
    node = Node("state_probe", context=ros_context)
    got: list = []
    node.create_subscription(JointTrajectoryControllerState, "/arm_controller/controller_state",
                             got.append, 100)
    steps = Stepper(ros_context, (node,), step_s=0.05)
    try:
        assert steps.until(lambda: len(got) >= 20, 40.0), "no controller_state"
    finally:
        steps.close()
    m = got[-1]
    assert list(m.joint_names) == ARM and m.speed_scaling_factor == 1.0
    np.testing.assert_allclose(m.reference.positions, READY, atol=1e-9)  # holding the start pose
    np.testing.assert_allclose(np.array(m.reference.positions) - np.array(m.feedback.positions),
                               m.error.positions, atol=1e-12)
    assert len(m.output.effort) == 7 and np.abs(m.output.effort).max() > 1.0  # gravity torque
    t = np.array([x.header.stamp.sec + x.header.stamp.nanosec * 1e-9 for x in got])
    assert np.median(np.diff(t)) == pytest.approx(0.02, abs=1e-6)  # 50 Hz of simulation time


@pytest.mark.timeout(120)
def test_a_diverging_simulation_is_an_error_status_and_aborts_the_goal(ros_context, spawn):
    """Issue 37, forced: xArm7 (example-robot-data) with ``integrator:=rk4`` asked explicitly,
    which its joint7's damping (2 N·m·s/rad on 1.4e-4 kg·m²) makes diverge at 1 ms once a goal
    moves it (the saturated torque bounds a huge gain's chatter, so a gain alone does not; the
    core test drives one unsaturated). The goal ends ABORTED with the fault's line,
    'dyn_sim: physics' goes ERROR with it (joint, quantity, step), joint_states never carries the
    diverging values, dyn_sim said at start that rk4 would diverge, and ~/reset clears it."""
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger

    from conftest import Collected, Spinner
    from dyn_node.core.robot.model import example_robot_data_dir
    from dyn_node.ros.fjt_client import FjtClient, goal

    urdf = example_robot_data_dir() / "xarm_description" / "urdf" / "xarm7.urdf"
    joints = [f"joint{i}" for i in range(1, 8)]
    proc = spawn(python_cmd("dyn_node.ros.sim_node", "--ros-args", "-p", f"robot_description_file:={urdf}",
                            "-p", "integrator:=rk4", "-p", "physics_diagnostics_period:=0.2"))
    got = Collected(("diag", "js"))
    node = Node("diverge_probe", context=ros_context)
    diag = got.collector("diag")
    node.create_subscription(DiagnosticArray, "/diagnostics",
                             lambda m: [diag(s) for s in m.status if s.name == "dyn_sim: physics"], 100)
    node.create_subscription(JointState, "joint_states", got.collector("js"), 1000)
    spinner = Spinner(ros_context, [node])
    client = FjtClient(ros_context, ACTION)
    try:
        client.wait_for_server(60.0)
        assert got.wait(lambda: len(got.got["js"]) > 0 and len(got.got["diag"]) > 0, 30)
        assert got.got["diag"][-1].level == bytes([0])  # holding still: nothing grows yet
        q0 = list(got.got["js"][-1].position)
        status, result = client.result(client.send(goal([1.0], [[q + 0.1 for q in q0]], names=joints)))
        assert status == GoalStatus.STATUS_ABORTED
        assert result.error_code == FollowJointTrajectory.Result.PATH_TOLERANCE_VIOLATED
        assert result.error_string.startswith("dyn_sim: physics diverged at step ")
        assert got.wait(lambda: any(s.level == bytes([2]) for s in got.got["diag"]), 30)
        err = next(s for s in got.got["diag"] if s.level == bytes([2]))
        assert result.error_string == f"dyn_sim: {err.message}" and " of joint joint" in err.message
        assert kv(err)["failure_label"] == "evaluation error"
        # ~/reset: the robot held at rest where it stopped; the status clears
        reset = node.create_client(Trigger, "/dyn_sim/reset")
        assert reset.wait_for_service(timeout_sec=30.0)
        fut = reset.call_async(Trigger.Request())
        assert got.wait(fut.done, 30) and fut.result().success
        assert fut.result().message.startswith("reset (was: physics diverged at step ")
        n = len(got.got["diag"])
        assert got.wait(lambda: len(got.got["diag"]) > n + 1, 30)
        assert got.got["diag"][-1].level == bytes([0]), got.got["diag"][-1].message
    finally:
        client.close()
        spinner.stop()
        node.destroy_node()
    assert all(max(abs(v) for v in m.velocity) < 100 and max(abs(q) for q in m.position) < 10
               for m in got.got["js"])
    rc, out, errtext = proc.stop(signal.SIGINT)
    assert rc == 0, errtext
    assert "kept as asked; expect the physics to diverge" in out + errtext


@pytest.mark.timeout(120)
def test_stamped_goals_are_judged_on_the_simulation_clock(sim):
    """Issue 37: in real time dyn_sim's stamps are wall-clock start + simulation time, and a
    goal's stamp is compared on that clock: one stamped 10 s ago with 1 s of points ends in the
    past and is rejected (JTC's rule); one stamped 0.3 s ahead runs and succeeds."""
    import time

    from action_msgs.msg import GoalStatus
    from builtin_interfaces.msg import Time
    from dyn_node.ros.fjt_client import goal

    client, proc = sim

    def stamped(offset_s: float):
        g = goal([1.0], [moved(0, 0.05)], names=ARM, goal_tolerance=[(n, 0.01) for n in ARM])
        ns = time.time_ns() + int(offset_s * 1e9)
        g.trajectory.header.stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return g

    assert not client.send(stamped(-10.0)).handle.accepted
    sent = client.send(stamped(0.3))
    assert sent.handle.accepted
    assert client.result(sent)[0] == GoalStatus.STATUS_SUCCEEDED
    rc, out, err = proc.stop(signal.SIGINT)
    assert rc == 0 and "trajectory with a non-zero start time ends in the past" in out + err
