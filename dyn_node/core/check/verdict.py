"""The verdict's words: the level, label and message of a checked trajectory, and what the
execution model adds to it (a jump at the start, velocity steps: unbounded accelerations that no
slowdown removes, :mod:`dyn_node.core.check.execution`)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from dyn_node.core.check.constraints import Blocked, Violation, _fmt, percent_text, with_unit
from dyn_node.core.check.kinds import KIND_CLASS, KINDS
from dyn_node.core.check.start_segment import REACH as START_REACH
from dyn_node.core.robot.status import ERROR, OK, WARN
from dyn_node.errors import PLANNING_ERROR

_KIND_LABEL = {c.kind: c.label for c in KINDS if c.label}


@dataclass
class Scale:
    """The time scale: k, where and which kind sets it, the factor per kind, and why no
    slowdown helps (when none does)."""

    k: float
    where: str
    kind: str
    by_kind: dict[str, float]
    blocked: Blocked | None
    start_binds: bool = False
    #: what the execution model found that no slowdown fixes (a jump, velocity steps): the
    #: infeasible verdict's head, in words
    head: str = ""



def kind_text(kind: str) -> str:
    return _KIND_LABEL.get(kind, kind)


def describe_violation(v: Violation) -> str:
    if v.kind == "position":
        return (f"{_fmt(v.peak_value)} {v.unit} beyond limit {_fmt(v.limit)} {v.unit} "
                f"at t = {v.peak_time_s:.2f} s")
    return percent_text(v)


def fmt_factor(f: float) -> str:
    if not math.isfinite(f):
        return "∞"
    return f"{f:.4f}" if abs(f - 1) < 0.01 else f"{f:.3g}" if f >= 100 else f"{f:.2f}"



def verdict(per_joint: Mapping[str, Mapping[str, Mapping[str, Any]]],
             per_frame: Mapping[str, Mapping[str, Mapping[str, Any]]],
             violations: list[Violation], warnings: list[str], scale: Scale,
             options: Any, units: Mapping[str, list[str]],
             start_segment: str) -> dict[str, Any]:
    """The level, label, message and worst joint (or place) and kind."""
    worst_joint, worst_kind, worst_ratio = "", "", 0.0
    for jn, kinds in (*per_joint.items(), *per_frame.items()):
        for kind, e in kinds.items():
            if kind != "position" and e["ratio"] is not None and e["ratio"] > worst_ratio:
                worst_joint, worst_kind, worst_ratio = jn, kind, e["ratio"]
    if violations:
        level, label = ERROR, PLANNING_ERROR
        message = infeasible_message(violations, warnings, scale, start_segment)
    else:
        warn = worst_ratio > options.effort_warn_ratio or bool(warnings)
        level = WARN if warn else OK
        what = f"{worst_joint} {kind_text(worst_kind)}"
        if worst_kind in per_frame.get(worst_joint, {}):
            e = per_frame[worst_joint][worst_kind]
            u = e["unit"]
            # "grasp slip" at the place "grasp": named once
            if kind_text(worst_kind).startswith(worst_joint):
                what = kind_text(worst_kind)
        elif worst_kind:
            e = per_joint[worst_joint][worst_kind]
            u = units[worst_kind][list(per_joint).index(worst_joint)]
        if worst_kind:
            head = (f"feasible: worst {what} {worst_ratio * 100:.0f}% of "
                    f"{with_unit(e['limit'], u)} at t = {e['time_s']:.2f} s")
        else:
            head = "feasible: no limits apply"
        k = scale.k
        tail = (f"; could run {fmt_factor(1 / k)}× faster" if 1e-6 < k < 1 else  # k ≤ 1e-6: a hold
                "; holds still: no speed-dependent limit binds" if k <= 1e-6 else "; no margin left")
        if scale.start_binds:
            tail += " (the segment from the current state binds)"
        message = head + tail
        if level == WARN and warnings and (worst_ratio <= options.effort_warn_ratio
                                           or start_segment.startswith("not_checked")):
            message += f" ({warnings[0].split(':')[0]})"
        label = PLANNING_ERROR if level != OK else ""
    return dict(feasible=not violations, level=level, message=message, failure_label=label,
                worst_joint=worst_joint, worst_constraint=worst_kind,
                worst_ratio=float(worst_ratio),
                first_violation_time_s=float(min((v.first_time_s for v in violations),
                                                 default=math.nan)))


def infeasible_message(violations: list[Violation], warnings: list[str], scale: Scale,
                       start_segment: str) -> str:
    pos = [v for v in violations if v.kind == "position"]
    v0 = pos[0] if pos else max(violations, key=lambda v: abs(v.peak_value) / v.limit
                                 if v.limit > 0 else math.inf)
    head = f"infeasible: {scale.head or KIND_CLASS[v0.kind].describe(v0)}"
    blocked = scale.blocked
    if pos and blocked is not None and blocked.timing_free and not scale.head:
        tail = "; position limits do not depend on timing, no slowdown helps"
    elif blocked is not None and blocked.reason:
        tail = "; " + blocked.reason
    elif scale.start_binds and not math.isfinite(scale.k):
        tail = (f"; no slowdown up to {START_REACH:g}× makes the segment from the current "
                "state feasible")
    else:
        tail = f"; run {fmt_factor(scale.k)}× slower"
        if scale.kind:
            tail += f": {kind_text(scale.kind)} of {scale.where} binds"
        if scale.start_binds:
            tail += " (the segment from the current state binds)"
    message = head + tail
    if len(violations) > 1:
        message += f" ({len(violations)} violations)"
    if start_segment.startswith("not_checked"):
        message += f"; {warnings[0].split(':')[0]}"
    return message


#: the kinds a velocity step breaks (an unbounded acceleration), the first a joint has a limit of
STEP_KINDS = ("acceleration", "jerk", "effort")
#: the kinds a position step (a jump) breaks first: an unbounded velocity
JUMP_KINDS = ("velocity", *STEP_KINDS)


def _step_kind(entry: Mapping[str, Mapping[str, Any]], kinds: tuple[str, ...]) -> str:
    return next((k for k in kinds if entry.get(k, {}).get("ratio") is not None), "")


def _unbounded(per_joint: dict, violations: list[Violation], units: Mapping[str, list[str]],
               names: list[str], j: int, t: float, kinds: tuple[str, ...], detail: str) -> str:
    """A step at joint j and time t as a violation of the first of ``kinds`` the joint has a
    limit of (ratio ∞); "" when it has none (then nothing is broken)."""
    joint = names[j]
    kind = _step_kind(per_joint[joint], kinds)
    if not kind or any(v.joint == joint and v.kind == kind and v.peak_value == math.inf
                       for v in violations):
        return kind           # one violation per joint and kind: the first step's
    lim = per_joint[joint][kind]["limit"]
    per_joint[joint][kind] = {"ratio": math.inf, "time_s": t, "value": math.inf, "limit": lim}
    violations.append(Violation(joint=joint, kind=kind, first_time_s=t, peak_time_s=t,
                                peak_value=math.inf, limit=float(lim), duration_s=0.0,
                                unit=units[kind][j], detail=detail))
    return kind


def apply_execution(ex: Any, per_joint: dict, violations: list[Violation], scale: Scale,
                    warnings: list[str], units: Mapping[str, list[str]]) -> None:
    """What the execution model found, into the verdict: a jump beyond ``start_tolerance`` and
    every velocity step beyond ``velocity_tolerance`` are unbounded velocities/accelerations:
    violations wherever a velocity, acceleration, jerk or effort limit applies, and no slowdown
    fixes them (k = ∞, blocked, with the reason in words). What the controller would refuse is
    a key of the verdict (``refused_by_controller``), judged all the same: the gate refuses."""
    names = list(per_joint)
    heads, reasons, where, kind0 = [], [], "", ""
    jump = ex.jump
    if jump is not None and jump.exceeds_position:
        j = jump.joint
        unit = units["position"][j]
        detail = f"the command steps {jump.position[j]:+.3g} {unit} at the start"
        for jj in np.flatnonzero(np.abs(jump.position) > ex.options.start_tolerance):
            k = _unbounded(per_joint, violations, units, names, int(jj), 0.0, JUMP_KINDS, detail)
            if jj == j:
                where, kind0 = names[j], k
        what = ("the first point" if ex.point_knots[0] >= 0 else
                f"started {ex.offset_s:.3g} s into it (past stamp), the trajectory")
        heads.append(f"{what} is {jump.size:.3g} {unit} from the robot ({names[j]}): "
                     "the controller steps to it at once")
        reasons.append(f"no slowdown helps: {what} is {jump.size:.3g} {unit} from the robot")
    elif jump is not None and jump.exceeds_velocity:
        j = jump.velocity_joint
        unit = units["velocity"][j]
        robot = ex.start.velocities[j]
        for jj in np.flatnonzero(np.abs(jump.velocity) > ex.options.velocity_tolerance):
            k = _unbounded(per_joint, violations, units, names, int(jj), 0.0, STEP_KINDS,
                           f"the commanded velocity steps {jump.velocity[jj]:+.3g} at the start")
            if jj == j:
                where, kind0 = names[j], k
        heads.append(f"the robot moves at {robot:.3g} {unit} ({names[j]}) and the controller "
                     f"steps its command to {robot + jump.velocity[j]:.3g} {unit} at once")
        reasons.append("no slowdown helps: the first point is due at once; start it later "
                       "(time_from_start > 0) from the robot's state")
    steps = ex.violating_steps()
    if steps:
        for s in steps:
            for j in s.joints:
                k = _unbounded(per_joint, violations, units, names, j, s.time_s, STEP_KINDS,
                               f"velocity step of {s.step[j]:+.3g} {units['velocity'][j]} at "
                               f"t = {s.time_s:.3g} s")
                if not where and k:
                    where, kind0 = names[j], k
        what = "positions only" if ex.trajectory.velocities is None else "linear segments"
        heads.append(f"{what}: velocity steps at {len(steps)} point{'s' if len(steps) > 1 else ''} "
                     "as the controller interpolates them")
        reasons.append("no slowdown removes a velocity step: send velocities (cubic) or "
                       "velocities and accelerations (quintic)")
    if where:
        scale.head = "; ".join(heads)
        scale.k, scale.where, scale.kind = math.inf, where, kind0
        scale.blocked = Blocked(where, "; ".join(reasons))
        scale.by_kind[kind0] = math.inf


def execution_values(ex: Any, names: list[str]) -> dict[str, Any]:
    """The summary keys naming what was judged (see docs/limits.md, "The execution model")."""
    jump = ex.jump
    counts = ex.mode_counts()
    steps = ex.velocity_steps
    return {
        "start_time": ex.start_rule, "start_offset_s": ex.offset_s,
        "start_jump": jump.size if jump is not None else math.nan,
        "start_jump_joint": names[jump.joint] if jump is not None else "",
        "start_velocity_step": jump.velocity_size if jump is not None else math.nan,
        "interpolation_segments": ", ".join(f"{m} {n}" for m, n in sorted(counts.items())),
        "linear_segments": ", ".join(str(i) for i in ex.linear_segments),
        "velocity_steps": len(ex.violating_steps()),
        "velocity_step_points": ", ".join("start" if s.point < 0 else str(s.point)
                                          for s in ex.violating_steps()),
        "refused_by_controller": "; ".join(code for code, _ in ex.refusals),
    }
