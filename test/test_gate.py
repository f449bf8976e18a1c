"""The FollowJointTrajectory gate across processes: a client here (as MoveIt's), dyn_node with the
gate in a child process, dyn_sim as the controller in another. Every decision path and error
code, feedback relayed, cancel and pre-emption, downstream absent and crashing."""
from __future__ import annotations

import json
import time
import signal

import numpy as np
import pytest

from conftest import Stepper, close_stack, kv, python_cmd
from service_event_counts import gate_goal_counts, gate_records
from test_sim_action import ARM, READY, moved
from test_sim_action import sim_cmd as sim_action_cmd

pytest.importorskip("control_msgs", reason="control_msgs not built into the venv (make)")

FINGERS = "panda_finger_joint1,panda_finger_joint2"
JTC = "/joint_trajectory_controller/follow_joint_trajectory"


def sim_cmd(*extra: str) -> list[str]:
    return sim_action_cmd("constraints.goal_time:=2.0") + list(extra)


def gate_cmd(name: str, *params: str, ns: str = "/") -> list[str]:
    """dyn_node with a gate; ``gate.max_state_age`` 0.5 s unless given: a dyn_sim starved of CPU on
    a loaded machine delivers joint_states late, and these tests are not about their freshness
    (test_gate_outcomes is, with the default)."""
    if not any(p.startswith("gate.max_state_age:=") for p in params):
        params = (*params, "gate.max_state_age:=0.5")
    args = ["--ros-args", "-r", f"__node:={name}", "-r", f"__ns:={ns}", "-p", f"locked_joints:={FINGERS}"]
    for p in params:
        args += ["-p", p]
    return python_cmd("dyn_node.ros.node", *args)


def move(q0, q1, duration_s: float) -> dict:
    from dyn_node.ros.fjt_client import quintic

    return quintic(q0, q1, duration_s)


FEASIBLE = move(READY, moved(0, 0.2), 1.5)     # 0.2 rad in 1.5 s
INFEASIBLE = move(READY, moved(0, 0.5), 0.15)  # 0.5 rad in 0.15 s: ~3× joint 1's speed limit
# back to READY from wherever the robot is: its first point 1 s ahead, so the controller runs a
# segment from the robot's state to it (a first point due at once would be a jump, refused)
HOME = {**move(READY, READY, 1.0), "times": [t + 1.0 for t in move(READY, READY, 1.0)["times"]]}


