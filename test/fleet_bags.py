"""Bags for the fleet tests and the fleet benchmark, written by dyn_node's own Recorder.

Each bag holds ``seconds`` of joint_states of one built-in robot (a slow sine about a pose inside
the limits), optionally a measured-effort spike over one joint's limit (a live violation) and
trajectories (``fast=True``: 20× too fast, infeasible), executed on ``/joint_trajectory`` or
asked as check-only questions on ``/dyn_node/check_trajectory``. The dyn_node metadata (URDF, parameters)
is written unless ``model=False``, which leaves a bag no model can be found for.
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

T0 = 1_700_000_000_000_000_000
PARAMS = "/dyn_node:\n  ros__parameters:\n    robot_model: {robot}\n"


@dataclass(frozen=True)
class BagSpec:
    """What :func:`write_bag` writes; ``start_s`` shifts the recording's start time."""

    name: str
    robot: str = "panda"
    seconds: float = 1.0
    rate_hz: float = 500.0
    spike: tuple[float, float] | None = None     # (start s, end s) of an effort spike on joint 2
    trajectories: tuple[bool, ...] = ()          # one per trajectory: True = too fast
    questions: tuple[bool, ...] = ()             # check-only requests (never executed): True = too fast
    model: bool = True
    start_s: float = 0.0


def _model(robot: str):
    from dyn_node.core.robot.model import load_model

    return load_model(builtin=robot)


def nominal_pose(model) -> np.ndarray:
    lo, hi = model.limits.position_lower, model.limits.position_upper
    mid = np.where(np.isfinite(lo) & np.isfinite(hi), 0.5 * (lo + hi), 0.0)
    return mid + 0.1


def _trajectory(model, stamp_ns: int, fast: bool, robot: tuple | None = None):
    """Rest at q0 → q0 + 0.3 → q0; ``robot`` (q, q̇): the first point there instead (the robot's
    state when it arrives: the controller steps to a first point due at once, so one elsewhere
    would be a jump)."""
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    m = JointTrajectory()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    m.joint_names = list(model.joint_names)
    q0 = nominal_pose(model)
    scale = 0.05 if fast else 2.0
    for k, t in enumerate((0.0, 0.5 * scale, 1.0 * scale)):
        p = JointTrajectoryPoint()
        p.positions = [float(x) for x in q0 + (0.3 if k == 1 else 0.0)]
        p.velocities = [0.0] * model.nv
        if k == 0 and robot is not None:
            p.positions, p.velocities = [float(x) for x in robot[0]], [float(x) for x in robot[1]]
        sec, ns = divmod(int(round(t * 1e9)), 1_000_000_000)
        p.time_from_start = Duration(sec=sec, nanosec=ns)
        m.points.append(p)
    return m


