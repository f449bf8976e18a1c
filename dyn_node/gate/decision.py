"""One goal's decision: checked from the robot's current state like an executed trajectory, then
forwarded (feasible, or any verdict in ``check`` mode), rejected (``reject``: infeasible; every
mode: input that cannot be checked) or retimed (``retime``: infeasible, or any with
``retime_all``; rejected when no retiming is found or its re-check fails).

The record of a decision (:meth:`Decision.to_dict`) is what the node publishes on
``~/gate_decisions`` and the bag keeps: the goal id, the decision, the verdict line, the numbers
behind it, the goal's tolerances and the trajectory forwarded.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping

import numpy as np

from dyn_node.core.check import feasibility
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.check.trajectory import Trajectory, validate_trajectory
from dyn_node.core.check.on_demand import options_for
from dyn_node.errors import PLANNING_ERROR, STATE_ERROR, SettingsError, TrajectoryError

MODES = ("reject", "retime", "check")
FORWARDED, REJECTED, RETIMED = "forwarded", "rejected", "retimed"
#: a goal the check let through that never reached (or was never accepted by) the controller:
#: the gate was busy or closing, the controller absent, late or refusing (gate.outcomes)
NOT_FORWARDED = "not_forwarded"
STALE_STATE = "stale_state"
RECORD_VERSION = 1


@dataclass(frozen=True)
class GateOptions:
    """``mode``: reject | retime | check; ``retime_all``: in retime mode, retime feasible goals too;
    ``max_state_age``: the oldest joint_states (s, by receipt) a goal is checked from in reject and
    retime (older, absent, or without a goal joint: refused, ``stale_state``); ``start_tolerance``:
    how far (rad) a goal's first point may lie from the measured state (used by the start check)."""

    mode: str = "reject"
    retime_all: bool = False
    max_state_age: float = 0.1
    start_tolerance: float = 0.01

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise SettingsError(f"gate.mode must be one of {', '.join(MODES)}, not {self.mode!r}")
        if not (self.max_state_age > 0 and self.start_tolerance >= 0):
            raise SettingsError("gate.max_state_age must be > 0 and gate.start_tolerance >= 0")

    def execution(self, base: feasibility.ExecutionOptions) -> feasibility.ExecutionOptions:
        """The execution model's options (the node's, ``base``) with the gate's start tolerance:
        a first point farther than it from the measured state is a jump the verdict refuses
        (MoveIt's allowed_start_tolerance)."""
        return dataclasses.replace(base, start_tolerance=self.start_tolerance)

    @property
    def fails_closed(self) -> bool:
        """reject and retime refuse what they cannot check from a fresh state; check forwards it."""
        return self.mode != "check"


