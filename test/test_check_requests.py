"""On-demand requests through a real dyn_node in another process: ~/check_trajectory and
~/inverse_dynamics_request, the request queue, the Python client, and dyn-check against the node.

One node process (Panda, check_queue_depth 3) serves the whole module."""
from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from conftest import REPO, ChildProcess, Collected, Spinner, child_env, kv, python_cmd
from dyn_node.audit import check as check_cli
from dyn_node.core import on_demand
from dyn_node.ros.client import (BlockingCallError, DynClient, NotRunningError, RequestRejected, Verdict,
                             states_message, trajectory_message)
from dyn_node.ros.demo import READY, demo_trajectories
from dyn_node.core.dynamics import Dynamics
from dyn_node.core.model import load_model
from dyn_node.core.settings import Settings
from dyn_node.audit.trajectory_files import read_trajectory

MODEL = load_model(builtin="panda")
NAMES = list(MODEL.joint_names)
DYN = Dynamics(MODEL)
SETTINGS = Settings(robot_model="panda")
EXAMPLES = REPO / "examples" / "trajectories"
LATCHED = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
SUMMARY = "dyn_node: trajectory feasibility"


@pytest.fixture(scope="module")
def bag_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("check_requests_bags")


@pytest.fixture(scope="module")
def node_process(bag_dir):
    cp = ChildProcess(python_cmd("dyn_node.ros.node", "--ros-args", "-p", "robot_model:=panda",
                                 "-p", "check_queue_depth:=3", "-p", "record.enabled:=true",
                                 "-p", f"record.directory:={bag_dir}"), env=child_env(), cwd=str(REPO))
    yield cp
    cp.stop()


class Rig:
    """A test node with raw publishers/collectors on dyn_node's topics, and a DynClient."""

    def __init__(self, ctx, node_process):
        self.proc = node_process
        self.node = Node("check_requests_test", context=ctx)
        self.got = Collected()
        n = self.node
        self.pub_check = n.create_publisher(JointTrajectory, "/dyn_node/check_trajectory", 10)
        self.pub_states = n.create_publisher(JointTrajectory, "/dyn_node/inverse_dynamics_request", 10)
        self.pub_exec = n.create_publisher(JointTrajectory, "/joint_trajectory", 10)
        self.pub_js = n.create_publisher(JointState, "/joint_states", 10)
        n.create_subscription(DiagnosticArray, "/dyn_node/feasibility", self.got.collector("feas"), LATCHED)
        n.create_subscription(JointTrajectory, "/dyn_node/trajectory_effort", self.got.collector("effort"), 100)
        n.create_subscription(DiagnosticStatus, "/dyn_node/controller_status",
                              self.got.collector("ctrl", stamp_receipt=True), 100)
        self.client = DynClient(n)
        self.spinner = Spinner(ctx, [n])
        def up() -> bool:   # matched, or the process is gone (no point waiting on)
            return node_process.proc.poll() is not None or bool(
                self.client.ready() and self.pub_exec.get_subscription_count()
                and self.pub_js.get_subscription_count())

        came_up = self.got.wait(up, 60.0)
        assert node_process.proc.poll() is None, node_process.stop()
        assert came_up, "dyn_node did not come up within 60 s"

    def answer(self, key: str, frame_id: str, timeout: float = 30.0):
        """The first collected message on ``key`` whose header frame_id is ``frame_id``."""
        def find():
            return next((m for m in self.got.got[key] if m.header.frame_id == frame_id), None)
        assert self.got.wait(lambda: find() is not None, timeout), (
            f"no {key} answer for {frame_id}; got {[m.header.frame_id for m in self.got.got[key]][-20:]}")
        return find()

    def close(self) -> None:
        self.spinner.stop()
        self.client.destroy()
        self.node.destroy_node()


@pytest.fixture(scope="module")
def rig(module_ros_context, node_process):
    r = Rig(module_ros_context, node_process)
    yield r
    r.close()


def summary_values(arr: DiagnosticArray) -> tuple[dict[str, str], DiagnosticStatus]:
    st = next(s for s in arr.status if s.name == SUMMARY)
    return kv(st), st


def reach(scale: float = 1.0, stamp: Time | None = None, frame_id: str = "") -> JointTrajectory:
    comfortable, _ = demo_trajectories(short=True)
    z = np.zeros((len(comfortable.times), 7))
    msg = trajectory_message(NAMES, [t * scale for t in comfortable.times], comfortable.positions, z, z)
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    return msg


def local_check(msg: JointTrajectory) -> on_demand.CheckOutcome:
    """What the node must answer, from the pure core on the message's own numbers."""
    pts = msg.points
    return on_demand.check(DYN, SETTINGS, list(msg.joint_names),
                           [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in pts],
                           [list(p.positions) for p in pts], [list(p.velocities) for p in pts],
                           [list(p.accelerations) for p in pts])


