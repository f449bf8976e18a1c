"""Dynamic feasibility of a joint trajectory: every limit kind, the exact time scale, payload margin.

The trajectory is interpolated as ros2_control's joint_trajectory_controller executes it (quintic
with positions, velocities and accelerations; cubic with positions and velocities; for positions
only a C² cubic spline with zero end velocities, announced in a warning) and sampled densely:
every segment is split uniformly into steps no longer than ``sample_period``, and both ends of
every segment are samples (an interior waypoint appears twice, once as the end of the segment
before it and once as the start of the one after it, so one-sided limits of discontinuous
derivatives are checked exactly).

Time scaling. Stretching the trajectory's duration by k (x = 1/k) gives q̇ ÷ k, q̈ ÷ k², q⃛ ÷ k³
(the deceleration limit applies to |q̈| where q̇·q̈ < 0, a sign that k does not change, so its
share is k = sqrt(|q̈| / max_deceleration) at the worst decelerating sample), and torque
τ(x) = s + w·x + i·x² with s = gravity + Coulomb friction, w = viscous friction,
i = inertial + Coriolis + armature (:class:`~dyn_node.dynamics.TorqueTerms`). Each constraint at
each sample is a polynomial of degree ≤ 3 in x (the torque-speed envelope piecewise so), so its
first exit from the allowed band is found in closed form, in one compiled loop over the samples
per constraint (:mod:`dyn_node.kernels`); cheap bounds (|s| + |w|·x + |i|·x² ≥ |τ(x)|) decide
which samples could hold the largest factor, and only those are solved exactly. The RMS (thermal) constraint, whose window covers a
k-dependent stretch of samples, is solved on k for that constraint alone (secant on log k, each
trial decided exactly on a sparse grid of windows plus the gaps a bound cannot clear; see
``_rms_time_scale``). ``time_scale`` is the largest of these per-sample factors: the smallest k
such that every k' ≥ k is feasible.

Start segment. When the first point lies ahead (t0 > 0) the controller moves there from the
robot's state; given that state (:class:`StartState`) the check prepends it
(:func:`~dyn_node.trajectory.from_current_state`) and checks that segment like any other. Its
start velocity is the robot's and does not scale with k, so when it is not zero the per-sample
laws cover only the samples after it, and the segment's share is searched
(:func:`_start_time_scale`: walk, then bisection, each trial checked directly).

Cost: the batched RNEA passes (the full torque, and the 1 kg payload for the margin) are the
largest part, then the compiled gravity pass the time scale needs (0.3 of an RNEA pass;
see :meth:`Dynamics.terms_batch`); everything else is a fixed number of passes over the samples,
the per-sample ones compiled and run without the GIL (the node's joint_states path keeps running
beside a check). With ``FeasibilityOptions.threads`` above one, the RNEA passes use that many
OpenMP threads and the RMS search and the payload margin run on a background thread beside the
other checks; every number is computed by the same operations either way, so the result is
identical.

Effort rate is dτ/dt, by finite differences inside each segment (where the interpolated motion is
a polynomial and τ is smooth). Where a waypoint joins segments whose accelerations differ (cubic
interpolation is only C¹), the commanded torque steps; a step is an unbounded rate at any k, so
it is not folded into the rate check but reported explicitly (per-joint ``effort_step`` and a
warning). Coulomb friction's step at a velocity reversal is likewise excluded from the rate.

RMS effort is over a sliding window of ``rms_window`` s ending at each sample; before the
trajectory starts the robot is assumed to hold the first pose (torque g(q0)).

Payload margin: τ is affine in an extra point mass m at the payload point, τ = τ0 + m·τ1 (τ1
from a second batched RNEA with 1 kg more), so effort, envelope, power and effort-rate limits
each give an interval of m per sample, and the RMS limit a quadratic in m per window; the margin
is the largest m in the intersection (−inf when it is empty, +inf when no effort-type limit
exists). Position, velocity, acceleration and jerk do not depend on payload.

Units: SI (rad, rad/s, rad/s², rad/s³, N·m, N·m/s, W, kg, s; m and N for prismatic joints).
Arrays are in model joint order.
"""
from __future__ import annotations

import math
import threading
import time
import weakref
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping

import numpy as np

from . import kernels
from .dynamics import Dynamics
from .errors import PLANNING_ERROR, TrajectoryError
from .limits import LIMIT_KINDS, JointLimits
from .model import Payload
from .status import ERROR, NAME_PREFIX, OK, WARN, Status
from .trajectory import Trajectory, from_current_state, interpolate
from .units import joint_units

STATUS_NAME = NAME_PREFIX + "trajectory feasibility"
#: Kinds whose value is a torque (or derived from one): these depend on payload and use
#: ``effort_warn_ratio``.
EFFORT_KINDS = ("effort", "effort_rate", "rms_effort", "power", "effort_speed")
_KIND_LABEL = {"effort_speed": "torque-speed envelope", "rms_effort": "RMS effort",
               "effort_rate": "effort rate"}


@dataclass(frozen=True)
class FeasibilityOptions:
    """``sample_period`` (s): longest step between samples; ``effort_warn_ratio``: a feasible
    trajectory whose peak ratio to any non-position limit exceeds this is WARN;
    ``max_samples``: the sample period is raised (with a warning) so that at most about this many
    samples are used, bounding memory for very long trajectories; ``threads``: OpenMP threads
    for the batched RNEA passes (None: the Dynamics' own setting, one unless built otherwise).
    Every state is computed by the same sequential RNEA whatever the count, so the result does
    not depend on it; more threads only help when cores are free (a live node's joint_states
    path needs one)."""

    sample_period: float = 0.001
    effort_warn_ratio: float = 0.9
    compute_payload_margin: bool = True
    max_samples: int = 250_000
    threads: int | None = None