@dataclass(frozen=True)
class Decision:
    """What the gate does with one goal. ``trajectory``: what is forwarded (model order), None when
    rejected; ``verdict``: the verdict line on the goal as sent (or why it could not be checked);
    ``reason``: "" when forwarded unchanged, else a code (``infeasible``, ``retime_failed``, a
    TrajectoryError code such as ``non_finite`` or ``unknown_joints``)."""

    decision: str
    verdict: str
    reason: str
    feasible: bool
    trajectory: Trajectory | None
    time_scale: float = math.nan
    worst: tuple[str, str, float] = ("", "", math.nan)
    check_time_s: float = 0.0
    duration_in: float = math.nan
    duration_out: float = math.nan
    duration_uniform: float = math.nan
    retime_message: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)
    #: the check of what is forwarded (the goal's, or the retimed answer's re-check): the node
    #: publishes it on ~/feasibility like any executed trajectory's; not part of the record
    result: Any = field(default=None, compare=False, repr=False)
    #: what the check judged (the execution model's keys: start time rule and offset, the
    #: start state's age, the jump, interpolation per segment, velocity steps); {} when the goal
    #: could not be checked
    judged: Mapping[str, Any] = field(default_factory=dict)

    @property
    def forwards(self) -> bool:
        return self.trajectory is not None

    @property
    def error_string(self) -> str:
        """The result's error_string of a rejected goal: the verdict line (and why no retiming)."""
        if self.reason == "retime_failed":
            return f"{self.verdict} Retiming failed: {self.retime_message}"
        return self.verdict

    @property
    def line(self) -> str:
        """One line for logs and the gate's status ("rejected: …" once, never twice)."""
        if self.decision == RETIMED:
            return (f"retimed: {self.duration_in:.3f} s → {self.duration_out:.3f} s "
                    f"(uniform slowdown {self.duration_uniform:.3f} s); was: {self.verdict}")
        if self.verdict.startswith(f"{self.decision}: "):
            return self.verdict
        return f"{self.decision}: {self.verdict}"

    @property
    def failure_label(self) -> str:
        """``state error`` for a goal refused for want of a fresh state, else ``planning error``."""
        return STATE_ERROR if self.reason == STALE_STATE else PLANNING_ERROR

    def to_dict(self, *, goal_id: str, mode: str, joint_names: list[str]) -> dict[str, Any]:
        """The JSON-ready record (NaN → null)."""
        tr = self.trajectory
        return {
            "version": RECORD_VERSION, "goal_id": goal_id, "mode": mode, "decision": self.decision,
            "reason": self.reason, "feasible": self.feasible, "verdict": self.verdict,
            "error_string": self.error_string if not self.forwards else "",
            "time_scale": _num(self.time_scale), "worst_joint": self.worst[0],
            "worst_constraint": self.worst[1], "worst_ratio": _num(self.worst[2]),
            "check_time_s": self.check_time_s, "duration_in": _num(self.duration_in),
            "duration_out": _num(self.duration_out), "duration_uniform": _num(self.duration_uniform),
            "retime_message": self.retime_message,
            "forwarded": None if tr is None else trajectory_dict(tr, joint_names),
            "judged": {k: _num(v) for k, v in self.judged.items()},
            **dict(self.extra),
        }


def _num(x: float) -> float | str | None:
    if isinstance(x, float) and math.isnan(x):
        return None
    if isinstance(x, float) and math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return x


def trajectory_dict(tr: Trajectory, joint_names: list[str]) -> dict[str, Any]:
    rows = lambda m: None if m is None else np.asarray(m, dtype=float).tolist()  # noqa: E731
    return {"joint_names": list(joint_names), "times": rows(tr.times), "positions": rows(tr.positions),
            "velocities": rows(tr.velocities), "accelerations": rows(tr.accelerations)}


def rejected(error: TrajectoryError, check_time_s: float = 0.0) -> Decision:
    """A goal that cannot be checked (malformed, no model, no retimer): never forwarded."""
    return Decision(REJECTED, f"rejected: {error}", getattr(error, "code", "error"), False, None,
                    check_time_s=check_time_s)


RetimeFn = Callable[..., Any]


def load_retimer() -> RetimeFn:
    """The retimer (imported when retime mode is used); TrajectoryError when it is not installed."""
    try:
        from dyn_node.retime import retime  # noqa: PLC0415 (optional: the retiming subpackage)
    except ImportError as exc:
        raise TrajectoryError(f"gate.mode retime needs dyn_node.retime ({exc})", code="no_retimer") from exc
    return retime


def state_problem(start: feasibility.StartState | None, max_age: float) -> str:
    """Why ``start`` cannot be checked from ("" when it can): none (no joint_states within the
    node's stale_timeout, or none naming every joint), or older than ``max_age`` s."""
    if start is None:
        return "no joint_states with every joint (or none recent)"
    if not start.age_s <= max_age:
        return f"joint_states {start.age_s * 1e3:.0f} ms old"
    return ""


def stale_state(problem: str, max_age: float) -> Decision:
    """A goal refused in reject and retime because the robot's state is unknown or too old."""
    err = TrajectoryError(f"{STALE_STATE}: {problem} (gate.max_state_age {max_age:g} s); the gate "
                          "does not forward what it cannot check from the robot's state", code=STALE_STATE)
    return rejected(err)


