"""dyn_sim with the press scene, as users run it (a separate process, DDS): ~/contact_truth only
while the hand touches the table, stamped like joint_states, and the 'dyn_sim: physics' status;
a bad scene file stops dyn_sim at start with the reason (exit 2, one line)."""
from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from conftest import kv
from test_sim_node import ARM, READY, sim_cmd, spin_until

from dyn_node.core.robot.model import load_model
from dyn_node.sim.press import PRESS_SCENE, plan_press
from dyn_node.sim.simulator import SimConfig, Simulator


def _interfaces():
    try:
        from dyn_node_interfaces.msg import ContactTruth
    except ImportError:
        pytest.skip("dyn_node_interfaces (ContactTruth) is not built into this environment")
    return ContactTruth


def _press_trajectory():
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    sim = Simulator(load_model(builtin="panda"), SimConfig(scene=PRESS_SCENE, initial_positions=tuple(READY)))
    times, positions, velocities = plan_press(sim).waypoints()
    msg = JointTrajectory(joint_names=ARM)  # zero stamp: on receipt
    for t, p, v in zip(times, positions, velocities):
        msg.points.append(JointTrajectoryPoint(positions=p, velocities=v,
                                               time_from_start=Duration(sec=int(t), nanosec=int(round((t % 1) * 1e9)))))
    return msg


@pytest.mark.timeout(90)
def test_press_publishes_truth_and_physics_status(ros_context, spawn):
    ContactTruth = _interfaces()
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory

    from dyn_node.ros.qos import LATCHED_HISTORY

    proc = spawn(sim_cmd("scene_file:=config/press_scene.yaml", "physics_diagnostics_period:=0.5"))
    node = Node("press_probe", context=ros_context)
    js, truth, diag = [], [], []
    node.create_subscription(JointState, "joint_states", js.append, 1000)
    node.create_subscription(ContactTruth, "/dyn_sim/contact_truth", truth.append, LATCHED_HISTORY)
    node.create_subscription(DiagnosticArray, "/diagnostics",
                             lambda m: diag.extend(s for s in m.status if s.name == "dyn_sim: physics"), 100)
    pub = node.create_publisher(JointTrajectory, "/joint_trajectory_controller/joint_trajectory", 10)
    try:
        spin_until(ros_context, node, lambda: len(diag) >= 2 and pub.get_subscription_count() > 0, 45,
                   "dyn_sim and two physics statuses")
        assert truth == []  # READY touches nothing: no truth published
        pub.publish(_press_trajectory())
        spin_until(ros_context, node, lambda: len(truth) >= 200, 40, "200 contact truth messages")
        spin_until(ros_context, node, lambda: float(kv(diag[-1])["max_penetration_m"]) > 0, 10,
                   "a physics status of the press")
        # each truth shares its step's joint_states stamp; the last truths' joint_states may
        # still be queued when the spinning above stops, so wait for them (not for later ones)
        needed = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in truth[-50:]}
        spin_until(ros_context, node, lambda: needed <= {(m.header.stamp.sec, m.header.stamp.nanosec)
                                                         for m in js[-3000:]}, 10,
                   "the joint_states of the last 50 contact truths")
    finally:
        node.destroy_node()
    last = truth[-1]
    assert last.header.frame_id == "panda_link0"
    assert set(last.link_names) <= {"panda_leftfinger", "panda_rightfinger", "panda_hand"} and last.link_names
    assert len(last.link_names) == len(last.link_wrenches)
    normal_force = 0.0
    for c in last.contacts:
        n = np.array([c.normal.x, c.normal.y, c.normal.z])
        f = np.array([c.force.x, c.force.y, c.force.z])
        assert c.body2 == "table" and c.body1 in last.link_names
        assert n @ [0, 0, -1] > 0.99 and 0 < c.penetration_depth < 5e-3
        assert abs(c.position.z - 0.40) < 5e-3  # on the table's top face
        normal_force += -f @ n
    assert normal_force > 20.0
    st = diag[-1]
    values = kv(st)
    assert st.level == bytes([0]), st.message
    assert {"solver_iterations_max", "solver_residual", "energy_j", "work_constraints_j", "energy_error_rel",
            "warnings"} <= set(values)
    assert float(values["energy_error_rel"]) < 1e-2 and values["warnings"] == "none"
    assert any(int(kv(s)["solver_iterations_max"]) > 0 for s in diag)  # the solver ran in contact
    rc, _, err = proc.stop(signal.SIGINT)
    assert rc == 0, err


@pytest.mark.timeout(60)
def test_bad_scene_file_stops_at_start(spawn, tmp_path):
    bad = tmp_path / "scene.yaml"
    bad.write_text("objects:\n  - {name: t, type: box, size: [0.4, -0.8, 0.4], position: [0.5, 0, 0.2]}\n")
    proc = spawn(sim_cmd(f"scene_file:={bad}"))
    out, err = proc.proc.communicate(timeout=30)  # exits by itself
    assert proc.proc.returncode == 2  # issue 37: a scene file that cannot be used is bad input (2)
    assert "object 't': size must be positive" in out + err


@pytest.mark.timeout(60)
def test_a_fifo_scene_file_stops_at_start_in_one_line(spawn, tmp_path):
    """A FIFO as scene_file (no writer: reading it used to hang) ends dyn_sim at once: exit 2,
    one line on stderr, no traceback."""
    fifo = tmp_path / "scene.fifo"
    os.mkfifo(fifo)
    proc = spawn(sim_cmd(f"scene_file:={fifo}"))
    out, err = proc.proc.communicate(timeout=30)
    assert proc.proc.returncode == 2
    assert [ln for ln in err.splitlines() if ln.startswith("dyn_sim: ")] == [
        f"dyn_sim: state error: scene file {fifo} cannot be read: is a FIFO, not a regular file"]
    assert "Traceback" not in out + err
