"""Every way a goal through the gate ends (dyn_node.gate.outcomes), across processes: a client
here, dyn_node's gate in a child process, and a controller double (test/fjt_double.py) that answers
late, stays silent, rejects and ignores cancels. For each path: the invariant (the controller's
goal ended or was cancelled; for the double that ignores cancels, the cancel was sent and
``downstream_cancel_unconfirmed`` recorded), the client's status and error string, the records.
Fail-closed: a deaf gate and stale joint_states forward nothing in reject mode. A flood: every
goal gets an answer. Each test sends its own goals, tagged; none depends on another's."""
from __future__ import annotations

import json
import sys
import threading
import time
import uuid

import pytest

from conftest import REPO, ChildProcess, Stepper, child_env, close_stack, js
from dyn_node.ros.fjt_client import steady
from test_gate import ARM, INFEASIBLE, READY, gate_cmd, move, moved

pytest.importorskip("control_msgs", reason="control_msgs not built into the venv (make)")

DOUBLE = "/dbl/controller/follow_joint_trajectory"
TIMEOUT = 1.0  # the gate's gate.timeout here
# the in-process gate's: closing lasts this long (the double ignores its cancel), long enough for a
# goal sent after close() began to arrive while it closes, on a loaded machine too
CLOSING_S = 5.0
GENTLE = move(READY, moved(0, 0.1), 1.5)
JOINTS9 = ARM + ["panda_finger_joint1", "panda_finger_joint2"]