def decide_goal(dynamics: Dynamics, settings: Any, options: GateOptions, names: list[str],
                times: list[float], positions: Any, velocities: Any, accelerations: Any, *,
                start: feasibility.StartState | None, retimer: RetimeFn | None = None,
                plan: "RetimePlan | None" = None,
                timing: feasibility.Timing | None = None) -> Decision:
    """A goal's trajectory as received (its joint order, empty fields as sent): validated as the
    node validates an executed trajectory (at least two points), refused in reject and retime
    without a fresh ``start`` (:func:`state_problem`), then :func:`decide` with the check options
    of ``settings`` (the node's) and the goal's ``timing`` (its header stamp and receipt; None:
    zero stamp). The gate and the audit's replay both call this; ``plan``: see
    :class:`RetimePlan`."""
    try:
        traj = validate_trajectory(dynamics.model.joint_names, names, times, positions, velocities,
                                   accelerations, min_points=2)
    except TrajectoryError as exc:
        return rejected(exc)
    problem = state_problem(start, options.max_state_age)
    if problem and options.fails_closed:
        return stale_state(problem, options.max_state_age)
    d = decide(dynamics, traj, options, start=start, check_options=options_for(settings), retimer=retimer,
               limit_margin=settings.retime_limit_margin, plan=plan,
               timing=timing)
    if problem and d.forwards:  # check mode: forwarded, but said to be unjudged from the state
        return dataclasses.replace(d, reason=STALE_STATE)
    return d


@dataclass
class RetimePlan:
    """Retime mode on a moving robot: the retimer plans from the measured state extrapolated by
    ``lead_s`` (its expected run time: the robot moves on meanwhile, at its measured velocity), and
    its answer is re-checked from ``fresh()``, the state when it is forwarded (refused when that
    fails or is stale). The states used are kept (``planned_from``, ``rechecked_from``) for the
    record; the audit replays with them (``fresh`` returning the recorded one)."""

    lead_s: float
    fresh: Callable[[], feasibility.StartState | None]
    max_state_age: float = 0.1
    planned_from: feasibility.StartState | None = None
    rechecked_from: feasibility.StartState | None = None


def extrapolate(start: feasibility.StartState | None, lead_s: float) -> feasibility.StartState | None:
    """The state ``lead_s`` s on at the measured velocity (acceleration unknown: 0, as JTC assumes)."""
    if start is None or lead_s <= 0:
        return start
    return feasibility.StartState(start.positions + start.velocities * lead_s, start.velocities.copy(),
                                  start.age_s + lead_s)


def goal_dict(names: list[str], times: list[float], positions: Any, velocities: Any,
              accelerations: Any) -> dict[str, Any]:
    """The goal's trajectory for the record, exactly as received (JSON keeps every finite float;
    NaN and ±inf become "nan", "inf", "-inf", which float() reads back)."""
    num = lambda x: float(x) if math.isfinite(x) else str(float(x))  # noqa: E731
    rows = lambda m: [[num(x) for x in r] for r in m]  # noqa: E731
    return {"joint_names": list(names), "times": [num(t) for t in times], "positions": rows(positions),
            "velocities": rows(velocities), "accelerations": rows(accelerations)}


def goal_arrays(d: dict[str, Any]) -> tuple[list[str], list[float], list, list, list]:
    """:func:`goal_dict`'s inverse: (names, times, positions, velocities, accelerations)."""
    rows = lambda m: [[float(x) for x in r] for r in m]  # noqa: E731
    return (list(d["joint_names"]), [float(t) for t in d["times"]], rows(d["positions"]),
            rows(d["velocities"]), rows(d["accelerations"]))


