"""Fuzzing (issue 9): hypothesis-generated JointState / JointTrajectory contents through the node's
conversions and the core, and random byte corruption of a bag through dyn-audit and
dyn-bag-recover. The only acceptable failures are our own clear errors: DynNodeError subclasses
from the core, exit codes 1-3 with a one-line ``error:`` message from the commands; never another
exception, never a traceback.

Sizes are CI-sized (bounded example counts, no deadline flakiness on a busy machine); set
``DYN_RELIABILITY_FULL=1`` for ten times the examples.
"""
from __future__ import annotations

import io
import math
import os
import shutil
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dyn_node.dynamics import Dynamics
from dyn_node.errors import InputError, TrajectoryError
from dyn_node.feasibility import FeasibilityOptions, check_trajectory
from dyn_node.model import load_model
from dyn_node.monitor import Monitor
from dyn_node.settings import Settings
from dyn_node.trajectory import validate_trajectory

FULL = os.environ.get("DYN_RELIABILITY_FULL") == "1"
SCALE = 10 if FULL else 1
PLANAR = load_model(builtin="planar_2link")
PANDA = load_model(builtin="panda")
MODELS = {"planar_2link": PLANAR, "panda": PANDA}
FUZZ = settings(max_examples=150 * SCALE, deadline=None, derandomize=not FULL,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# any float, biased towards the ones that break things
floats = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                   st.sampled_from([0.0, -0.0, 1e308, -1e308, 5e-324, math.nan, math.inf, -math.inf]),
                   st.floats(-10, 10))


def names_for(model):
    known = list(model.joint_names) + ["panda_finger_joint1", "unknown", ""]
    return st.lists(st.one_of(st.sampled_from(known), st.text(max_size=8)), max_size=10)


@st.composite
def joint_states(draw, model):
    """Names, position, velocity, effort of any lengths; usually consistent, sometimes not."""
    if draw(st.booleans()):
        names = draw(st.permutations(list(model.joint_names)))
        names = names + draw(st.lists(st.sampled_from(["panda_finger_joint1", "extra"]), max_size=2,
                                      unique=True))
    else:
        names = draw(names_for(model))
    n = len(names)
    def arr(allow_empty=True):
        k = draw(st.sampled_from([n, n, n, 0] if allow_empty else [n, n, n + 1, max(n - 1, 0)]))
        if draw(st.integers(0, 9)) == 0:
            k = draw(st.integers(0, 12))
        return draw(st.lists(floats, min_size=k, max_size=k))
    return names, arr(False), arr(), arr()


# Absurd but finite velocities (≈1e308) overflow the finite-difference acceleration to inf,
# which the torque check then reports; NumPy's warning about it is expected here, and silencing
# it in the monitor would cost every joint_states message an errstate context (~3 µs).
@pytest.mark.filterwarnings("ignore:overflow encountered in divide:RuntimeWarning")
@pytest.mark.parametrize("model_name", ["planar_2link", "panda"])
def test_joint_state_conversion_and_monitor_only_clear_errors(model_name):
    model = MODELS[model_name]
    mon = Monitor(model, Settings())
    t = [1.0]

    @FUZZ
    @given(joint_states(model), st.one_of(st.floats(0, 1e6), st.just(0.0), st.floats()))
    def run(js, stamp):
        names, pos, vel, eff = js
        try:
            s = model.to_model_order(names, pos, vel, eff)
        except InputError as exc:
            assert exc.code and str(exc)
        else:
            assert np.all(np.isfinite(s.q)) and len(s.q) == model.nv
            assert s.v is None or (len(s.v) == model.nv and np.all(np.isfinite(s.v)))
        t[0] += 0.001
        r = mon.process(names, pos, vel, eff, stamp, t[0])  # never raises
        if r.accepted:
            assert len(r.q) == len(r.tau) == len(r.gravity) == model.nv
            assert np.all(np.isfinite(r.q)) and np.all(np.isfinite(r.v))
            # nothing non-finite is ever published (|q̇| ~ 1e300 overflows the dynamics)
            assert np.all(np.isfinite(r.tau)) and np.all(np.isfinite(r.gravity))
        else:
            assert isinstance(r.error, InputError) and r.error.code
        # reports stay buildable whatever came in
        assert mon.statuses(t[0], "fuzz")

    run()
    c = mon.counts
    assert c.received == c.accepted + c.invalid


