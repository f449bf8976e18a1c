"""The node's trajectory path: joint_trajectory → check in a worker → ~/feasibility and
~/trajectory_effort, malformed trajectories rejected, joint_states answered during a long check."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.errors import PLANNING_ERROR
from dyn_node.core.check.feasibility import STATUS_NAME, Timing, check_trajectory
from dyn_node.core.robot.model import load_model
from dyn_node.ros.node import DynNode
from dyn_node.core.robot.status import ERROR, OK, WARN, format_value
from dyn_node.core.check.trajectory import interpolate, validate_trajectory
from conftest import NodeHarness, kv  # noqa: E402

MODEL = load_model(builtin="planar_2link")
NAMES = list(MODEL.joint_names)
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
SUMMARY_KEYS = ("feasible", "worst_joint", "worst_constraint", "worst_ratio",
                "first_violation_time_s", "time_scale", "payload_margin_kg", "n_points",
                "duration_s", "failure_label")
_stamp = [500.0]


def next_stamp() -> Time:
    _stamp[0] += 1.0
    return Time(sec=int(_stamp[0]), nanosec=250_000_000)


def same(a: Time, b: Time) -> bool:
    return a.sec == b.sec and a.nanosec == b.nanosec


def dur(t: float) -> Duration:
    sec = int(math.floor(t))
    return Duration(sec=sec, nanosec=int(round((t - sec) * 1e9)))


def trajectory(names, times, positions, velocities=None, accelerations=None) -> JointTrajectory:
    msg = JointTrajectory()
    msg.header.stamp = next_stamp()
    msg.joint_names = list(names)
    for i, t in enumerate(times):
        p = JointTrajectoryPoint(positions=[float(x) for x in positions[i]], time_from_start=dur(t))
        if velocities is not None:
            p.velocities = [float(x) for x in velocities[i]]
        if accelerations is not None:
            p.accelerations = [float(x) for x in accelerations[i]]
        msg.points.append(p)
    return msg


class Harness(NodeHarness):
    default_timeout = 15.0

    def __init__(self, ctx: Context, namespace: str, extra: tuple = ()):
        super().__init__(ctx, namespace, [Parameter("robot_model", value="planar_2link"), *extra])
        self.traj_pub = self.probe.create_publisher(JointTrajectory, "joint_trajectory", 10)
        self.js_pub = self.probe.create_publisher(JointState, "joint_states", RELIABLE)
        self.sub("feas", DiagnosticArray, "dyn_node/feasibility", LATCHED)
        self.sub("teff", JointTrajectory, "dyn_node/trajectory_effort", 10)
        self.sub("gravity", JointState, "dyn_node/gravity_torque", RELIABLE)
        self.start(lambda: self.traj_pub.get_subscription_count() >= 1
                   and self.js_pub.get_subscription_count() >= 1
                   and self.probe.count_publishers(f"{namespace}/dyn_node/feasibility") >= 1
                   and self.probe.count_publishers(f"{namespace}/dyn_node/gravity_torque") >= 1)

    def verdict(self, msg: JointTrajectory, timeout: float = 30.0) -> DiagnosticArray:
        hit: list = []

        def pred() -> bool:
            hit[:] = [a for a in self.got["feas"] if same(a.header.stamp, msg.header.stamp)]
            return bool(hit)

        assert self.wait(pred, timeout), "no ~/feasibility verdict for the trajectory"
        return hit[0]

    def make_current(self, q: list[float], v: list[float]) -> None:
        """Publish the joint state (q, v) and wait until the node has answered it, so it is the
        node's current state."""
        js = JointState(name=NAMES, position=q, velocity=v)
        js.header.stamp = next_stamp()
        self.js_pub.publish(js)
        assert self.wait(lambda: any(same(g.header.stamp, js.header.stamp) for g in self.got["gravity"]))


@pytest.fixture(scope="module")
def harness(module_ros_context):
    h = Harness(module_ros_context, "/feas")
    yield h
    h.close()