class Probe:
    """Decisions on ~/gate_decisions, /diagnostics and joint_states, collected here."""

    def __init__(self, ctx, gate: str, ready: tuple[str, ...] = (), ns: str = ""):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String

        self.node = Node(f"probe_{gate}", context=ctx)
        self.records: list[dict] = []
        self.gate_status: list = []
        self.js: list = []
        # stamps (s) of js and state, taken at receipt: a wait's condition counts the newest
        # without scanning every message of the module (a Stepper spins one callback per check)
        self.js_t: list[float] = []
        self.state_t: list[float] = []
        self.inverse: dict[str, list[float]] = {g: [] for g in ready}  # receipt times
        self.node.create_subscription(String, f"{ns}/{gate}/gate_decisions", self._on_record,
                                      QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 50)
        from diagnostic_msgs.msg import DiagnosticStatus

        self.ctrl: list = []  # the gate node's ~/controller_status: it tracks what it forwarded
        self.node.create_subscription(DiagnosticStatus, f"{ns}/{gate}/controller_status", self.ctrl.append, 100)
        self.node.create_subscription(JointState, f"{ns}/joint_states",
                                      lambda m: self._keep(m, self.js, self.js_t), 1000)
        from control_msgs.msg import JointTrajectoryControllerState

        self.state: list = []  # the controller's reference: it changes only with a new trajectory
        self.node.create_subscription(JointTrajectoryControllerState,
                                      f"{ns}/joint_trajectory_controller/controller_state",
                                      lambda m: self._keep(m, self.state, self.state_t), 100)
        # a gate checks from the robot's state: ready once it computes torques from joint_states
        for g in ready:
            self.node.create_subscription(JointState, f"{ns}/{g}/inverse_dynamics",
                                          lambda _m, xs=self.inverse[g]: xs.append(time.monotonic()), 10)
        self.steps = Stepper(ctx, (self.node,), step_s=0.02)

    @staticmethod
    def _keep(msg, msgs: list, stamps: list[float]) -> None:
        msgs.append(msg)
        stamps.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)

    @staticmethod
    def count_since(stamps: list[float], t: float) -> int:
        """How many of the newest ``stamps`` (in arrival order, ascending) are at or after ``t``."""
        n = 0
        for x in reversed(stamps):
            if x < t:
                break
            n += 1
        return n

    def _on_record(self, msg) -> None:
        self.records.append(json.loads(msg.data))

    def _on_diag(self, msg) -> None:
        self.gate_status += [s for s in msg.status if s.name == "dyn_node: gate"]

    def wait_ready(self, timeout: float = 90.0) -> None:
        from dyn_node.ros.fjt_client import steady

        self.until(lambda: all(steady(v, time.monotonic()) for v in self.inverse.values()), timeout,
                   f"{', '.join(self.inverse)} to load the model and keep up with joint_states")

    def until(self, cond, timeout: float, what: str) -> None:
        if not self.steps.until(cond, timeout):
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")

    def record(self, goal_id_event: str, n: int, timeout: float = 15.0) -> dict:
        self.until(lambda: len([r for r in self.records if r["event"] == goal_id_event]) >= n, timeout,
                   f"{n} {goal_id_event} record(s)")
        return [r for r in self.records if r["event"] == goal_id_event][n - 1]

    def decision_of(self, spec: dict, timeout: float = 15.0) -> dict:
        """The decision record of the goal with ``spec``'s points: found by content, as records
        come after the goal response and may arrive after a later goal was sent."""
        found = lambda: [r for r in self.records if r["event"] == "decision"  # noqa: E731
                         and (r.get("goal") or {}).get("positions") == spec["points"]]
        self.until(lambda: len(found()) == 1, timeout, "the goal's decision record")
        return found()[0]

    def close(self) -> None:
        self.steps.close()


def _counting_client():
    from dyn_node.ros.fjt_client import FjtClient

    class Counting(FjtClient):
        """Counts the goals it sends (each one gets a decision record from the gate)."""

        goals_sent = 0

        def send(self, g, timeout: float = 15.0):
            self.goals_sent += 1
            return super().send(g, timeout)

    return Counting


@pytest.fixture(scope="module")
def stack(module_ros_context, tmp_path_factory):
    """dyn_sim, a gate in reject mode and one in check mode, both in front of dyn_sim."""
    from conftest import ChildProcess, child_env

    CountingClient = _counting_client()
    bags = tmp_path_factory.mktemp("gate_bags")
    procs = [ChildProcess(sim_cmd(), env=child_env()),
             ChildProcess(gate_cmd("gate_reject", f"gate.controller_action:={JTC}", "record.enabled:=true",
                                   f"record.directory:={bags}"), env=child_env()),
             ChildProcess(gate_cmd("gate_check", f"gate.controller_action:={JTC}", "gate.mode:=check"),
                          env=child_env())]
    clients = {m: CountingClient(module_ros_context, f"/gate_{m}/follow_joint_trajectory", f"client_{m}")
               for m in ("reject", "check")}
    probe = Probe(module_ros_context, "gate_reject", ready=("gate_reject", "gate_check"))
    try:
        for c in clients.values():
            c.wait_for_server(90.0)
        probe.wait_ready()
        yield clients, probe, procs, bags
    finally:
        close_stack([probe, *clients.values()], procs)


def _goal(spec: dict, **kw):
    from dyn_node.ros.fjt_client import goal

    return goal(**spec, names=ARM, **kw)


@pytest.fixture(autouse=True)
def _at_ready(request):
    """Every test on the stack starts with dyn_sim at READY (a test may leave it elsewhere, and a
    goal whose first point, due at once, lies away from the robot is a jump the gate refuses):
    the order of the tests does not matter."""
    if "stack" in request.fixturenames:
        from action_msgs.msg import GoalStatus

        client = request.getfixturevalue("stack")[0]["reject"]
        assert client.result(client.send(_goal(HOME)))[0] == GoalStatus.STATUS_SUCCEEDED
    yield