def _msg(names, times, P, V, A):
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    m = JointTrajectory()
    m.joint_names = list(names)
    pts = []
    for i, tm in enumerate(times):
        p = JointTrajectoryPoint()
        sec = int(math.floor(tm))
        p.time_from_start.sec = sec
        p.time_from_start.nanosec = min(int((tm - sec) * 1e9), 999_999_999)
        p.positions = P[i]
        p.velocities = V[i]
        p.accelerations = A[i]
        pts.append(p)
    m.points = pts
    return m


@st.composite
def trajectories(draw):
    model = PLANAR
    names = draw(st.one_of(st.permutations(list(model.joint_names)), names_for(model)))
    n = len(names)
    npts = draw(st.integers(0, 6))
    times = sorted(draw(st.lists(st.floats(0, 5), min_size=npts, max_size=npts)))
    if draw(st.booleans()):
        times = draw(st.lists(st.floats(0, 5), min_size=npts, max_size=npts))  # any order
    def rows(empty_ok):
        k = draw(st.sampled_from([n, n, 0] if empty_ok else [n, n, n + 1]))
        return [draw(st.lists(st.one_of(floats, st.floats(-3, 3)), min_size=k, max_size=k))
                if draw(st.integers(0, 7)) else draw(st.lists(floats, max_size=4))
                for _ in range(npts)]
    return names, times, rows(False), rows(True), rows(True)


@FUZZ
@given(trajectories())
def test_trajectory_conversion_validation_and_check_only_clear_errors(tr):
    """rclpy serialises the message; the node's own CDR reader must read back exactly what
    rclpy's objects hold; validation and the feasibility check raise only TrajectoryError."""
    from rclpy.serialization import deserialize_message, serialize_message
    from trajectory_msgs.msg import JointTrajectory

    from dyn_node.ros_convert import parse_joint_trajectory_cdr, trajectory_arrays

    names, times, P, V, A = tr
    data = serialize_message(_msg(names, times, P, V, A))
    raw = parse_joint_trajectory_cdr(data)
    # the oracle is what a subscriber gets from rclpy (e.g. a name cut at an embedded NUL)
    ref = trajectory_arrays(deserialize_message(data, JointTrajectory))
    assert raw.names == ref[0] and raw.times == ref[1]
    for mine, theirs in zip(raw.fields[:3], ref[2:]):
        assert len(mine) == len(theirs)
        for a, b in zip(mine, theirs):
            np.testing.assert_array_equal(np.asarray(a, dtype=float), np.asarray(b, dtype=float))
    try:
        traj = validate_trajectory(PLANAR.joint_names, raw.names, raw.times, *raw.fields[:3])
    except TrajectoryError as exc:
        assert exc.code and str(exc)
        return
    assert np.all(np.isfinite(traj.positions))
    try:
        r = check_trajectory(Dynamics(PLANAR), traj, FeasibilityOptions(sample_period=0.01,
                                                                        max_samples=20_000))
    except TrajectoryError as exc:
        assert exc.code and str(exc)
        return
    assert r.feasible in (True, False) and r.level in (0, 1, 2)
    assert r.time_scale >= 0 and not math.isnan(r.time_scale)


@settings(max_examples=300 * SCALE, deadline=None, derandomize=not FULL)
@given(st.binary(max_size=400))
def test_trajectory_cdr_reader_random_bytes(data):
    """Random bytes (what a corrupt sample would be): only the errors the node catches before
    falling back to rclpy's deserialiser."""
    import struct

    from dyn_node.ros_convert import parse_joint_trajectory_cdr

    try:
        parse_joint_trajectory_cdr(b"\x00\x01\x00\x00" + data if data[:1] == b"!" else data)
    except (ValueError, IndexError, struct.error, UnicodeDecodeError):
        pass


