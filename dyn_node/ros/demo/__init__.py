"""``make demo`` (``python -m dyn_node.ros.demo [--short] [--out DIR]``): the model table, then the
whole loop over DDS with an independent simulator; README "The demo" says what it prints.

Parts: :mod:`~dyn_node.ros.demo.driver` runs the scenes in order and decides the exit code; one
module per scene, each a function with its PASS checks (``moves`` the three trajectories,
``retime`` the core retimer's answer, ``task_limits``, ``push``, ``press``, ``gate``, ``audit``);
shared pieces: ``trajectories`` (poses, table, trajectories, statistics; no ROS), ``processes``
(the children), ``stack`` (the rclpy client), ``run`` (what the scenes share), ``summary`` and
``output`` (what is printed).
"""
from __future__ import annotations

from dyn_node.ros.demo.audit import audit_check, audit_outcome, audit_recheck_lines
from dyn_node.ros.demo.processes import Child
from dyn_node.ros.demo.summary import Outcome, acceptance, states_text, summary_table
from dyn_node.ros.demo.task_limits import task_checks
from dyn_node.ros.demo.trajectories import (DEMO_TASK_LIMITS, FINGERS, LEAD_S, PANDA_POSES, READY,
                                            SAFETY_FACTOR, SETTLE_S, TASK_PLACE, TRACKING_TOLERANCE,
                                            DemoTrajectory, demo_trajectories, effort_residual,
                                            model_table, named_poses, task_transfer, tracking_error)

__all__ = ["DEMO_TASK_LIMITS", "FINGERS", "LEAD_S", "PANDA_POSES", "READY", "SAFETY_FACTOR", "SETTLE_S",
           "TASK_PLACE", "TRACKING_TOLERANCE", "Child", "DemoTrajectory", "Outcome", "acceptance",
           "audit_check", "audit_outcome", "audit_recheck_lines", "demo_trajectories", "effort_residual",
           "main", "model_table", "named_poses", "states_text", "summary_table", "task_checks",
           "task_transfer", "tracking_error"]


def main(argv: list[str] | None = None) -> int:
    """The ``dyn_node_demo`` console script (:func:`dyn_node.ros.demo.driver.main`)."""
    # imported when run, not with the package: ``python -m dyn_node.ros.demo.gate`` then runs
    # a module the package has not already imported
    from dyn_node.ros.demo.driver import main as run

    return run(argv)