@pytest.mark.timeout(120)
def test_feasible_goal_forwarded_with_feedback_and_result(stack):
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    clients, probe, *_ = stack
    client = clients["reject"]
    n_ctrl = len(probe.ctrl)
    sent = client.send(_goal(FEASIBLE))
    assert sent.handle.accepted
    status, result = client.result(sent)
    # ~/controller_status follows the forwarded goal as it follows a topic trajectory
    probe.until(lambda: any(kv(m)["state"] == "tracking" for m in probe.ctrl[n_ctrl:]), 10.0,
                "~/controller_status to track the forwarded goal")
    assert (status, result.error_code, result.error_string) == (
        GoalStatus.STATUS_SUCCEEDED, FollowJointTrajectory.Result.SUCCESSFUL, "Goal successfully reached!")
    # dyn_sim's 20 Hz feedback relayed: its joint order, desired − actual = error
    assert len(sent.feedback) >= 10
    f = sent.feedback[-1]
    assert list(f.joint_names) == ARM
    np.testing.assert_allclose(np.array(f.desired.positions) - np.array(f.actual.positions),
                               f.error.positions, atol=1e-12)
    rec = probe.decision_of(FEASIBLE)
    assert (rec["decision"], rec["feasible"], rec["reason"], rec["mode"]) == ("forwarded", True, "", "reject")
    assert rec["forwarded"]["joint_names"] == ARM
    assert rec["forwarded"]["positions"] == FEASIBLE["points"]  # unchanged
    ends = lambda: [r for r in probe.records if r["event"] == "result" and r["goal_id"] == rec["goal_id"]]  # noqa: E731
    probe.until(lambda: bool(ends()), 15.0, "the goal's result record")
    assert [(r["status"], r["error_code"]) for r in ends()] == [(GoalStatus.STATUS_SUCCEEDED, 0)]


@pytest.mark.timeout(120)
def test_infeasible_goal_rejected_with_the_verdict_and_sim_never_moves(stack):
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    from dyn_node.core.check import feasibility
    from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
    from dyn_node.core.robot.model import load_model
    from dyn_node.core.robot.settings import Settings
    from dyn_node.core.check.trajectory import validate_trajectory

    clients, probe, *_ = stack
    client = clients["reject"]
    # from READY, where the goal starts (the last test left the robot 0.2 rad away: a jump)
    assert client.result(client.send(_goal(HOME)))[0] == GoalStatus.STATUS_SUCCEEDED
    g = _goal(INFEASIBLE)
    # on the states' own clock (wall-clock start + simulation time: never ahead of the wall
    # clock), so HOME's success was stamped before this instant; the probe's own delivery may lag
    # under load (CI: states from before HOME's end were taken as "after"), so it waits for them
    t_sent = time.time()
    probe.until(lambda: probe.count_since(probe.js_t, t_sent) > 0, 20.0,
                "joint_states stamped after HOME's result")
    sent = client.send(g)
    assert sent.handle.accepted  # accepted, then ended at once: the string reaches MoveIt
    status, result = client.result(sent)
    assert (status, result.error_code) == (GoalStatus.STATUS_ABORTED, FollowJointTrajectory.Result.INVALID_GOAL)
    # the verdict line of the core's check of the same trajectory (first point at t = 0 where
    # the robot rests, within start_tolerance: no start segment, no jump, so the verdict is the
    # one without a state)
    model = load_model(builtin="panda")
    times = [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in g.trajectory.points]
    traj = validate_trajectory(model.joint_names, ARM, times, INFEASIBLE["points"],
                               INFEASIBLE["velocities"], INFEASIBLE["accelerations"])
    node = Settings()  # the node's defaults: friction included, its sample period
    verdict = feasibility.check_trajectory(
        Dynamics(model, DynamicsOptions(include_friction=node.include_friction)), traj,
        feasibility.FeasibilityOptions(sample_period=node.sample_period, effort_warn_ratio=node.effort_warn_ratio))
    assert not verdict.feasible and result.error_string == verdict.message
    assert "velocity" in result.error_string and "slower" in result.error_string
    assert sent.feedback == []
    rec = probe.decision_of(INFEASIBLE)
    assert (rec["decision"], rec["reason"], rec["forwarded"]) == ("rejected", "infeasible", None)
    assert rec["time_scale"] == pytest.approx(verdict.time_scale, rel=1e-12)
    # dyn_sim never moved: from the goal on (stamps are wall-clock start + simulation time) the
    # controller's reference stays exactly where it held, for 1 s, and the joints within 1 mrad
    # (the last goal's settling) of where they were, not 0.5 rad away
    after = lambda xs: [m for m in xs if m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 >= t_sent]  # noqa: E731
    probe.until(lambda: probe.count_since(probe.js_t, t_sent) > 500 and probe.count_since(probe.state_t, t_sent) > 50,
                20.0, "1 s of states")
    ref = np.array([m.reference.positions for m in after(probe.state)])
    assert np.array_equal(ref, np.repeat(ref[:1], len(ref), axis=0))
    q = np.array([m.position[:7] for m in after(probe.js)])
    assert np.abs(q - q[0]).max() < 1e-3


