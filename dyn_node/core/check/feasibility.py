"""Dynamic feasibility of a joint trajectory: every limit kind, the exact time scale, payload margin.

The trajectory is interpolated as joint_trajectory_controller executes it, sampled densely, and
checked by each constraint kind that applies (:mod:`dyn_node.core.check.constraints`); the method (sampling,
time scaling, the start segment, payload margin) is in docs/FEASIBILITY.md. Units SI; arrays in
model joint order.
"""
from __future__ import annotations

import math
import threading
import time
import weakref
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from dyn_node.core.check import constraints, exact_peaks, task_motion
from dyn_node.core.compiled import kernels
from dyn_node.core.check.constraints import (Constraint, Motion, PayloadTerms, Samples,
                                             Violation, _fmt, _Job, json_scalar, with_unit)
from dyn_node.core.check.kinds import KIND_CLASS, KINDS
# reached here by the tests of the helpers they name
from dyn_node.core.check.constraints import _take, rms_time_scale as _rms_time_scale  # noqa: F401
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.errors import PLANNING_ERROR, TrajectoryError
from dyn_node.core.robot.limits import LIMIT_KINDS
from dyn_node.core.robot.model import Payload
from dyn_node.core.check.start_segment import StartSegment
from dyn_node.core.check import execution as jtc
from dyn_node.core.check.execution import Execution, ExecutionOptions, Timing  # noqa: F401
from dyn_node.core.check.verdict import (Scale as _Scale, apply_execution, describe_violation as _describe_violation,
                                         execution_values, kind_text as _kind_text, verdict as _verdict)
from dyn_node.core.check.start_segment import (NO_CURRENT_STATE, START_CHECKED, START_NONE,  # noqa: F401
                                               StartState, current_state)
from dyn_node.core.robot.status import ERROR, NAME_PREFIX, OK, WARN, Status
from dyn_node.core.check.trajectory import PiecewisePolynomial, Trajectory, interpolate, segment_steps
from dyn_node.core.robot.units import joint_units

STATUS_NAME = NAME_PREFIX + "trajectory feasibility"
#: Kinds whose value is a torque (or derived from one): these depend on payload and use
#: ``effort_warn_ratio``.
EFFORT_KINDS = tuple(k for k in LIMIT_KINDS if any(c.kind == k and c.payload_dependent
                                                   for c in KINDS))


@dataclass(frozen=True)
class FeasibilityOptions:
    """``sample_period`` (s): longest step between samples; ``effort_warn_ratio``: a feasible
    trajectory whose peak ratio to any non-position limit exceeds this is WARN;
    ``max_samples``: at most this many samples; beyond, the longest segments get fewer steps
    (with a warning), never fewer than MIN_SEGMENT_STEPS each (else rejected as too long); ``threads``: OpenMP threads
    for the batched RNEA passes (None: the Dynamics' own setting, one unless built otherwise;
    with two or more and a task section configured, one of them runs the frame pass instead).
    Every state is computed by the same sequential RNEA whatever the count, so the result does
    not depend on it; more threads only help when cores are free (a live node's joint_states
    path needs one). ``execution``: the execution model's options (start tolerance, the
    controller's allow_nonzero_velocity_at_trajectory_end)."""

    sample_period: float = 0.001
    effort_warn_ratio: float = 0.9
    compute_payload_margin: bool = True
    max_samples: int = 250_000
    threads: int | None = None
    execution: ExecutionOptions = field(default_factory=ExecutionOptions)


