"""A FollowJointTrajectory controller that misbehaves on request, run as a child process by the
gate tests (``python test/fjt_double.py NAMESPACE``).

It serves ``NAMESPACE/controller/follow_joint_trajectory`` and publishes ``NAMESPACE/joint_states``
(the Panda at READY, 100 Hz) so a gate in NAMESPACE has a fresh state. Each goal says how to
behave in its first goal tolerance's name, ``double:<behaviour>:<tag>``:

- ``ok``: accepts, feedback at 20 Hz, SUCCEEDED after 0.3 s (a cancel ends it CANCELED);
- ``late``: answers the goal request 2.5 s late (accepts), then runs until cancelled;
- ``silent``: accepts, never sends feedback, runs until cancelled (then CANCELED);
- ``reject``: rejects the goal at its goal response;
- ``long``: as ``ok`` for 8 s (time for a cancel);
- ``ignore_cancel``: accepts, feedback at 20 Hz, refuses every cancel, SUCCEEDED after 8 s.

Every step of every goal is published as JSON on ``NAMESPACE/double_events`` (reliable,
transient local): ``{"tag", "behaviour", "event"}`` with event received, accepted, rejected,
cancel_requested, cancel_refused, canceled, succeeded.
"""
from __future__ import annotations

import json
import sys
import threading

READY = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]
JOINTS = [f"panda_joint{i}" for i in range(1, 8)] + ["panda_finger_joint1", "panda_finger_joint2"]


def behaviour(goal) -> tuple[str, str]:
    for t in goal.goal_tolerance:
        if t.name.startswith("double:"):
            _, how, tag = t.name.split(":", 2)
            return how, tag
    return "ok", ""


def main(ns: str) -> None:
    import rclpy
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionServer, CancelResponse, GoalResponse
    from rclpy.callback_groups import ReentrantCallbackGroup
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    rclpy.init()
    node = rclpy.create_node("fjt_double", namespace=ns)
    group = ReentrantCallbackGroup()
    events = node.create_publisher(String, "double_events", QoSProfile(
        depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    lock = threading.Lock()

    def say(goal, event: str) -> None:
        how, tag = behaviour(goal)
        with lock:
            events.publish(String(data=json.dumps({"tag": tag, "behaviour": how, "event": event})))

    js = node.create_publisher(JointState, "joint_states", 10)

    def publish_js() -> None:
        m = JointState(name=JOINTS, position=READY + [0.0, 0.0], velocity=[0.0] * 9)
        m.header.stamp = node.get_clock().now().to_msg()
        js.publish(m)

    node.create_timer(0.01, publish_js, callback_group=group)

    def on_goal(goal):
        say(goal, "received")
        how, _ = behaviour(goal)
        if how == "late":
            threading.Event().wait(2.5)  # the misbehaviour itself: a goal response 2.5 s late
        if how == "reject":
            say(goal, "rejected")
            return GoalResponse.REJECT
        say(goal, "accepted")
        return GoalResponse.ACCEPT

    def on_cancel(handle):
        say(handle.request, "cancel_requested")
        if behaviour(handle.request)[0] == "ignore_cancel":
            say(handle.request, "cancel_refused")
            return CancelResponse.REJECT
        return CancelResponse.ACCEPT

    def execute(handle):
        how, _ = behaviour(handle.request)
        run_s = {"ok": 0.3, "long": 8.0, "ignore_cancel": 8.0}.get(how, 3600.0)
        fb = FollowJointTrajectory.Feedback(joint_names=JOINTS[:7])
        tick = threading.Event()
        for _ in range(int(run_s * 20)):
            if handle.is_cancel_requested:
                handle.canceled()
                say(handle.request, "canceled")
                return FollowJointTrajectory.Result(error_code=0, error_string="cancelled by the double")
            if how != "silent":
                handle.publish_feedback(fb)
            tick.wait(0.05)  # the controller's 20 Hz monitor rate
        handle.succeed()
        say(handle.request, "succeeded")
        return FollowJointTrajectory.Result(error_code=0, error_string="done")

    ActionServer(node, FollowJointTrajectory, "controller/follow_joint_trajectory", execute_callback=execute,
                 goal_callback=on_goal, cancel_callback=on_cancel, callback_group=group)
    ex = MultiThreadedExecutor(num_threads=16)
    ex.add_node(node)
    try:
        ex.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass


if __name__ == "__main__":
    main(sys.argv[1])