def rest_to_rest(duration: float):
    """Quintic rest-to-rest move of joint1 by 2 rad: peak speed 1.875·2/duration (limit 3 rad/s)."""
    return ([0.0, duration], [[0.0, 0.3], [2.0, 0.8]], [[0.0, 0.0], [0.0, 0.0]], [[0.0, 0.0], [0.0, 0.0]])


def received(msg) -> Timing:
    """The timing the node judges ``msg`` with: its stamp (these tests' stamps lie decades back,
    so the controller would refuse the trajectory as ended: judged as if stamped zero, whatever
    the exact receipt) and a receipt on the node's clock (the wall clock)."""
    return Timing(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, time.time())


def core_result(times, P, V, A):
    traj = validate_trajectory(NAMES, NAMES, times, P, V, A)
    return check_trajectory(Dynamics(MODEL), traj)


@pytest.mark.timeout(90)
@pytest.mark.parametrize("duration,feasible", [(4.0, True), (1.0, False)])
def test_verdict_statuses_match_the_core(harness, duration, feasible):
    times, P, V, A = rest_to_rest(duration)
    # the robot at rest at the first point (another test may have left it elsewhere: a first
    # point due at once away from the robot would be a jump)
    harness.make_current(P[0], V[0])
    msg = trajectory(NAMES, times, P, V, A)
    harness.traj_pub.publish(msg)
    arr = harness.verdict(msg)
    want = core_result(times, P, V, A)
    assert want.feasible is feasible
    top = arr.status[0]
    assert top.name == STATUS_NAME
    assert top.hardware_id == MODEL.name
    values = kv(top)
    # every summary key: the closed form of this quintic where there is one (joint1's peak
    # speed 1.875·2/duration against 3 rad/s sets the time scale), else the core's number
    closed = {"feasible": "true" if feasible else "false", "n_points": "2",
              "duration_s": repr(float(duration)),
              "failure_label": "" if feasible else PLANNING_ERROR}
    core = {k: format_value(v) for k, v in want.summary_values().items()}
    assert set(SUMMARY_KEYS) <= set(values)
    for key in SUMMARY_KEYS:
        assert values[key] == closed.get(key, core[key]), (key, values[key])
    assert top.message == want.message
    assert float(values["time_scale"]) == pytest.approx(want.time_scale, rel=1e-12)
    assert float(values["time_scale"]) == pytest.approx(1.875 * 2 / duration / 3.0, rel=1e-9)
    if feasible:
        assert want.worst_ratio < 0.9 and not want.warnings
        assert top.level == bytes([OK])      # nothing near a limit, nothing assumed
        assert top.message.startswith(f"feasible: worst {want.worst_joint} ")
        assert top.message.endswith("could run 3.20× faster")
        assert values["failure_label"] == ("" if top.level[0] == OK else PLANNING_ERROR)
        assert values["first_violation_time_s"] == "nan"
    else:
        assert top.level[0] == ERROR
        assert top.message.startswith("infeasible: joint1 velocity 125% of 3 rad/s at t = 0.50 s")
        assert "run 1.25× slower" in top.message
        assert values["failure_label"] == PLANNING_ERROR
        assert 0.0 < float(values["first_violation_time_s"]) < 0.5
    assert [s.name for s in arr.status[1:]] == [f"{STATUS_NAME}/{n}" for n in NAMES]
    j1 = kv(arr.status[1])
    assert float(j1["velocity_ratio"]) == pytest.approx(1.875 * 2 / duration / 3.0, rel=1e-9)
    assert float(j1["effort_ratio"]) == pytest.approx(want.per_joint["joint1"]["effort"]["ratio"],
                                                      rel=1e-12)
    # joint1's own status: ERROR with its velocity violation, else OK or WARN by its worst ratio
    worst1 = max(e["ratio"] for k, e in want.per_joint["joint1"].items()
                 if k != "position" and e["ratio"] is not None)
    assert arr.status[1].level == bytes([ERROR if not feasible else WARN if worst1 > 0.9 else OK])
    if not feasible:
        assert arr.status[1].message.startswith("velocity 125% of 3 rad/s")


