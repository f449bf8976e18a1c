"""The demo's retiming scene, its pure parts: the retimed aggressive trajectory and the PASS lines."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.feasibility import check_trajectory
from dyn_node.core.robot.model import load_model
from dyn_node.ros.demo import demo_trajectories
from dyn_node.ros.demo_retime import retime_checks, retimed


@pytest.fixture(scope="module")
def answer():
    model = load_model(builtin="panda")
    _, aggressive = demo_trajectories(short=True)
    return model, aggressive, *retimed(model, aggressive)


def test_retimed_aggressive_passes_the_check_and_keeps_the_ends(answer):
    model, aggressive, traj, res = answer
    assert traj is not None and res.feasible
    again = check_trajectory(Dynamics(model), traj.validated())
    assert again.feasible and again.interpolation == "quintic"
    np.testing.assert_allclose(traj.positions[0], aggressive.positions[0], atol=1e-12)
    np.testing.assert_allclose(traj.positions[-1], aggressive.positions[-1], atol=1e-12)
    # the aggressive one is infeasible as given; the answer is the optimal search's (its stops
    # cut the path into pieces, each by arc length), no shorter than T*, and shorter than the
    # demo's uniformly slowed one
    k = check_trajectory(Dynamics(model), aggressive.validated(model.joint_names)).time_scale
    assert k > 1 and res.method == "optimal"
    assert res.lower_bound * (1 - 1e-3) <= traj.duration < aggressive.duration * k


def test_retime_checks_fail_on_a_live_violation(answer):
    _, aggressive, traj, res = answer
    slowed = aggressive.duration * 2
    clean = SimpleNamespace(verdict="OK", saturated_samples=0, states=["idle", "executing", "idle"])
    assert all(ok for ok, _ in retime_checks(res, clean, slowed))
    for bad in (SimpleNamespace(verdict="ERROR", saturated_samples=0, states=["executing"]),
                SimpleNamespace(verdict="OK", saturated_samples=3, states=["executing"]),
                SimpleNamespace(verdict="WARN", saturated_samples=0, states=["executing", "deviating"])):
        assert [ok for ok, _ in retime_checks(res, bad, slowed)] == [True, False]
    assert not retime_checks(res, None, slowed)[1][0]
    # an answer slower than the uniform slowdown fails the first line
    assert not retime_checks(res, clean, traj.duration * 0.5)[0][0]