@pytest.mark.timeout(120)
def test_malformed_goals_rejected_with_the_reason(stack):
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    client = stack[0]["reject"]
    nan = moved(0, float("nan"))
    from dyn_node.ros.fjt_client import goal

    cases = [(goal([0.5, 1.0], [READY, nan], names=ARM), "rejected: point 1: positions of panda_joint1 is nan"),
             (goal([1.0], [READY], names=ARM), "rejected: trajectory has 1 point(s); at least 2 are needed"),
             (goal([0.5, 1.0], [READY, READY], names=ARM[:6] + ["elbow"]),
              "rejected: joints not in the model: elbow")]
    for g, text in cases:
        sent = client.send(g)
        status, result = client.result(sent)
        assert (status, result.error_code) == (GoalStatus.STATUS_ABORTED, FollowJointTrajectory.Result.INVALID_GOAL)
        assert result.error_string.startswith(text), result.error_string


@pytest.mark.timeout(120)
def test_controller_results_pass_through_unchanged(stack):
    """The controller's goal rejection (non-zero end velocity, which the check allows) and its
    PATH_TOLERANCE_VIOLATED come back to the client as the controller sent them."""
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    client = stack[0]["reject"]
    from dyn_node.ros.fjt_client import goal

    g = goal([0.0, 1.0], [READY, moved(0, 0.1)], names=ARM, velocities=[[0.0] * 7, [0.01] + [0.0] * 6])
    assert not client.send(g).handle.accepted
    sent = client.send(_goal(move(READY, moved(3, 0.2), 0.6), path_tolerance=[("panda_joint4", 1e-6)]))
    status, result = client.result(sent)
    assert (status, result.error_code, result.error_string) == (
        GoalStatus.STATUS_ABORTED, FollowJointTrajectory.Result.PATH_TOLERANCE_VIOLATED,
        "Aborted due to path tolerance violation")
    # back to READY for the next tests
    assert client.result(client.send(_goal(HOME)))[0] == GoalStatus.STATUS_SUCCEEDED


@pytest.mark.timeout(120)
def test_cancel_and_preemption_through_the_gate(stack):
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    client = stack[0]["reject"]
    first = client.send(_goal(move(READY, moved(0, 0.3), 4.0)))
    assert first.feedback_event.wait(15.0)
    second = client.send(_goal(HOME))
    status, result = client.result(first)
    assert (status, result.error_code, result.error_string) == (
        GoalStatus.STATUS_CANCELED, FollowJointTrajectory.Result.INVALID_GOAL,
        "Current goal cancelled due to new incoming action.")
    assert client.result(second)[0] == GoalStatus.STATUS_SUCCEEDED
    third = client.send(_goal(move(READY, moved(0, 0.3), 4.0)))
    assert third.feedback_event.wait(15.0)
    assert len(client.cancel(third).goals_canceling) == 1
    assert client.result(third)[0] == GoalStatus.STATUS_CANCELED
    assert client.result(client.send(_goal(HOME)))[0] == GoalStatus.STATUS_SUCCEEDED