def start_dict(start: feasibility.StartState | None) -> dict[str, Any] | None:
    if start is None:
        return None
    return {"positions": [float(x) for x in start.positions], "velocities": [float(x) for x in start.velocities],
            "age_s": float(start.age_s)}


def timing_dict(timing: feasibility.Timing | None) -> dict[str, float] | None:
    """A goal's timing for the record (the replay decides from the same)."""
    return None if timing is None else {"stamp_s": timing.stamp_s, "receipt_s": timing.receipt_s}


def timing_from_dict(d: dict[str, Any] | None) -> feasibility.Timing | None:
    """:func:`timing_dict`'s inverse (None, as in records made before it: zero stamp)."""
    return None if d is None else feasibility.Timing(float(d["stamp_s"]), float(d["receipt_s"]))


def start_from_dict(d: dict[str, Any] | None) -> feasibility.StartState | None:
    if d is None:
        return None
    return feasibility.StartState(np.asarray(d["positions"], dtype=float), np.asarray(d["velocities"], dtype=float),
                                  float(d["age_s"]))


def decide(dynamics: Dynamics, traj: Trajectory, options: GateOptions, *,
           start: feasibility.StartState | None,
           check_options: feasibility.FeasibilityOptions = feasibility.FeasibilityOptions(),
           retimer: RetimeFn | None = None, limit_margin: float = 0.995,
           plan: RetimePlan | None = None,
           timing: feasibility.Timing | None = None) -> Decision:
    """Check ``traj`` (model order, validated) as the controller executes it, received at
    ``timing`` by a robot in ``start``, and decide; see the module docstring. ``retimer``
    defaults to :func:`load_retimer`'s, loaded only when a goal is to be retimed;
    ``limit_margin``: the retimer's (the node's ``retime.limit_margin``); ``plan``: how a retiming
    follows the robot (:class:`RetimePlan`; None: planned and re-checked from ``start``)."""
    t0 = time.perf_counter()
    try:
        result = feasibility.check_trajectory(dynamics, traj, check_options, start=start,
                                              start_unknown=feasibility.NO_CURRENT_STATE,
                                              timing=timing, execution=options.execution(check_options.execution))
    except TrajectoryError as exc:
        return rejected(exc, time.perf_counter() - t0)
    worst = (result.worst_joint, result.worst_constraint, result.worst_ratio)
    base = dict(verdict=result.message, feasible=result.feasible, time_scale=result.time_scale,
                worst=worst, duration_in=traj.duration, judged=judged_values(result))
    wants_retime = options.mode == "retime" and (options.retime_all or not result.feasible)
    if not wants_retime:
        elapsed = time.perf_counter() - t0
        if result.feasible or options.mode == "check":
            return Decision(FORWARDED, reason="" if result.feasible else "infeasible", trajectory=traj,
                            check_time_s=elapsed, duration_out=traj.duration, result=result, **base)
        return Decision(REJECTED, reason="infeasible", trajectory=None, check_time_s=elapsed, **base)
    return _retimed(dynamics, traj, start, check_options, retimer, limit_margin, t0, base, result, plan)


def judged_values(result: feasibility.FeasibilityResult) -> dict[str, Any]:
    """The record's ``judged``: the execution model's summary keys and the start segment."""
    v = result.summary_values()
    keys = ("interpolation", "start_segment", "start_state_age_s", "start_time", "start_offset_s",
            "start_jump", "start_jump_joint", "start_velocity_step", "interpolation_segments",
            "linear_segments", "velocity_steps", "velocity_step_points", "refused_by_controller")
    return {k: v[k] for k in keys if k in v}