@dataclass(frozen=True)
class FeasibilityResult:
    """The verdict on one trajectory. ``per_joint[joint][kind]`` = {ratio, time_s, value, limit}
    (ratio None: no limit of that kind); ``time_scale_by_kind[kind]`` is the per-kind factor."""

    feasible: bool
    level: int
    message: str
    failure_label: str
    worst_joint: str
    worst_constraint: str
    worst_ratio: float
    first_violation_time_s: float
    time_scale: float
    time_scale_joint: str
    time_scale_constraint: str
    time_scale_by_kind: Mapping[str, float]
    payload_margin_kg: float
    n_points: int
    n_samples: int
    duration_s: float
    interpolation: str
    violations: tuple[Violation, ...]
    per_joint: Mapping[str, Mapping[str, Mapping[str, Any]]]
    effort_step: Mapping[str, float]
    waypoint_effort: np.ndarray = field(repr=False)
    compute_time_s: float = 0.0
    #: the task kinds' peaks: place (a frame, "robot_limits", "base_limits", "grasp") → kind →
    #: {ratio, time_s, value, limit, unit}, only the configured kinds of each place
    per_frame: Mapping[str, Mapping[str, Mapping[str, Any]]] = field(default_factory=dict)
    #: place → kind → (t (s), |value|) of the task kinds at the given timing, each bin's
    #: largest of at most :data:`CURVE_POINTS` bins (peaks survive): for plots, not published
    task_curves: Mapping[str, Mapping[str, tuple[np.ndarray, np.ndarray]]] = field(
        default_factory=dict, repr=False)
    warnings: tuple[str, ...] = ()
    effort_warn_ratio: float = 0.9
    #: the segment from the robot's current state to the first point: START_CHECKED,
    #: START_NONE, or "not_checked (<why>)"; the state's age (s, NaN without one); whether
    #: that segment sets ``time_scale``
    start_segment: str = "none (first point at t = 0)"
    start_state_age_s: float = math.nan
    time_scale_start_segment: bool = False
    #: what was judged: the trajectory as the controller executes it
    #: (:class:`~dyn_node.core.check.execution.Execution`; None only for results made by hand)
    execution: Any = field(default=None, repr=False, compare=False)

    @property
    def binding_joint(self) -> str:
        """The joint or place whose slowdown sets ``time_scale`` ("" when none does); the
        largest ratio (``worst_joint``) may be elsewhere: velocity needs k = r, acceleration √r."""
        return self.time_scale_joint

    @property
    def binding_constraint(self) -> str:
        """The limit kind that sets ``time_scale`` (beside ``worst_constraint``, the largest ratio)."""
        return self.time_scale_constraint

    def summary_values(self) -> dict[str, Any]:
        return {
            "feasible": self.feasible, "worst_joint": self.worst_joint,
            "worst_constraint": self.worst_constraint, "worst_ratio": self.worst_ratio,
            "first_violation_time_s": self.first_violation_time_s, "time_scale": self.time_scale,
            "payload_margin_kg": self.payload_margin_kg, "n_points": self.n_points,
            "duration_s": self.duration_s, "failure_label": self.failure_label,
            "interpolation": self.interpolation, "n_samples": self.n_samples,
            "time_scale_joint": self.time_scale_joint,
            "time_scale_constraint": self.time_scale_constraint,
            "binding_joint": self.binding_joint, "binding_constraint": self.binding_constraint,
            "violations": len(self.violations), "compute_time_s": self.compute_time_s,
            "warnings": "; ".join(self.warnings),
            "start_segment": self.start_segment, "start_state_age_s": self.start_state_age_s,
            "time_scale_start_segment": self.time_scale_start_segment,
            **(execution_values(self.execution, list(self.per_joint))
               if self.execution is not None else {}),
        }

    def statuses(self, hardware_id: str = "") -> list[Status]:
        """The summary status, then one per joint with its peak ratio per limit kind."""
        out = [Status(STATUS_NAME, self.level, self.message, hardware_id, self.summary_values())]
        for joint, kinds in self.per_joint.items():
            values: dict[str, Any] = {}
            level, worst_kind, worst = OK, "", -1.0
            for kind in LIMIT_KINDS:
                entry = kinds[kind]
                r = entry["ratio"]
                values[f"{kind}_ratio"] = "unlimited" if r is None else r
                values[f"{kind}_time_s"] = "" if entry["time_s"] is None else entry["time_s"]
                if r is not None and kind != "position" and r > worst:
                    worst, worst_kind = r, kind
            values["effort_step"] = self.effort_step.get(joint, 0.0)
            bad = [v for v in self.violations if v.joint == joint]
            if bad:
                level = ERROR
                msg = "; ".join(f"{v.kind} {_describe_violation(v)}" for v in bad)
            else:
                if worst > self.effort_warn_ratio:
                    level = WARN
                msg = (f"worst {_kind_text(worst_kind)} {worst * 100:.0f}% of limit "
                       f"at t = {kinds[worst_kind]['time_s']:.2f} s" if worst_kind else "no limits")
            values["failure_label"] = PLANNING_ERROR if level != OK else ""
            out.append(Status(f"{STATUS_NAME}/{joint}", level, msg, hardware_id, values))
        out += [self._place_status(place, kinds, hardware_id)
                for place, kinds in self.per_frame.items()]
        return out

    def _place_status(self, place: str, kinds: Mapping[str, Mapping[str, Any]],
                      hardware_id: str) -> Status:
        """``<name>/<place>``: each configured task kind's ratio, time, peak, limit and the unit
        of those two (a key beside them: the status values carry no unit otherwise)."""
        values: dict[str, Any] = {}
        worst_kind, worst = next(iter(kinds)), -1.0
        for kind, e in kinds.items():
            values.update({f"{kind}_ratio": e["ratio"], f"{kind}_time_s": e["time_s"],
                           f"{kind}_peak": e["value"], f"{kind}_limit": e["limit"],
                           f"{kind}_unit": e["unit"]})
            if e["ratio"] > worst:
                worst, worst_kind = e["ratio"], kind
        bad = [v for v in self.violations if v.joint == place]
        level = ERROR if bad else WARN if worst > self.effort_warn_ratio else OK
        if bad:
            msg = "; ".join(KIND_CLASS[v.kind].describe(v) for v in bad)
        else:
            e = kinds[worst_kind]
            msg = (f"worst {_kind_text(worst_kind)} {worst * 100:.0f}% of "
                   f"{with_unit(e['limit'], e['unit'])} at t = {e['time_s']:.2f} s")
        values["failure_label"] = PLANNING_ERROR if level != OK else ""
        return Status(f"{STATUS_NAME}/{place}", level, msg, hardware_id, values)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: NaN (undefined) → null, ±inf → "inf"/"-inf"."""
        return {
            **{k: json_scalar(v) for k, v in self.summary_values().items() if k != "warnings"},
            "level": {OK: "OK", WARN: "WARN", ERROR: "ERROR"}[self.level],
            "message": self.message,
            "time_scale_by_kind": {k: json_scalar(v) for k, v in self.time_scale_by_kind.items()},
            "violations": [v.to_dict() for v in self.violations],
            "per_joint": {j: {k: {kk: json_scalar(vv) for kk, vv in e.items()} for k, e in kinds.items()}
                          for j, kinds in self.per_joint.items()},
            "per_frame": {p: {k: {kk: json_scalar(vv) for kk, vv in e.items()} for k, e in kinds.items()}
                          for p, kinds in self.per_frame.items()},
            "effort_step": {j: json_scalar(v) for j, v in self.effort_step.items()},
            "waypoint_effort": [[json_scalar(float(x)) for x in row] for row in self.waypoint_effort],
            "warnings": list(self.warnings),
            "start_state": _start_state_dict(self.execution),
        }


def _start_state_dict(ex: Any) -> dict[str, Any] | None:
    """The robot's state the execution started from (model order), None without one."""
    st = None if ex is None else ex.start
    if st is None:
        return None
    return {"positions": [float(x) for x in st.positions],
            "velocities": [float(x) for x in st.velocities], "age_s": json_scalar(float(st.age_s))}