@pytest.mark.timeout(120)
def test_check_mode_forwards_an_infeasible_goal(stack):
    from action_msgs.msg import GoalStatus

    from diagnostic_msgs.msg import DiagnosticArray

    from dyn_node.ros.node import FEASIBILITY_QOS

    clients, probe, *_ = stack
    verdicts: list = []  # check mode says what it let through: the verdict on ~/feasibility
    probe.node.create_subscription(DiagnosticArray, "/gate_check/feasibility", verdicts.append, FEASIBILITY_QOS)
    sent = clients["check"].send(_goal(INFEASIBLE))
    assert sent.handle.accepted
    status, _ = clients["check"].result(sent)
    assert status == GoalStatus.STATUS_SUCCEEDED  # dyn_sim limits effort only: it ran, too fast
    assert len(sent.feedback) >= 1
    infeasible = lambda: [a for a in verdicts if a.status[0].message.startswith("infeasible: ")  # noqa: E731
                          and kv(a.status[0]).get("request") == "execute"]
    probe.until(lambda: bool(infeasible()), 15.0, "the forwarded goal's verdict on ~/feasibility")
    assert "velocity" in infeasible()[-1].status[0].message
    warned = lambda: [st for st in probe.gate_status if kv(st).get("mode") == "check"  # noqa: E731
                      and int(kv(st)["forwarded_unchecked"]) >= 1]
    probe.until(lambda: bool(warned()), 20.0, "the check gate's status to count it")
    assert clients["check"].result(clients["check"].send(_goal(HOME)))[0] == GoalStatus.STATUS_SUCCEEDED


@pytest.mark.timeout(60)
def test_gate_status_counts(stack):
    """dyn_node: gate counts what ~/gate_decisions recorded (both delivered late by DDS here, so
    wait until they agree) and names the last decision. Its own goals: 4 rejected, 4 forwarded
    (whatever other tests sent before, the counts and the records agree)."""
    from action_msgs.msg import GoalStatus

    clients, probe, *_ = stack
    client = clients["reject"]
    for i in range(4):
        client.result(client.send(_goal(move(READY, moved(i, 0.5 + 0.01 * i), 0.15))))
    for i in range(2):  # out and back, each checked and forwarded
        assert client.result(client.send(_goal(move(READY, moved(2, 0.1 + 0.01 * i), 0.8))))[0] == \
            GoalStatus.STATUS_SUCCEEDED
        assert client.result(client.send(_goal(HOME)))[0] == GoalStatus.STATUS_SUCCEEDED

    def agree() -> bool:
        st = [s for s in probe.gate_status if kv(s).get("mode") == "reject"]
        decisions = [r for r in probe.records if r["event"] == "decision"]
        if not st or len(decisions) < 8:
            return False
        v = kv(st[-1])
        return (int(v["forwarded"]), int(v["rejected"]), v["last_decision"].split(":")[0]) == (
            sum(r["decision"] == "forwarded" for r in decisions),
            sum(r["decision"] == "rejected" for r in decisions), decisions[-1]["decision"])

    probe.until(agree, 20.0, "the gate status to count the recorded decisions")
    v = kv([s for s in probe.gate_status if kv(s).get("mode") == "reject"][-1])
    assert int(v["rejected"]) >= 4 and int(v["forwarded"]) >= 4 and int(v["retimed"]) == 0


@pytest.mark.timeout(180)
def test_audit_replays_the_gate_decisions_identically(stack, module_ros_context, spawn, tmp_path):
    """A recording gate of its own in front of dyn_sim, sent goals forwarded, rejected and refused
    by the controller; stopped to close its bag: dyn-audit decides every recorded goal again,
    identically, and lists the decisions."""
    from dyn_node.audit.bag_audit import AuditOptions, run_audit
    from dyn_node.ros.fjt_client import goal

    bags = tmp_path / "bags"
    gate = spawn(gate_cmd("gate_rec", f"gate.controller_action:={JTC}", "record.enabled:=true",
                          f"record.directory:={bags}"))
    client = _counting_client()(module_ros_context, "/gate_rec/follow_joint_trajectory", "client_rec")
    probe = Probe(module_ros_context, "gate_rec", ready=("gate_rec",))
    try:
        client.wait_for_server(90.0)
        probe.wait_ready()
        _audited_goals(client, goal)
        # one decision record per goal sent, published off the goal's path (and 47 kB each, which
        # DDS may deliver late on a busy machine): wait for all of them before the gate stops
        sent = client.goals_sent
        probe.until(lambda: len([r for r in probe.records if r["event"] == "decision"]) == sent >= 8, 20.0,
                    f"a decision record for each of the {sent} goals sent")
        rc, _, err = gate.stop(signal.SIGINT)
        assert rc == 0, err[-2000:]
        _audit_agrees(probe, bags, run_audit, AuditOptions)
    finally:
        probe.close()
        client.close()


