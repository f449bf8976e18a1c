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
import json
import math
import os
import random
import shutil
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.errors import PLANNING_ERROR, InputError, TrajectoryError
from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
from dyn_node.core.robot.model import load_model
from dyn_node.core.live.monitor import Monitor
from dyn_node.core.robot.settings import Settings
from dyn_node.core.robot.status import ERROR, OK, WARN
from dyn_node.core.check.trajectory import Trajectory, validate_trajectory

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

    from dyn_node.ros.convert import parse_joint_trajectory_cdr, trajectory_arrays

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
    _assert_verdict_consistent(r)


def _assert_verdict_consistent(r) -> None:
    """Every field a client reads tells the same story (README, summary status): feasible exactly
    when nothing is violated and k <= 1; OK/WARN/ERROR and the label by the documented rule."""
    assert isinstance(r.feasible, bool) and r.feasible == (not r.violations), (r.feasible, r.violations)
    assert not math.isnan(r.time_scale) and r.time_scale >= 0.0
    assert r.feasible == (r.time_scale <= 1.0), (r.time_scale, r.message)
    assert r.message.startswith("feasible: " if r.feasible else "infeasible: "), r.message
    ratios = [e["ratio"] for kinds in r.per_joint.values() for kind, e in kinds.items()
              if kind != "position" and e["ratio"] is not None]
    assert r.worst_ratio == max(ratios, default=0.0)
    if not r.feasible:
        expected = ERROR
    elif r.worst_ratio > r.effort_warn_ratio or r.warnings:
        expected = WARN
    else:
        expected = OK
    assert r.level == expected, (r.level, r.message, r.warnings)
    assert r.failure_label == ("" if expected == OK else PLANNING_ERROR)


@st.composite
def valid_trajectories(draw):
    """Well-formed planar_2link trajectories (the mostly-malformed ones above rarely get checked):
    increasing times, positions across and beyond the limits, sometimes velocities."""
    n = draw(st.integers(2, 5))
    times = np.cumsum(draw(st.lists(st.floats(0.05, 2.0), min_size=n, max_size=n)))
    pos = np.array(draw(st.lists(st.lists(st.floats(-3.2, 3.2), min_size=2, max_size=2),
                                 min_size=n, max_size=n)))
    vel = None
    if draw(st.booleans()):
        vel = np.array(draw(st.lists(st.lists(st.floats(-6, 6), min_size=2, max_size=2),
                                     min_size=n, max_size=n)))
    return validate_trajectory(PLANAR.joint_names, PLANAR.joint_names, times, pos, vel, None)


def _holds_still(traj: Trajectory) -> bool:
    """Moves less than a micro-radian: its true k is below the ~1e-8 rounding residue pinned by
    test_held_pose_needs_no_time_scale."""
    tiny = 1e-6
    return bool(np.ptp(traj.positions, axis=0).max() < tiny
                and (traj.velocities is None or np.abs(traj.velocities).max() < tiny))


@pytest.mark.parametrize("q", [[0.0, 0.0], [0.5, -1.0]])
def test_held_pose_needs_no_time_scale(q):
    """Nothing moves, so no speed-dependent limit binds: k = 0 (README: "no speed-dependent limit
    binds"), not a residue of g(q) subtracted from rnea(q, 0, 0)."""
    traj = validate_trajectory(PLANAR.joint_names, PLANAR.joint_names, [1.0, 2.0], [q, q], None, None)
    r = check_trajectory(Dynamics(PLANAR), traj)
    assert r.feasible and r.time_scale == 0.0, r.message


def _stretch(traj: Trajectory, k: float) -> Trajectory:
    return Trajectory(times=traj.times * k, positions=traj.positions,
                      velocities=None if traj.velocities is None else traj.velocities / k)


@settings(max_examples=40 * SCALE, deadline=None, derandomize=not FULL,
          suppress_health_check=[HealthCheck.too_slow])
@given(valid_trajectories())
def test_checked_verdicts_consistent_and_time_scale_contract(traj):
    """Random feasible and infeasible verdicts keep the README's rules, and k is what DESIGN says:
    stretched by 1.001·k the trajectory is feasible, by 0.97·k it is not."""
    dyn, opts = Dynamics(PLANAR), FeasibilityOptions()   # the node's sample period: k's accuracy
    r = check_trajectory(dyn, traj, opts)
    _assert_verdict_consistent(r)
    assume(not _holds_still(traj))   # k of a held pose: test_held_pose_needs_no_time_scale
    k = r.time_scale
    if 0.0 < k < math.inf:
        assert check_trajectory(dyn, _stretch(traj, 1.001 * k), opts).feasible, (k, r.message)
        assert not check_trajectory(dyn, _stretch(traj, 0.97 * k), opts).feasible, (k, r.message)
    elif k == math.inf:  # "no slowdown helps"
        assert not check_trajectory(dyn, _stretch(traj, 100.0), opts).feasible, r.message


