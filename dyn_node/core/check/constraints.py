"""The limit kinds of the feasibility check, one class each behind :class:`Constraint`.

A constraint reads the sampled motion (:class:`Motion`) and gives its value per sample, its peak
ratio and time per joint (or frame: its ``where``), its time-scale factor from its scaling law
(or a search where no per-sample law exists, as for RMS) and its payload interval. The method is
in docs/FEASIBILITY.md; :func:`dyn_node.core.check.feasibility.check_trajectory` loops over these.
"""
from __future__ import annotations

import math
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, ClassVar, Mapping, Sequence

import numpy as np

from dyn_node.core.compiled import kernels
from dyn_node.io.jsonable import json_scalar
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.limits import JointLimits

if TYPE_CHECKING:
    from dyn_node.core.robot.model import RobotModel
    from dyn_node.core.check.task_motion import TaskMotion
    from dyn_node.core.check.trajectory import PiecewisePolynomial

Band = tuple[float, float]


# ----------------------------------------------------------------------------------------------
# what every constraint reads, and what it gives back

@dataclass
class Samples:
    t: np.ndarray        # M sample times (s)
    seg: np.ndarray      # M segment index
    first: np.ndarray    # index of each segment's first sample
    last: np.ndarray     # index of each segment's last sample
    h: np.ndarray        # M step of the sample's segment (s)
    weight: np.ndarray   # M time each sample stands for (s), summing to the duration
    period: float


@dataclass(eq=False)
class Motion:
    """The sampled trajectory at its given timing (k = 1), M samples × nv joints, column-major
    but Q: q, q̇, q̈, q⃛ (J has no rows when no kind needs it), the torque terms by how they
    scale (S static, W viscous, I inertial; τ = S + W + I; G = S without Coulomb friction), the
    hold torque g(q0), and ``r0``: the first sample the per-sample laws cover (a start segment
    from a moving robot does not stretch with k; its share is searched)."""

    dynamics: Dynamics
    smp: Samples
    Q: np.ndarray
    V: np.ndarray
    A: np.ndarray
    J: np.ndarray
    S: np.ndarray
    W: np.ndarray
    I: np.ndarray
    tau: np.ndarray
    G: np.ndarray
    coulomb: np.ndarray
    hold: np.ndarray
    r0: int
    parallel: bool
    units: Mapping[str, list[str]]
    #: the frame terms the task kinds read (None: no task section configured)
    task: "TaskMotion | None" = None
    #: the executed trajectory's pieces, sample segment k = piece k: the kinematic kinds'
    #: exact peaks (:mod:`dyn_node.core.check.exact_peaks`)
    pieces: "PiecewisePolynomial | None" = None

    @property
    def limits(self) -> JointLimits:
        return self.dynamics.model.limits

    @property
    def names(self) -> list[str]:
        return list(self.dynamics.model.joint_names)

    @property
    def rows(self) -> slice:
        return slice(self.r0, None)


@dataclass(frozen=True)
class PayloadTerms:
    """τ1 (M×nv, per kg): the torque of 1 kg more at the payload point, and that heavier robot."""

    tau1: np.ndarray
    heavy: Dynamics


@dataclass(frozen=True)
class Violation:
    """One limit exceeded at one place (a joint, for the joint kinds): times in s from the
    trajectory start, value and limit in the kind's unit (for the envelope, the limit at the
    peak sample's speed)."""

    joint: str
    kind: str
    first_time_s: float
    peak_time_s: float
    peak_value: float
    limit: float
    duration_s: float
    unit: str
    #: what the kind's message adds (task kinds: e.g. the grasp frame); "" for joint kinds
    detail: str = ""

    def to_dict(self) -> dict[str, Any]:
        out = {k: json_scalar(getattr(self, k)) for k in (
            "joint", "kind", "first_time_s", "peak_time_s", "peak_value", "limit", "duration_s",
            "unit")}
        if self.detail:
            out["detail"] = self.detail
        return out


@dataclass(frozen=True)
class Peak:
    """The largest ratio to the limit at one place, at the given timing."""

    where: str
    ratio: float
    time_s: float
    value: float
    limit: float

    def entry(self) -> dict[str, float]:
        return {"ratio": self.ratio, "time_s": self.time_s, "value": self.value,
                "limit": self.limit}


@dataclass(frozen=True)
class Blocked:
    """No slowdown makes the kind feasible at ``where``: ``timing_free`` when its value does not
    depend on timing at all (position), else ``reason`` says what the still pose needs."""

    where: str
    reason: str = ""
    timing_free: bool = False