def _audited_goals(client, goal) -> None:
    """2 forwarded (out and back), 5 rejected (2 infeasible, 3 malformed), 1 refused by dyn_sim."""
    from action_msgs.msg import GoalStatus

    assert client.result(client.send(_goal(move(READY, moved(1, 0.15), 1.0))))[0] == GoalStatus.STATUS_SUCCEEDED
    assert client.result(client.send(_goal(HOME)))[0] == GoalStatus.STATUS_SUCCEEDED
    for g in (_goal(INFEASIBLE), _goal(move(READY, moved(0, -0.5), 0.15)),
              goal([0.5, 1.0], [READY, moved(0, float("nan"))], names=ARM), goal([1.0], [READY], names=ARM),
              goal([0.5, 1.0], [READY, READY], names=ARM[:6] + ["elbow"])):
        assert client.result(client.send(g))[0] == GoalStatus.STATUS_ABORTED
    end_moving = goal([0.0, 1.0], [READY, moved(0, 0.1)], names=ARM, velocities=[[0.0] * 7, [0.01] + [0.0] * 6])
    assert not client.send(end_moving).handle.accepted


def _audit_agrees(probe, bags, run_audit, AuditOptions) -> None:
    bag = next(bags.iterdir())
    audit = run_audit(AuditOptions(bag=str(bag), out=str(bags / "audit"), report=True))
    out = audit.record["outputs"]
    gate = out["gate"]
    live = [r for r in probe.records if r["event"] == "decision"]
    # a goal is an executed trajectory, not a question: counted from the bag by the official
    # mcap reader and rosbags, and from what the node published live
    n_goals, n_bad = gate_goal_counts(bag)
    # "no": rejected by the check, or never reached the controller (it refused one: not_forwarded)
    assert (n_goals, n_bad) == (len(live), sum(r["decision"] in ("rejected", "not_forwarded") for r in live))
    assert n_bad >= 4 and "gate" not in out["questions"]
    c = out["trajectory_counts"]
    assert c["by_request"]["gate_goal"] == {"total": n_goals, "infeasible_or_rejected": n_bad}
    assert (c["executed"], c["executed_infeasible_or_rejected"], c["questions"]) == (n_goals, n_bad, 0)
    assert out["trajectories_infeasible_or_rejected"] == n_bad
    assert audit.record["verdict"]["result"] == "violations" and "planning error" in audit.record["failure_labels"]
    assert f"{n_bad} of {n_goals} executed trajectories ({n_goals} gate goals) infeasible or rejected" \
        in audit.record["verdict"]["summary"]
    from dyn_node.fleet import engine as fleet
    from dyn_node.fleet.rows import row_from_record

    cfg = fleet.FleetConfig(report=False)
    job = fleet.BagJob(str(bag), fleet.bag_id(bag), str(bags / "fleet"), cfg, fleet.config_hash(cfg))
    row = row_from_record(job, audit.record, audit.exit_code, "digest").row
    assert (row["trajectories"], row["trajectories_bad"], row["questions"]) == (n_goals, n_bad, 0)
    assert (gate["requests"], gate["answered"], gate["not_replayed"]) == (len(live), len(live), 0)
    assert (gate["forwarded"], gate["rejected"]) == (sum(r["decision"] == "forwarded" for r in live),
                                                     sum(r["decision"] == "rejected" for r in live))
    assert [d["goal_id"] for d in gate["decisions"]] == [r["goal_id"] for r in live]
    # the gate records a decision once the goal is on its way (off the latency path), yet always
    # before that goal's end: in the bag, every result record follows its goal's decision
    recs = gate_records(bag)
    assert [r["goal_id"] for r in recs if r["event"] == "decision"] == [r["goal_id"] for r in live]
    decided: set[str] = set()
    for r in recs:
        if r["event"] == "decision":
            decided.add(r["goal_id"])
        else:
            assert r["goal_id"] in decided, f"{r['event']} recorded before its decision: {r}"
    assert {"result", "downstream_rejected"} <= {r["event"] for r in recs}
    assert [d["verdict"] for d in gate["decisions"]] == [r["verdict"] for r in live]
    recheck = audit.record["outputs"]["recheck"]["/gate_rec/gate_decisions"]
    assert (recheck["matched"], recheck["identical"]) == (len(live), True), recheck
    # the replay's controller tracker follows the forwarded goals from the timing and state the
    # node's did (``tracked`` records), as the node's ~/controller_status showed them
    assert sum(r["event"] == "tracked" for r in recs) == sum(r["decision"] == "forwarded" for r in live)
    assert any(kv(m)["state"] == "tracking" for m in probe.ctrl)
    assert "tracking" in out["controller_states"]["states_seen"], out["controller_states"]
    report = (bags / "audit" / "report.html").read_text()
    assert "Gate decisions" in report and live[1]["verdict"].split(";")[0] in report