def rejected_statuses(error: TrajectoryError, hardware_id: str = "", n_points: int = 0,
                      duration_s: float = math.nan) -> list[Status]:
    """ERROR status for a trajectory that could not be checked, with the same keys as a verdict."""
    values = {
        "feasible": False, "worst_joint": "", "worst_constraint": "", "worst_ratio": math.nan,
        "first_violation_time_s": math.nan, "time_scale": math.nan,
        "payload_margin_kg": math.nan, "n_points": int(n_points), "duration_s": float(duration_s),
        "failure_label": error.failure_label, "reason": getattr(error, "code", "error"),
        "binding_joint": "", "binding_constraint": "",
    }
    return [Status(STATUS_NAME, ERROR, f"rejected: {error}", hardware_id, values)]


# ----------------------------------------------------------------------------------------------
# helpers

def _colmax(X: np.ndarray) -> np.ndarray:
    """X.max(axis=0), the same numbers, faster for M×m arrays with few columns: max along axis
    0 runs a short inner loop per row, argmax works down each column at once (no copy for the
    column-major arrays the check uses)."""
    if X.ndim != 2 or not X.shape[0]:
        return X.max(axis=0)
    return X[np.argmax(X, axis=0), np.arange(X.shape[1])]


def _sample(times: np.ndarray, period: float, max_samples: int,
            min_steps: np.ndarray | None = None) -> Samples:
    """Every segment sampled on its own: uniform steps of at most ``period``, at least ``min_steps``,
    fewer only for the longest when samples would exceed ``max_samples`` (:func:`segment_steps`)."""
    T = np.diff(times)
    n = segment_steps(times, period, max_samples, min_steps)
    counts = n + 1
    first = np.concatenate(([0], np.cumsum(counts)[:-1]))
    last = first + n
    seg = np.repeat(np.arange(len(T)), counts)
    j = np.arange(counts.sum()) - first[seg]
    hseg = T / n
    h = hseg[seg]
    s = j * h
    s[last] = T
    t = times[:-1][seg] + s
    weight = h.copy()
    weight[first] *= 0.5
    weight[last] *= 0.5
    return Samples(t=t, seg=seg, first=first, last=last, h=h, weight=weight, period=period)