class Constraint(ABC):
    """One limit kind over the places it applies to (``where``). Built from a :class:`Motion`
    when :meth:`applies`; everything is computed then, the methods hand it out."""

    kind: ClassVar[str]
    #: how messages name it
    label: ClassVar[str] = ""
    #: the table its peaks go to (``per_joint`` for "joint")
    scope: ClassVar[str] = "joint"
    #: its value is a torque or derived from one: it depends on payload
    payload_dependent: ClassVar[bool] = False
    #: the highest time derivative of q its value needs
    order: ClassVar[int] = 2
    #: its value at a sample depends on samples before it (a window): with a start segment
    #: that does not stretch, its share of the time scale is left to the start-segment search
    reaches_back: ClassVar[bool] = False
    #: it starts background work when built: built before the others so that work runs beside
    background: ClassVar[bool] = False

    where: tuple[str, ...]
    units: list[str]
    warnings: list[str]

    @classmethod
    @abstractmethod
    def applies(cls, model: "RobotModel") -> bool:
        """Whether any limit of this kind is set (joint kinds: in model.limits, task kinds: in
        model.task_limits)."""

    @classmethod
    def describe(cls, v: Violation) -> str:
        """The message text of a violation after "infeasible: " (its place, kind and peak)."""
        return f"{v.joint} {cls.label or cls.kind} {percent_text(v)}"

    @abstractmethod
    def values(self) -> np.ndarray:
        """The value per sample (M × len(where), signed: its magnitude is checked)."""

    @abstractmethod
    def report(self, motion: Motion) -> tuple[list[Peak], list[Violation]]:
        """The peak per place and the violations at the given timing."""

    @abstractmethod
    def time_scale(self) -> np.ndarray | None:
        """Per place, the smallest k such that every k′ ≥ k is feasible (0: any; inf: none);
        None when the kind does not depend on timing."""

    def blocked(self) -> Blocked | None:
        """Why no slowdown helps, when none does."""
        return None

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        """The interval of extra payload mass (kg) that keeps the kind within its limits at the
        given timing (lo > hi: none); None when payload does not change it."""
        return None


@dataclass(frozen=True)
class ScanRequest:
    """What a kind asks of the fused pass (:func:`scan`), one channel per column c of the kind:
    its value from up to three ``sources`` by ``op`` (scan_kernels.ABS: |a|, DECEL: |a·(b·a <
    0)|, PRODUCT: |a·b|, SUM3: |a + b + c|), each the name of a Motion array ("V", "A", "J",
    "tau", "S") read at the motion columns ``cols``, or an M×m array of the kind's own; and its
    ``limit``: m constants, or M×m per sample (an array of its own)."""

    op: int
    sources: tuple[str | np.ndarray, ...]
    limit: np.ndarray
    cols: np.ndarray | None = None


@dataclass(frozen=True)
class Scanned:
    """The fused pass's answers for one request, per column (see scan_kernels.peak_scan): the
    sample of the largest ratio, that ratio, the first sample over the limit (−1: none), the
    time over it, |value| and limit at the largest ratio, and the sample and size of the
    largest |value| over the rows the laws cover (from ``Motion.r0``)."""

    peak_at: np.ndarray
    ratio: np.ndarray
    first: np.ndarray
    above: np.ndarray
    value: np.ndarray
    limit: np.ndarray
    abs_at: np.ndarray
    abs_peak: np.ndarray


_SOURCES = {"V": 0, "A": 1, "J": 2, "tau": 3, "S": 4}


def scan(motion: Motion, requests: Sequence[ScanRequest]) -> list[Scanned]:
    """Every request's answers from the fused compiled pass
    (:func:`dyn_node.core.compiled.scan_kernels.peak_scan`), the arrays read in place: one call
    for all the requests on the Motion's arrays, and one per array of a kind's own (a request
    with several has them side by side in one copy)."""
    from dyn_node.core.compiled import scan_kernels as sk

    groups: dict[int, tuple[np.ndarray | None, list[int]]] = {}
    for q, r in enumerate(requests):
        own = [x for x in (*r.sources, r.limit) if isinstance(x, np.ndarray) and x.ndim == 2]
        P = None if not own else own[0] if len(own) == 1 else np.hstack(own)
        groups.setdefault(id(P) if len(own) == 1 else -1 - q, (P, []))[1].append(q)
    answers: list[Scanned | None] = [None] * len(requests)
    for P, members in groups.values():
        out = _scan_group(motion, [requests[q] for q in members], P, sk)
        for q, answer in zip(members, out):
            answers[q] = answer
    return answers