@pytest.mark.timeout(90)
@pytest.mark.parametrize("mode", ["quintic", "cubic", "linear"])
def test_trajectory_effort_is_rnea_at_waypoints_in_input_order(harness, mode):
    t = np.array([0.0, 0.7, 1.5, 2.4])
    P = np.column_stack([0.4 * np.sin(t), 0.2 + 0.5 * np.cos(t)])
    V = np.column_stack([0.4 * np.cos(t), -0.5 * np.sin(t)]) if mode != "linear" else None
    A = np.column_stack([-0.4 * np.sin(t), -0.5 * np.cos(t)]) if mode == "quintic" else None
    order = [1, 0]  # the message lists joint2 first
    msg = trajectory([NAMES[i] for i in order], t, P[:, order],
                     None if V is None else V[:, order], None if A is None else A[:, order])
    harness.traj_pub.publish(msg)
    harness.verdict(msg)
    assert harness.wait(lambda: any(same(m.header.stamp, msg.header.stamp) for m in harness.got["teff"]))
    out = next(m for m in harness.got["teff"] if same(m.header.stamp, msg.header.stamp))
    assert list(out.joint_names) == [NAMES[i] for i in order]
    assert len(out.points) == len(t)
    traj = validate_trajectory(NAMES, NAMES, t, P, V, A)
    q, v, a, _ = interpolate(traj).evaluate(t)
    if mode == "linear":
        # positions only: the controller's linear segments (trajectory.cpp 315-333): at each
        # point the slope leaving it (the last: arriving), no acceleration
        slope = np.diff(P, axis=0) / np.diff(t)[:, None]
        v, a = np.vstack([slope, slope[-1:]]), np.zeros_like(P)
    dyn = Dynamics(MODEL)
    for i, p in enumerate(out.points):
        want = dyn.rnea(q[i], v[i], a[i])[order]
        np.testing.assert_allclose(np.asarray(p.effort), want, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(np.asarray(p.positions), P[i, order])


def _bad_messages():
    good_t, good_p = [0.0, 1.0], [[0.0, 0.0], [0.1, 0.1]]
    out = []
    m = trajectory(NAMES, [], [])
    out.append(("empty points", m, "no points"))
    m = trajectory(NAMES, [0.0], [[0.0, 0.0]])
    out.append(("single point", m, "at least 2"))
    m = trajectory(NAMES, [0.0, 1.0, 1.0], [[0, 0], [0.1, 0.1], [0.2, 0.2]])
    out.append(("non-increasing", m, "not strictly increasing"))
    m = trajectory(NAMES, good_t, good_p)
    m.points[1].positions = [0.1]
    out.append(("length mismatch", m, "1 positions for 2 joints"))
    m = trajectory(NAMES, good_t, good_p)
    m.points[0].effort = [1.0]      # joint_trajectory_controller refuses it
    out.append(("effort length", m, "point 0: 1 effort for 2 joints"))
    m = trajectory(["joint1", "elbow"], good_t, good_p)
    out.append(("unknown joint", m, "elbow"))
    m = trajectory(["joint1"], good_t, [[0.0], [0.1]])
    out.append(("missing joint", m, "joint2"))
    m = trajectory(NAMES, good_t, [[0.0, 0.0], [float("nan"), 0.1]])
    out.append(("nan", m, "nan"))
    m = trajectory([], good_t, [[], []])
    out.append(("no names", m, "no joint names"))
    return out


@pytest.mark.timeout(90)
def test_malformed_trajectories_rejected_with_reason(harness):
    cases = _bad_messages()
    for label, msg, reason in cases:
        # one at a time: ~/feasibility keeps only the last verdict (depth 1, transient local)
        harness.traj_pub.publish(msg)
        arr = harness.verdict(msg)
        top = arr.status[0]
        assert top.name == STATUS_NAME, label
        assert top.level[0] == ERROR, label
        assert reason in top.message, (label, top.message)
        values = kv(top)
        for key in SUMMARY_KEYS:
            assert key in values, (label, key)
        assert values["failure_label"] == PLANNING_ERROR
        assert values["feasible"] == "false"
    # a rejected trajectory produces no ~/trajectory_effort
    assert not any(same(m.header.stamp, msg.header.stamp) for _, msg, _ in cases
                   for m in harness.got["teff"])


@pytest.mark.timeout(180)
def test_hundred_thousand_points_checked_while_joint_states_answered(harness):
    n = 100_000
    t = np.linspace(0.0, 100.0, n)
    # from where the robot is (its joint_states below: [0.1, 0.2] at rest), else a jump
    P = np.column_stack([0.1 + 0.3 * (1 - np.cos(2 * np.pi * t / 20)),
                         0.2 + 0.2 * (1 - np.cos(2 * np.pi * t / 25))])
    # with velocities (cubic): positions alone the controller interpolates linearly
    V = np.column_stack([0.3 * 2 * np.pi / 20 * np.sin(2 * np.pi * t / 20),
                         0.2 * 2 * np.pi / 25 * np.sin(2 * np.pi * t / 25)])
    msg = JointTrajectory()
    msg.header.stamp = next_stamp()
    msg.joint_names = NAMES
    msg.points = [JointTrajectoryPoint(positions=[float(a), float(b)], velocities=[float(c), float(d)],
                                       time_from_start=dur(float(x)))
                  for x, a, b, c, d in zip(t, P[:, 0], P[:, 1], V[:, 0], V[:, 1])]
    harness.traj_pub.publish(msg)
    answered_before_verdict = 0
    stamp = 9000.0
    done = lambda: any(same(a.header.stamp, msg.header.stamp) for a in harness.got["feas"])  # noqa: E731
    deadline = time.monotonic() + 150
    while not done() and time.monotonic() < deadline:
        stamp += 0.001
        js = JointState(name=NAMES, position=[0.1, 0.2], velocity=[0.0, 0.0])
        js.header.stamp = Time(sec=int(stamp), nanosec=int(round((stamp % 1) * 1e9)))
        harness.js_pub.publish(js)
        got = harness.wait(lambda: done() or any(same(g.header.stamp, js.header.stamp)
                                                 for g in harness.got["gravity"][-5:]), 20.0)
        assert got, "a joint_state went unanswered during the check"
        if not done():
            answered_before_verdict += 1
    arr = harness.verdict(msg, timeout=1.0)
    values = kv(arr.status[0])
    assert values["n_points"] == str(n)
    assert float(values["compute_time_s"]) > 0
    # 0.094 rad/s at most, mostly gravity: WARN only for the sampling bound (1.00001 ms
    # segments get one step each); positions alone would be linear: velocity steps
    assert values["feasible"] == "true", arr.status[0].message
    assert float(values["worst_ratio"]) < 0.9
    assert arr.status[0].level == bytes([WARN])
    assert arr.status[0].message.endswith("to bound memory)"), arr.status[0].message
    assert values["interpolation"] == "cubic" and values["velocity_steps"] == "0"
    print(f"answered {answered_before_verdict} joint_states during the check; compute_time_s {values['compute_time_s']}")
    assert answered_before_verdict >= 3, answered_before_verdict


def test_destroy_during_a_check_publishes_nothing_and_raises_nothing(ros_context, monkeypatch):
    """destroy_node waits only briefly for a check in progress; when that check ends after the
    publishers are gone, its verdict is dropped, not published into a destroyed handle (seen in
    CI as an InvalidHandle traceback during the SIGINT shutdown races)."""
    import threading

    from rclpy.serialization import serialize_message

    import dyn_node.core.check.feasibility as feasibility

    entered, release = threading.Event(), threading.Event()
    real_check = feasibility.check_trajectory

    def held_check(*args, **kwargs):
        entered.set()
        release.wait(10.0)
        return real_check(*args, **kwargs)

    monkeypatch.setattr(feasibility, "check_trajectory", held_check)
    node = DynNode(namespace="/destroy_race", context=ros_context,
                   parameter_overrides=[Parameter("robot_model", value="planar_2link")])
    times, P, V, A = rest_to_rest(4.0)
    node._jobs.put((serialize_message(trajectory(NAMES, times, P, V, A)), 0.0, node._core))
    assert entered.wait(10.0), "the worker never started the check"
    worker = node._worker
    node.destroy_node()          # the worker is inside the check: joined for 0.5 s, then left
    assert worker.is_alive()
    release.set()
    worker.join(10.0)
    assert not worker.is_alive()
    assert node._callback_errors == 0


START_TIMES = [0.5, 2.0]
START_P = [[0.5, 0.3], [1.5, 0.8]]
START_ZERO = [[0.0, 0.0], [0.0, 0.0]]


@pytest.mark.timeout(90)
def test_start_segment_checked_from_the_last_joint_states(harness):
    """The first point 0.5 s ahead and the robot moving away from it at 2.5 rad/s (its last
    joint_states): the node checks the segment the controller runs from that state, as the
    core does from the same state, and the verdict says so."""
    from dyn_node.core.check.feasibility import StartState

    node = harness.node
    # a long stale_timeout: the state must still count when the trajectory arrives under load
    assert node.set_parameters([Parameter("stale_timeout", value=60.0)])[0].successful
    try:
        qm, vm = [0.0, 0.3], [-2.5, 0.0]
        harness.make_current(qm, vm)
        msg = trajectory(NAMES, START_TIMES, START_P, START_ZERO, START_ZERO)
        harness.traj_pub.publish(msg)
        arr = harness.verdict(msg)
    finally:
        assert node.set_parameters([Parameter("stale_timeout", value=0.5)])[0].successful
    values = kv(arr.status[0])
    assert values["start_segment"] == "checked"
    age = float(values["start_state_age_s"])
    assert 0.0 <= age <= 60.0
    traj = validate_trajectory(NAMES, NAMES, START_TIMES, START_P, START_ZERO, START_ZERO)
    want = check_trajectory(Dynamics(MODEL), traj, timing=received(msg),
                            start=StartState(np.array(qm), np.array(vm), age_s=age))
    assert not want.feasible and want.time_scale_start_segment
    assert arr.status[0].level == bytes([ERROR])
    assert arr.status[0].message == want.message
    assert "(the segment from the current state binds)" in arr.status[0].message
    for key, value in want.summary_values().items():
        if key != "compute_time_s":
            assert values[key] == format_value(value), key
    # without the start segment this trajectory is feasible: the verdict is the segment's
    assert check_trajectory(Dynamics(MODEL), traj).feasible


@pytest.mark.timeout(90)
def test_start_segment_not_checked_without_joint_states(harness):
    """A node that has had no joint_states cannot know where the robot is: the verdict on a
    trajectory whose first point lies ahead is WARN and says the start segment was not checked."""
    fresh = Harness(harness.node.context, "/feas_no_state")
    try:
        msg = trajectory(NAMES, START_TIMES, START_P, START_ZERO, START_ZERO)
        fresh.traj_pub.publish(msg)
        arr = fresh.verdict(msg)
    finally:
        fresh.close()
    top = arr.status[0]
    values = kv(top)
    assert values["start_segment"] == "not_checked (no current state within stale_timeout)"
    assert values["start_state_age_s"] == "nan"
    assert values["feasible"] == "true"
    assert top.level == bytes([WARN])
    assert top.message.endswith("(start segment not checked (no current state within stale_timeout))")
    assert values["failure_label"] == PLANNING_ERROR


@pytest.mark.timeout(90)
def test_start_segment_not_checked_when_the_state_is_stale(harness):
    """joint_states older than stale_timeout are not the robot's current state."""
    node = harness.node
    harness.make_current([0.0, 0.3], [-2.5, 0.0])
    assert node.set_parameters([Parameter("stale_timeout", value=0.001)])[0].successful
    try:
        msg = trajectory(NAMES, START_TIMES, START_P, START_ZERO, START_ZERO)
        harness.traj_pub.publish(msg)
        arr = harness.verdict(msg)
    finally:
        assert node.set_parameters([Parameter("stale_timeout", value=0.5)])[0].successful
    values = kv(arr.status[0])
    assert values["start_segment"] == "not_checked (no current state within stale_timeout)"
    assert arr.status[0].level == bytes([WARN]) and values["feasible"] == "true"


@pytest.mark.timeout(90)
def test_check_request_starts_from_the_last_joint_states_too(harness):
    """~/check_trajectory with from_current_state is checked like joint_trajectory: from the
    robot's current state (and dyn-audit replays both so)."""
    from dyn_node_interfaces.srv import CheckTrajectory

    node = harness.node
    cli = harness.probe.create_client(CheckTrajectory, "dyn_node/check_trajectory")
    assert harness.wait(cli.service_is_ready)
    assert node.set_parameters([Parameter("stale_timeout", value=60.0)])[0].successful
    try:
        harness.make_current([0.0, 0.3], [-2.5, 0.0])
        msg = trajectory(NAMES, START_TIMES, START_P, START_ZERO, START_ZERO)
        fut = cli.call_async(CheckTrajectory.Request(trajectory=msg, from_current_state=True))
        assert harness.wait(fut.done)
        r = fut.result()
    finally:
        assert node.set_parameters([Parameter("stale_timeout", value=0.5)])[0].successful
        harness.probe.destroy_client(cli)
    values = kv(r.statuses[0])
    assert r.accepted and r.start_segment == values["start_segment"] == "checked"
    assert list(r.start_state.position) == [0.0, 0.3] and list(r.start_state.velocity) == [-2.5, 0.0]
    assert not r.feasible and values["feasible"] == "false" and values["time_scale_start_segment"] == "true"


# --- task limits (#18): frame_limits and robot_limits statuses on ~/feasibility -----------------
TASK_LIMITS = """\
joint_limits: {}
frame_limits:
  tool: {max_linear_speed: 1.0}
robot_limits: {max_kinetic_energy: 1.0}
"""
Q2 = 0.3  # joint2 held: the tool circles joint1's axis at r = |l1 + l2·e^(i·q2)|
R_TOOL = math.sqrt(0.5 ** 2 + 0.4 ** 2 + 2 * 0.5 * 0.4 * math.cos(Q2))
I_AXIS = 1.5 * 0.5 ** 2 + 1.0 * R_TOOL ** 2  # point masses: m1 at l1, m2 at the tool


@pytest.fixture(scope="module")
def task_harness(module_ros_context, tmp_path_factory):
    path = tmp_path_factory.mktemp("task") / "limits.yaml"
    path.write_text(TASK_LIMITS)
    h = Harness(module_ros_context, "/feas_task", (Parameter("limits_file", value=str(path)),))
    yield h
    h.close()


@pytest.mark.timeout(90)
@pytest.mark.parametrize("duration", [2.0, 4.0])
def test_task_place_statuses_reach_feasibility_with_closed_form_peaks(task_harness, duration):
    """joint1 0 → 2 rad quintic, joint2 still: peak q̇1 = 1.875·2/D at t = D/2 (a sample), so the
    tool's peak speed is R·q̇1 and the kinetic energy ½·I·q̇1² (point masses about joint1's axis)."""
    times, P = [0.0, duration], [[0.0, Q2], [2.0, Q2]]
    Z = [[0.0, 0.0], [0.0, 0.0]]
    msg = trajectory(NAMES, times, P, Z, Z)
    task_harness.traj_pub.publish(msg)
    arr = task_harness.verdict(msg)
    names = [s.name for s in arr.status]
    assert names == [STATUS_NAME, *(f"{STATUS_NAME}/{n}" for n in NAMES),
                     f"{STATUS_NAME}/tool", f"{STATUS_NAME}/robot_limits"]
    qd = 1.875 * 2 / duration
    speed, energy = R_TOOL * qd, 0.5 * I_AXIS * qd ** 2
    tool, robot = kv(arr.status[3]), kv(arr.status[4])
    assert float(tool["frame_speed_peak"]) == pytest.approx(speed, rel=1e-9)
    assert float(tool["frame_speed_ratio"]) == pytest.approx(speed / 1.0, rel=1e-9)
    assert float(tool["frame_speed_time_s"]) == pytest.approx(duration / 2, abs=1e-12)
    assert float(robot["kinetic_energy_peak"]) == pytest.approx(energy, rel=1e-9)
    assert float(robot["kinetic_energy_limit"]) == 1.0
    top = kv(arr.status[0])
    # speed scales as 1/k, energy as 1/k²: the tool's speed sets k when it binds
    want_k = max(speed, math.sqrt(energy), qd / 3.0)
    assert float(top["time_scale"]) == pytest.approx(want_k, rel=1e-9)
    if duration == 2.0:
        # the worst ratio is the energy's (≈ 2.05 > 1.67), the time scale the speed's
        assert top["feasible"] == "false" and top["worst_joint"] == "robot_limits"
        assert top["worst_constraint"] == "kinetic_energy"
        assert float(top["worst_ratio"]) == pytest.approx(energy, rel=1e-9)
        assert (top["time_scale_joint"], top["time_scale_constraint"]) == ("tool", "frame_speed")
        assert arr.status[3].level == bytes([ERROR]) and arr.status[4].level == bytes([ERROR])
        assert tool["failure_label"] == PLANNING_ERROR
    else:
        assert top["feasible"] == "true"
        assert arr.status[3].level in (bytes([OK]), bytes([WARN]))
    # the node publishes exactly the core's statuses for the same model and trajectory
    model = load_model(builtin="planar_2link", limits_yaml=TASK_LIMITS)
    want = check_trajectory(Dynamics(model), validate_trajectory(NAMES, NAMES, times, P, Z, Z),
                            timing=received(msg))
    for st, ref in zip(arr.status, want.statuses(model.name)):
        assert st.name == ref.name and st.message == ref.message
        got = kv(st)
        for key, value in ref.values.items():
            if "compute_time" not in key:
                assert got[key] == format_value(value), (st.name, key)


def test_alternating_workers_build_each_dynamics_once(monkeypatch):
    """Two worker threads taking 20 jobs in turn build one Dynamics each (a shared cache cleared
    on every miss rebuilt one per job), and a replaced model is rebuilt once per thread."""
    import threading
    from concurrent.futures import ThreadPoolExecutor
    from types import SimpleNamespace

    from dyn_node.core.robot.settings import Settings
    from dyn_node.ros.node import trajectories

    built: list[int] = []
    real = trajectories.Dynamics

    def counting(*args, **kwargs):
        built.append(threading.get_ident())
        return real(*args, **kwargs)

    monkeypatch.setattr(trajectories, "Dynamics", counting)
    worker = type("Worker", (trajectories.TrajectoryWorker,), {})()
    worker._worker_dyn = threading.local()
    settings = Settings(robot_model="planar_2link")
    pools = [ThreadPoolExecutor(1), ThreadPoolExecutor(1)]
    try:
        def run(core, n: int) -> list:
            return [pools[i % 2].submit(worker._worker_dynamics, core).result(timeout=30)
                    for i in range(n)]

        got = run(SimpleNamespace(model=MODEL, settings=settings), 20)
        assert len(built) == 2 and len(set(built)) == 2
        assert got[0] is not got[1] and all(d is got[i % 2] for i, d in enumerate(got))
        other = load_model(builtin="planar_2link")
        again = run(SimpleNamespace(model=other, settings=settings), 6)
        assert len(built) == 4 and all(d.model is other for d in again)
        assert again[0] is not again[1] and all(d is again[i % 2] for i, d in enumerate(again))
    finally:
        for p in pools:
            p.shutdown()