def _evaluate(coeffs: np.ndarray, breaks: np.ndarray, smp: Samples,
              n_derivatives: int = 4) -> list[np.ndarray]:
    """q, q̇, q̈, q⃛ (M×nv; the first ``n_derivatives`` of them) of the piecewise polynomial at
    the samples, each on its own segment."""
    s = smp.t - breaks[smp.seg]
    s[smp.last] = breaks[1:] - breaks[:-1]
    # every derivative's coefficients in one zero-padded table (a zero leading coefficient
    # leaves Horner's result unchanged)
    K, P, nv = coeffs.shape
    tables = np.zeros((n_derivatives, K, max(P, 1), nv))
    c = coeffs
    for d in range(n_derivatives):
        tables[d, :, :c.shape[1]] = c
        c = c[:, 1:, :] * np.arange(1, c.shape[1], dtype=float)[None, :, None]
    return list(kernels.piecewise_eval(tables, smp.seg, s))


_PAYLOAD_CACHE: "weakref.WeakKeyDictionary[Dynamics, tuple[Any, Dynamics]]" = weakref.WeakKeyDictionary()
_CACHE_LOCK = threading.Lock()


def _unit_payload_dynamics(dynamics: Dynamics) -> Dynamics:
    """Dynamics of the same robot carrying 1 kg more at the payload point (cached per instance)."""
    model = dynamics.model
    with _CACHE_LOCK:
        hit = _PAYLOAD_CACHE.get(dynamics)
        if hit is not None and hit[0] is model:
            return hit[1]
    p = model.payload
    heavier = model.with_payload(Payload(mass=p.mass + 1.0, com=p.com, frame=p.frame))
    dyn = Dynamics(heavier, dynamics.options, threads=getattr(dynamics, "_threads", None))
    with _CACHE_LOCK:
        _PAYLOAD_CACHE[dynamics] = (model, dyn)
    return dyn


def _batch_threads(dynamics: Dynamics, threads: int | None) -> int:
    bt = getattr(dynamics, "batch_threads", None)
    return int(bt(threads)) if bt is not None else 1


# ----------------------------------------------------------------------------------------------

def check_trajectory(dynamics: Dynamics, traj: Trajectory,
                     options: FeasibilityOptions = FeasibilityOptions(), *,
                     start: StartState | None = None,
                     start_unknown: str = "no current state given",
                     timing: Timing | None = None,
                     execution: ExecutionOptions | None = None) -> FeasibilityResult:
    """Check ``traj`` (model order) as joint_trajectory_controller executes it
    (:func:`dyn_node.core.check.execution.execute`: received at ``timing``, None = zero stamp,
    by a robot in ``start``, with the ``execution`` options, else ``options.execution``) against every limit of
    ``dynamics.model``; see docs/FEASIBILITY.md and docs/limits.md.

    Without ``start`` the first point is the start; when it lies ahead the verdict is at least
    WARN and says why (``start_unknown``). A jump or a velocity step is an infeasible verdict,
    never an error. Raises only :class:`TrajectoryError` (so a caller can always publish a
    rejected status): a numerical failure deep inside (overflow, a Pinocchio error) becomes one
    with code ``evaluation_failed``.
    """
    try:
        _validate(traj, options, single=start is not None)
        ex = jtc.execute(traj, start, timing, execution or options.execution)
        return _check(dynamics, ex, options, start_unknown)
    except TrajectoryError:
        raise
    except (ArithmeticError, ValueError, RuntimeError, MemoryError) as exc:
        raise TrajectoryError(f"trajectory could not be evaluated: {type(exc).__name__}: {exc}",
                              code="evaluation_failed") from exc


