"""dyn-check --retime: the optimal retiming (:func:`dyn_node.retime.retime`) of each file, written
in the input's format, re-checked from the written text, one line per file.

The written file carries the model's joints in the model's order with positions, velocities and
accelerations at every point (joint_trajectory_controller then interpolates quintic between
them, the curve the check passed). Untimed waypoints (every time_from_start zero, which the
node's validation rejects) are retimed along the spline through them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from dyn_node.audit.trajectory_files import TrajectoryFile, format_trajectory, parse_trajectory
from dyn_node.errors import TrajectoryError


@dataclass(frozen=True)
class OptimalRetimed:
    """One file's retiming: ``written`` (path or None), the line's text, the core result."""

    path: str
    written: Path | None
    note: str
    result: Any = None


def retime_file(checker: Any, v: Any, dest: Path) -> OptimalRetimed:
    """Retime ``v`` (a :class:`dyn_node.audit.check.FileVerdict`) and write it to ``dest`` when
    the re-check of the written text passes."""
    from dyn_node.core.check.on_demand import options_for
    from dyn_node.retime import retime

    tf = v.trajectory
    if tf is None:
        return OptimalRetimed(v.path, None, "not written: unreadable")
    try:
        traj = _model_trajectory(checker, v)
        # the verdict just printed is the check of this very trajectory: not made again
        checked = v.outcome.result if v.outcome is not None and v.outcome.trajectory is traj \
            else None
        res = retime(checker.dynamics, traj, feasibility=options_for(checker.settings),
                     input_check=checked)
    except TrajectoryError as exc:
        return OptimalRetimed(v.path, None, f"not written: {exc}")
    if not res.feasible:
        why = res.blocked or res.message
        return OptimalRetimed(v.path, None, f"not written: {why}", res)
    out = res.trajectory
    if res.method == "unchanged":
        text = format_trajectory(tf)
    else:
        text = format_trajectory(replace(
            tf, joint_names=list(checker.model.joint_names), times=out.times.tolist(),
            positions=out.positions.tolist(), velocities=out.velocities.tolist(),
            accelerations=out.accelerations.tolist()))
    again = checker.check(parse_trajectory(text, tf.format, str(dest)))
    figures = _figures(res)
    if again.result is None or not again.result.feasible:
        return OptimalRetimed(v.path, None, f"not written: {figures}; the written text re-checks "
                              f"{again.statuses[0].message}", res)
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(text, encoding="utf-8")
    return OptimalRetimed(v.path, dest, f"{figures}; re-check: FEASIBLE ({again.result.message})",
                          res)


def _figures(res: Any) -> str:
    def s(x: float) -> str:
        return "n/a" if not math.isfinite(x) else f"{x:.4g} s"

    gap = "n/a" if not math.isfinite(res.gap) else f"{res.gap:.3f}"
    return (f"{res.method}: {s(res.duration_in)} → {s(res.duration_out)}, uniform "
            f"{s(res.duration_uniform)}, T* {s(res.lower_bound)}{_steps(res)}, gap {gap}")


def _steps(res: Any) -> str:
    """The grid T* is certified against (dyn_node/retime/bound.py), when there is one."""
    return f" (certified, {res.bound_steps} steps)" if res.bound_steps else ""


def _model_trajectory(checker: Any, v: Any):
    """The checked trajectory (model order), or for untimed waypoints their positions in model
    order with all times zero."""
    from dyn_node.core.check.trajectory import Trajectory, check_joint_names

    if v.outcome is not None and v.outcome.trajectory is not None:
        return v.outcome.trajectory
    tf: TrajectoryFile = v.trajectory
    model = checker.model
    if len(tf.times) >= 2 and all(t == 0 for t in tf.times):
        names = check_joint_names(model.joint_names, tf.joint_names,
                                  ignored_joints=tuple(model.locked_joints),
                                  what="trajectory")
        order = [names.index(n) for n in model.joint_names]
        P = np.asarray(tf.positions, dtype=float)
        if P.ndim != 2 or P.shape[1] != len(names):
            raise TrajectoryError("positions do not match the joint names", code="length_mismatch")
        return Trajectory(times=np.zeros(len(tf.times)), positions=P[:, order])
    raise TrajectoryError(v.outcome.statuses[0].message if v.outcome else "not checked",
                          code="rejected")


def write_outputs(checker: Any, rt: OptimalRetimed, d: Path) -> None:
    """``d/retime.json`` (the figures) and ``d/retime.png`` (the profiles) beside the report."""
    import json

    from dyn_node.audit.retime_plot import write_plot

    d.mkdir(parents=True, exist_ok=True)
    summary = {k: (None if isinstance(x, float) and not math.isfinite(x) else x)
               for k, x in rt.result.summary().items()}
    summary["written"] = str(rt.written)
    (d / "retime.json").write_text(json.dumps(summary, indent=1, ensure_ascii=False))
    write_plot(checker.dynamics, rt.result, d / "retime.png")