@settings(max_examples=300 * SCALE, deadline=None, derandomize=not FULL)
@given(st.binary(max_size=400))
def test_trajectory_cdr_reader_random_bytes(data):
    """Random bytes (what a corrupt sample would be): only the errors the node catches before
    falling back to rclpy's deserialiser."""
    import struct

    from dyn_node.ros.convert import parse_joint_trajectory_cdr

    try:
        parse_joint_trajectory_cdr(b"\x00\x01\x00\x00" + data if data[:1] == b"!" else data)
    except (ValueError, IndexError, struct.error, UnicodeDecodeError):
        pass


# --- bag corruption ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_bag(tmp_path_factory) -> Path:
    """A small Panda bag written by the recorder: 300 joint_states at 1 kHz, description inside,
    inside every limit (so a damaged copy that still audits can only be partial, or a value the
    damage changed)."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from dyn_node.bag.recorder import Recorder, RecorderConfig, TopicInfo, qos_profile_dict

    d = tmp_path_factory.mktemp("fuzzbag")
    mid = (PANDA.limits.position_lower + PANDA.limits.position_upper) / 2
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
        m.position = [float(mid[k]) + 0.1 * math.sin(0.01 * i + k) for k in range(7)]
        m.velocity = [0.1 * math.cos(0.01 * i + k) for k in range(7)]
        rec.write("/joint_states", serialize_message(m), t0 + i * 10**6 + 1000)
    stats = rec.close()
    assert stats.topics["/joint_states"].written == 300
    return Path(stats.path)


@st.composite
def corruptions(draw) -> tuple[list[tuple[float, int]], float | None]:
    """1-8 bytes set anywhere in the file, and half the time a cut, both uniformly placed:
    hypothesis's own floats pile up at 0.0, the magic, where every damage reads as "not an MCAP
    file" and nothing past it is exercised."""
    rng = random.Random(draw(st.integers(0, 2**32 - 1)))
    edits = [(rng.random(), rng.randrange(256)) for _ in range(draw(st.integers(1, 8)))]
    return edits, (rng.random() if draw(st.booleans()) else None)


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


def test_undecodable_description_record_makes_the_audit_partial(small_bag, tmp_path):
    """One byte of the dyn_node metadata record's URDF made invalid UTF-8 (found by the corrupt-bag
    fuzz): dyn-bag-recover skips that record and exits 3; the audit must not read a description
    nobody wrote and call the bag whole (exit 0)."""
    from dyn_node.audit.bag_audit import main as audit
    from dyn_node.bag.recover import main as recover

    src = next(small_bag.glob("*.mcap")).read_bytes()
    at = src.index(b"</visual>\n") + len(b"</visual>")   # a newline inside the description
    assert src.index(b"robot_description") < at < src.index(b"/joint_states")
    bag = _corrupt(small_bag, tmp_path / "bag", [(at / len(src), 0xE9)], None)
    code, out, err = _run(recover, [str(next(bag.glob("*.mcap"))), "-o", str(tmp_path / "r.mcap")])
    assert code == 3 and "0 metadata records kept" in out, out
    code, out, err = _run(audit, [str(bag), "--out", str(tmp_path / "audit"), "--no-report"])
    rec = json.loads((tmp_path / "audit" / "evidence.json").read_text())
    assert code == 3 and rec["input_quality"]["unreadable_ranges"], (code, out, rec["input_quality"])
    assert any("dyn_node metadata record is damaged" in f for f in rec["verdict"]["findings"]), rec


def _data_section_records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of every record of a file's data section, up to Data End."""
    import struct

    out, off = [], 8
    while off + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, off)
        out.append((off, op, length))
        if op == 0x0F:
            break
        off += 9 + length
    return out