#: Beyond this magnitude a motion or torque is treated as non-finite: its square (RMS, power)
#: and the time-scale polynomials would overflow.
_HUGE = 1e100


def _check(dynamics: Dynamics, ex: Execution, options: FeasibilityOptions,
           start_unknown: str = "no current state given",
           search_start: bool = True) -> FeasibilityResult:
    """The check of an execution: sample, build the constraints that apply, collect their
    peaks, violations, time-scale factors and payload intervals, add what the execution model
    found (jump, velocity steps), then the verdict."""
    t_start = time.perf_counter()
    traj = ex.trajectory
    warnings: list[str] = []
    start_segment = _start_segment(ex, start_unknown, warnings)
    # with a start velocity the start segment does not stretch like the rest (q̇0 stays): its
    # share of the time scale is searched (StartSegment), the laws cover the samples after it
    fixed_start = ex.fixed_start
    motion, tau1 = _motion(dynamics, ex.pp, options, fixed_start, warnings)
    waypoints = np.concatenate((motion.smp.first, motion.smp.last[-1:]))
    # the message's points (a prepended state is not one); one passed before a past stamp's
    # start gets its torque as the message has it (it was never executed)
    waypoint_effort = np.empty((traj.n_points, motion.tau.shape[1]))
    done = ex.point_knots >= 0
    waypoint_effort[done] = motion.tau[waypoints[ex.point_knots[done]]]
    if not done.all():
        waypoint_effort[~done] = _passed_point_torques(dynamics, traj, ~done)
    effort_step = _effort_steps(motion, ex, warnings)
    kinds = constraints.build(motion, KINDS)
    warnings += [w for c in kinds for w in c.warnings]
    # the payload margin beside the rest when parallel
    margin_job = None if tau1 is None else _Job(
        _payload_margin, (kinds, motion, PayloadTerms(tau1, _unit_payload_dynamics(dynamics))),
        background=motion.parallel)
    per_joint, per_frame, violations = _report(kinds, motion)
    scale = _time_scale(kinds, fixed_start)
    apply_execution(ex, per_joint, violations, scale, warnings, motion.units)
    if fixed_start and search_start and scale.blocked is None and math.isfinite(scale.k):
        search = StartSegment(_check, dynamics, ex, options, motion.smp.period,
                              whole=any(c.reaches_back for c in kinds))
        _search_start(scale, search, feasible=not violations)
    _exact(scale, not violations, warnings)
    _refuse_nan(per_joint, per_frame, scale)
    margin = math.inf if margin_job is None else margin_job.result()
    verdict = _verdict(per_joint, per_frame, violations, warnings, scale, options,
                       motion.units, start_segment)
    return FeasibilityResult(
        **verdict, time_scale=float(scale.k), time_scale_joint=scale.where,
        time_scale_constraint=scale.kind, time_scale_by_kind=scale.by_kind,
        payload_margin_kg=float(margin), n_points=traj.n_points, n_samples=len(motion.smp.t),
        duration_s=traj.duration, interpolation=ex.interpolation,
        violations=tuple(violations), per_joint=per_joint, effort_step=effort_step,
        waypoint_effort=waypoint_effort, compute_time_s=time.perf_counter() - t_start,
        warnings=tuple(warnings), effort_warn_ratio=options.effort_warn_ratio,
        start_segment=start_segment, start_state_age_s=ex.start_age_s,
        time_scale_start_segment=scale.start_binds, per_frame=per_frame,
        task_curves=_task_curves(kinds, motion.smp.t), execution=ex)