@dataclass(frozen=True)
class Violation:
    """One limit exceeded by one joint: times in s from the trajectory start, value and limit in
    the kind's unit (for the envelope, the limit at the peak sample's speed)."""

    joint: str
    kind: str
    first_time_s: float
    peak_time_s: float
    peak_value: float
    limit: float
    duration_s: float
    unit: str

    def to_dict(self) -> dict[str, Any]:
        return {k: _json(getattr(self, k)) for k in (
            "joint", "kind", "first_time_s", "peak_time_s", "peak_value", "limit", "duration_s",
            "unit")}


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
    warnings: tuple[str, ...] = ()
    effort_warn_ratio: float = 0.9
    #: the segment from the robot's current state to the first point: START_CHECKED,
    #: START_NONE, or "not_checked (<why>)"; the state's age (s, NaN without one); whether
    #: that segment sets ``time_scale``
    start_segment: str = "none (first point at t = 0)"
    start_state_age_s: float = math.nan
    time_scale_start_segment: bool = False

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
            "violations": len(self.violations), "compute_time_s": self.compute_time_s,
            "warnings": "; ".join(self.warnings),
            "start_segment": self.start_segment, "start_state_age_s": self.start_state_age_s,
            "time_scale_start_segment": self.time_scale_start_segment,
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
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: NaN (undefined) → null, ±inf → "inf"/"-inf"."""
        return {
            **{k: _json(v) for k, v in self.summary_values().items() if k != "warnings"},
            "level": {OK: "OK", WARN: "WARN", ERROR: "ERROR"}[self.level],
            "message": self.message,
            "time_scale_by_kind": {k: _json(v) for k, v in self.time_scale_by_kind.items()},
            "violations": [v.to_dict() for v in self.violations],
            "per_joint": {j: {k: {kk: _json(vv) for kk, vv in e.items()} for k, e in kinds.items()}
                          for j, kinds in self.per_joint.items()},
            "effort_step": {j: _json(v) for j, v in self.effort_step.items()},
            "waypoint_effort": [[_json(float(x)) for x in row] for row in self.waypoint_effort],
            "warnings": list(self.warnings),
        }


#: ``start_segment`` when the first point is at t = 0 (nothing runs before it)
START_NONE = "none (first point at t = 0)"
START_CHECKED = "checked"
#: why the start segment was not checked, when the node or the audit had no usable state
NO_CURRENT_STATE = "no current state within stale_timeout"


@dataclass(frozen=True)
class StartState:
    """The robot's state when a trajectory arrived, in model order: q and q̇ of the last accepted
    joint_states (q̇ = 0 when it carried no velocity; q̈ = 0 is assumed, as
    joint_trajectory_controller does), and its age in s."""

    positions: np.ndarray
    velocities: np.ndarray
    age_s: float


def current_state(last: tuple[int, np.ndarray, np.ndarray] | None, now_ns: int,
                  stale_timeout: float) -> StartState | None:
    """The state a trajectory received at ``now_ns`` starts from: ``last`` = (receipt time ns,
    q, q̇) of the last accepted joint_states, when it is at most ``stale_timeout`` s old (None
    otherwise: :data:`NO_CURRENT_STATE`). The node passes receipt times, the audit the log times
    the node recorded with them, so a replay starts from the same state."""
    if last is None:
        return None
    age = (now_ns - last[0]) * 1e-9
    if not 0.0 <= age <= stale_timeout:
        return None
    return StartState(positions=np.asarray(last[1], dtype=float),
                      velocities=np.asarray(last[2], dtype=float), age_s=age)


def rejected_statuses(error: TrajectoryError, hardware_id: str = "", n_points: int = 0,
                      duration_s: float = math.nan) -> list[Status]:
    """ERROR status for a trajectory that could not be checked, with the same keys as a verdict."""
    values = {
        "feasible": False, "worst_joint": "", "worst_constraint": "", "worst_ratio": math.nan,
        "first_violation_time_s": math.nan, "time_scale": math.nan,
        "payload_margin_kg": math.nan, "n_points": int(n_points), "duration_s": float(duration_s),
        "failure_label": error.failure_label, "reason": getattr(error, "code", "error"),
    }
    return [Status(STATUS_NAME, ERROR, f"rejected: {error}", hardware_id, values)]


# ----------------------------------------------------------------------------------------------
# helpers

def _json(v: Any) -> Any:
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isnan(v):
            return None
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return v
    if isinstance(v, np.integer):
        return int(v)
    return v


def _kind_text(kind: str) -> str:
    return _KIND_LABEL.get(kind, kind)


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def _describe_violation(v: Violation) -> str:
    if v.kind == "position":
        return (f"{_fmt(v.peak_value)} {v.unit} beyond limit {_fmt(v.limit)} {v.unit} "
                f"at t = {v.peak_time_s:.2f} s")
    return (f"{abs(v.peak_value) / v.limit * 100 if v.limit > 0 else math.inf:.0f}% of "
            f"{_fmt(v.limit)} {v.unit} at t = {v.peak_time_s:.2f} s")


def _power_exit(L: np.ndarray, peak: np.ndarray, power: int) -> np.ndarray:
    """First exit x = 1/k of peak·x^power ≤ L per column: (L/peak)^(1/power); inf (never) when
    the value is zero at every sample and L ≥ 0; 0 (every k fails) when L < 0. A YAML limit of 0
    is a real limit: 0 for a moving joint, inf for one that does not move."""
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (L / peak) ** (1.0 / power)
    return np.where(L < 0, 0.0, np.where(peak > 0, x, np.inf))


def _take(X: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """X[:, cols] without the copy when cols is every column in order (the common case); the
    caller must not write into the result."""
    if len(cols) == X.shape[1] and (len(cols) == 0 or (cols[0] == 0 and cols[-1] == len(cols) - 1
                                                         and np.all(np.diff(cols) == 1))):
        return X
    return X[:, cols]


def _colmax(X: np.ndarray) -> np.ndarray:
    """X.max(axis=0), the same numbers, faster for M×m arrays with few columns: max along axis
    0 runs a short inner loop per row, argmax works down each column at once (no copy for the
    column-major arrays ``_check`` uses)."""
    if X.ndim != 2 or not X.shape[0]:
        return X.max(axis=0)
    return X[np.argmax(X, axis=0), np.arange(X.shape[1])]


@dataclass
class _Samples:
    t: np.ndarray        # M sample times (s)
    seg: np.ndarray      # M segment index
    first: np.ndarray    # index of each segment's first sample
    last: np.ndarray     # index of each segment's last sample
    h: np.ndarray        # M step of the sample's segment (s)
    weight: np.ndarray   # M time each sample stands for (s), summing to the duration
    period: float


def _sample(times: np.ndarray, period: float, max_samples: int) -> _Samples:
    T = np.diff(times)
    n = np.maximum(1, np.ceil(T / period - 1e-9)).astype(np.int64)
    if n.sum() + len(T) > max_samples and len(T) < max_samples:
        period = float(times[-1] - times[0]) / max(1, max_samples - 2 * len(T))
        n = np.maximum(1, np.ceil(T / period - 1e-9)).astype(np.int64)
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
    return _Samples(t=t, seg=seg, first=first, last=last, h=h, weight=weight, period=period)


def _evaluate(coeffs: np.ndarray, breaks: np.ndarray, smp: _Samples,
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


def _cumtrapz_rows(tt: np.ndarray, fT: np.ndarray) -> np.ndarray:
    """Cumulative trapezoid integral of each row of fT (r×M, C-contiguous) over times tt."""
    out = np.empty_like(fT)
    out[..., 0] = 0.0
    np.add(fT[..., 1:], fT[..., :-1], out=out[..., 1:])
    out[..., 1:] *= 0.5 * np.diff(tt)
    np.cumsum(out[..., 1:], axis=-1, out=out[..., 1:])
    return out


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


class _Job:
    """``fn(*args)``, either on a background thread (started now) or on the caller's thread when
    its result is asked for. NumPy releases the GIL inside its array loops, so a background job
    uses the second core; the result is the same either way (the job only reads its inputs)."""

    def __init__(self, fn, args: tuple, background: bool):
        self._fn, self._args = fn, args
        self._out: Any = None
        self._exc: BaseException | None = None
        self._thread: threading.Thread | None = None
        if background:
            self._thread = threading.Thread(target=self._run, name="dyn_node feasibility",
                                            daemon=True)
            self._thread.start()

    def _run(self) -> None:
        try:
            self._out = self._fn(*self._args)
        except BaseException as exc:  # re-raised on the caller's thread by result()
            self._exc = exc

    def result(self) -> Any:
        if self._thread is None:
            self._run()
        else:
            self._thread.join()
        if self._exc is not None:
            raise self._exc
        return self._out


def _batch_threads(dynamics: Dynamics, threads: int | None) -> int:
    bt = getattr(dynamics, "batch_threads", None)
    return int(bt(threads)) if bt is not None else 1


# ----------------------------------------------------------------------------------------------

def check_trajectory(dynamics: Dynamics, traj: Trajectory,
                     options: FeasibilityOptions = FeasibilityOptions(), *,
                     start: StartState | None = None,
                     start_unknown: str = "no current state given") -> FeasibilityResult:
    """Check ``traj`` (model order) against every limit of ``dynamics.model``; see module doc.

    When the first point's time is > 0 the controller first moves from the robot's state to it:
    with ``start`` that segment is checked too (:func:`~dyn_node.trajectory.from_current_state`);
    without, the verdict is at least WARN and says why (``start_unknown``).

    Raises only :class:`TrajectoryError` (so a caller can always publish a rejected status):
    a numerical failure deep inside (overflow, a Pinocchio error) becomes one with code
    ``evaluation_failed``.
    """
    try:
        return _check(dynamics, traj, options, start, start_unknown)
    except TrajectoryError:
        raise
    except (ArithmeticError, ValueError, RuntimeError, MemoryError) as exc:
        raise TrajectoryError(f"trajectory could not be evaluated: {type(exc).__name__}: {exc}",
                              code="evaluation_failed") from exc


#: Beyond this magnitude a motion or torque is treated as non-finite: its square (RMS, power)
#: and the time-scale polynomials would overflow.
_HUGE = 1e100


def _check(dynamics: Dynamics, traj: Trajectory, options: FeasibilityOptions,
           start: StartState | None = None,
           start_unknown: str = "no current state given",
           search_start: bool = True) -> FeasibilityResult:
    t_start = time.perf_counter()
    if traj.n_points < 2:
        raise TrajectoryError(f"trajectory has {traj.n_points} point(s); at least 2 are needed "
                              "to check motion", code="too_few_points")
    if not (options.sample_period > 0 and math.isfinite(options.sample_period)):
        raise TrajectoryError("sample_period must be a positive number of seconds",
                              code="bad_options")
    model = dynamics.model
    lim: JointLimits = model.limits
    names = list(model.joint_names)
    nv = model.nv
    warnings: list[str] = []
    mode = traj.natural_interpolation
    if mode == "spline":
        warnings.append("positions only: assumed a C² cubic spline through the waypoints with zero "
                        "velocity at both ends (the controller would interpolate linearly, which "
                        "needs unbounded acceleration at every waypoint)")
    # the segment from the robot's state to a first point ahead (t0 > 0) is executed too
    work, start_segment, start_age = traj, START_NONE, math.nan
    if traj.times[0] > 0 and start is None:
        start_segment = f"not_checked ({start_unknown})"
        warnings.insert(0, f"start segment not checked ({start_unknown}): the controller moves "
                           f"from the robot's state to the first point in {traj.times[0]:.3g} s")
    elif traj.times[0] > 0:
        work, start_segment, start_age = from_current_state(
            traj, start.positions, start.velocities), START_CHECKED, float(start.age_s)
    # with a start velocity the start segment does not stretch like the rest (q̇0 stays):
    # its share of the time scale is searched (_start_time_scale), the rest's rows from r0
    fixed_start = work is not traj and bool(np.any(start.velocities != 0.0))
    pp = interpolate(work, work.natural_interpolation)
    smp = _sample(work.times, options.sample_period, options.max_samples)
    r0 = int(smp.first[1]) if fixed_start else 0
    rows = slice(r0, None)
    if smp.period > options.sample_period * (1 + 1e-9):
        warnings.append(f"sample period raised from {options.sample_period * 1e3:.3g} ms to "
                        f"{smp.period * 1e3:.3g} ms to bound memory")
    tt = smp.t
    jerk_limited = bool(np.any(np.isfinite(lim.jerk)))
    Q, V, A, *rest = _evaluate(pp.coeffs, pp.breaks, smp, 4 if jerk_limited else 3)
    J = rest[0] if jerk_limited else np.zeros((0, nv))
    terms = dynamics.terms_batch(Q, V, A, options.threads)
    parallel = _batch_threads(dynamics, options.threads) > 1
    S, W, I, tau = terms.static, terms.viscous, terms.inertial, terms.full
    with np.errstate(invalid="ignore"):
        # |X|.max() < _HUGE without forming |X| (NaN fails either comparison, as it should)
        huge = not all(X.size == 0 or (X.max() < _HUGE and X.min() > -_HUGE)
                       for X in (tau, V, A, J))
    if huge:
        raise TrajectoryError("the interpolated motion or its torque is not finite (values too "
                              "large for the time steps)", code="non_finite")
    # the third batched RNEA pass (1 kg more at the payload point), done here with the other
    # two; only the effort-type limits depend on payload
    effort_limited = bool(np.any(np.isfinite(lim.effort)) or np.any(np.isfinite(lim.power))
                          or np.any(np.isfinite(lim.effort_rate))
                          or np.any(np.isfinite(lim.rms_effort))
                          or any(c is not None for c in lim.effort_speed_curve))
    tau1 = _payload_torque(dynamics, Q, V, A, tau, options.threads) \
        if options.compute_payload_margin and effort_limited else None
    # From here on the per-sample arrays are column-major (each joint's samples contiguous,
    # as the torque terms already are): per-joint reductions and per-joint limits then run
    # along contiguous memory. Q stays row-major (single states go to Pinocchio).
    del terms, rest      # no second copy of the row-major arrays stays alive
    V = np.asfortranarray(V)     # one at a time: each row-major original goes at once
    A = np.asfortranarray(A)
    J = np.asfortranarray(J)
    coulomb = np.asarray(model.pin_model.friction, dtype=float) if dynamics.options.include_friction \
        else np.zeros(nv)
    G = S - coulomb * np.sign(V) if np.any(coulomb) else S
    units = joint_units(dynamics.model)

    # waypoint torque: each waypoint as the start of its segment (the last as the end of the last)
    wp_idx = np.concatenate((smp.first, smp.last[-1:]))
    if work is not traj:     # the prepended current state is not one of the message's points
        wp_idx = wp_idx[1:]
    waypoint_effort = tau[wp_idx].copy()

    # --- values at k = 1, limits, and first-exit x = 1/k per kind -----------------------------
    # kind -> (cols, value, limit): M×len(cols) values, signed (their magnitude is checked)
    values: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    xstar: dict[str, np.ndarray] = {}   # kind -> per limited column, smallest first-exit x
    infinite_reason: list[tuple[str, str, int, float, float]] = []

    def limited(arr: np.ndarray) -> np.ndarray:
        return np.flatnonzero(np.isfinite(arr))

    # RMS: the time-scale search (the largest share of the work after the RNEA passes) needs
    # only S, W, I; with more than one thread it runs beside everything else until it is needed
    rms_cols = limited(lim.rms_effort)
    hold = dynamics.gravity(Q[0])
    rms_search: _Job | None = None
    if len(rms_cols):
        R = lim.rms_effort[rms_cols]
        Wn = lim.rms_window[rms_cols]
        h2 = hold[rms_cols] ** 2
        # (a moving start segment's path changes with k: its static torque is not static)
        s_max = np.maximum(kernels.abs_peak(_take(S, rms_cols)[rows])[1], np.abs(hold[rms_cols]))
        static_bad = s_max > R
        good = ~static_bad
        if np.any(good):
            gc = rms_cols[good]
            # RMS ≤ peak |τ| ≤ max|s| + max|w|·x + max|i|·x², so where that stays within the
            # RMS limit every k is feasible: a bracket end (the exact peak-torque exit where
            # gravity alone just reaches the limit and that bound is useless)
            sg, wg, ig = _take(S, gc), _take(W, gc), _take(I, gc)
            x_up = np.array([kernels.band_exit_bound(*b) for b in zip(
                kernels.abs_peak(sg)[1], kernels.abs_peak(wg)[1], kernels.abs_peak(ig)[1], R[good])])
            tight = ~(x_up > 0)
            if np.any(tight):
                x_up[tight] = kernels.band_exit(sg[:, tight], wg[:, tight], ig[:, tight],
                                           R[good][tight])
            with np.errstate(divide="ignore"):
                k_up = np.where(np.isinf(x_up), 0.0, 1.0 / x_up)
            rms_search = _Job(_rms_time_scale, (tt, sg, wg, ig, h2[good], Wn[good], R[good], k_up),
                              background=parallel)

    for kind, arr, power, lim_arr in (("velocity", V, 1, lim.velocity),
                                      ("acceleration", A, 2, lim.acceleration),
                                      ("deceleration", A, 2, lim.deceleration),
                                      ("jerk", J, 3, lim.jerk)):
        cols = limited(lim_arr)
        if len(cols):
            val = _take(arr, cols)
            if kind == "deceleration":
                # |q̈| counts only where |q̇| decreases (q̇·q̈ < 0); the sign of q̇·q̈ does not
                # change with k, so the value scales as 1/k² like the acceleration
                val = val * (_take(V, cols) * val < 0)
            L = lim_arr[cols]
            values[kind] = (cols, val, np.broadcast_to(L, val.shape))
            xstar[kind] = _power_exit(L, kernels.abs_peak(val[rows])[1], power)
    del J  # the largest temporaries go as soon as they are used: long trajectories are big

    cols = limited(lim.effort)
    if len(cols):
        L = lim.effort[cols]
        values["effort"] = (cols, _take(tau, cols), np.broadcast_to(L, (len(tt), len(cols))))
        s, w, i = _take(S, cols), _take(W, cols), _take(I, cols)
        xstar["effort"] = kernels.band_exit(s[rows], w[rows], i[rows], L)
        at, peak = kernels.abs_peak(s[rows])
        if np.any(peak > L):
            with np.errstate(divide="ignore"):  # a zero (YAML) limit: inf, the worst
                c = int(np.argmax(peak / L))      # the worst pose
            infinite_reason.append(("effort", names[cols[c]], r0 + int(at[c]), float(peak[c]),
                                    float(L[c])))

    ecols = np.array([j for j in range(nv) if lim.effort_speed_curve[j] is not None], dtype=int)
    if len(ecols):
        curves = [lim.effort_speed_curve[j] for j in ecols]
        npts = np.array([len(cv) for cv in curves])
        sp = np.zeros((len(ecols), npts.max()))
        ef = np.zeros_like(sp)
        for c, cv in enumerate(curves):
            sp[c, :len(cv)], ef[c, :len(cv)] = cv[:, 0], cv[:, 1]
        ve = _take(V, ecols)
        env = kernels.envelope_values(ve, sp, ef, npts)
        values["effort_speed"] = (ecols, _take(tau, ecols), env)
        xs = kernels.envelope_exit_min(_take(S, ecols)[rows], _take(W, ecols)[rows],
                                       _take(I, ecols)[rows], ve[rows], sp, ef, npts)
        for c, j in enumerate(ecols):
            e0 = float(np.interp(0.0, curves[c][:, 0], curves[c][:, 1]))
            sj = S[r0:, j]
            if np.any(np.abs(sj) > e0):
                n = r0 + int(np.argmax(np.abs(sj)))   # the worst pose
                infinite_reason.append(("effort_speed", names[j], n, float(abs(sj[n])), e0))
        xstar["effort_speed"] = xs

    cols = limited(lim.power)
    if len(cols):
        L = lim.power[cols]
        v = _take(V, cols)
        values["power"] = (cols, _take(tau, cols) * v, np.broadcast_to(L, v.shape))
        xstar["power"] = kernels.odd_exit(_take(S, cols)[rows], _take(W, cols)[rows],
                                          _take(I, cols)[rows], v[rows], L)

    rate_cols = limited(lim.effort_rate)
    need_step = work.natural_interpolation == "cubic"  # C¹ only (a spline from a start state too)
    if len(rate_cols):
        L = lim.effort_rate[rate_cols]
        dG = kernels.segment_derivative(_take(G, rate_cols), smp.first, smp.last, smp.h)
        dW = kernels.segment_derivative(_take(W, rate_cols), smp.first, smp.last, smp.h)
        dI = kernels.segment_derivative(_take(I, rate_cols), smp.first, smp.last, smp.h)
        rate = dG + dW + dI
        values["effort_rate"] = (rate_cols, rate, np.broadcast_to(L, rate.shape))
        xstar["effort_rate"] = kernels.odd_exit(dG[rows], dW[rows], dI[rows],
                                                np.broadcast_to(1.0, dG[rows].shape), L)
    effort_step = {}
    if len(work.times) > 2:
        steps = np.abs(tau[smp.first[1:]] - tau[smp.last[:-1]])  # (N-2)×nv
        peak = _colmax(steps)
        for j in range(nv):
            effort_step[names[j]] = float(peak[j])
        scale = np.maximum(kernels.abs_peak(tau)[1], 1e-9)
        if need_step and np.any(peak > 1e-6 * scale):
            j = int(np.argmax(peak / scale))
            w_ = int(np.argmax(steps[:, j])) + 1
            warnings.append(f"cubic interpolation: acceleration jumps at waypoints make the torque "
                            f"step by up to {_fmt(peak[j])} {units['effort'][j]} ({names[j]} at "
                            f"t = {work.times[w_]:.2f} s); effort rate is checked within segments")
    if np.any(coulomb) and np.any(np.diff(np.sign(V), axis=0) != 0) and len(rate_cols):
        warnings.append("Coulomb friction steps at velocity reversals are not counted as effort rate")

    if len(rms_cols):
        # windowed ∫τ² at k = 1, by the kernel the time-scale search uses, so both agree on
        # whether k = 1 is feasible (the payload margin's RMS part reuses it)
        rms_win = kernels.rms_windowed(tt, _take(S, rms_cols), _take(W, rms_cols),
                                       _take(I, rms_cols), np.ones(len(rms_cols)), Wn, h2)
        vals = np.sqrt(np.maximum(rms_win, 0.0) / Wn[:, None]).T
        values["rms_effort"] = (rms_cols, vals, np.broadcast_to(R, vals.shape))

    # payload margin: every effort-type value is in place; beside the rest when parallel
    margin_job = None if tau1 is None else _Job(
        _payload_margin, (dynamics, Q, V, tau, tau1, values, smp, lim, hold,
                               rms_win if "rms_effort" in values else None), background=parallel)

    if len(rms_cols):
        for c in np.flatnonzero(static_bad):
            j = rms_cols[c]
            n = r0 + int(np.argmax(np.abs(S[r0:, j])))
            infinite_reason.append(("rms_effort", names[j], n, float(s_max[c]), float(R[c])))
        kr = np.full(len(rms_cols), np.inf)
        if rms_search is not None:
            kr[good] = rms_search.result()
        xstar["rms_effort"] = np.where(kr > 0, 1.0 / np.where(kr > 0, kr, 1.0), np.inf)

    # --- per-joint peaks and violations at k = 1 -----------------------------------------------
    per_joint: dict[str, dict[str, dict[str, Any]]] = {
        n: {k: {"ratio": None, "time_s": None, "value": None, "limit": None} for k in LIMIT_KINDS}
        for n in names}
    # position: hard limits (violations, independent of k), soft limits (warnings); whole
    # columns at once, each joint's samples contiguous
    pos_cols = np.flatnonzero(np.isfinite(lim.position_lower) | np.isfinite(lim.position_upper))
    pos_viol = []
    rest_pos_bad = False     # beyond a hard limit after the start segment: no k helps
    if len(pos_cols):
        Qp = np.asfortranarray(_take(Q, pos_cols))
        lo, hi = lim.position_lower[pos_cols], lim.position_upper[pos_cols]
        over = np.maximum(Qp - hi, lo - Qp)              # > 0: beyond a hard limit
        rest_pos_bad = bool(np.any(over[r0:] > 0))
        at_over = np.argmax(over, axis=0)
        # beyond a soft bound when > 0 (an infinite bound gives −inf, never a warning)
        soft = [(b, side * (Qp - b))
                for side, b in ((-1, lim.soft_lower[pos_cols]), (1, lim.soft_upper[pos_cols]))]
        at_soft = [np.argmax(x, axis=0) for _, x in soft]
        ranged = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
        mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        at_mid = np.argmax(np.abs(Qp - mid), axis=0)
        for c, j in enumerate(pos_cols):
            for (bound, beyond), at in zip(soft, at_soft):
                n = at[c]
                if beyond[n, c] > 0:
                    warnings.append(f"{names[j]} enters its soft-limit zone: q = {_fmt(Qp[n, c])} "
                                    f"{units['position'][j]} beyond {_fmt(bound[c])} at "
                                    f"t = {tt[n]:.2f} s")
            n = at_over[c]
            if over[n, c] > 0:
                bad = over[:, c] > 0
                q = float(Qp[n, c])
                pos_viol.append(Violation(
                    names[j], "position", float(tt[np.argmax(bad)]), float(tt[n]), q,
                    float(hi[c] if q > hi[c] else lo[c]), float(smp.weight[bad].sum()),
                    units["position"][j]))
            if ranged[c]:
                n = at_mid[c]
                q = float(Qp[n, c])
                per_joint[names[j]]["position"] = {
                    "ratio": float(abs(Qp[n, c] - mid[c]) / half[c]), "time_s": float(tt[n]),
                    "value": q, "limit": float(hi[c] if q >= mid[c] else lo[c])}
    violations: list[Violation] = list(pos_viol)
    for kind in LIMIT_KINDS:
        if kind not in values:
            continue
        cols, val, L = values[kind]
        peak, ratio, firsts, dur = kernels.limit_peaks(val, L, smp.weight)
        for c, j in enumerate(cols):
            n = int(peak[c])
            value = abs(float(val[n, c]))
            per_joint[names[j]][kind] = {"ratio": float(ratio[c]), "time_s": float(tt[n]),
                                         "value": value, "limit": float(L[n, c])}
            if firsts[c] >= 0:
                violations.append(Violation(names[j], kind, float(tt[firsts[c]]), float(tt[n]),
                                            value, float(L[n, c]), float(dur[c]),
                                            units[kind][j]))
    feasible = not violations

    # --- time scale ----------------------------------------------------------------------------
    by_kind: dict[str, float] = {}
    ts_joint, ts_kind, k = "", "", 0.0
    # RMS windows reaching into a start segment that does not scale: the search decides RMS by
    # checking the whole stretched trajectory (_start_time_scale), not by its per-sample share
    rms_in_trials = fixed_start and "rms_effort" in xstar
    for kind, xs in xstar.items():
        cols = values[kind][0]
        with np.errstate(divide="ignore"):
            kk = np.where(xs > 0, 1.0 / xs, np.inf)
        kk = np.where(np.isinf(xs), 0.0, kk)
        c = int(np.argmax(kk))
        by_kind[kind] = float(kk[c])
        if kk[c] > k and not (kind == "rms_effort" and rms_in_trials):
            k, ts_joint, ts_kind = float(kk[c]), names[cols[c]], kind
    static_msg = ""
    if rest_pos_bad:
        v0 = max(pos_viol, key=lambda v: abs(v.peak_value - v.limit))
        k, ts_joint, ts_kind = math.inf, v0.joint, "position"
        by_kind["position"] = math.inf
    elif infinite_reason:
        kind, jn, n, need, L = infinite_reason[0]
        k, ts_joint, ts_kind = math.inf, jn, kind
        by_kind[kind] = math.inf
        qtxt = "[" + ", ".join(f"{x:.3g}" for x in Q[n]) + "]"
        static_msg = (f"gravity and friction alone need {_fmt(need)} {units['effort'][names.index(jn)]}"
                      f" of {_fmt(L)} at q = {qtxt} (t = {tt[n]:.2f} s); no slowdown helps")
    ts_start = False
    if fixed_start and search_start and not static_msg and math.isfinite(k):
        if rms_in_trials:
            plain = replace(options, compute_payload_margin=False)

            def trial(kt: float) -> FeasibilityResult:
                return _check(dynamics, _stretched(traj, kt), plain, start, start_unknown,
                              search_start=False)
        else:
            # the segment alone, on the main check's own sample period (raised for very long
            # trajectories)
            seg_options = replace(options, sample_period=smp.period)

            def trial(kt: float) -> FeasibilityResult:
                return _start_segment_at(dynamics, work, seg_options, kt)
        found = _start_time_scale(trial, k, feasible)
        if found is not None:
            k, ts_joint, ts_kind = found
            ts_start = True
            by_kind[ts_kind] = max(by_kind.get(ts_kind, 0.0), k)
    # The per-constraint roots and the direct check agree up to rounding; make the contract exact.
    if feasible and 1.0 < k < 1.0 + 1e-6:
        k = 1.0
    elif not feasible and math.isfinite(k) and k <= 1.0:
        if k > 1.0 - 1e-6:
            k = float(np.nextafter(1.0, 2.0))
        else:
            warnings.append(f"time scale {k:.6g} disagrees with the direct check (rounding)")

    # --- payload margin -------------------------------------------------------------------------
    margin = math.inf if margin_job is None else margin_job.result()

    # --- verdict ---------------------------------------------------------------------------------
    worst_joint, worst_kind, worst_ratio = "", "", 0.0
    for jn, kinds in per_joint.items():
        for kind, e in kinds.items():
            if kind != "position" and e["ratio"] is not None and e["ratio"] > worst_ratio:
                worst_joint, worst_kind, worst_ratio = jn, kind, e["ratio"]
    first_violation = min((v.first_time_s for v in violations), default=math.nan)
    if feasible:
        warn = worst_ratio > options.effort_warn_ratio or bool(warnings)
        level = WARN if warn else OK
        if worst_kind:
            e = per_joint[worst_joint][worst_kind]
            u = units[worst_kind][names.index(worst_joint)]
            head = (f"feasible: worst {worst_joint} {_kind_text(worst_kind)} {worst_ratio * 100:.0f}% "
                    f"of {_fmt(e['limit'])} {u} at t = {e['time_s']:.2f} s")
        else:
            head = "feasible: no limits apply"
        if k > 0 and k < 1:
            tail = f"; could run {_fmt_factor(1 / k)}× faster"
        elif k == 0:
            tail = "; no speed-dependent limit binds"
        else:
            tail = "; no margin left"
        if ts_start:
            tail += " (the segment from the current state binds)"
        message = head + tail
        if level == WARN and warnings and (worst_ratio <= options.effort_warn_ratio
                                           or start_segment.startswith("not_checked")):
            message += f" ({warnings[0].split(':')[0]})"
        label = PLANNING_ERROR if level != OK else ""
    else:
        level, label = ERROR, PLANNING_ERROR
        pos = [v for v in violations if v.kind == "position"]
        v0 = pos[0] if pos else max(violations, key=lambda v: abs(v.peak_value) / v.limit
                                     if v.limit > 0 else math.inf)
        head = f"infeasible: {v0.joint} {_kind_text(v0.kind)} {_describe_violation(v0)}"
        if pos and rest_pos_bad:
            tail = "; position limits do not depend on timing, no slowdown helps"
        elif static_msg:
            tail = "; " + static_msg
        elif ts_start and not math.isfinite(k):
            tail = (f"; no slowdown up to {_START_REACH:g}× makes the segment from the current "
                    "state feasible")
        else:
            tail = f"; run {_fmt_factor(k)}× slower"
            if ts_start:
                tail += " (the segment from the current state binds)"
        message = head + tail
        if len(violations) > 1:
            message += f" ({len(violations)} violations)"
        if start_segment.startswith("not_checked"):
            message += f"; {warnings[0].split(':')[0]}"
    result = FeasibilityResult(
        feasible=feasible, level=level, message=message, failure_label=label,
        worst_joint=worst_joint, worst_constraint=worst_kind, worst_ratio=float(worst_ratio),
        first_violation_time_s=float(first_violation), time_scale=float(k),
        time_scale_joint=ts_joint, time_scale_constraint=ts_kind, time_scale_by_kind=by_kind,
        payload_margin_kg=float(margin), n_points=traj.n_points, n_samples=len(tt),
        duration_s=traj.duration, interpolation=mode, violations=tuple(violations),
        per_joint=per_joint, effort_step=effort_step, waypoint_effort=waypoint_effort,
        compute_time_s=time.perf_counter() - t_start, warnings=tuple(warnings),
        effort_warn_ratio=options.effort_warn_ratio, start_segment=start_segment,
        start_state_age_s=start_age, time_scale_start_segment=ts_start)
    return result


#: The start segment's time-scale search: the walk's step factor from the given timing, the
#: relative bracket width the bisection stops at, the smallest k walked down to, and how far
#: above the first k tried the walk up looks before answering "no slowdown helps".
_START_WALK, _START_RTOL, _START_FLOOR, _START_REACH = 2.0, 1e-6, 1e-6, 1e3


def _start_segment_at(dynamics: Dynamics, work: Trajectory, options: FeasibilityOptions,
                      k: float) -> FeasibilityResult:
    """The start segment alone with the trajectory stretched by k, checked directly: from the
    measured q, q̇ (q̇ does not scale: it is the robot's) and q̈ = 0 to the first point, whose
    velocity and acceleration scale as 1/k and 1/k², in k·t0 s, on the same samples (the sample
    period stretched by k too)."""
    t0 = float(work.times[1])
    v, a = work.velocities, work.accelerations
    seg = Trajectory(times=np.array([0.0, k * t0]), positions=work.positions[:2],
                     velocities=np.vstack([v[0], v[1] / k]),
                     accelerations=None if a is None else np.vstack([a[0], a[1] / (k * k)]))
    opts = replace(options, sample_period=options.sample_period * k, compute_payload_margin=False)
    return _check(dynamics, seg, opts)


def _stretched(traj: Trajectory, k: float) -> Trajectory:
    """``traj`` run k times slower: times × k, velocities ÷ k, accelerations ÷ k²."""
    return Trajectory(times=traj.times * k, positions=traj.positions,
                      velocities=None if traj.velocities is None else traj.velocities / k,
                      accelerations=None if traj.accelerations is None else traj.accelerations / (k * k))


def _start_time_scale(trial: Callable[[float], FeasibilityResult], k_rest: float,
                      feasible: bool) -> tuple[float, str, str] | None:
    """The time scale when the start segment's share exceeds ``k_rest`` (the rest's, from the
    per-sample laws: the rest is feasible exactly for k ≥ k_rest): (k, joint, kind that fails
    just below k), or None when k_rest stands.

    The start velocity is the robot's, so the segment does not stretch like the rest; it is
    re-interpolated and checked directly at each trial k (``trial``: :func:`_start_segment_at`,
    or the whole stretched trajectory when an RMS window can reach into the segment). From the
    given timing (k = 1, whose verdict is ``feasible``) the search walks by factors of 2 towards
    the boundary, down to k_rest when feasible, up (at most ``_START_REACH``×) when not, then
    bisects the last step to a relative width of 1e-6 and answers its feasible end: the
    smallest k such that every k′ from k to the given timing (when feasible) is, on the walk's
    grid; a stretch narrower than a factor of 2 that the walk steps over is not seen.
    """
    trials: dict[float, FeasibilityResult | None] = {}

    def ok(k: float) -> bool:
        try:
            trials[k] = trial(k)
        except TrajectoryError:   # motion beyond any physical range at this k: not feasible
            trials[k] = None
            return False
        return trials[k].feasible

    if feasible:
        hi, lo = 1.0, None
        kt = hi / _START_WALK
        while kt > max(k_rest, _START_FLOOR):
            if not ok(kt):
                lo = kt
                break
            hi, kt = kt, kt / _START_WALK
        if lo is None:
            if k_rest <= 0 or ok(k_rest):
                return None          # the rest's bound (or none at all) stands
            lo = k_rest
    else:
        base = max(1.0, k_rest)
        if ok(base):
            return None              # the rest binds at k_rest > 1 (or rounding at k = 1)
        lo, hi = base, None
        kt = base * _START_WALK
        while kt <= base * _START_REACH:
            if ok(kt):
                hi = kt
                break
            lo, kt = kt, kt * _START_WALK
        if hi is None:
            return (math.inf, *_worst_violation(trials[lo]))
    while hi / lo - 1.0 > _START_RTOL:
        mid = math.sqrt(lo * hi)
        if ok(mid):
            hi = mid
        else:
            lo = mid
    return (hi, *_worst_violation(trials[lo]))


def _worst_violation(r: FeasibilityResult | None) -> tuple[str, str]:
    if r is None or not r.violations:
        return "", ""
    v = max(r.violations, key=lambda v: abs(v.peak_value) / v.limit if v.limit > 0 else math.inf)
    return v.joint, v.kind


def _fmt_factor(f: float) -> str:
    if not math.isfinite(f):
        return "∞"
    return f"{f:.4f}" if abs(f - 1) < 0.01 else f"{f:.3g}" if f >= 100 else f"{f:.2f}"


def _rms_time_scale(tt: np.ndarray, s: np.ndarray, w: np.ndarray, i: np.ndarray,
                    hold2: np.ndarray, window: np.ndarray, R: np.ndarray, k_up: np.ndarray,
                    rtol: float = 1e-6) -> np.ndarray:
    """Smallest k per column with windowed RMS ≤ R (the windowed mean square is taken to fall
    with k, as everywhere in this module), bracketed by k = 1 (so the answer agrees with the
    direct check) and ``k_up``; the result is the feasible end of a bracket of relative width
    ≤ ``rtol``, found by the secant method on log k (safeguarded by bisection).

    Each trial k is decided exactly, in one compiled pass per column
    (:func:`kernels.rms_worst`): the integral of τ² = (s + w·x + i·x²)², x = 1/k, from the
    start, and its largest trailing-window difference (with the hold torque before the start).
    """
    moving = k_up > 0
    if not np.all(moving):   # k_up = 0: no speed-dependent torque at all, nothing to search
        out = np.zeros(len(k_up))
        if np.any(moving):
            out[moving] = _rms_time_scale(tt, s[:, moving], w[:, moving], i[:, moving],
                                          hold2[moving], window[moving], R[moving],
                                          k_up[moving], rtol)
        return out
    m = s.shape[1]
    R2W = R * R * window
    every = np.ones(m, dtype=np.bool_)

    def g(k: np.ndarray, sel: np.ndarray | None = None) -> np.ndarray:
        """log of the largest windowed-mean-square / R² per column (≤ 0: feasible at k), for
        the columns ``sel`` (boolean; None: all) and NaN for the others. Columns are
        independent, so evaluating fewer changes nothing in the ones evaluated."""
        with np.errstate(divide="ignore", invalid="ignore"):
            worst = kernels.rms_worst(tt, s, w, i, 1.0 / k, window, hold2,
                                      every if sel is None else sel)
            return np.log(np.maximum(k / R2W * worst, 1e-300))

    ltol = math.log1p(rtol)
    g1 = g(np.ones(m))
    ok1 = g1 <= 0.0
    hi = np.where(ok1, np.minimum(1.0, np.maximum(k_up, 1e-12)), np.maximum(k_up, 1.0))
    # lower end: k = 1 where that fails, else step down by 8× while still feasible (below
    # 8⁻⁶ of the feasible end the speed-dependent torque has vanished for any purpose)
    lo = np.where(ok1, hi / 8, 1.0)
    gl = np.where(ok1, g(lo, ok1), g1)
    for _ in range(6):
        down = ok1 & (gl <= 0)
        if not np.any(down):
            break
        hi = np.where(down, lo, hi)
        lo = np.where(down, lo / 8, lo)
        gl = np.where(down, g(lo, down), gl)
    hi = np.maximum(hi, lo)
    gh = np.where(hi == 1.0, g1, np.nan)
    need = np.isnan(gh)
    if np.any(need):
        gh = np.where(need, g(hi, need), gh)
    ll, lh = np.log(lo), np.log(hi)
    # secant through the last two trial points (g is smooth near the root, but for kinks where
    # window starts cross samples), kept inside the bracket; a secant step that is not at most
    # half the previous one bisects instead; a step inside the tolerance is pushed 0.4·tol
    # past the newest point so that it brackets the root
    u1, f1, u2, f2 = ll, gl, lh, gh
    for _ in range(200):
        width = lh - ll
        active = width > ltol
        if not np.any(active):
            break
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            u = u1 - f1 * (u1 - u2) / (f1 - f2)
            step = np.abs(u - u1)
            slow = ~np.isfinite(u) | (u <= ll) | (u >= lh) | (step > 0.5 * np.abs(u1 - u2))
        u = np.where(slow, 0.5 * (ll + lh), u)
        small = ~slow & (step < 0.4 * ltol)
        u = np.where(small, u1 + np.where(f1 > 0, 0.4, -0.4) * ltol, u)
        u = np.clip(u, ll + 0.4 * ltol, lh - 0.4 * ltol)
        u = np.where(active, u, lh)
        gu = g(np.exp(u), active)
        good = gu <= 0.0
        lh = np.where(active & good, u, lh)
        ll = np.where(active & ~good, u, ll)
        u2, f2 = np.where(active, u1, u2), np.where(active, f1, f2)
        u1, f1 = np.where(active, u, u1), np.where(active, gu, f1)
    hi = np.where(lh == math.log(1.0), 1.0, np.exp(lh))
    return np.where(k_up > 0, hi, 0.0)


def _payload_torque(dynamics: Dynamics, Q, V, A, tau0, threads: int | None = None) -> np.ndarray:
    """τ1 (M×nv, N·m per kg): the torque of 1 kg more at the payload point, as the difference
    of a batched RNEA with that mass and the trajectory's own torque τ0."""
    heavy = _unit_payload_dynamics(dynamics).rnea_batch(Q, V, A, threads)
    return np.subtract(heavy, tau0, out=np.empty_like(tau0))    # in τ0's memory order