def _scan_group(motion: Motion, requests: list[ScanRequest], P: np.ndarray | None,
                sk: Any) -> list[Scanned]:
    """:func:`scan` of requests whose own arrays are the columns of P (None: none)."""
    M = len(motion.smp.t)
    pool = np.empty((M, 0)) if P is None else P
    rows: list[list[int]] = []
    limits: list[float] = []
    widths = []
    for r in requests:
        m = len(r.limit) if r.limit.ndim == 1 else r.limit.shape[1]
        widths.append(m)
        cols = range(m) if r.cols is None else r.cols.tolist()
        refs, at = [], 0
        for x in r.sources:
            if isinstance(x, str):
                refs.append([(_SOURCES[x], c) for c in cols])
            else:
                refs.append([(5, at + c) for c in range(m)])
                at += m
        refs += [refs[0]] * (3 - len(refs))     # unused sources: the first again
        lcols = [-1] * m
        if r.limit.ndim == 2:
            lcols = list(range(at, at + m))
            limits += [0.0] * m
        else:
            limits += r.limit.tolist()
        rows += [[r.op, *refs[0][c], *refs[1][c], *refs[2][c], lcols[c]] for c in range(m)]
    channels = np.array(rows, dtype=np.int64).reshape(-1, sk.CHANNEL_COLUMNS)
    # a Motion array no channel reads may be absent or empty (J without a jerk limit): the
    # pool stands in for it
    src = [getattr(motion, name, None) for name in _SOURCES]
    src = [pool if x is None or not x.size else x for x in src]
    out = sk.peak_scan(*src, pool, motion.smp.weight, motion.r0, channels,
                       np.array(limits, dtype=float))
    answers, k = [], 0
    for m in widths:
        answers.append(Scanned(*(x[k:k + m] for x in out)))
        k += m
    return answers


def merge(answers: Sequence[Scanned]) -> Scanned:
    """Several requests' answers as one, their columns side by side."""
    return Scanned(*(np.concatenate(x) for x in zip(*(vars(a).values() for a in answers))))


def _limits(L: np.ndarray) -> np.ndarray:
    """A kind's limit as the fused pass takes it: one per column when it is a broadcast row
    (the same at every sample), else the M×m array."""
    return L[0] if L.ndim == 2 and L.strides[0] == 0 and len(L) else L


class LimitedConstraint(Constraint):
    """A kind whose value per sample is compared in magnitude with a limit per sample; its
    peaks come from the fused pass (:func:`scan`, run by :func:`build` for every kind at
    once, or on its own when asked first)."""

    value: np.ndarray
    limit: np.ndarray
    _scanned: list[Scanned] | None = None

    def values(self) -> np.ndarray:
        return self.value

    def scan_requests(self) -> list[ScanRequest]:
        """What the fused pass computes for this kind; the first request is its value against
        its limit (:meth:`report`)."""
        return [ScanRequest(0, (self.values(),), _limits(self.limit))]

    def scanned(self, motion: Motion) -> list[Scanned]:
        """The answers to :meth:`scan_requests` (scanned now unless :func:`build` did)."""
        if self._scanned is None:
            self._scanned = scan(motion, self.scan_requests())
        return self._scanned

    def _peak_answer(self, motion: Motion) -> Scanned:
        """The answers for the value against the limit, every place side by side."""
        return self.scanned(motion)[0]

    def report(self, motion: Motion) -> tuple[list[Peak], list[Violation]]:
        sc, tt = self._peak_answer(motion), motion.smp.t
        peaks, violations = [], []
        for c, where in enumerate(self.where):
            n = int(sc.peak_at[c])
            value, lim = float(sc.value[c]), float(sc.limit[c])
            peaks.append(Peak(where, float(sc.ratio[c]), float(tt[n]), value, lim))
            if sc.first[c] >= 0:
                violations.append(Violation(where, self.kind, float(tt[sc.first[c]]),
                                            float(tt[n]), value, lim, float(sc.above[c]),
                                            self.units[c]))
        return peaks, violations


class JointConstraint(LimitedConstraint):
    """A per-joint kind with one limit per joint (``limit_array``): its columns are the joints
    where that limit is finite."""

    @classmethod
    def limit_array(cls, limits: JointLimits) -> np.ndarray:
        return getattr(limits, cls.kind)

    @classmethod
    def applies(cls, model: "RobotModel") -> bool:
        return bool(np.any(np.isfinite(cls.limit_array(model.limits))))

    def __init__(self, motion: Motion, cols: np.ndarray | None = None):
        self.cols = np.flatnonzero(np.isfinite(self.limit_array(motion.limits))) \
            if cols is None else cols
        names = motion.names
        self.where = tuple(names[j] for j in self.cols)
        self.units = [motion.units[self.kind][j] for j in self.cols]
        self.warnings = []
        self._x = np.zeros(0)       # per column, the first exit x = 1/k of the band

    def time_scale(self) -> np.ndarray:
        return _k_of_x(self._x)

    def terms(self, motion: Motion) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The torque terms S, W, I (static, viscous, inertial) of the kind's columns."""
        return _take(motion.S, self.cols), _take(motion.W, self.cols), _take(motion.I, self.cols)


