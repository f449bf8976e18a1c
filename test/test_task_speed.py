"""What the check's fast path for the task kinds computes (issue #18, "Speed"): the frame
kernel's per-kg payload torque against Pinocchio's RNEA with 1 kg more, effective masses only
at the points asked for, the kinetic energy without M's factor, and one or two threads giving
the same verdict (the frame kernel's own RNEA: test_kernel_rnea)."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from dyn_node.core.check import feasibility, task_motion
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.feasibility import FeasibilityOptions, check_trajectory
from dyn_node.core.check.frames import FrameKinematics, FramePoint
from dyn_node.core.robot.model import Payload, load_model

TOL = 1e-9
PAYLOAD = Payload(1.5, (0.01, -0.02, 0.08), "panda_hand")
HOME = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8])
STEP = np.array([0.8, 0.4, -0.3, 0.5, 0.2, -0.3, 0.5])
SECTIONS = {
    "frame_limits": {"panda_link8": {"point": [0.0, 0.0, 0.1], "max_linear_speed": 5.0,
                                     "max_transferred_energy": 20.0},
                     "panda_link4": {"max_linear_acceleration": 50.0}},
    "robot_limits": {"max_kinetic_energy": 50.0},
    "task_wrench": {"frame": "panda_link8", "force": [3.0, -2.0, 20.0], "torque": [0.4, 0, 0]},
    "base_limits": {"max_force": 900.0, "max_moment": 400.0, "base_mass": 20.0,
                    "base_com": [0.0, 0.0, 0.1],
                    "support_polygon": [[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]]},
    "grasp": {"frame": "panda_hand", "normal_axis": [0.0, 1.0, 0.0],
              "friction_coefficient": 0.5, "grip_force": 80.0, "faces": 2},
}


def panda(sections: dict = SECTIONS, payload: Payload = PAYLOAD):
    effort = {"has_effort_limits": True, "max_effort": 80.0}
    joints = {f"panda_joint{i}": effort for i in range(1, 8)}
    return load_model(builtin="panda", limits_yaml={"joint_limits": joints, **sections},
                      payload=payload)


def traj(T: float = 1.5, n: int = 7) -> feasibility.Trajectory:
    t = np.linspace(0.0, T, n)
    return feasibility.Trajectory(times=t, positions=HOME + np.outer(
        (1 - np.cos(np.pi * t / T)) / 2, STEP))


def states(n: int = 40, seed: int = 3):
    rng = np.random.default_rng(seed)
    return (HOME + rng.normal(scale=0.6, size=(n, 7)), rng.normal(scale=1.5, size=(n, 7)),
            rng.normal(scale=4.0, size=(n, 7)))


def test_unit_mass_torque_is_pinocchio_rnea_with_one_kg_more():
    """J_cᵀ(a_c − g) at the payload point = RNEA of the robot with 1 kg more there minus RNEA
    of the robot as it is (the payload a point mass, as model.with_payload adds it)."""
    model = panda()
    Q, V, A = states()
    com = tuple(PAYLOAD.com)
    fk = FrameKinematics(model, [FramePoint("panda_link4"), FramePoint("panda_hand", com)],
                         unit_mass_point=1)
    out = fk.compute(Q, V, A, inertia=False, base=False, unit_mass=True)
    heavy = model.with_payload(Payload(PAYLOAD.mass + 1.0, com, PAYLOAD.frame)).pin_model
    pm = model.pin_model
    d, dh = pm.createData(), heavy.createData()
    for n in range(len(Q)):
        ref = pin.rnea(heavy, dh, Q[n], V[n], A[n]) - pin.rnea(pm, d, Q[n], V[n], A[n])
        np.testing.assert_allclose(out.unit_mass_torque[n], ref, rtol=0, atol=TOL)
    assert out.unit_mass_torque.flags.f_contiguous      # as the torque terms
    assert fk.compute(Q, V, A).unit_mass_torque is None
    with pytest.raises(ValueError):
        FrameKinematics(model, [FramePoint("panda_link4")]).compute(Q, V, A, unit_mass=True)


def test_effective_masses_only_at_the_points_asked_for_and_the_same_there():
    model = panda()
    Q, V, A = states()
    points = [FramePoint("panda_link8", (0.0, 0.0, 0.1)), FramePoint("panda_link4"),
              FramePoint("panda_hand", (0.0, 0.0, 0.05))]
    every = FrameKinematics(model, points, couple_point=2).compute(Q, V, A)
    some = FrameKinematics(model, points, couple_point=2, mass_points=[0]).compute(Q, V, A)
    assert some.frames[1].effective_mass is None and some.frames[2].coupling is None
    assert np.array_equal(some.frames[0].effective_mass, every.frames[0].effective_mass)
    assert np.array_equal(some.frames[0].coupling, every.frames[0].coupling)
    assert np.array_equal(some.inertia.couple_inertia, every.inertia.couple_inertia)
    # no effective mass at all: M is not factored, the kinetic energy is still ½ q̇ᵀMq̇
    none = FrameKinematics(model, points, mass_points=[]).compute(Q, V, A)
    pm = model.pin_model
    d = pm.createData()
    for n in range(len(Q)):
        Mq = pin.crba(pm, d, Q[n])
        Mq = np.triu(Mq) + np.triu(Mq, 1).T
        assert abs(none.inertia.kinetic_energy[n] - 0.5 * V[n] @ Mq @ V[n]) < TOL
    # points without a wrench: a zero task torque, no row computed
    assert not some.frames[1].task_torque.any() and some.frames[1].task_torque.shape == (40, 7)


def test_task_payload_torque_matches_the_second_rnea_pass_the_margin_made():
    model = panda()
    dyn = Dynamics(model)
    Q, V, A = states()
    task = task_motion.build(dyn, Q, V, A, payload_torque=True)
    ref = feasibility._payload_torque(dyn, Q, V, A, dyn.rnea_batch(Q, V, A), 1)
    np.testing.assert_allclose(task.payload_torque, ref, rtol=0, atol=TOL)
    assert task_motion.build(dyn, Q, V, A).payload_torque is None


@pytest.mark.parametrize("margin", [True, False])
def test_frame_kernel_beside_the_rnea_gives_the_same_result(margin):
    """threads=2 (the payload margin on a second thread): the same verdict, peaks, time
    scale and payload margin as on one thread."""
    dyn = Dynamics(panda())
    tr = traj()
    one = check_trajectory(dyn, tr, FeasibilityOptions(threads=1, compute_payload_margin=margin))
    two = check_trajectory(dyn, tr, FeasibilityOptions(threads=2, compute_payload_margin=margin))
    assert one.to_dict() | {"compute_time_s": 0} == two.to_dict() | {"compute_time_s": 0}
    assert set(one.per_frame) == {"panda_link8", "panda_link4", "robot_limits", "base_limits",
                                  "grasp"}
    assert np.isfinite(one.payload_margin_kg) == margin


def test_bin_peaks_is_each_bins_first_sample_at_its_largest_magnitude():
    """The task curves' bins: against a plain loop, with ties, NaN (counted as inf), signs and
    bins of unequal length."""
    from dyn_node.core.compiled import kernels

    rng = np.random.default_rng(7)
    val = np.round(rng.normal(size=(103, 3)), 1)         # rounding: many ties
    val[[5, 60], 1] = np.nan
    val[40, 2] = -np.inf
    edges = np.unique(np.linspace(0, 103, 11).astype(np.int64))
    got = kernels.bin_peaks(np.asfortranarray(val), edges)
    for c in range(3):
        for b in range(len(edges) - 1):
            seg = np.nan_to_num(np.abs(val[edges[b]:edges[b + 1], c]), nan=np.inf)
            assert got[b, c] == edges[b] + int(np.argmax(seg == seg.max()))
    assert kernels.bin_peaks(val[:0], np.zeros(1, dtype=np.int64)).shape == (0, 3)