def _payload_margin(dynamics, Q, V, tau0, tau1, values, smp, lim, hold, rms_win) -> float:
    """Largest extra mass m (kg) at the payload point keeping every effort-type limit at the
    trajectory's own timing: τ = τ0 + m·τ1 is affine in m (τ1 from :func:`_payload_torque`), so
    each sample gives an interval. ``rms_win``: the windowed ∫τ0² of the RMS-limited joints
    (m×M), already computed."""
    heavy = _unit_payload_dynamics(dynamics)
    bands: list[tuple[float, float]] = []

    def linear(a: np.ndarray, b: np.ndarray, L: np.ndarray, scale: np.ndarray | None = None):
        # |(a + m·b)·scale| ≤ L at every sample: an interval of m
        if a.size:
            one = np.broadcast_to(1.0, a.shape) if scale is None else scale
            bands.append(kernels.affine_band(a, b, one, np.broadcast_to(L, a.shape)))

    if ("effort" in values and "effort_speed" in values
            and np.array_equal(values["effort"][0], values["effort_speed"][0])):
        # the same joints: both bands at once, with the tighter limit at each sample
        cols, _, L = values["effort"]
        linear(_take(tau0, cols), _take(tau1, cols), np.minimum(L, values["effort_speed"][2]))
    else:
        for kind in ("effort", "effort_speed"):
            if kind in values:
                cols, _, L = values[kind]
                linear(_take(tau0, cols), _take(tau1, cols), L)
    if "power" in values:
        cols, _, L = values["power"]
        linear(_take(tau0, cols), _take(tau1, cols), L, _take(V, cols))
    if "effort_rate" in values:
        cols, _, L = values["effort_rate"]
        coul = np.asarray(dynamics.model.pin_model.friction, dtype=float)[cols] \
            if dynamics.options.include_friction else 0.0
        smooth0 = _take(tau0, cols) - coul * np.sign(_take(V, cols))
        d0 = kernels.segment_derivative(smooth0, smp.first, smp.last, smp.h)
        d1 = kernels.segment_derivative(_take(tau1, cols), smp.first, smp.last, smp.h)
        linear(d0, d1, L)
    if "rms_effort" in values:
        cols = values["rms_effort"][0]
        heavy_hold = (heavy.gravity(Q[0]) - hold)[cols]
        h0 = hold[cols]
        Wn, R = lim.rms_window[cols], lim.rms_effort[cols]
        tt = smp.t
        a0, a1 = _take(tau0, cols), _take(tau1, cols)
        # windowed integrals of a0·a1 and a1² (hold torques before the start); a0² is given:
        # the windowed ∫(a0 + m·a1)² = A·m² + 2B·m + C must stay within R²·window
        f = np.empty((2 * len(cols), len(tt)))
        np.multiply(a0.T, a1.T, out=f[:len(cols)])
        np.multiply(a1.T, a1.T, out=f[len(cols):])
        win = kernels.windowed(tt, _cumtrapz_rows(tt, f), np.concatenate([Wn, Wn]),
                               np.concatenate([h0 * heavy_hold, heavy_hold * heavy_hold]))
        del f
        m_ = len(cols)
        bands.append(kernels.quadratic_band(win[m_:], win[:m_],
                                            rms_win - (R * R * Wn)[:, None]))
    lo = max((b[0] for b in bands), default=-math.inf)
    hi = min((b[1] for b in bands), default=math.inf)
    if lo > hi:
        return -math.inf
    return hi
