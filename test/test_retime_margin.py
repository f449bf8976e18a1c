"""Issue 37: does every candidate the node's retimer returns stay within retime.limit_margin × each
limit? Measured on the demo's goals (the shake and the gate's goal, from READY at rest) at the
node's default margin, for the optimal answer and for the uniform stretch candidate.

The optimal answer holds the margin on TOPP-RA's grid and the full limit in the exact check: it
may go over margin × limit by TOPP-RA's grid error (measured 0.909 at 0.9, docs/retime.md), so it
is held to margin × 1.015 here. The stretch is timed at the full limits (time_scale × 1.001): it
does not keep the margin — strict xfail, the gap left to the retimer (reported to the lead)."""
from __future__ import annotations

import numpy as np
import pytest

from dyn_node.core.check import on_demand
from dyn_node.core.check.feasibility import check_trajectory
from dyn_node.core.check.start_segment import StartState
from dyn_node.core.check.trajectory import Trajectory
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import load_model
from dyn_node.core.robot.settings import Settings

pytest.importorskip("toppra", reason="the retimer needs toppra")

READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
GRID_SLACK = 1.015


@pytest.fixture(scope="module")
def setup():
    from dyn_node.ros.demo.trajectories import demo_trajectories
    from dyn_node.ros.fjt_client import quintic

    model = load_model(builtin="panda")
    shake = demo_trajectories()[1].validated(model.joint_names)
    g = quintic(list(READY), list(READY + np.eye(7)[0] * 0.5), 0.15)
    gate = Trajectory(times=np.array(g["times"]), positions=np.array(g["points"]),
                      velocities=np.array(g["velocities"]), accelerations=np.array(g["accelerations"]))
    return Dynamics(model), on_demand.options_for(Settings()), {"shake": shake, "gate": gate}


def test_the_node_default_margin_is_the_measured_one():
    """docs/retime.md: 0.9 is the largest measured margin keeping dyn_sim unsaturated; dyn-check
    --retime keeps the retimer's own 0.995."""
    import inspect

    from dyn_node.retime import retime

    assert Settings().retime_limit_margin == 0.9
    assert inspect.signature(retime).parameters["limit_margin"].default == 0.995


@pytest.mark.parametrize("goal", ["shake", "gate"])
def test_the_optimal_answer_stays_near_the_margin(setup, goal):
    from dyn_node.retime import retime

    dyn, opts, goals = setup
    margin = Settings().retime_limit_margin
    res = retime(dyn, goals[goal], start=StartState(READY.copy(), np.zeros(7), 0.0), feasibility=opts,
                 limit_margin=margin)
    assert res.feasible and res.method == "optimal"
    again = check_trajectory(dyn, res.trajectory, opts)
    assert margin * 0.97 < again.worst_ratio <= margin * GRID_SLACK


@pytest.mark.xfail(strict=True, reason="the uniform stretch is timed at the full limits, not margin × limit")
@pytest.mark.parametrize("goal", ["shake", "gate"])
def test_the_stretch_candidate_stays_within_the_margin(setup, goal):
    from dyn_node.retime.path import build_path
    from dyn_node.retime.retimer import _uniform

    dyn, opts, goals = setup
    margin = Settings().retime_limit_margin
    traj = goals[goal]
    k = check_trajectory(dyn, traj, opts).time_scale
    cand = _uniform(dyn, build_path(traj), traj, k, opts, None, 0.004, False, 1e-4)
    assert cand is not None and cand["method"] == "uniform"
    assert check_trajectory(dyn, cand["trajectory"], opts).worst_ratio <= margin * GRID_SLACK