@pytest.mark.timeout(150)
def test_downstream_absent_and_crashing(module_ros_context, spawn):
    """In a namespace of their own (their own joint_states): a gate whose controller does not
    exist, and one whose controller is killed mid-goal."""
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    from dyn_node.ros.fjt_client import FjtClient

    ns = "/crash"
    sim = spawn(sim_cmd("-r", f"__ns:={ns}", "-p", "controller_name:=crashing"))
    spawn(gate_cmd("gate_absent", "gate.controller_action:=/nobody/follow_joint_trajectory",
                   "gate.timeout:=0.5", ns=ns))
    spawn(gate_cmd("gate_crash", f"gate.controller_action:={ns}/crashing/follow_joint_trajectory",
                   "gate.timeout:=1.0", ns=ns))
    absent = FjtClient(module_ros_context, f"{ns}/gate_absent/follow_joint_trajectory", "client_absent")
    crash = FjtClient(module_ros_context, f"{ns}/gate_crash/follow_joint_trajectory", "client_crash")
    probe = Probe(module_ros_context, "gate_crash", ready=("gate_absent", "gate_crash"), ns=ns)
    try:
        absent.wait_for_server(90.0)
        crash.wait_for_server(90.0)
        probe.wait_ready()
        sent = absent.send(_goal(FEASIBLE))
        status, result = absent.result(sent, timeout=10.0)
        assert (status, result.error_code) == (GoalStatus.STATUS_ABORTED, FollowJointTrajectory.Result.INVALID_GOAL)
        assert result.error_string == ("dyn_node gate: downstream action server /nobody/follow_joint_trajectory "
                                       "not available within 0.5 s (gate.timeout)")
        # dyn_node: gate says so: ERROR, state error, the failure counted
        absent_status = lambda: [st for st in probe.gate_status  # noqa: E731
                                 if kv(st).get("controller_action") == "/nobody/follow_joint_trajectory"
                                 and kv(st).get("downstream_failures") == "1"]
        probe.until(lambda: bool(absent_status()), 20.0, "the absent gate's status")
        st = absent_status()[-1]
        assert (st.level, kv(st)["failure_label"]) == (bytes([2]), "state error")
        assert st.message == "downstream action server /nobody/follow_joint_trajectory not available"
        sent = crash.send(_goal(move(READY, moved(0, 0.3), 6.0)))
        assert sent.handle.accepted and sent.feedback_event.wait(15.0)
        sim.signal(signal.SIGKILL)
        status, result = crash.result(sent, timeout=20.0)
        assert (status, result.error_code) == (GoalStatus.STATUS_ABORTED, FollowJointTrajectory.Result.INVALID_GOAL)
        # silent: the gate cancels downstream, nobody confirms (the controller is dead), it ends
        assert result.error_string == (f"dyn_node gate: downstream action server {ns}/crashing/follow_joint_trajectory "
                                       "went away during the goal (no feedback and no result for 1 s); cancel sent, "
                                       "not confirmed within 1 s")
        rec = probe.record("downstream_cancel_unconfirmed", 1)
        assert (rec["status"], rec["cause"], rec["cancel"]) == (GoalStatus.STATUS_ABORTED, "downstream_silent",
                                                                "downstream_cancel_unconfirmed")
        # the goal's decision (recorded from its execution) came first, with its inputs
        events = [(r["event"], r["goal_id"]) for r in probe.records]
        assert events.index(("decision", rec["goal_id"])) < events.index(("downstream_cancel_unconfirmed", rec["goal_id"]))
        decision = next(r for r in probe.records if r["event"] == "decision" and r["goal_id"] == rec["goal_id"])
        assert (decision["decision"], decision["goal"]["joint_names"]) == ("forwarded", ARM)
    finally:
        probe.close()
        absent.close()
        crash.close()


