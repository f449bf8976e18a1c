"""Issue 37: does every candidate the node's retimer returns stay within retime.limit_margin × each
limit? Measured on the demo's goals (the shake and the gate's goal, from READY at rest) at the
node's default margin, for the optimal answer and for the uniform stretch candidate.

The optimal answer holds the margin on TOPP-RA's grid and the full limit in the exact check: it
may go over margin × limit by TOPP-RA's grid error (measured 0.909 at 0.9, docs/retime.md), so it
is held to margin × 1.015 here. The stretch keeps the margin by its own exact check."""
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


@pytest.mark.parametrize("goal", ["shake", "gate"])
def test_the_stretch_candidate_stays_within_the_margin(setup, goal):
    """The stretch keeps margin × each limit too (issue 37), by its own exact check; at dyn-check's
    0.995 its last pad (1.005 × k) already keeps it, so issue 39's bound holds there."""
    from dyn_node.retime import candidates
    from dyn_node.retime.path import build_path

    dyn, opts, goals = setup
    margin = Settings().retime_limit_margin
    traj = goals[goal]
    k = check_trajectory(dyn, traj, opts).time_scale
    path = build_path(traj)
    dense = lambda *a: (None, 0.0)  # noqa: E731  (the input's own points: no resampling needed)
    full = candidates.stretch(dyn, path, traj, k, opts, None, 0.004, True, dense, 1e-4)
    kept = candidates.stretch(dyn, path, traj, k, opts, None, 0.004, True, dense, 1e-4, margin=margin)
    assert full is not None and kept is not None
    ratio_full = check_trajectory(dyn, full["trajectory"], opts).worst_ratio
    ratio_kept = check_trajectory(dyn, kept["trajectory"], opts).worst_ratio
    assert ratio_full > margin, ratio_full          # without the margin the stretch uses more
    assert margin * 0.98 < ratio_kept <= margin * (1 + 1e-4)
    assert full["trajectory"].duration <= 1.005 * k * traj.duration * (1 + 1e-12)
    assert 1 / 1.005 <= candidates.stretch_share(0.995) < 0.9951