def _refuse_nan(per_joint: Mapping[str, Mapping[str, Mapping[str, Any]]],
                per_frame: Mapping[str, Mapping[str, Mapping[str, Any]]], scale: _Scale) -> None:
    """A NaN (or negative) ratio or time scale never reaches a verdict: rejected, place named."""
    for place, kinds in (*per_joint.items(), *per_frame.items()):
        for kind, e in kinds.items():
            r, v = e["ratio"], e["value"]
            if (r is not None and not r >= 0) or (isinstance(v, float) and math.isnan(v)):
                raise TrajectoryError(f"{place} {kind} could not be evaluated (NaN: check its limits)",
                                      code="evaluation_failed")
    if math.isnan(scale.k):
        raise TrajectoryError(f"time scale of {scale.where} {scale.kind} is NaN", code="evaluation_failed")


def _validate(traj: Trajectory, options: FeasibilityOptions, single: bool = False) -> None:
    """``single``: one point is motion too (from the robot's state to it, then held)."""
    if traj.n_points < (1 if single else 2):
        raise TrajectoryError(f"trajectory has {traj.n_points} point(s); at least 2 are needed "
                              "to check motion", code="too_few_points")
    if not (options.sample_period > 0 and math.isfinite(options.sample_period)):
        raise TrajectoryError("sample_period must be a positive number of seconds",
                              code="bad_options")


def _passed_point_torques(dynamics: Dynamics, traj: Trajectory, which: np.ndarray) -> np.ndarray:
    """τ at the message's points ``which`` on its own interpolation (zero stamp, no state), as
    on_demand.inverse_dynamics computes a state's torque."""
    Q, V, A, _ = jtc.execute(traj).pp.evaluate(traj.times[which])
    tau = task_motion.inverse_dynamics(dynamics, Q, V, A)
    return tau if tau is not None else dynamics.terms_batch(Q, V, A).full


def _start_segment(ex: Execution, start_unknown: str, warnings: list[str]) -> str:
    """``start_segment``: checked (from the robot's state), not checked (no state, the first
    point ahead: warned), or none (the first point due at once, or a past stamp)."""
    if ex.start_segment:
        return START_CHECKED
    t0 = float(ex.knots.times[0])
    if t0 > 0:
        warnings.insert(0, f"start segment not checked ({start_unknown}): the controller moves "
                           f"from the robot's state to the first point in {t0:.3g} s")
        return f"not_checked ({start_unknown})"
    if ex.offset_s > 0 and ex.point_knots[0] < 0:
        return f"none (started {ex.offset_s:.3g} s into the trajectory: past stamp)"
    return START_NONE


