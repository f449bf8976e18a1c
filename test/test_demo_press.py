"""The demo's press scene, its pure parts: the truth moved to the estimate's frame (against
MuJoCo's generalized forces), and the acceptance lines (detection, settled force)."""
from __future__ import annotations

import mujoco
import numpy as np
import pytest

from dyn_node.core.robot.model import load_model
from dyn_node.ros.demo import DemoTrajectory
from dyn_node.ros.demo.press import PressOutcome, press_checks, press_trajectories, wrench_at_frame
from dyn_node.sim.press import PRESS_SCENE, READY, plan_press
from dyn_node.sim.simulator import SimConfig, Simulator


@pytest.fixture(scope="module")
def panda():
    return load_model(builtin="panda")


def test_truth_at_the_estimate_frame_has_the_same_joint_torque(panda):
    """Held press: the finger wrenches moved to panda_link8 exert, by MuJoCo's mj_applyFT (world
    force and torque at a point of a body), the same generalized force as the fingers' own."""
    sim = Simulator(panda, SimConfig(scene=PRESS_SCENE, initial_positions=READY))
    sim.execute(list(panda.joint_names), *plan_press(sim).waypoints())
    sim.run(4.0)
    truth = sim.contact_truth()
    links = [w.link for w in truth.link_wrenches]
    W = wrench_at_frame(panda, sim.q, links, [w.wrench for w in truth.link_wrenches], "panda_link8")
    mj, d = sim.mj, sim.data
    mujoco.mj_forward(mj, d)

    def qfrc(body: str, wrench: np.ndarray) -> np.ndarray:
        b = mj.body(body).id
        R = d.xmat[b].reshape(3, 3)
        out = np.zeros(mj.nv)
        mujoco.mj_applyFT(mj, d, R @ wrench[:3], R @ wrench[3:], d.xpos[b].copy(), b, out)
        return out

    fingers = sum(qfrc(w.link, w.wrench) for w in truth.link_wrenches)
    np.testing.assert_allclose(qfrc("panda_link8", W), fingers, atol=1e-9 * np.abs(fingers).max())
    assert np.linalg.norm(W[:3]) > 20.0


def test_press_trajectories_start_and_end_at_ready(panda):
    press, release = press_trajectories(panda, DemoTrajectory)
    assert press.positions[0] == tuple(READY) and release.positions[-1] == tuple(READY)
    assert press.positions[-1] == release.positions[0] and press.times[-1] == 2.5


def _outcome(est: float, reported_after: float | None) -> PressOutcome:
    o = PressOutcome(frame="panda_link8", first_contact_stamp_s=10.0, first_contact_wall_s=10.0)
    o.truth = [(10.0 + 0.002 * i, np.array([0.0, 0.0, 90.0])) for i in range(1000)]
    o.estimates = [(10.0 + 0.002 * i, np.array([0.0, 0.0, est if i > 50 else 0.0])) for i in range(1000)]
    if reported_after is not None:
        o.reported_wall_s, o.reported_state = 10.0 + reported_after, "contact"
    return o


def test_press_checks():
    ok = press_checks(_outcome(88.0, 0.06))
    assert [c[0] for c in ok] == [True, True]
    assert "reported contact 60 ms after the first touch" in ok[0][1]
    assert "past half the force 102 ms after the touch" in ok[1][1]
    assert [c[0] for c in press_checks(_outcome(70.0, 0.06))] == [True, False]  # 20 N off > 10 N
    assert [c[0] for c in press_checks(_outcome(88.0, 0.8))] == [False, True]   # too late
    assert [c[0] for c in press_checks(_outcome(88.0, None))] == [False, True]  # never
    none = press_checks(PressOutcome(frame="panda_link8"))
    assert len(none) == 1 and not none[0][0] and "no ~/contact_truth" in none[0][1]


def test_bench_press_row():
    """The bench's press row (simulated time, no DDS): the monitor reports contact within its
    20 ms minimum duration plus a few observer time constants of the touch, and its settled
    wrench equals the truth moved to panda_link8 (both explain the same static torques)."""
    from benchmarks import contact_bench

    r = contact_bench.press()
    assert 20.0 <= r["touch_to_contact_ms"] <= 100.0
    assert r["settled_force_n"] > 20.0 and r["settled_error_rel"] < 1e-6