class Observer:
    """The gates' records, the double's events and the deaf gate's diagnostics, collected here."""

    def __init__(self, ctx):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.node import Node
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String

        self.node = Node(f"observer_{uuid.uuid4().hex[:6]}", context=ctx)
        self.records: list[dict] = []
        self.events: list[dict] = []
        self.deaf_diag: list = []
        self.inverse: dict[str, list] = {"dbl": [], "deaf": []}
        reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        for topic in ("/dbl/gate/gate_decisions", "/deaf/gate_deaf/gate_decisions"):
            self.node.create_subscription(String, topic, lambda m: self.records.append(json.loads(m.data)), reliable)
        self.node.create_subscription(String, "/dbl/double_events", lambda m: self.events.append(json.loads(m.data)),
                                      QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                                                 durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.node.create_subscription(DiagnosticArray, "/deaf/diagnostics", self.deaf_diag.append, 50)
        self.node.create_subscription(JointState, "/dbl/gate/inverse_dynamics",  # receipt times
                                      lambda _m: self.inverse["dbl"].append(time.monotonic()), 10)
        self.node.create_subscription(JointState, "/deaf/gate_deaf/inverse_dynamics", self.inverse["deaf"].append, 10)
        self.deaf_js = self.node.create_publisher(JointState, "/deaf/joint_states", 10)
        self.steps = Stepper(ctx, (self.node,), step_s=0.02)

    def until(self, cond, timeout: float, what: str) -> None:
        if not self.steps.until(cond, timeout):
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")

    def of(self, tag: str, n: int = 0) -> list[str]:
        """The double's events for the goal tagged ``tag``, in order (once there are ``n``)."""
        got = lambda: [e["event"] for e in self.events if e["tag"] == tag]  # noqa: E731
        self.until(lambda: len(got()) >= n, 15.0, f"{n} events of the double's goal {tag}")
        return got()

    def decision(self, tag: str, timeout: float = 15.0) -> dict:
        found = lambda: [r for r in self.records if r["event"] == "decision"  # noqa: E731
                         and any(t[0].endswith(f":{tag}") for t in r["tolerances"]["goal"])]
        self.until(lambda: len(found()) == 1, timeout, f"the decision record of goal {tag}")
        return found()[0]

    def ends(self, goal_id: str) -> list[dict]:
        return [r for r in self.records if r["goal_id"] == goal_id and r["event"] != "decision"]

    def end(self, goal_id: str, event: str, timeout: float = 15.0) -> dict:
        self.until(lambda: any(r["event"] == event for r in self.ends(goal_id)), timeout, f"{event} of {goal_id}")
        return next(r for r in self.ends(goal_id) if r["event"] == event)

    def model_status(self, level: int) -> bool:
        return any(s.name == "dyn_node: model" and s.level == bytes([level]) for a in self.deaf_diag for s in a.status)

    def close(self) -> None:
        self.steps.close()


@pytest.fixture(scope="module")
def paths(module_ros_context):
    """The double in /dbl (it publishes /dbl/joint_states), a reject gate in front of it in /dbl, and
    a deaf one in /deaf (no joint_states there but the ones a test publishes)."""
    from dyn_node.ros.fjt_client import FjtClient

    common = ("robot_model:=panda", f"gate.controller_action:={DOUBLE}", f"gate.timeout:={TIMEOUT}")
    # the deaf gate keeps the default gate.max_state_age (0.1 s); the other one 0.5 s (gate_cmd)
    procs = [ChildProcess([sys.executable, str(REPO / "test" / "fjt_double.py"), "/dbl"], env=child_env()),
             ChildProcess(gate_cmd("gate", *common, "gate.max_pending:=20", ns="/dbl"), env=child_env()),
             ChildProcess(gate_cmd("gate_deaf", *common, "gate.max_state_age:=0.1", "diagnostics_period:=0.1",
                                   ns="/deaf")
                          + ["-r", "/diagnostics:=/deaf/diagnostics"], env=child_env())]
    clients = {k: FjtClient(module_ros_context, f"{ns}/follow_joint_trajectory", f"client_{k}")
               for k, ns in (("dbl", "/dbl/gate"), ("deaf", "/deaf/gate_deaf"))}
    obs = Observer(module_ros_context)
    try:
        for c in clients.values():
            c.wait_for_server(90.0)
        obs.until(lambda: steady(obs.inverse["dbl"], time.monotonic()), 90.0,
                  "the gate to keep up with the double's joint_states")
        obs.until(lambda: obs.model_status(0), 90.0, "the deaf gate's model")
        yield clients, obs, procs
    finally:
        close_stack([obs, *clients.values()], procs)


def tagged(how: str, spec: dict = GENTLE) -> tuple:
    """A goal the double treats as ``how``, and its tag."""
    from dyn_node.ros.fjt_client import goal

    tag = uuid.uuid4().hex[:10]
    return goal(**spec, names=ARM, goal_tolerance=[(f"double:{how}:{tag}", 0.0)]), tag


def _texts():
    from dyn_node.gate import outcomes

    return outcomes


def _aborted(client, g, what: str = ""):
    """Send ``g`` (accepted at its goal response) and return its result, which must be ABORTED
    with INVALID_GOAL."""
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    sent = client.send(g)
    assert sent.handle.accepted, what
    status, result = client.result(sent)
    assert (status, result.error_code) == (GoalStatus.STATUS_ABORTED, FollowJointTrajectory.Result.INVALID_GOAL), what
    return result


@pytest.mark.timeout(60)
def test_late_acceptance_is_cancelled_on_arrival(paths):
    from action_msgs.msg import GoalStatus

    out = _texts()
    clients, obs, _ = paths
    g, tag = tagged("late")
    result = _aborted(clients["dbl"], g)
    assert result.error_string == out.late_text(DOUBLE, TIMEOUT)
    rec = obs.decision(tag)
    assert (rec["decision"], rec["reason"], rec["checked_decision"], rec["forwarded"]) == (
        "not_forwarded", "downstream_late", "forwarded", None)
    assert obs.end(rec["goal_id"], "downstream_late")["status"] == GoalStatus.STATUS_ABORTED
    # the double accepted 2.5 s late; the gate cancelled that goal at once, and it ended
    late = obs.end(rec["goal_id"], "late_goal_cancelled", timeout=20.0)
    assert late["cancel"] == "confirmed"
    assert obs.of(tag, 4) == ["received", "accepted", "cancel_requested", "canceled"]


@pytest.mark.timeout(60)
def test_silent_controller_is_cancelled_then_the_goal_aborted(paths):
    from action_msgs.msg import GoalStatus

    out = _texts()
    clients, obs, _ = paths
    g, tag = tagged("silent")
    result = _aborted(clients["dbl"], g)
    assert result.error_string == out.silent_text(DOUBLE, TIMEOUT, True)
    # the client's goal ended only after the controller's: cancelled, confirmed
    assert obs.of(tag, 4) == ["received", "accepted", "cancel_requested", "canceled"]
    rec = obs.decision(tag)
    assert rec["decision"] == "forwarded"
    end = obs.end(rec["goal_id"], "downstream_silent")
    assert (end["status"], end["cancel"], end["error_string"]) == (GoalStatus.STATUS_ABORTED, "confirmed",
                                                                   result.error_string)
    assert end["elapsed_s"] >= TIMEOUT


@pytest.mark.timeout(60)
def test_controller_rejection_is_the_clients_and_recorded_not_forwarded(paths):
    clients, obs, _ = paths
    g, tag = tagged("reject")
    assert not clients["dbl"].send(g).handle.accepted
    rec = obs.decision(tag)
    assert (rec["decision"], rec["reason"], rec["checked_decision"]) == ("not_forwarded", "downstream_rejected",
                                                                         "forwarded")
    end = obs.end(rec["goal_id"], "downstream_rejected")
    assert (end["status"], end["cancel"]) == (None, None)
    assert obs.of(tag, 2) == ["received", "rejected"]


@pytest.mark.timeout(60)
def test_client_cancel_reaches_the_controller(paths):
    from action_msgs.msg import GoalStatus

    clients, obs, _ = paths
    g, tag = tagged("long")
    sent = clients["dbl"].send(g)
    assert sent.handle.accepted and sent.feedback_event.wait(10.0)
    assert len(clients["dbl"].cancel(sent).goals_canceling) == 1
    status, result = clients["dbl"].result(sent)
    assert (status, result.error_string) == (GoalStatus.STATUS_CANCELED, "cancelled by the double")
    assert obs.of(tag, 4) == ["received", "accepted", "cancel_requested", "canceled"]
    end = obs.end(obs.decision(tag)["goal_id"], "result")
    assert (end["status"], end["cancel"]) == (GoalStatus.STATUS_CANCELED, "confirmed")


@pytest.mark.timeout(60)
def test_ignored_cancel_is_recorded_unconfirmed(paths):
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    out = _texts()
    clients, obs, _ = paths
    g, tag = tagged("ignore_cancel")
    sent = clients["dbl"].send(g)
    assert sent.handle.accepted and sent.feedback_event.wait(10.0)
    clients["dbl"].cancel(sent)
    status, result = clients["dbl"].result(sent)
    assert (status, result.error_code) == (GoalStatus.STATUS_ABORTED, FollowJointTrajectory.Result.INVALID_GOAL)
    assert result.error_string == out.unconfirmed_text(DOUBLE, TIMEOUT, "client_cancel")
    assert obs.of(tag, 4) == ["received", "accepted", "cancel_requested", "cancel_refused"]
    end = obs.end(obs.decision(tag)["goal_id"], "downstream_cancel_unconfirmed")
    assert (end["cause"], end["cancel"], end["status"]) == ("client_cancel", "downstream_cancel_unconfirmed",
                                                            GoalStatus.STATUS_ABORTED)


@pytest.mark.timeout(60)
def test_gentle_goal_and_one_starting_ahead_are_forwarded(paths):
    from action_msgs.msg import GoalStatus

    clients, obs, _ = paths
    ahead = {k: v for k, v in GENTLE.items()}
    ahead["times"] = [t + 0.5 for t in GENTLE["times"]]  # the first point (READY) 0.5 s ahead
    for spec in (GENTLE, ahead):
        g, tag = tagged("ok", spec)
        sent = clients["dbl"].send(g)
        assert sent.handle.accepted
        status, result = clients["dbl"].result(sent)
        assert (status, result.error_string) == (GoalStatus.STATUS_SUCCEEDED, "done")
        rec = obs.decision(tag)
        assert (rec["decision"], rec["reason"], rec["feasible"]) == ("forwarded", "", True)
        assert 0.0 <= rec["start"]["age_s"] <= rec["max_state_age"] == 0.5
        assert obs.end(rec["goal_id"], "result")["status"] == GoalStatus.STATUS_SUCCEEDED
        assert obs.of(tag, 3) == ["received", "accepted", "succeeded"]


@pytest.mark.timeout(90)
def test_reject_forwards_no_start_jump_past_stamp_or_positions_only(paths):
    """Judged as the controller would execute them (the execution model, with the goal's stamp and
    its receipt): a first point due at once 0.15 rad from the robot, a goal stamped 0.4 s ago (the
    controller starts inside it, away from the robot) and positions-only points (linear segments,
    velocity steps) are refused in reject mode; the controller never hears of them."""
    from action_msgs.msg import GoalStatus
    from rclpy.clock import Clock
    from rclpy.duration import Duration

    clients, obs, _ = paths
    fast = move(READY, moved(0, 0.3), 1.5)
    cases = {
        "jump": (move(moved(1, 0.15), moved(1, 0.25), 1.5), None, "the first point is 0.15 rad from the robot"),
        "past": (fast, 0.4, "started "),
        "positions": ({"times": fast["times"], "points": fast["points"]}, None, "positions only: velocity steps"),
    }
    tags = []
    for name, (spec, ago, words) in cases.items():
        g, tag = tagged("ok", spec)
        tags.append(tag)
        if ago is not None:
            g.trajectory.header.stamp = (Clock().now() - Duration(seconds=ago)).to_msg()
        result = _aborted(clients["dbl"], g, name)
        rec = obs.decision(tag)
        assert (rec["decision"], rec["reason"], rec["feasible"], rec["forwarded"]) == ("rejected", "infeasible", False,
                                                                                       None), name
        assert words in rec["verdict"], (name, rec["verdict"])
        if ago is not None:  # judged from inside: the offset is the receipt's lag behind the stamp
            assert ago <= rec["judged"]["start_offset_s"] < ago + 0.5, rec["judged"]
            assert rec["timing"]["receipt_s"] - rec["timing"]["stamp_s"] == pytest.approx(rec["judged"]["start_offset_s"])
    # the same fast goal with a zero stamp starts at the robot's state: forwarded
    g, tag = tagged("ok", fast)
    assert clients["dbl"].result(clients["dbl"].send(g))[0] == GoalStatus.STATUS_SUCCEEDED
    assert obs.of(tag, 3) == ["received", "accepted", "succeeded"]
    assert [obs.of(t) for t in tags] == [[], [], []]


@pytest.mark.timeout(90)
def test_deaf_and_stale_gate_forwards_nothing(paths):
    """No joint_states at all, then one that has gone stale: refused, stale_state, state error;
    the controller never hears of the goals."""
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    clients, obs, _ = paths
    deaf = clients["deaf"]
    tags = []
    for stage in ("deaf", "stale"):
        if stage == "stale":  # one joint_states, then silence: wait until the node calls it STALE
            n = len(obs.inverse["deaf"])
            obs.deaf_js.publish(js(JOINTS9, READY + [0.0, 0.0], [0.0] * 9, stamp=1.0))
            obs.until(lambda: len(obs.inverse["deaf"]) > n, 10.0, "the deaf gate to take one joint_states")
            obs.deaf_diag.clear()
            levels = lambda: [s.level for a in obs.deaf_diag for s in a.status  # noqa: E731
                              if s.name == "dyn_node: joint_states"]
            fresh_then_stale = lambda: bytes([0]) in levels() and bytes([3]) in levels()[levels().index(bytes([0])):]  # noqa: E731
            obs.until(fresh_then_stale, 10.0, "joint_states OK, then STALE")
        g, tag = tagged("ok")
        tags.append(tag)
        sent = deaf.send(g)
        assert sent.handle.accepted
        status, result = deaf.result(sent)
        assert (status, result.error_code) == (GoalStatus.STATUS_ABORTED, FollowJointTrajectory.Result.INVALID_GOAL)
        assert result.error_string.startswith("rejected: stale_state: "), result.error_string
        rec = obs.decision(tag)
        assert (rec["decision"], rec["reason"], rec["failure_label"], rec["forwarded"]) == (
            "rejected", "stale_state", "state error", None)
        assert obs.end(rec["goal_id"], "refused")["error_string"] == result.error_string
    # the same goal through the gate that hears the double's joint_states reaches the double
    g, tag = tagged("ok")
    assert clients["dbl"].result(clients["dbl"].send(g))[0] == GoalStatus.STATUS_SUCCEEDED
    assert obs.of(tag, 3) == ["received", "accepted", "succeeded"]
    assert [obs.of(t) for t in tags] == [[], []]  # the double's events come in order: none for these


@pytest.mark.timeout(90)
def test_flood_every_goal_gets_an_answer(paths):
    """200 infeasible goals at 100 Hz from one client: each gets its goal response and its end,
    refused with the verdict or, when the check queue is full, as busy; none goes unanswered. The
    client keeps up to 1000 responses unread (rclpy's default keeps 10: a Python client busy
    sending 100 goals a second drops its own responses, whoever answers)."""
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionClient
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from dyn_node.ros.fjt_client import goal

    out = _texts()
    clients, obs, _ = paths
    deep = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    thread = clients["dbl"].thread
    action = ActionClient(thread.node, FollowJointTrajectory, "/dbl/gate/follow_joint_trajectory",
                          goal_service_qos_profile=deep, result_service_qos_profile=deep)
    assert action.wait_for_server(timeout_sec=30.0)
    n = 200
    g = goal(**INFEASIBLE, names=ARM)
    results: list = []
    done = threading.Event()
    lock = threading.Lock()

    def on_result(fut) -> None:
        with lock:
            results.append(fut.result())
            if len(results) == n:
                done.set()

    responses = []

    def on_response(fut) -> None:  # on the client's thread, as its requests must be
        responses.append(fut.result().accepted)
        fut.result().get_result_async().add_done_callback(on_result)

    sent = [0]

    def tick() -> None:
        if sent[0] < n:
            sent[0] += 1
            action.send_goal_async(g).add_done_callback(on_response)

    timer = thread.node.create_timer(0.01, tick)
    try:
        assert done.wait(60.0), f"{len(responses)} goal responses, {len(results)} results of {n} goals"
    finally:
        timer.cancel()
        thread.call(lambda: (thread.node.destroy_timer(timer), action.destroy()) and None, 10.0)
    assert sent[0] == n
    assert {(r.status, r.result.error_code) for r in results} == {
        (GoalStatus.STATUS_ABORTED, FollowJointTrajectory.Result.INVALID_GOAL)}
    refused = [r for r in results if "velocity" in r.result.error_string]
    busy = [r for r in results if r.result.error_string.startswith("dyn_node gate: busy, ")]
    assert len(refused) + len(busy) == n and len(refused) >= 20
    assert all(r.result.error_string == out.busy_text(20) for r in busy)  # the queue was full: 20 waiting


@pytest.mark.timeout(90)
def test_shutdown_cancels_the_running_goal_and_refuses_new_ones(paths, module_ros_context):
    """A gate in this process in front of the double: close() while a goal runs whose controller
    ignores cancels (so closing lasts gate.timeout): the goal is cancelled downstream, recorded
    unconfirmed (cause cancelled_on_shutdown); a goal arriving meanwhile is refused, never sent."""
    from types import SimpleNamespace

    import numpy as np
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory
    from rclpy.node import Node

    from dyn_node.core.check.feasibility import StartState
    from dyn_node.core.robot.model import load_model
    from dyn_node.core.robot.settings import Settings
    from dyn_node.ros.fjt_client import FjtClient, wait_future
    from dyn_node.ros.gate import Gate

    out = _texts()
    _, obs, _ = paths
    node = Node("gate_inproc", namespace="/inproc", context=module_ros_context)
    core = SimpleNamespace(model=load_model(builtin="panda"), settings=Settings())
    records: list[dict] = []
    state = lambda: (core, StartState(np.array(READY), np.zeros(7), 0.0))  # noqa: E731
    params = {"gate.controller_action": DOUBLE, "gate.mode": "reject", "gate.retime_all": False,
              "gate.timeout": CLOSING_S, "gate.max_state_age": 0.1, "gate.start_tolerance": 0.01, "gate.max_pending": 5}
    gate = Gate(node, params, state, lambda _pub, msg: records.append(json.loads(msg.data)))
    client = FjtClient(module_ros_context, "/inproc/gate_inproc/follow_joint_trajectory", "client_inproc")
    closer = threading.Thread(target=gate.close)
    try:
        client.wait_for_server(30.0)
        g, tag = tagged("ignore_cancel")
        running = client.send(g)
        assert running.handle.accepted and running.feedback_event.wait(10.0)
        # its result asked for now, as a client does at once: the server goes with the gate
        result_of_running = client.thread.call(running.handle.get_result_async, 10.0)
        closer.start()
        obs.until(lambda: gate._closing, 5.0, "close() to begin")
        late, late_tag = tagged("ok")
        refused = client.send(late)
        assert refused.handle.accepted
        status, result = client.result(refused)
        assert (status, result.error_code, result.error_string) == (
            GoalStatus.STATUS_ABORTED, FollowJointTrajectory.Result.INVALID_GOAL, out.closing_text())
        got = wait_future(result_of_running, 30.0, "the running goal's result")
        status, result = got.status, got.result
        assert (status, result.error_string) == (GoalStatus.STATUS_ABORTED,
                                                 out.unconfirmed_text(DOUBLE, CLOSING_S, "cancelled_on_shutdown"))
        closer.join(10.0)
        assert not closer.is_alive()
        assert obs.of(tag, 4) == ["received", "accepted", "cancel_requested", "cancel_refused"]
        ends = {r["event"]: r for r in records if r["event"] != "decision"}
        assert (ends["downstream_cancel_unconfirmed"]["cause"], ends["refused_closing"]["status"]) == (
            "cancelled_on_shutdown", GoalStatus.STATUS_ABORTED)
        decisions = [(r["decision"], r["reason"]) for r in records if r["event"] == "decision"]
        assert decisions == [("forwarded", ""), ("not_forwarded", "refused_closing")]
        assert obs.of(late_tag) == []  # the double's events come in order: it never heard of it
    finally:
        client.close()
        if not closer.is_alive() and not closer.ident:
            gate.close()
        node.destroy_node()


@pytest.mark.timeout(90)
def test_idle_gate_decides_in_the_goal_callback_and_a_long_goal_on_the_check_thread(paths, module_ros_context):
    """A gate in this process in front of the double: a goal reaching an idle gate is checked on
    the gate's executor thread, in its goal callback (no crossing to the check thread and back);
    one of more than INLINE_MAX_POINTS points, or lasting more than INLINE_MAX_DURATION_S, is
    checked on the check thread. All forwarded."""
    from types import SimpleNamespace

    import numpy as np
    from action_msgs.msg import GoalStatus
    from rclpy.node import Node

    from dyn_node.core.check.feasibility import StartState
    from dyn_node.core.robot.model import load_model
    from dyn_node.core.robot.settings import Settings
    from dyn_node.ros.fjt_client import FjtClient, goal, quintic
    from dyn_node.ros.gate import INLINE_MAX_DURATION_S, INLINE_MAX_POINTS, Gate

    node = Node("gate_inline", namespace="/inline", context=module_ros_context)
    core = SimpleNamespace(model=load_model(builtin="panda"), settings=Settings())
    threads: list[str] = []

    def state():
        threads.append(threading.current_thread().name)
        return core, StartState(np.array(READY), np.zeros(7), 0.0)

    records: list[dict] = []
    params = {"gate.controller_action": DOUBLE, "gate.mode": "reject", "gate.retime_all": False,
              "gate.timeout": 10.0, "gate.max_state_age": 0.1, "gate.start_tolerance": 0.01, "gate.max_pending": 5}
    gate = Gate(node, params, state, lambda _pub, msg: records.append(json.loads(msg.data)))
    client = FjtClient(module_ros_context, "/inline/gate_inline/follow_joint_trajectory", "client_inline")
    try:
        client.wait_for_server(30.0)
        short, _ = tagged("ok")
        long_goal = goal(**quintic(READY, moved(0, 0.1), 3.0, INLINE_MAX_POINTS + 1), names=ARM,
                         goal_tolerance=[(f"double:ok:{uuid.uuid4().hex[:10]}", 0.0)])
        # two points lasting longer than INLINE_MAX_DURATION_S: a long check too (samples)
        slow_goal = goal(**quintic(READY, moved(0, 0.1), INLINE_MAX_DURATION_S + 1.0, 2), names=ARM,
                         goal_tolerance=[(f"double:ok:{uuid.uuid4().hex[:10]}", 0.0)])
        for g in (short, long_goal, slow_goal):
            assert client.result(client.send(g))[0] == GoalStatus.STATUS_SUCCEEDED
        assert threads == ["dyn_node gate", "dyn_node gate check", "dyn_node gate check"]
        assert [r["decision"] for r in records if r["event"] == "decision"] == ["forwarded"] * 3
    finally:
        client.close()
        gate.close()
        node.destroy_node()