# --- bag corruption ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_bag(tmp_path_factory) -> Path:
    """A small Panda bag written by the recorder: 300 joint_states at 1 kHz, description inside."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from dyn_node.recording import Recorder, RecorderConfig, TopicInfo, qos_profile_dict

    d = tmp_path_factory.mktemp("fuzzbag")
    rec = Recorder(RecorderConfig(directory=str(d), chunk_size=4096, fsync=False),
                   robot_description=PANDA.urdf,
                   parameters_yaml="/dyn_node:\n  ros__parameters:\n    robot_model: panda\n")
    rec.add_topic(TopicInfo("/joint_states", "sensor_msgs/msg/JointState", (qos_profile_dict(),)))
    t0 = 1_700_000_000 * 10**9
    for i in range(300):
        m = JointState()
        m.header.stamp.sec = (t0 + i * 10**6) // 10**9
        m.header.stamp.nanosec = (t0 + i * 10**6) % 10**9
        m.name = list(PANDA.joint_names)
        m.position = [0.1 * math.sin(0.01 * i + k) for k in range(7)]
        m.velocity = [0.1 * math.cos(0.01 * i + k) for k in range(7)]
        rec.write("/joint_states", serialize_message(m), t0 + i * 10**6 + 1000)
    stats = rec.close()
    assert stats.topics["/joint_states"].written == 300
    return Path(stats.path)


corruptions = st.lists(st.tuples(st.floats(0, 1), st.integers(0, 255)), min_size=1, max_size=8)


def _corrupt(src: Path, dst: Path, edits, cut: float | None) -> Path:
    shutil.copytree(src, dst)
    mcap = next(dst.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    for where, byte in edits:
        data[min(int(where * len(data)), len(data) - 1)] = byte
    if cut is not None:
        data = data[:int(cut * len(data))]
    mcap.write_bytes(bytes(data))
    return dst


def _run(main, argv):
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def test_intact_bag_audits_and_recovers(small_bag, tmp_path):
    from dyn_node.audit import main as audit
    from dyn_node.bag_recover import main as recover

    code, out, err = _run(audit, [str(small_bag), "--out", str(tmp_path / "a"), "--no-report"])
    assert code in (0, 1) and "Traceback" not in err, err
    mcap = next(small_bag.glob("*.mcap"))
    code, out, err = _run(recover, [str(mcap), "-o", str(tmp_path / "r.mcap")])
    assert code == 0 and "nothing lost" in out, (out, err)


_counter = [0]


@settings(max_examples=25 * SCALE, deadline=None, derandomize=not FULL,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(corruptions, st.one_of(st.none(), st.floats(0, 1)))
def test_corrupt_bag_through_audit_and_recover(small_bag, tmp_path, edits, cut):
    from dyn_node.audit import main as audit
    from dyn_node.bag_recover import main as recover

    _counter[0] += 1
    work = tmp_path / f"c{_counter[0]}"
    bag = _corrupt(small_bag, work / "bag", edits, cut)
    code, out, err = _run(audit, [str(bag), "--out", str(work / "audit"), "--no-report"])
    assert "Traceback" not in err + out
    assert code in (0, 1, 2), (code, err)
    if code == 2:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("dyn-audit: error:"), err
    mcap = next(bag.glob("*.mcap"))
    code, out, err = _run(recover, [str(mcap), "-o", str(work / "r.mcap")])
    assert "Traceback" not in err + out
    assert code in (0, 1, 3), (code, err)
    if code == 1:
        assert err.startswith("dyn-bag-recover: error:") or "nothing recoverable" in out, (out, err)
    if code == 0:
        assert "nothing lost" in out