def test_damage_only_in_a_message_index_loses_nothing_in_both_tools(small_bag, tmp_path):
    """One byte changed in a Message Index record (outside every chunk; both tools rebuild it):
    nothing was lost, so dyn-bag-recover exits 0 with a note naming that record, and dyn-audit
    exits 0 with the same note and data_crc "index_only". One byte changed in the metadata
    record instead (no CRC of its own, the data-section CRC the only witness): both say the
    file cannot be vouched for (recover 3, audit partial 3)."""
    from dyn_node.audit.bag_audit import main as audit
    from dyn_node.bag.recover import main as recover

    mcap = next(small_bag.glob("*.mcap"))
    data = mcap.read_bytes()
    recs = _data_section_records(data)
    at, _op, length = [r for r in recs if r[1] == 0x07][1]
    bag = _corrupt(small_bag, tmp_path / "idx", [], None)
    f = next(bag.glob("*.mcap"))
    damaged = bytearray(data)
    damaged[at + 9 + length - 3] ^= 0x40  # a high byte of the last entry's record offset
    f.write_bytes(bytes(damaged))
    code, out, err = _run(recover, [str(f), "-o", str(tmp_path / "r.mcap")])
    note = (f"{f.name}: data section CRC mismatch, all of it in the message index record(s) at "
            f"byte {at} (rebuilt from their chunks, the CRC then matches): nothing lost")
    assert code == 0 and f"  note: {note}" in out and "lost:" not in out, out
    assert _contents(tmp_path / "r.mcap") == _contents(mcap)
    code, out, err = _run(audit, [str(bag), "--out", str(tmp_path / "a"), "--no-report"])
    q = json.loads((tmp_path / "a" / "evidence.json").read_text())["input_quality"]
    assert code == 0 and q["data_crc"] == {f.name: "index_only"} and q["notes"] == [note], (code, q)
    assert q["unreadable_ranges"] == []

    (meta_at, _, meta_len), = [r for r in recs if r[1] == 0x0C]
    damaged = bytearray(data)
    k = data.index(b"\x07\x00\x00\x00version", meta_at, meta_at + 9 + meta_len) + 11
    damaged[k + 4 + data[k] - 1] ^= 0x01  # the last digit of the version: still UTF-8, parses
    f.write_bytes(bytes(damaged))
    code, out, err = _run(recover, [str(f), "-o", str(tmp_path / "r2.mcap")])
    assert code == 3 and "lost: data section CRC mismatch" in out, out
    code, out, err = _run(audit, [str(bag), "--out", str(tmp_path / "a2"), "--no-report"])
    rec = json.loads((tmp_path / "a2" / "evidence.json").read_text())
    assert code == 3 and rec["input_quality"]["data_crc"] == {f.name: "mismatch"}, (code, out)
    assert [u["reason"] for u in rec["input_quality"]["unreadable_ranges"]] == [
        f"{f.name}: data section CRC mismatch outside every chunk and message index (a record "
        "without a CRC of its own, e.g. metadata or a message outside a chunk, holds damaged "
        "bytes)"]


def test_intact_bag_audits_and_recovers(small_bag, tmp_path):
    from dyn_node.audit.bag_audit import main as audit
    from dyn_node.bag.recover import main as recover

    code, out, err = _run(audit, [str(small_bag), "--out", str(tmp_path / "a"), "--no-report"])
    assert code == 0 and "Traceback" not in err, (code, out, err)
    verdict = json.loads((tmp_path / "a" / "evidence.json").read_text())["verdict"]
    assert verdict["result"] == "feasible" and verdict["partial"] is False, verdict
    mcap = next(small_bag.glob("*.mcap"))
    code, out, err = _run(recover, [str(mcap), "-o", str(tmp_path / "r.mcap")])
    assert code == 0 and "nothing lost" in out, (out, err)


_counter = [0]


@settings(max_examples=25 * SCALE, deadline=None, derandomize=not FULL,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(corruptions())
def test_corrupt_bag_through_audit_and_recover(small_bag, tmp_path, damage):
    from dyn_node.audit.bag_audit import main as audit
    from dyn_node.bag.recover import main as recover

    _counter[0] += 1
    work = tmp_path / f"c{_counter[0]}"
    bag = _corrupt(small_bag, work / "bag", *damage)
    code, out, err = _run(audit, [str(bag), "--out", str(work / "audit"), "--no-report"])
    assert "Traceback" not in err + out
    if code == 2:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("dyn-audit: error:"), err
    else:   # the README's codes: 1 violations (wins), 3 partial, 0 only for a whole, clean audit
        rec = json.loads((work / "audit" / "evidence.json").read_text())
        verdict, unreadable = rec["verdict"], rec["input_quality"]["unreadable_ranges"]
        assert verdict["partial"] == bool(unreadable), (verdict, unreadable)
        expected = 1 if verdict["result"] == "violations" else 3 if unreadable else 0
        assert code == verdict["exit_code"] == expected, (code, verdict, unreadable)
    audit_code = code
    mcap = next(bag.glob("*.mcap"))
    code, out, err = _run(recover, [str(mcap), "-o", str(work / "r.mcap")])
    assert "Traceback" not in err + out
    assert code in (0, 1, 3), (code, err)
    if code == 1:
        assert err.startswith("dyn-bag-recover: error:") or "nothing recoverable" in out, (out, err)
    if code == 3:
        assert "  lost: " in out, out
    if code == 0:
        assert "nothing lost" in out
    if audit_code == 0:   # the audit read all of it, so the recovered file holds all of it
        assert _contents(work / "r.mcap") == _contents(next(small_bag.glob("*.mcap"))), (out, err)


def _contents(path: Path) -> tuple[list, list]:
    """Messages and metadata records as the official ``mcap`` reader sees them from the start."""
    from mcap.stream_reader import StreamReader
    from mcap.records import Channel, Message, Metadata

    topics, messages, metadata = {}, [], []
    with open(path, "rb") as f:
        for r in StreamReader(f, skip_magic=False).records:
            if isinstance(r, Channel):
                topics[r.id] = r.topic
            elif isinstance(r, Message):
                messages.append((topics[r.channel_id], r.log_time, r.data))
            elif isinstance(r, Metadata):
                metadata.append((r.name, dict(r.metadata)))
    return messages, metadata
