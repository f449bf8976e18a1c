"""The demo's retiming scene, its pure parts: the aggressive trajectory answered by
``~/retime_trajectory``'s code with the demo node's ``retime.limit_margin``, the trajectory taken
from that answer, and the PASS lines."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from dyn_node.client import Retimed
from dyn_node.core.check import on_demand
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.feasibility import check_trajectory
from dyn_node.core.robot.model import load_model
from dyn_node.core.robot.settings import Settings, settings_from_mapping
from dyn_node.errors import SettingsError
from dyn_node.retime import retime
from dyn_node.ros.demo import READY, demo_trajectories
from dyn_node.ros.demo.retime import LIMIT_MARGIN, from_answer, retime_checks
from dyn_node.ros.service_answers import answer_retime


def _ask(model, aggressive, settings: Settings):
    """The service's answer (the node's answer_retime, as its worker runs it) as the client has it."""
    from builtin_interfaces.msg import Duration
    from dyn_node_interfaces.srv import RetimeTrajectory
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    msg = JointTrajectory(joint_names=list(model.joint_names))
    for t, p in zip(aggressive.times, aggressive.positions):
        ns = int(round(t * 1e9))
        msg.points.append(JointTrajectoryPoint(positions=list(p), velocities=[0.0] * 7, accelerations=[0.0] * 7,
                                               time_from_start=Duration(sec=ns // 10**9, nanosec=ns % 10**9)))
    resp = answer_retime(Dynamics(model), settings, RetimeTrajectory.Request(trajectory=msg),
                         RetimeTrajectory.Response(), None)
    return Retimed.from_response(resp), msg


@pytest.fixture(scope="module")
def answer():
    model = load_model(builtin="panda")
    _, aggressive = demo_trajectories(short=True)
    settings = settings_from_mapping({"retime.limit_margin": LIMIT_MARGIN})
    got, msg = _ask(model, aggressive, settings)
    return model, aggressive, settings, got, msg


def test_the_answer_is_the_retimers_with_the_nodes_margin(answer):
    model, aggressive, settings, got, msg = answer
    assert got.accepted and got.feasible and got.verdict is not None and got.verdict.feasible
    traj = from_answer(got, list(model.joint_names))
    assert traj is not None
    # the same call as the core's, with the parameter's margin: identical to the last bit
    names = list(msg.joint_names)
    direct = retime(Dynamics(model), on_demand.validated(names, names, list(aggressive.times),
                                                        [list(p) for p in aggressive.positions],
                                                        [[0.0] * 7] * len(aggressive.times),
                                                        [[0.0] * 7] * len(aggressive.times)),
                    feasibility=on_demand.options_for(settings), limit_margin=LIMIT_MARGIN)
    np.testing.assert_array_equal(np.array(traj.positions), direct.trajectory.positions)
    np.testing.assert_array_equal(np.array(traj.velocities), direct.trajectory.velocities)
    assert got.duration_out == direct.duration_out
    # the margin is used: the default (0.995) answers faster
    default, _ = _ask(model, aggressive, Settings())
    assert default.feasible and default.duration_out < got.duration_out * (1 - 1e-3)


def test_the_answers_trajectory_passes_the_check_and_keeps_the_ends(answer):
    model, aggressive, _, got, _ = answer
    traj = from_answer(got, list(model.joint_names))
    again = check_trajectory(Dynamics(model), traj.validated())
    assert again.feasible and again.interpolation == "quintic"
    np.testing.assert_allclose(traj.positions[0], READY, atol=1e-12)
    np.testing.assert_allclose(traj.positions[-1], aggressive.positions[-1], atol=1e-12)
    k = check_trajectory(Dynamics(model), aggressive.validated(model.joint_names)).time_scale
    assert k > 1
    assert got.lower_bound * (1 - 1e-3) <= traj.duration < aggressive.duration * k
    # no trajectory from an answer without one, or in another joint order
    assert from_answer(None, list(model.joint_names)) is None
    assert from_answer(SimpleNamespace(accepted=False, feasible=False), list(model.joint_names)) is None
    assert from_answer(got, list(reversed(model.joint_names))) is None


def test_the_margin_is_validated():
    for bad in (0.0, 1.5, -1.0):
        with pytest.raises(SettingsError, match="retime.limit_margin"):
            settings_from_mapping({"retime.limit_margin": bad})


def test_retime_checks_fail_on_a_live_violation(answer):
    _, aggressive, _, got, _ = answer
    slowed = aggressive.duration * 2
    clean = SimpleNamespace(verdict="OK", saturated_samples=0, states=["idle", "executing", "idle"])
    assert all(ok for ok, _ in retime_checks(got, clean, slowed))
    for bad in (SimpleNamespace(verdict="ERROR", saturated_samples=0, states=["executing"]),
                SimpleNamespace(verdict="OK", saturated_samples=3, states=["executing"]),
                SimpleNamespace(verdict="WARN", saturated_samples=0, states=["executing", "deviating"])):
        assert [ok for ok, _ in retime_checks(got, bad, slowed)] == [True, False]
    assert not retime_checks(got, None, slowed)[1][0]
    # an answer slower than the uniform slowdown, or not retimed, fails the first line
    assert not retime_checks(got, clean, got.duration_out * 0.5)[0][0]
    refused = SimpleNamespace(accepted=False, feasible=False, reason="retimer_unavailable", message="x",
                              verdict=None, duration_out=0.0)
    assert not retime_checks(refused, clean, slowed)[0][0]
    assert not retime_checks(None, None, slowed)[0][0]