def build(motion: Motion, kinds: Sequence[type[Constraint]]) -> list[Constraint]:
    """The constraints of ``kinds`` (every kind: :data:`dyn_node.core.check.kinds.KINDS`, passed in
    by the caller so that this module never imports the kinds that subclass it) that apply to
    ``motion``, in ``kinds`` order; those with background work are built first, so that work runs
    beside the others'."""
    todo = [cls for cls in kinds if cls.applies(motion.dynamics.model)]
    built = {cls: cls(motion) for cls in sorted(todo, key=lambda cls: not cls.background)}
    out = [built[cls] for cls in todo]
    # every limited kind's peaks and exits in one fused pass, handed back kind by kind
    limited = [c for c in out if isinstance(c, LimitedConstraint)]
    requests = [c.scan_requests() for c in limited]
    answers = iter(scan(motion, [r for rs in requests for r in rs]))
    for c, rs in zip(limited, requests):
        c._scanned = [next(answers) for _ in rs]
    return out


# ----------------------------------------------------------------------------------------------
# helpers

def rms_time_scale(tt: np.ndarray, s: np.ndarray, w: np.ndarray, i: np.ndarray,
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
            out[moving] = rms_time_scale(tt, s[:, moving], w[:, moving], i[:, moving],
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
    ll, gl, lh, gh = _rms_bracket(g, k_up, m)
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


def _rms_bracket(g: Callable[..., np.ndarray], k_up: np.ndarray, m: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The search's first bracket per column: (log lo, g(lo), log hi, g(hi))."""
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
    return np.log(lo), gl, np.log(hi), gh


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def percent_text(v: Violation) -> str:
    """"NN% of L unit at t = T s" of a violation."""
    return (f"{abs(v.peak_value) / v.limit * 100 if v.limit > 0 else math.inf:.0f}% of "
            f"{with_unit(v.limit, v.unit)} at t = {v.peak_time_s:.2f} s")


def with_unit(x: float, unit: str) -> str:
    """"x unit" (just "x" for a gauge without a unit)."""
    return f"{_fmt(x)} {unit}" if unit else _fmt(x)


def _static_block(motion: Motion, j: int, n: int, need: float, limit: float) -> Blocked:
    """Gravity and friction alone exceed the limit at sample n: no slowdown helps."""
    qtxt = "[" + ", ".join(f"{x:.3g}" for x in motion.Q[n]) + "]"
    names = motion.names
    alone = "gravity and friction" if motion.task is None or motion.task.task_torque is None \
        else "gravity, friction and the task wrench"
    return Blocked(names[j], f"{alone} alone need {_fmt(need)} "
                             f"{motion.units['effort'][j]} of {_fmt(limit)} at q = {qtxt} "
                             f"(t = {motion.smp.t[n]:.2f} s); no slowdown helps")


def _k_of_x(xs: np.ndarray) -> np.ndarray:
    """k = 1/x per column, with x = inf (never leaves the band) → 0 and x = 0 → inf."""
    with np.errstate(divide="ignore"):
        kk = np.where(xs > 0, 1.0 / xs, np.inf)
    return np.where(np.isinf(xs), 0.0, kk)


def _power_exit(L: np.ndarray, peak: np.ndarray, power: int) -> np.ndarray:
    """First exit x = 1/k of peak·x^power ≤ L per column: (L/peak)^(1/power); inf (never) when
    the value is zero at every sample and L ≥ 0; 0 (every k fails) when L < 0. A YAML limit of 0
    is a real limit: 0 for a moving joint, inf for one that does not move."""
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (L / peak) ** (1.0 / power)
    return np.where(L < 0, 0.0, np.where(peak > 0, x, np.inf))


def _affine_band(a: np.ndarray, b: np.ndarray, L: np.ndarray,
                 scale: np.ndarray | None = None) -> Band | None:
    """|(a + m·b)·scale| ≤ L at every sample: an interval of m."""
    if not a.size:
        return None
    one = np.broadcast_to(1.0, a.shape) if scale is None else scale
    return kernels.affine_band(a, b, one, np.broadcast_to(L, a.shape))


def _take(X: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """X[:, cols] without the copy when cols is every column in order (the common case); the
    caller must not write into the result."""
    if len(cols) == X.shape[1] and (len(cols) == 0 or (cols[0] == 0 and cols[-1] == len(cols) - 1
                                                         and np.all(np.diff(cols) == 1))):
        return X
    return X[:, cols]


def _cumtrapz_rows(tt: np.ndarray, fT: np.ndarray) -> np.ndarray:
    """Cumulative trapezoid integral of each row of fT (r×M, C-contiguous) over times tt."""
    out = np.empty_like(fT)
    out[..., 0] = 0.0
    np.add(fT[..., 1:], fT[..., :-1], out=out[..., 1:])
    out[..., 1:] *= 0.5 * np.diff(tt)
    np.cumsum(out[..., 1:], axis=-1, out=out[..., 1:])
    return out


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
