"""A FollowJointTrajectory client as MoveIt's controller handler uses one: send a goal, collect
its feedback, wait for the goal response and the result (waits on futures, never sleeps). Used
by the gate demo, the gate bench and the tests."""
from __future__ import annotations

import bisect
import threading
from dataclasses import dataclass, field
from typing import Any, Sequence


#: How long a gate's per-sample output (``~/inverse_dynamics``, one per joint_states it takes) must
#: have flowed with no gap over :data:`STEADY_GAP_S` before a client that just started the gate
#: sends goals: the gate refuses goals whose joint_states are older than ``gate.max_state_age``
#: (0.1 s), and its own start (model, question worker) can starve it for a few hundred ms on a
#: small machine (measured: 246–281 ms, 2 cores, a fresh clone's first run).
STEADY_S = 1.0
STEADY_GAP_S = 0.08


def steady(receipts: Sequence[float], now: float, *, window: float = STEADY_S,
           max_gap: float = STEADY_GAP_S) -> bool:
    """True when the receipt times ``receipts`` (monotonic, ascending) cover the ``window`` s up
    to ``now`` with no gap over ``max_gap`` s, the one since the last receipt included."""
    first = bisect.bisect_right(receipts, now - window) - 1
    if first < 0 or now - receipts[-1] > max_gap:
        return False
    recent = receipts[first:]
    return all(b - a <= max_gap for a, b in zip(recent, recent[1:]))


def duration(t: float) -> Any:
    from dyn_node.ros.convert import s_to_duration  # the one rounding rule

    return s_to_duration(t)


def goal(times: Sequence[float], points: Sequence[Sequence[float]], *, names: Sequence[str],
         velocities: Sequence[Sequence[float]] | None = None,
         accelerations: Sequence[Sequence[float]] | None = None,
         path_tolerance: Sequence[tuple[str, float]] = (), goal_tolerance: Sequence[tuple[str, float]] = (),
         goal_time: float = 0.0) -> Any:
    """A FollowJointTrajectory goal (zero stamp: start on receipt); tolerances as (joint, position)."""
    from control_msgs.action import FollowJointTrajectory
    from control_msgs.msg import JointTolerance
    from trajectory_msgs.msg import JointTrajectoryPoint

    g = FollowJointTrajectory.Goal()
    g.trajectory.joint_names = list(names)
    for i, (t, q) in enumerate(zip(times, points)):
        p = JointTrajectoryPoint(positions=[float(x) for x in q], time_from_start=duration(t))
        if velocities is not None:
            p.velocities = [float(x) for x in velocities[i]]
        if accelerations is not None:
            p.accelerations = [float(x) for x in accelerations[i]]
        g.trajectory.points.append(p)
    g.path_tolerance = [JointTolerance(name=n, position=float(x)) for n, x in path_tolerance]
    g.goal_tolerance = [JointTolerance(name=n, position=float(x)) for n, x in goal_tolerance]
    g.goal_time_tolerance = duration(goal_time)
    return g


def quintic(q0: Sequence[float], q1: Sequence[float], duration_s: float, n: int = 11) -> dict[str, Any]:
    """A rest-to-rest quintic move as a planner would time it: ``n`` points from t = 0 (q0) to
    ``duration_s`` (q1) with positions, velocities and accelerations (keywords of :func:`goal`)."""
    import numpy as np

    s = np.linspace(0.0, 1.0, n)
    dq = np.asarray(q1, dtype=float) - np.asarray(q0, dtype=float)
    pos = 10 * s**3 - 15 * s**4 + 6 * s**5
    vel = (30 * s**2 - 60 * s**3 + 30 * s**4) / duration_s
    acc = (60 * s - 180 * s**2 + 120 * s**3) / duration_s**2
    return {"times": (s * duration_s).tolist(), "points": (np.asarray(q0) + np.outer(pos, dq)).tolist(),
            "velocities": np.outer(vel, dq).tolist(), "accelerations": np.outer(acc, dq).tolist()}


def wait_future(fut: Any, timeout: float, what: str) -> Any:
    done = threading.Event()
    fut.add_done_callback(lambda _f: done.set())
    if not done.wait(timeout):
        raise AssertionError(f"timed out after {timeout} s waiting for {what}")
    return fut.result()


@dataclass
class Sent:
    """One goal sent: its handle (None until answered), feedback received, and the result."""

    handle: Any = None
    feedback: list = field(default_factory=list)
    feedback_event: threading.Event = field(default_factory=threading.Event)


class ClientThread:
    """A FollowJointTrajectory ActionClient on a node and a thread of its own, every request sent
    from that thread. rclpy (Jazzy) registers a request's future only after sending it, so a
    response taken by another thread in between is dropped ("Ignoring unexpected result
    response") and its future never completes: requests and responses must share one thread."""

    def __init__(self, ctx: Any, action: str, node_name: str, *, namespace: str = "",
                 use_global_arguments: bool = True):
        from control_msgs.action import FollowJointTrajectory
        from rclpy.action import ActionClient
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self.node = Node(node_name, context=ctx, namespace=namespace or None,
                         use_global_arguments=use_global_arguments, enable_rosout=False,
                         start_parameter_services=False)
        self.client = ActionClient(self.node, FollowJointTrajectory, action)
        self.action = action
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=f"{node_name} client", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.ex.context.ok():
            self.ex.spin_once(timeout_sec=0.1)

    def call(self, request: Any, timeout: float) -> Any:
        """Run ``request()`` (it returns an rclpy Future) on the client's thread; that Future, or
        None when the thread did not get to it within ``timeout`` s."""
        task = self.ex.create_task(request)
        done = threading.Event()
        task.add_done_callback(lambda _t: done.set())
        if not done.wait(timeout):
            task.cancel()
            return None
        return task.result()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10.0)
        self.client.destroy()
        self.ex.shutdown(timeout_sec=5.0)
        self.node.destroy_node()


class FjtClient:
    """A client as a planner uses one: send, wait for the goal response, the result, cancel."""

    def __init__(self, ctx: Any, action: str, node_name: str = "fjt_client"):
        self.thread = ClientThread(ctx, action, node_name)
        self.client = self.thread.client

    def wait_for_server(self, timeout: float = 30.0) -> None:
        if not self.client.wait_for_server(timeout_sec=timeout):
            raise AssertionError(f"no action server {self.thread.action} within {timeout} s")

    def _call(self, request: Any, timeout: float, what: str) -> Any:
        fut = self.thread.call(request, timeout)
        if fut is None:
            raise AssertionError(f"timed out after {timeout} s sending {what}")
        return wait_future(fut, timeout, what)

    def send(self, g: Any, timeout: float = 15.0) -> Sent:
        """Send ``g`` and wait for the goal response; ``sent.handle.accepted`` says which."""
        sent = Sent()

        def on_feedback(msg: Any) -> None:
            sent.feedback.append(msg.feedback)
            sent.feedback_event.set()

        sent.handle = self._call(lambda: self.client.send_goal_async(g, feedback_callback=on_feedback),
                                 timeout, "the goal response")
        return sent

    def result(self, sent: Sent, timeout: float = 30.0) -> tuple[int, Any]:
        """(terminal GoalStatus, FollowJointTrajectory.Result) of an accepted goal."""
        res = self._call(sent.handle.get_result_async, timeout, "the goal's result")
        return res.status, res.result

    def cancel(self, sent: Sent, timeout: float = 10.0) -> Any:
        return self._call(sent.handle.cancel_goal_async, timeout, "the cancel response")

    def close(self) -> None:
        self.thread.close()