def _motion(dynamics: Dynamics, work: PiecewisePolynomial | Trajectory, options: FeasibilityOptions,
            fixed_start: bool, warnings: list[str]) -> tuple[Motion, np.ndarray | None]:
    """The sampled motion of ``work`` (the executed polynomials; a Trajectory, for the
    constraint kinds' tests, by its natural interpolation) and its torque terms, and τ1 (the
    torque per kg of payload) when the margin is wanted and a limit depends on payload: the
    batched RNEA passes, done together."""
    model = dynamics.model
    nv = model.nv
    pp = work if isinstance(work, PiecewisePolynomial) else interpolate(work, work.natural_interpolation)
    least = exact_peaks.min_steps(pp)
    smp = _sample(pp.breaks, options.sample_period, options.max_samples, least)
    warnings += exact_peaks.sampling_warnings(smp, least, options.sample_period)
    applicable = [cls for cls in KINDS if cls.applies(model)]
    n_derivatives = 1 + max((cls.order for cls in applicable), default=2)
    Q, V, A, *rest = _evaluate(pp.coeffs, pp.breaks, smp, max(3, n_derivatives))
    J = rest[0] if rest else np.zeros((0, nv))
    margin = options.compute_payload_margin and any(c.payload_dependent for c in applicable)
    parallel = _batch_threads(dynamics, options.threads) > 1
    # the torque terms (τ1 too) from one compiled frame pass; on_demand.inverse_dynamics alike
    task = task_motion.build(dynamics, Q, V, A, payload_torque=margin, rnea=True)
    terms, unit = (task.terms, task.payload_torque) if task is not None else \
        task_motion.joint_terms(dynamics, Q, V, A, payload_torque=margin)
    kernel = terms is not None
    terms = terms if kernel else dynamics.terms_batch(Q, V, A, options.threads)
    S, W, I, tau = terms.static, terms.viscous, terms.inertial, terms.full
    with np.errstate(invalid="ignore"):
        # |X|.max() < _HUGE without forming |X| (NaN fails either comparison, as it should)
        huge = not all(X.size == 0 or (X.max() < _HUGE and X.min() > -_HUGE)
                       for X in (tau, V, A, J))
    if huge:
        raise TrajectoryError("the interpolated motion or its torque is not finite (values too "
                              "large for the time steps)", code="non_finite")
    tau1 = (unit if kernel else _payload_torque(dynamics, Q, V, A, tau, options.threads)) \
        if margin else None
    if task is not None and task.task_torque is not None:
        # the environment's −W on the tool: J_frameᵀ·W more, static (it does not scale with k)
        S, tau = (np.add(X, task.task_torque, out=np.empty_like(X)) for X in (S, tau))
    # From here on the per-sample arrays are column-major (each joint's samples contiguous,
    # as the torque terms already are): per-joint reductions and per-joint limits then run
    # along contiguous memory. Q stays row-major (single states go to Pinocchio).
    del terms, rest      # no second copy of the row-major arrays stays alive
    V = np.asfortranarray(V)     # one at a time: each row-major original goes at once
    A = np.asfortranarray(A)
    J = np.asfortranarray(J)
    coulomb = np.asarray(model.pin_model.friction, dtype=float) \
        if dynamics.options.include_friction else np.zeros(nv)
    G = S - coulomb * np.sign(V) if np.any(coulomb) else S
    return Motion(dynamics=dynamics, smp=smp, Q=Q, V=V, A=A, J=J, S=S, W=W, I=I, tau=tau, G=G,
                  coulomb=coulomb, hold=dynamics.gravity(Q[0]), task=task,
                  r0=int(smp.first[1]) if fixed_start else 0,
                  parallel=parallel, units=joint_units(model), pieces=pp), tau1


def _effort_steps(motion: Motion, ex: Execution, warnings: list[str]) -> dict[str, float]:
    """Per joint, the largest step of the commanded torque where a knot joins segments whose
    accelerations differ: an unbounded rate at any k, so it is reported, not checked (a warning
    when a cubic segment is among them, only C¹)."""
    times = ex.knots.times
    if len(times) <= 2:
        return {}
    tau, smp, names = motion.tau, motion.smp, motion.names
    steps = np.abs(tau[smp.first[1:]] - tau[smp.last[:-1]])  # (N-2)×nv
    peak = _colmax(steps)
    effort_step = {names[j]: float(peak[j]) for j in range(len(names))}
    scale = np.maximum(kernels.abs_peak(tau)[1], 1e-9)
    if jtc.CUBIC in ex.modes and np.any(peak > 1e-6 * scale):
        j = int(np.argmax(peak / scale))
        w_ = int(np.argmax(steps[:, j])) + 1
        warnings.append(f"cubic interpolation: acceleration jumps at waypoints make the torque "
                        f"step by up to {_fmt(peak[j])} {motion.units['effort'][j]} ({names[j]} "
                        f"at t = {times[w_]:.2f} s); effort rate is checked within segments")
    return effort_step


def _report(kinds: list[Constraint], motion: Motion
            ) -> tuple[dict[str, dict[str, dict[str, Any]]], dict[str, dict[str, dict[str, Any]]],
                       list[Violation]]:
    """Every kind's peak per joint (None where a kind has no limit), the task kinds' per place
    (with the unit), and the violations, in :data:`KINDS` order (joint kinds first)."""
    per_joint: dict[str, dict[str, dict[str, Any]]] = {
        n: {k: {"ratio": None, "time_s": None, "value": None, "limit": None} for k in LIMIT_KINDS}
        for n in motion.names}
    per_frame: dict[str, dict[str, dict[str, Any]]] = {}
    violations: list[Violation] = []
    for c in kinds:
        peaks, bad = c.report(motion)
        for p in peaks:
            if c.scope == "joint":
                per_joint[p.where][c.kind] = p.entry()
            else:
                unit = c.units[c.where.index(p.where)]
                per_frame.setdefault(p.where, {})[c.kind] = {**p.entry(), "unit": unit}
        violations += bad
    order = {kind: n for n, kind in enumerate((*LIMIT_KINDS, *KIND_CLASS))}
    violations.sort(key=lambda v: order.get(v.kind, len(order)))
    return per_joint, per_frame, violations