def efforts_of(msg: JointTrajectory, names=NAMES) -> np.ndarray:
    order = [list(msg.joint_names).index(n) for n in names]
    return np.array([[p.effort[i] for i in order] for p in msg.points])


def test_concurrent_tagged_requests_are_answered_and_matched(rig):
    # three different trajectories in flight at once: each answer must carry its own request's
    # header and the numbers of that request's trajectory
    reqs = {f"req-{i}": reach(scale, Time(sec=100 + i, nanosec=7), f"req-{i}")
            for i, scale in enumerate((1.0, 0.5, 2.0))}
    for msg in reqs.values():
        rig.pub_check.publish(msg)
    for rid, msg in reqs.items():
        arr = rig.answer("feas", rid)
        vals, st = summary_values(arr)
        assert (arr.header.stamp.sec, arr.header.stamp.nanosec) == (msg.header.stamp.sec, 7)
        assert vals["request"] == "check"
        want = local_check(msg).result
        assert float(vals["time_scale"]) == want.time_scale
        assert float(vals["worst_ratio"]) == want.worst_ratio
        eff = rig.answer("effort", rid)
        assert (eff.header.stamp.sec, eff.header.stamp.nanosec) == (msg.header.stamp.sec, 7)
        np.testing.assert_array_equal(efforts_of(eff), want.waypoint_effort)
    scales = {float(summary_values(rig.answer("feas", rid))[0]["time_scale"]) for rid in reqs}
    assert len(scales) == 3  # three different answers, so a mix-up could not go unnoticed


def _publish_joint_states(rig, stop: threading.Event) -> None:
    while not stop.is_set():
        js = JointState(name=NAMES, position=list(READY), velocity=[0.0] * 7)
        ns = time.time_ns()
        js.header.stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
        rig.pub_js.publish(js)
        stop.wait(0.01)


def _ctrl_after(rig, t0: float) -> list[dict[str, str]]:
    return [kv(m) for t, m in rig.got.got["ctrl"] if t > t0]


