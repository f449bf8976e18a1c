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
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.limits import JointLimits

if TYPE_CHECKING:
    from dyn_node.core.robot.model import RobotModel
    from dyn_node.core.check.task_motion import TaskMotion

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
        out = {k: _json(getattr(self, k)) for k in (
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


class LimitedConstraint(Constraint):
    """A kind whose value per sample is compared in magnitude with a limit per sample."""

    value: np.ndarray
    limit: np.ndarray

    def values(self) -> np.ndarray:
        return self.value

    def report(self, motion: Motion) -> tuple[list[Peak], list[Violation]]:
        val, L, tt = self.value, self.limit, motion.smp.t
        peak, ratio, firsts, dur = kernels.limit_peaks(val, L, motion.smp.weight)
        peaks, violations = [], []
        for c, where in enumerate(self.where):
            n = int(peak[c])
            value = abs(float(val[n, c]))
            peaks.append(Peak(where, float(ratio[c]), float(tt[n]), value, float(L[n, c])))
            if firsts[c] >= 0:
                violations.append(Violation(where, self.kind, float(tt[firsts[c]]), float(tt[n]),
                                            value, float(L[n, c]), float(dur[c]), self.units[c]))
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


# ----------------------------------------------------------------------------------------------
# the kinds

class _PowerLaw(JointConstraint):
    """|value| ∝ x^power (x = 1/k) at every sample: the first exit is (L / peak)^(1/power)."""

    power: ClassVar[int]

    @abstractmethod
    def _array(self, motion: Motion) -> np.ndarray:
        """The value per sample at k = 1, for the limited columns."""

    def __init__(self, motion: Motion):
        super().__init__(motion)
        val = self._array(motion)
        L = self.limit_array(motion.limits)[self.cols]
        self.value, self.limit = val, np.broadcast_to(L, val.shape)
        self._x = _power_exit(L, kernels.abs_peak(val[motion.rows])[1], self.power)


class Velocity(_PowerLaw):
    kind, power, order = "velocity", 1, 1

    def _array(self, motion: Motion) -> np.ndarray:
        return _take(motion.V, self.cols)


class Acceleration(_PowerLaw):
    kind, power = "acceleration", 2

    def _array(self, motion: Motion) -> np.ndarray:
        return _take(motion.A, self.cols)


class Deceleration(_PowerLaw):
    """|q̈| where |q̇| decreases (q̇·q̈ < 0); that sign does not change with k, so the value
    scales as 1/k² like the acceleration."""

    kind, power = "deceleration", 2

    def _array(self, motion: Motion) -> np.ndarray:
        val = _take(motion.A, self.cols)
        return val * (_take(motion.V, self.cols) * val < 0)


class Jerk(_PowerLaw):
    kind, power, order = "jerk", 3, 3

    def _array(self, motion: Motion) -> np.ndarray:
        return _take(motion.J, self.cols)


class Effort(JointConstraint):
    """|τ| ≤ L, τ(x) = s + w·x + i·x²: the band's first exit per sample, in closed form."""

    kind, payload_dependent = "effort", True

    def __init__(self, motion: Motion):
        super().__init__(motion)
        cols, rows = self.cols, motion.rows
        L = motion.limits.effort[cols]
        self.value = _take(motion.tau, cols)
        self.limit = np.broadcast_to(L, self.value.shape)
        s, w, i = _take(motion.S, cols), _take(motion.W, cols), _take(motion.I, cols)
        self._x = kernels.band_exit(s[rows], w[rows], i[rows], L)
        self._blocked = None
        at, peak = kernels.abs_peak(s[rows])
        if np.any(peak > L):
            with np.errstate(divide="ignore"):  # a zero (YAML) limit: inf, the worst
                c = int(np.argmax(peak / L))      # the worst pose
            self._blocked = _static_block(motion, int(cols[c]), motion.r0 + int(at[c]),
                                          float(peak[c]), float(L[c]))

    def blocked(self) -> Blocked | None:
        return self._blocked

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        return _affine_band(_take(motion.tau, self.cols), _take(payload.tau1, self.cols),
                            self.limit)


class EffortSpeed(JointConstraint):
    """|τ| ≤ the torque-speed envelope at |q̇|: piecewise the same band, per envelope piece."""

    kind, label, payload_dependent = "effort_speed", "torque-speed envelope", True

    @classmethod
    def applies(cls, model: "RobotModel") -> bool:
        return any(c is not None for c in model.limits.effort_speed_curve)

    def __init__(self, motion: Motion):
        curves_all = motion.limits.effort_speed_curve
        super().__init__(motion, np.array([j for j, cv in enumerate(curves_all) if cv is not None],
                                          dtype=int))
        cols, rows, r0 = self.cols, motion.rows, motion.r0
        curves = [curves_all[j] for j in cols]
        npts = np.array([len(cv) for cv in curves])
        sp = np.zeros((len(cols), npts.max()))
        ef = np.zeros_like(sp)
        for c, cv in enumerate(curves):
            sp[c, :len(cv)], ef[c, :len(cv)] = cv[:, 0], cv[:, 1]
        ve = _take(motion.V, cols)
        self.value, self.limit = _take(motion.tau, cols), kernels.envelope_values(ve, sp, ef, npts)
        s, w, i = (_take(X, cols)[rows] for X in (motion.S, motion.W, motion.I))
        self._x = kernels.envelope_exit_min(s, w, i, ve[rows], sp, ef, npts)
        self._blocked = None
        for c, j in enumerate(cols):
            e0 = float(np.interp(0.0, curves[c][:, 0], curves[c][:, 1]))
            sj = np.abs(motion.S[r0:, j])
            if np.any(sj > e0):
                n = int(np.argmax(sj))   # the worst pose
                self._blocked = _static_block(motion, int(j), r0 + n, float(sj[n]), e0)
                break

    def blocked(self) -> Blocked | None:
        return self._blocked

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        return _affine_band(_take(motion.tau, self.cols), _take(payload.tau1, self.cols),
                            self.limit)


class Power(JointConstraint):
    """|τ·q̇| ≤ L: odd powers of x, (s + w·x + i·x²)·v·x."""

    kind, payload_dependent = "power", True

    def __init__(self, motion: Motion):
        super().__init__(motion)
        cols, rows = self.cols, motion.rows
        L = motion.limits.power[cols]
        v = _take(motion.V, cols)
        self.value, self.limit = _take(motion.tau, cols) * v, np.broadcast_to(L, v.shape)
        self._x = kernels.odd_exit(_take(motion.S, cols)[rows], _take(motion.W, cols)[rows],
                                   _take(motion.I, cols)[rows], v[rows], L)

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        return _affine_band(_take(motion.tau, self.cols), _take(payload.tau1, self.cols),
                            self.limit, _take(motion.V, self.cols))


class EffortRate(JointConstraint):
    """|dτ/dt| ≤ L, by finite differences inside each segment (τ is smooth there); Coulomb
    friction's step at a velocity reversal is left out, and says so."""

    kind, label, payload_dependent = "effort_rate", "effort rate", True

    def __init__(self, motion: Motion):
        super().__init__(motion)
        cols, rows, smp = self.cols, motion.rows, motion.smp
        L = motion.limits.effort_rate[cols]
        dG, dW, dI = (kernels.segment_derivative(_take(X, cols), smp.first, smp.last, smp.h)
                      for X in (motion.G, motion.W, motion.I))
        self.value = dG + dW + dI
        self.limit = np.broadcast_to(L, self.value.shape)
        self._x = kernels.odd_exit(dG[rows], dW[rows], dI[rows],
                                   np.broadcast_to(1.0, dG[rows].shape), L)
        if np.any(motion.coulomb) and np.any(np.diff(np.sign(motion.V), axis=0) != 0):
            self.warnings.append("Coulomb friction steps at velocity reversals are not counted "
                                 "as effort rate")

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        cols, smp, dyn = self.cols, motion.smp, motion.dynamics
        coul = np.asarray(dyn.model.pin_model.friction, dtype=float)[cols] \
            if dyn.options.include_friction else 0.0
        smooth0 = _take(motion.tau, cols) - coul * np.sign(_take(motion.V, cols))
        d0 = kernels.segment_derivative(smooth0, smp.first, smp.last, smp.h)
        d1 = kernels.segment_derivative(_take(payload.tau1, cols), smp.first, smp.last, smp.h)
        return _affine_band(d0, d1, self.limit)


class RmsEffort(JointConstraint):
    """RMS of τ over a sliding window ending at each sample (the first pose held before the
    start). The window covers a k-dependent stretch of samples, so there is no per-sample law:
    k is searched (:func:`rms_time_scale`), on a background thread when parallel."""

    kind, label, payload_dependent = "rms_effort", "RMS effort", True
    reaches_back = background = True

    def __init__(self, motion: Motion):
        super().__init__(motion)
        cols, rows, tt = self.cols, motion.rows, motion.smp.t
        R, Wn = motion.limits.rms_effort[cols], motion.limits.rms_window[cols]
        h2 = motion.hold[cols] ** 2
        S, W, I = _take(motion.S, cols), _take(motion.W, cols), _take(motion.I, cols)
        # (a moving start segment's path changes with k: its static torque is not static)
        s_max = np.maximum(kernels.abs_peak(S[rows])[1], np.abs(motion.hold[cols]))
        self._good = ~(s_max > R)
        self._search = self._start_search(tt, S, W, I, h2, Wn, R, motion.parallel)
        # windowed ∫τ² at k = 1, by the kernel the search uses, so both agree on whether k = 1
        # is feasible (the payload band reuses it)
        self._win = kernels.rms_windowed(tt, S, W, I, np.ones(len(cols)), Wn, h2)
        self.value = np.sqrt(np.maximum(self._win, 0.0) / Wn[:, None]).T
        self.limit = np.broadcast_to(R, self.value.shape)
        self._blocked = None
        bad = np.flatnonzero(~self._good)
        if len(bad):
            c, r0 = bad[0], motion.r0
            n = r0 + int(np.argmax(np.abs(motion.S[r0:, cols[c]])))
            self._blocked = _static_block(motion, int(cols[c]), n, float(s_max[c]), float(R[c]))

    def _start_search(self, tt, S, W, I, h2, Wn, R, parallel: bool) -> "_Job | None":
        good = self._good
        if not np.any(good):
            return None
        idx, Rg = np.flatnonzero(good), R[good]
        sg, wg, ig = _take(S, idx), _take(W, idx), _take(I, idx)
        # RMS ≤ peak |τ| ≤ max|s| + max|w|·x + max|i|·x², so where that stays within the RMS
        # limit every k is feasible: a bracket end (the exact peak-torque exit where gravity
        # alone just reaches the limit and that bound is useless)
        x_up = np.array([kernels.band_exit_bound(*b) for b in zip(
            kernels.abs_peak(sg)[1], kernels.abs_peak(wg)[1], kernels.abs_peak(ig)[1], Rg)])
        tight = ~(x_up > 0)
        if np.any(tight):
            x_up[tight] = kernels.band_exit(sg[:, tight], wg[:, tight], ig[:, tight], Rg[tight])
        with np.errstate(divide="ignore"):
            k_up = np.where(np.isinf(x_up), 0.0, 1.0 / x_up)
        return _Job(rms_time_scale, (tt, sg, wg, ig, h2[good], Wn[good], Rg, k_up),
                    background=parallel)

    def time_scale(self) -> np.ndarray:
        kr = np.full(len(self.cols), np.inf)
        if self._search is not None:
            kr[self._good] = self._search.result()
        # through x = 1/k like the other kinds (the same factors to the last bit)
        return _k_of_x(np.where(kr > 0, 1.0 / np.where(kr > 0, kr, 1.0), np.inf))

    def blocked(self) -> Blocked | None:
        return self._blocked

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        """The windowed ∫(a0 + m·a1)² = A·m² + 2B·m + C must stay within R²·window: a
        quadratic in m per window (hold torques before the start)."""
        cols, tt, lim = self.cols, motion.smp.t, motion.limits
        heavy_hold = (payload.heavy.gravity(motion.Q[0]) - motion.hold)[cols]
        h0 = motion.hold[cols]
        Wn, R = lim.rms_window[cols], lim.rms_effort[cols]
        a0, a1 = _take(motion.tau, cols), _take(payload.tau1, cols)
        m = len(cols)
        f = np.empty((2 * m, len(tt)))
        np.multiply(a0.T, a1.T, out=f[:m])
        np.multiply(a1.T, a1.T, out=f[m:])
        win = kernels.windowed(tt, _cumtrapz_rows(tt, f), np.concatenate([Wn, Wn]),
                               np.concatenate([h0 * heavy_hold, heavy_hold * heavy_hold]))
        del f
        return kernels.quadratic_band(win[m:], win[:m], self._win - (R * R * Wn)[:, None])


class Position(Constraint):
    """Hard limits (violations; no timing helps) and soft limits (warnings). The ratio is the
    distance from the range's middle over its half-width, for joints limited on both sides."""

    kind = "position"
    order = 0

    @classmethod
    def applies(cls, model: "RobotModel") -> bool:
        lim = model.limits
        return bool(np.any(np.isfinite(lim.position_lower) | np.isfinite(lim.position_upper)))

    @classmethod
    def describe(cls, v: Violation) -> str:
        return (f"{v.joint} {cls.kind} {_fmt(v.peak_value)} {v.unit} beyond limit "
                f"{_fmt(v.limit)} {v.unit} at t = {v.peak_time_s:.2f} s")

    def __init__(self, motion: Motion):
        lim, names = motion.limits, motion.names
        cols = np.flatnonzero(np.isfinite(lim.position_lower) | np.isfinite(lim.position_upper))
        self.cols, self.where = cols, tuple(names[j] for j in cols)
        self.units = [motion.units["position"][j] for j in cols]
        self.value = np.asfortranarray(_take(motion.Q, cols))   # each joint's samples contiguous
        # > 0: beyond a hard limit
        over = np.maximum(self.value - lim.position_upper[cols],
                          lim.position_lower[cols] - self.value)
        self.warnings = self._soft(motion)
        self._peaks, self._violations = self._hard(motion, over)
        self._blocked = None
        if np.any(over[motion.r0:] > 0):   # beyond a hard limit after the start segment
            v0 = max(self._violations, key=lambda v: abs(v.peak_value - v.limit))
            self._blocked = Blocked(v0.joint, timing_free=True)

    def _soft(self, motion: Motion) -> list[str]:
        lim, cols, Qp, tt = motion.limits, self.cols, self.value, motion.smp.t
        # beyond a soft bound when > 0 (an infinite bound gives −inf, never a warning)
        soft = [(b, side * (Qp - b))
                for side, b in ((-1, lim.soft_lower[cols]), (1, lim.soft_upper[cols]))]
        at_soft = [np.argmax(x, axis=0) for _, x in soft]
        out = []
        for c, where in enumerate(self.where):
            for (bound, beyond), at in zip(soft, at_soft):
                n = at[c]
                if beyond[n, c] > 0:
                    out.append(f"{where} enters its soft-limit zone: q = {_fmt(Qp[n, c])} "
                               f"{self.units[c]} beyond {_fmt(bound[c])} at t = {tt[n]:.2f} s")
        return out

    def _hard(self, motion: Motion, over: np.ndarray) -> tuple[list[Peak], list[Violation]]:
        lim, cols, Qp, tt = motion.limits, self.cols, self.value, motion.smp.t
        lo, hi = lim.position_lower[cols], lim.position_upper[cols]
        at_over = np.argmax(over, axis=0)
        ranged = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
        mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        at_mid = np.argmax(np.abs(Qp - mid), axis=0)
        peaks, violations = [], []
        for c, where in enumerate(self.where):
            n = at_over[c]
            if over[n, c] > 0:
                bad = over[:, c] > 0
                q = float(Qp[n, c])
                violations.append(Violation(
                    where, "position", float(tt[np.argmax(bad)]), float(tt[n]), q,
                    float(hi[c] if q > hi[c] else lo[c]), float(motion.smp.weight[bad].sum()),
                    self.units[c]))
            if ranged[c]:
                n = at_mid[c]
                q = float(Qp[n, c])
                peaks.append(Peak(where, float(abs(Qp[n, c] - mid[c]) / half[c]), float(tt[n]), q,
                                  float(hi[c] if q >= mid[c] else lo[c])))
        return peaks, violations

    def values(self) -> np.ndarray:
        return self.value

    def report(self, motion: Motion) -> tuple[list[Peak], list[Violation]]:
        return self._peaks, self._violations

    def time_scale(self) -> None:
        return None

    def blocked(self) -> Blocked | None:
        return self._blocked


#: The joint kinds, in the order the time scale breaks ties and warnings are listed.
JOINT_KINDS: tuple[type[Constraint], ...] = (Velocity, Acceleration, Deceleration, Jerk, Effort,
                                             EffortSpeed, Power, EffortRate, RmsEffort, Position)


def build(motion: Motion, kinds: Sequence[type[Constraint]] | None = None) -> list[Constraint]:
    """The constraints that apply to ``motion``, in ``kinds`` order (None: every registered kind,
    :data:`dyn_node.core.check.kinds.KINDS`; those with background work are built first, so that work
    runs beside the others')."""
    if kinds is None:
        from dyn_node.core.check.kinds import KINDS as kinds
    todo = [cls for cls in kinds if cls.applies(motion.dynamics.model)]
    built = {cls: cls(motion) for cls in sorted(todo, key=lambda cls: not cls.background)}
    return [built[cls] for cls in todo]


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