#: Points per curve of :attr:`FeasibilityResult.task_curves` at most.
CURVE_POINTS = 400


def _task_curves(kinds: list[Constraint], tt: np.ndarray
                 ) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Each task kind's |value| per place, the largest sample of each of ≤ CURVE_POINTS equal
    bins of samples (with its time)."""
    out: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    M = len(tt)
    edges = np.unique(np.linspace(0, M, min(M, CURVE_POINTS) + 1).astype(np.int64))
    for c in kinds:
        if c.scope != "task":
            continue
        val = c.values()
        first = kernels.bin_peaks(val, edges)   # each bin's first sample at its largest |val|
        for col, where in enumerate(c.where):
            at = first[:, col]
            out.setdefault(where, {})[c.kind] = (tt[at], np.abs(val[at, col]))
    return out


def _time_scale(kinds: list[Constraint], fixed_start: bool) -> _Scale:
    """The largest factor over the kinds (the first kind and place on a tie), unless a kind
    blocks every slowdown (a timing-free one first)."""
    scale = _Scale(0.0, "", "", {}, None)
    for c in kinds:
        kk = c.time_scale()
        if kk is None or not len(kk):
            continue
        n = int(np.argmax(kk))
        scale.by_kind[c.kind] = float(kk[n])
        # a kind reaching back into a start segment that does not scale is decided by the
        # start-segment search (which checks the whole stretched trajectory)
        if kk[n] > scale.k and not (c.reaches_back and fixed_start):
            scale.k, scale.where, scale.kind = float(kk[n]), c.where[n], c.kind
    blocked = [(c.kind, b) for c in kinds if (b := c.blocked()) is not None]
    if blocked:
        kind, scale.blocked = next((kb for kb in blocked if kb[1].timing_free), blocked[0])
        scale.k, scale.where, scale.kind = math.inf, scale.blocked.where, kind
        scale.by_kind[kind] = math.inf
    return scale


def _search_start(scale: _Scale, search: StartSegment, *, feasible: bool) -> None:
    found = search.time_scale(scale.k, feasible)
    if found is not None:
        scale.k, scale.where, scale.kind = found
        scale.start_binds = True
        scale.by_kind[scale.kind] = max(scale.by_kind.get(scale.kind, 0.0), scale.k)


def _exact(scale: _Scale, feasible: bool, warnings: list[str]) -> None:
    """The per-constraint roots and the direct check agree up to rounding; make the contract
    exact."""
    k = scale.k
    if feasible and 1.0 < k < 1.0 + 1e-6:
        scale.k = 1.0
    elif not feasible and math.isfinite(k) and k <= 1.0:
        if k > 1.0 - 1e-6:
            scale.k = float(np.nextafter(1.0, 2.0))
        else:
            warnings.append(f"time scale {k:.6g} disagrees with the direct check (rounding)")


def _payload_torque(dynamics: Dynamics, Q, V, A, tau0, threads: int | None = None) -> np.ndarray:
    """τ1 (M×nv, N·m per kg): the torque of 1 kg more at the payload point, as the difference
    of a batched RNEA with that mass and the trajectory's own torque τ0."""
    heavy = _unit_payload_dynamics(dynamics).rnea_batch(Q, V, A, threads)
    return np.subtract(heavy, tau0, out=np.empty_like(tau0))    # in τ0's memory order


def _payload_margin(kinds: list[Constraint], motion: Motion, payload: PayloadTerms) -> float:
    """Largest extra mass m (kg) at the payload point keeping every payload-dependent limit at
    the trajectory's own timing: τ = τ0 + m·τ1 is affine in m, so each kind gives an interval
    (−inf when they do not meet, +inf when no kind depends on payload)."""
    bands = [b for c in kinds if c.payload_dependent
             and (b := c.payload_band(motion, payload)) is not None]
    lo = max((b[0] for b in bands), default=-math.inf)
    hi = min((b[1] for b in bands), default=math.inf)
    if lo > hi:
        return -math.inf
    return hi