def test_check_only_leaves_controller_status_alone_and_execution_does_not(rig):
    stop = threading.Event()
    pub = threading.Thread(target=_publish_joint_states, args=(rig, stop), daemon=True)
    pub.start()
    try:
        t0 = time.monotonic()
        assert rig.got.wait(lambda: any(v["state"] == "idle" for v in _ctrl_after(rig, t0)), 20)
        for request, pub_to in (("check", rig.pub_check), ("execute", rig.pub_exec)):
            ns = time.time_ns() + 200_000_000
            msg = reach(0.5, Time(sec=ns // 10**9, nanosec=ns % 10**9), f"ctrl-{request}")
            t_sent = time.monotonic()
            pub_to.publish(msg)
            arr = rig.answer("feas", f"ctrl-{request}")
            assert summary_values(arr)[0]["request"] == request
            # until well after the trajectory's last point (start + 0.8 s)
            end = t_sent + 0.2 + 0.8 + 0.3
            assert rig.got.wait(lambda: any(t > end for t, _ in rig.got.got["ctrl"]), 20)
            seen = {(v["state"], v["trajectory_active"]) for v in _ctrl_after(rig, t_sent)}
            if request == "check":
                assert seen == {("idle", "false")}, seen
            else:
                assert ("tracking", "true") in seen or ("deviating", "true") in seen, seen
    finally:
        stop.set()
        pub.join()


def test_queue_overflow_is_answered_rejected_busy(rig):
    # long enough that the worker is still on the first when the rest arrive; depth is 3
    n_pts = 400
    t = np.linspace(0.0, 40.0, n_pts)
    P = np.array(READY) + 0.2 * np.sin(t[:, None] * np.arange(1, 8) * 0.1)
    ids = [f"busy-{i}" for i in range(9)]  # within the topics' depth of 10: none lost in DDS
    for rid in ids:
        msg = trajectory_message(NAMES, t, P)
        msg.header.frame_id = rid
        rig.pub_check.publish(msg)
    verdicts = [Verdict.from_msg(rig.answer("feas", rid, timeout=60)) for rid in ids]
    busy = [v for v in verdicts if v.message.startswith("rejected: busy")]
    checked = [v for v in verdicts if not v.rejected]
    # at least the 3 a full queue holds are checked (4 once the worker has taken the first)
    assert busy and len(checked) >= 3, [v.message for v in verdicts]
    assert len(busy) + len(checked) == len(ids)
    assert all(v.reason == "busy" and v.request == "check" and not v.feasible for v in busy)
    # answered in order: feasibility answers of the checked ones arrive in request order
    order = [m.header.frame_id for m in rig.got.got["feas"] if m.header.frame_id.startswith("busy-")
             and not summary_values(m)[1].message.startswith("rejected: busy")]
    assert order == sorted(order, key=lambda r: int(r.split("-")[1]))


def test_client_verdict_equals_what_the_node_published(rig):
    _, aggressive = demo_trajectories(short=True)
    z = np.zeros((len(aggressive.times), 7))
    msg = trajectory_message(NAMES, aggressive.times, aggressive.positions, z, z)
    v = rig.client.check(msg, timeout=30)
    published = rig.answer("feas", v.frame_id)
    vals, st = summary_values(published)
    want = local_check(msg).result
    assert not v.feasible and v.level == 2 and not v.rejected and v.request == "check"
    assert v.message == st.message == want.message
    assert v.time_scale == float(vals["time_scale"]) == want.time_scale
    assert (v.worst_joint, v.worst_constraint) == (want.worst_joint, want.worst_constraint)
    assert v.worst_ratio == want.worst_ratio
    assert v.first_violation_time_s == want.first_violation_time_s
    assert {(x.joint, x.kind) for x in v.violations} == {(x.joint, x.kind) for x in want.violations}
    for x in v.violations:
        assert x.ratio == want.per_joint[x.joint][x.kind]["ratio"] > 1.0
    assert v.ratios["panda_joint2"]["effort"] == want.per_joint["panda_joint2"]["effort"]["ratio"]
    # a rejected one: the node's reason, as a Verdict
    bad = reach()
    bad.points[1].positions[3] = math.nan
    r = rig.client.check(bad, timeout=30)
    assert r.rejected and r.reason == "non_finite" and not r.feasible
    assert r.message == local_check(bad).statuses[0].message


def test_client_efforts_match_pinocchio(rig):
    q = np.array([READY, [0.3, 0.2, -0.1, -1.5, 0.2, 1.0, 0.1]])
    v = np.array([[0.0] * 7, [0.5, -0.4, 0.3, 0.2, -0.1, 0.6, -0.7]])
    a = np.array([[0.0] * 7, [1.0, 2.0, -1.0, 0.5, 0.0, -2.0, 3.0]])
    rev = NAMES[::-1]
    got = rig.client.efforts(states_message(rev, q[:, ::-1], v[:, ::-1], a[:, ::-1]), timeout=30)
    pm, data = MODEL.pin_model, MODEL.pin_model.createData()
    for i in range(2):
        want = pin.rnea(pm, data, q[i], v[i], a[i]) + np.array(pm.damping) * v[i] \
            + np.array(pm.friction) * np.sign(v[i])
        np.testing.assert_allclose(got[i], want[::-1], rtol=0, atol=1e-9)  # the request's order
    # positions alone: gravity
    g = rig.client.efforts(states_message(NAMES, q[:1]), timeout=30)
    np.testing.assert_allclose(g[0], pin.computeGeneralizedGravity(pm, data, q[0]), rtol=0, atol=1e-9)
    with pytest.raises(RequestRejected, match="joints not in the model: nope"):
        rig.client.efforts(states_message(NAMES[:6] + ["nope"], q[:1]), timeout=30)


def test_blocking_call_from_the_only_executor_thread_raises(rig, module_ros_context):
    node = Node("check_requests_blocking", context=module_ros_context)
    client = DynClient(node)
    ex = SingleThreadedExecutor(context=module_ros_context)
    ex.add_node(node)
    out: dict = {}

    def cb() -> None:
        timer.cancel()
        try:
            client.check(reach(), timeout=5)
        except Exception as exc:  # noqa: BLE001 - what is raised is the assertion
            out["exc"] = exc
        fut = client.check_async(reach(), timeout=30)  # the async variant is the way there
        out["fut"] = fut

    timer = node.create_timer(0.01, cb)
    try:
        deadline = time.monotonic() + 40
        while not ("fut" in out and out["fut"].done()) and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        assert isinstance(out.get("exc"), BlockingCallError), out
        assert out["fut"].done() and out["fut"].result().feasible
    finally:
        ex.shutdown()
        client.destroy()
        node.destroy_node()


def test_client_reports_no_node_running(module_ros_context):
    node = Node("check_requests_nobody", context=module_ros_context)
    client = DynClient(node, namespace="/nobody_here")
    spinner = Spinner(module_ros_context, [node])
    try:
        with pytest.raises(NotRunningError, match="not running at /nobody_here"):
            client.check(reach(), timeout=1.0)
        with pytest.raises(NotRunningError):
            client.efforts(states_message(NAMES, [READY]), timeout=1.0)
    finally:
        spinner.stop()
        client.destroy()
        node.destroy_node()


@pytest.mark.parametrize("name", ["panda_reach.yaml", "panda_reach.json", "panda_reach.csv",
                                  "panda_shake.yaml"])
def test_dyn_check_gives_the_nodes_verdict_and_torques(rig, name):
    path = EXAMPLES / name
    checker = check_cli.make_checker(robot_model="panda")
    mine = check_cli.check_file(checker, str(path))
    tf = read_trajectory(path)
    msg = trajectory_message(tf.joint_names, tf.times, tf.positions, tf.velocities, tf.accelerations)
    msg.header.frame_id = f"file-{name}"
    rig.pub_check.publish(msg)
    vals, st = summary_values(rig.answer("feas", f"file-{name}"))
    r = mine.outcome.result
    assert st.message == r.message
    assert vals["feasible"] == ("true" if r.feasible else "false")
    assert (float(vals["time_scale"]), float(vals["worst_ratio"])) == (r.time_scale, r.worst_ratio)
    np.testing.assert_array_equal(efforts_of(rig.answer("effort", f"file-{name}"), tf.joint_names),
                                  r.waypoint_effort[:, [NAMES.index(n) for n in tf.joint_names]])
    assert check_cli.verdict_line(mine).endswith(st.message)


def test_dyn_check_rejects_like_the_node(rig, tmp_path):
    text = (EXAMPLES / "panda_reach.csv").read_text().splitlines()
    cells = text[2].split(",")
    cells[2] = "nan"
    (tmp_path / "nan.csv").write_text("\n".join([text[0], text[1], ",".join(cells), text[3]]) + "\n")
    checker = check_cli.make_checker(robot_model="panda")
    mine = check_cli.check_file(checker, str(tmp_path / "nan.csv"))
    tf = read_trajectory(tmp_path / "nan.csv")
    msg = trajectory_message(tf.joint_names, tf.times, tf.positions, tf.velocities, tf.accelerations)
    msg.header.frame_id = "file-nan"
    rig.pub_check.publish(msg)
    _, st = summary_values(rig.answer("feas", "file-nan"))
    assert st.message.startswith("rejected: point 1: positions of panda_joint2 is nan")
    assert mine.outcome.statuses[0].message == st.message
    assert check_cli.verdict_line(mine) == f"{tmp_path / 'nan.csv'}: REJECTED: " + \
        st.message.removeprefix("rejected: ")


def test_the_audit_rechecks_check_only_and_torque_answers(rig, tmp_path):
    from std_srvs.srv import Trigger

    from dyn_node.audit.bag_audit import AuditOptions, run_audit

    _, aggressive = demo_trajectories(short=True)
    z = np.zeros((len(aggressive.times), 7))
    shake = trajectory_message(NAMES, aggressive.times, aggressive.positions, z, z)
    assert not rig.client.check(shake, timeout=30).feasible
    q = np.array([READY, [0.3, 0.2, -0.1, -1.5, 0.2, 1.0, 0.1]])
    rig.client.efforts(states_message(NAMES, q, q * 0.5, q * 0.1), timeout=30)
    with pytest.raises(RequestRejected):
        rig.client.efforts(states_message(NAMES[:6] + ["nope"], q), timeout=30)
    cli = rig.node.create_client(Trigger, "/dyn_node/stop_recording")
    assert cli.wait_for_service(timeout_sec=10)
    fut = cli.call_async(Trigger.Request())
    done = threading.Event()
    fut.add_done_callback(lambda _f: done.set())
    assert done.wait(30) and fut.result().success, fut.result()
    bag = fut.result().message
    res = run_audit(AuditOptions(bag=bag, out=str(tmp_path / "audit"), report=False))
    rc = res.record["outputs"]["recheck"]
    feas = next(d for t, d in rc.items() if t.endswith("/feasibility"))
    effort = next(d for t, d in rc.items() if t.endswith("/trajectory_effort"))
    # every verdict and every torque answer the node gave, recomputed from the bag alone
    assert feas["matched"] >= 3 and feas["unmatched"] == 0 and feas["identical"], feas
    assert effort["matched"] >= 2 and effort["unmatched"] == 0 and effort["identical"], effort
    trajs = res.record["outputs"]["trajectories"]
    checks = [t for t in trajs if t["request"] == "check"]
    assert any(not t["feasible"] and t["accepted"] for t in checks)
    executed_bad = sum(not t["feasible"] for t in trajs if t["request"] == "execute")
    # a check-only "no" is an answered question, not a violation of the run
    assert res.record["outputs"]["trajectories_infeasible_or_rejected"] == executed_bad