@pytest.mark.timeout(150)
def test_clean_shutdown_cancels_what_was_forwarded(module_ros_context, spawn):
    """SIGINT to dyn_node while a forwarded goal runs: the controller's goal ends CANCELED (its
    action status topic says so), the robot held before the trajectory's end."""
    from action_msgs.msg import GoalStatus, GoalStatusArray
    from rclpy.qos import qos_profile_action_status_default

    from dyn_node.ros.fjt_client import FjtClient

    ns = "/shutdown"
    spawn(sim_cmd("-r", f"__ns:={ns}"))
    gate = spawn(gate_cmd("gate_stop", f"gate.controller_action:={ns}/joint_trajectory_controller/"
                          "follow_joint_trajectory", ns=ns))
    client = FjtClient(module_ros_context, f"{ns}/gate_stop/follow_joint_trajectory", "client_stop")
    probe = Probe(module_ros_context, "gate_stop", ready=("gate_stop",), ns=ns)
    statuses: list = []
    # transient local, as an action client subscribes to it: the server publishes the status only
    # when it changes, and a subscription matched after the change still gets the last array
    probe.node.create_subscription(GoalStatusArray, f"{ns}/joint_trajectory_controller/follow_joint_trajectory"
                                   "/_action/status", statuses.append, qos_profile_action_status_default)
    try:
        client.wait_for_server(90.0)
        probe.wait_ready()
        sent = client.send(_goal(move(READY, moved(0, 0.3), 8.0)))
        assert sent.handle.accepted and sent.feedback_event.wait(15.0)
        rc, _, err = gate.stop(signal.SIGINT)
        assert rc == 0, err[-2000:]
        canceled = lambda: any(s.status == GoalStatus.STATUS_CANCELED  # noqa: E731
                               for m in statuses for s in m.status_list)
        probe.steps.until(canceled, 10.0)
        assert canceled(), f"the controller's goal did not end CANCELED; dyn_node said:\n{err[-3000:]}"
        assert "Traceback" not in err
    finally:
        probe.close()
        client.close()


def test_the_reference_verdict_for_the_infeasible_goal_is_the_closed_form():
    """The gate's decisions are compared with the core's check of the same goal: that reference
    against what we did not write. The goal is one rest-to-rest quintic (11 knots carrying its
    positions, velocities and accelerations, so the controller's quintic pieces are the quintic
    itself): its peak speed 15/8·Δq/T = 6.25 rad/s at the middle knot, velocity binds, so
    time_scale = 6.25 / panda_joint1's 2.175 rad/s."""
    from dyn_node.core.check import feasibility
    from dyn_node.core.check.trajectory import validate_trajectory
    from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
    from dyn_node.core.robot.model import load_model
    from dyn_node.core.robot.settings import Settings

    model = load_model(builtin="panda")
    traj = validate_trajectory(model.joint_names, ARM, INFEASIBLE["times"], INFEASIBLE["points"],
                               INFEASIBLE["velocities"], INFEASIBLE["accelerations"])
    node = Settings()
    verdict = feasibility.check_trajectory(
        Dynamics(model, DynamicsOptions(include_friction=node.include_friction)), traj,
        feasibility.FeasibilityOptions(sample_period=node.sample_period, effort_warn_ratio=node.effort_warn_ratio))
    assert model.limits.velocity[0] == 2.175  # example-robot-data's panda_joint1
    assert verdict.time_scale == pytest.approx(15 / 8 * 0.5 / 0.15 / 2.175, rel=1e-12)
    assert verdict.message.endswith("velocity of panda_joint1 binds")