def write_bag(parent: Path, spec: BagSpec) -> Path:
    """Record ``spec`` under ``parent`` (a rosbag2 directory named after ``spec.name``)."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from dyn_node.bag.recorder import Recorder, RecorderConfig, TopicInfo

    model = _model(spec.robot)
    t0 = T0 + int(spec.start_s * 1e9)
    rec = Recorder(RecorderConfig(directory=str(parent), prefix=spec.name, fsync=False,
                                  chunk_size=64 * 1024, queue_size=1_000_000,
                                  queue_bytes=1 << 30),
                   robot_description=model.urdf if spec.model else "",
                   parameters_yaml=PARAMS.format(robot=spec.robot) if spec.model else "",
                   clock_ns=lambda: t0)  # the description copy's log time: the bag's start
    rec.add_topic(TopicInfo("/joint_states", "sensor_msgs/msg/JointState"))
    if spec.trajectories:
        rec.add_topic(TopicInfo("/joint_trajectory", "trajectory_msgs/msg/JointTrajectory"))
    if spec.questions:
        rec.add_topic(TopicInfo("/dyn_node/check_trajectory", "trajectory_msgs/msg/JointTrajectory"))
    n = int(round(spec.seconds * spec.rate_hz))
    dt = int(round(1e9 / spec.rate_hz))
    q0 = nominal_pose(model)
    ph = np.arange(model.nv) * 0.3
    limit = float(model.limits.effort[1])
    traj_at = {int(n * (k + 1) / (len(spec.trajectories) + 1)): fast
               for k, fast in enumerate(spec.trajectories)}
    ask_at = {int(n * (k + 1) / (len(spec.questions) + 1)) + 1: fast  # beside, never on, a trajectory
              for k, fast in enumerate(spec.questions)}
    m = JointState()
    m.header.frame_id = "base"
    m.name = list(model.joint_names)
    def state(i: int) -> tuple:
        t = i / spec.rate_hz
        return (q0 + 0.05 * np.sin(2 * np.pi * 0.5 * t + ph), 0.05 * np.pi * np.cos(2 * np.pi * 0.5 * t + ph))

    for i in range(n):
        t_ns = t0 + i * dt
        if i in traj_at:
            rec.write("/joint_trajectory", serialize_message(_trajectory(model, t_ns, traj_at[i], state(i))),
                      t_ns + 500)
        if i in ask_at:
            rec.write("/dyn_node/check_trajectory",
                      serialize_message(_trajectory(model, t_ns + 1, ask_at[i], state(i))), t_ns + 700)
        t = i / spec.rate_hz
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
        q, v = state(i)
        m.position = [float(x) for x in q]
        m.velocity = [float(x) for x in v]
        effort = [float("nan")] * model.nv
        if spec.spike and spec.spike[0] <= t < spec.spike[1]:
            effort[1] = limit * 1.05 + (t - spec.spike[0])  # peak at the spike's last sample
        m.effort = effort
        rec.write("/joint_states", serialize_message(m), t_ns)
    stats = rec.close(timeout=60.0)
    assert stats.topics["/joint_states"].written == n if n else True
    final = parent / spec.name  # a deterministic name (files keep theirs: metadata.yaml lists them)
    Path(stats.path).rename(final)
    return final


def truncate(bag: Path, fraction: float) -> Path:
    """Cut the bag's (first) MCAP file to ``fraction`` of its length, as a recorder that died."""
    f = sorted(bag.glob("*.mcap"))[0]
    data = f.read_bytes()
    f.write_bytes(data[: int(len(data) * fraction)])
    return bag


def damage_chunk(bag: Path, which: int = 1) -> Path:
    """Flip one byte inside chunk ``which`` of the bag's MCAP file (its CRC no longer matches)."""
    from mcap.reader import make_reader

    f = sorted(bag.glob("*.mcap"))[0]
    with open(f, "rb") as fh:
        chunks = sorted(make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    c = chunks[min(which, len(chunks) - 1)]
    data = bytearray(f.read_bytes())
    data[c.chunk_start_offset + c.chunk_length // 2] ^= 0x01
    f.write_bytes(bytes(data))
    return bag


def copy_bag(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def write_split_bag(parent: Path, name: str, seconds: float = 6.0, split_s: float = 1.0,
                    rate_hz: float = 500.0) -> Path:
    """``seconds`` of in-limit Panda joint_states recorded in files of ``split_s`` each (log time)."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from dyn_node.bag.recorder import Recorder, RecorderConfig, TopicInfo

    model = _model("panda")
    rec = Recorder(RecorderConfig(directory=str(parent), prefix=name, fsync=False, chunk_size=64 * 1024,
                                  max_bag_duration_s=split_s, queue_size=1_000_000, queue_bytes=1 << 30),
                   robot_description=model.urdf, parameters_yaml=PARAMS.format(robot="panda"),
                   clock_ns=lambda: T0)
    rec.add_topic(TopicInfo("/joint_states", "sensor_msgs/msg/JointState"))
    m = JointState()
    m.name, m.effort = list(model.joint_names), [float("nan")] * model.nv
    q0, dt = nominal_pose(model), int(round(1e9 / rate_hz))
    for i in range(int(round(seconds * rate_hz))):
        t_ns = T0 + i * dt
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
        m.position = [float(x) for x in q0 + 0.01 * np.sin(i / rate_hz)]
        m.velocity = [0.01 * float(np.cos(i / rate_hz))] * model.nv
        rec.write("/joint_states", serialize_message(m), t_ns)
    stats = rec.close(timeout=60.0)
    final = parent / name
    Path(stats.path).rename(final)
    return final