def junction_lead(dynamics: Dynamics, checked: feasibility.FeasibilityResult,
                  start: feasibility.StartState | None) -> float:
    """s by which retime mode delays a goal whose first point, due at once, is a jump from the
    measured state (beyond the start tolerance), so that the controller's start segment from that
    state to it (the execution model's) becomes the junction the retimer times; 0 without a jump.
    The lead only shapes that segment's path (twice the time at each joint's velocity and
    acceleration limits to cover the step); the retimer sets its timing."""
    ex = checked.execution
    jump = None if ex is None else ex.jump
    if start is None or jump is None or not (jump.exceeds_position or jump.exceeds_velocity):
        return 0.0
    lim = dynamics.model.limits
    with np.errstate(divide="ignore", invalid="ignore"):
        by_v = np.abs(jump.position) / lim.velocity
        by_a = np.abs(jump.velocity) / lim.acceleration
    need = [x for x in (*by_v, *by_a) if math.isfinite(x)]
    return max(0.1, 2.0 * max(need, default=0.0))


def _retimed(dynamics: Dynamics, traj: Trajectory, start: feasibility.StartState | None,
             check_options: feasibility.FeasibilityOptions, retimer: RetimeFn | None,
             limit_margin: float, t0: float, base: dict[str, Any],
             checked: feasibility.FeasibilityResult, plan: RetimePlan | None = None) -> Decision:
    def failed(message: str, uniform: float = math.nan) -> Decision:
        # a feasible goal (retime_all) whose retiming failed still goes as it came
        kept = traj if base["feasible"] else None
        return Decision(FORWARDED if kept is not None else REJECTED, reason="retime_failed",
                        trajectory=kept, retime_message=message, duration_uniform=uniform,
                        check_time_s=time.perf_counter() - t0, result=checked if kept is not None else None,
                        **base)

    planned = start
    if plan is not None:  # from where the robot will be when the answer goes out
        planned = plan.planned_from = extrapolate(start, plan.lead_s)
    junction = junction_lead(dynamics, checked, start)
    if junction > 0:  # a start jump: the plan begins with a junction from the measured state
        traj = replace(traj, times=traj.times + junction)
    try:
        fn = retimer or load_retimer()
        # the goal's check just made (from the measured state): the retimer checks its input
        # again only when it plans from an extrapolated one or a junction
        out = fn(dynamics, traj, start=planned, feasibility=check_options, limit_margin=limit_margin,
                 input_check=checked if planned is start and not junction else None,
                 certify=False)   # the robot moves on while it computes; nobody reads T* here
    except TrajectoryError as exc:
        return failed(str(exc))
    uniform = float(out.duration_uniform)
    if not out.feasible or out.trajectory is None:
        return failed(out.message, uniform)
    # what is forwarded passed this gate's check: the retimer's own exact check of its answer
    # (same options, same start) when it has one, else checked here as the controller will run it
    ok, why, again = _recheck(dynamics, out, check_options, start, plan)
    if not ok:
        return failed(f"the retimed trajectory failed the re-check: {why}", uniform)
    base["duration_in"] = float(out.duration_in) if out.duration_in > 0 else traj.duration
    return Decision(RETIMED, reason="", trajectory=out.trajectory, retime_message=out.message,
                    duration_out=float(out.duration_out), duration_uniform=uniform,
                    check_time_s=time.perf_counter() - t0, result=again, **base)


def _recheck(dynamics: Dynamics, out: Any, check_options: feasibility.FeasibilityOptions,
             start: feasibility.StartState | None, plan: RetimePlan | None) -> tuple[bool, str, Any]:
    """The retimed answer checked as the controller will run it: from a fresh state when the
    retiming follows the robot (never a stale "feasible"), else the retimer's own exact check
    (same options and start) when it has one."""
    recheck_from = start
    if plan is not None:
        recheck_from = plan.rechecked_from = plan.fresh()
        problem = state_problem(recheck_from, plan.max_state_age)
        if problem:
            return False, f"{STALE_STATE}: {problem} when the answer was ready", None
    try:
        again = out.check if out.check is not None and plan is None else feasibility.check_trajectory(
            dynamics, out.trajectory, check_options, start=recheck_from, start_unknown=feasibility.NO_CURRENT_STATE)
    except TrajectoryError as exc:
        return False, str(exc), None
    return bool(again.feasible), again.message, again
