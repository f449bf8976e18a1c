"""The joint kinds of the feasibility check (velocity, acceleration, deceleration, jerk, effort,
effort–speed, power, effort rate, RMS effort, position), each a :class:`Constraint` of
:mod:`dyn_node.core.check.constraints`; :mod:`dyn_node.core.check.kinds` lists them with the
frame, robot, base and grasp kinds."""
from __future__ import annotations

from abc import abstractmethod
from typing import ClassVar

import numpy as np

from dyn_node.core.check import exact_peaks
from dyn_node.core.check.constraints import (Band, Blocked, Constraint, JointConstraint, Motion,
                                             PayloadTerms, Peak, ScanRequest, Violation,
                                             _affine_band,
                                             _cumtrapz_rows, _fmt, _Job, _k_of_x, _power_exit,
                                             _static_block, _take, rms_time_scale)
from dyn_node.core.compiled import kernels
from dyn_node.core.compiled import peak_kernels as pk
from dyn_node.core.compiled import scan_kernels as sk
from dyn_node.core.robot.limits import JointLimits


class _PowerLaw(JointConstraint):
    """|value| ∝ x^power (x = 1/k) at every instant: the first exit is (L / peak)^(1/power),
    the peak taken exactly on each polynomial piece (:mod:`~dyn_node.core.check.exact_peaks`);
    the per-sample value is formed only when asked for (:meth:`values`)."""

    power: ClassVar[int]
    sources: ClassVar[tuple[str, ...]]

    def __init__(self, motion: Motion):
        super().__init__(motion)
        self._motion = motion
        self._L = self.limit_array(motion.limits)[self.cols]
        self.limit = np.broadcast_to(self._L, (len(motion.smp.t), len(self.cols)))
        self._value: np.ndarray | None = None
        self._peaks = self._exact(motion)

    def _exact(self, motion: Motion) -> exact_peaks.ExactPeaks:
        return exact_peaks.magnitude_peaks(motion, self.order, self.cols)

    @property
    def value(self) -> np.ndarray:
        if self._value is None:
            self._value = self._array(self._motion)
        return self._value

    def _array(self, motion: Motion) -> np.ndarray:
        """The value per sample at k = 1, for the limited columns."""
        return _take(getattr(motion, self.sources[0]), self.cols)

    def scan_requests(self) -> list[ScanRequest]:
        return []       # exact peaks: nothing for the fused pass over the samples

    def report(self, motion: Motion) -> tuple[list[Peak], list[Violation]]:
        return exact_peaks.report(self.kind, motion, self._peaks, self.cols, self._L,
                                  self.where, self.units, self.order)

    def time_scale(self) -> np.ndarray:
        return _k_of_x(_power_exit(self._L, self._peaks.law_peak, self.power))


class Velocity(_PowerLaw):
    kind, power, order, sources = "velocity", 1, 1, ("V",)


class Acceleration(_PowerLaw):
    kind, power, sources = "acceleration", 2, ("A",)


class Deceleration(_PowerLaw):
    """|q̈| where |q̇| decreases (q̇·q̈ < 0); that sign does not change with k, so the value
    scales as 1/k² like the acceleration. Its exact peak is the supremum over each deceleration
    phase (one ending in a stop reaches its |q̈| at the stop)."""

    kind, power, sources = "deceleration", 2, ("A", "V")

    def _exact(self, motion: Motion) -> exact_peaks.ExactPeaks:
        return exact_peaks.deceleration_peaks(motion, self.cols)

    def _array(self, motion: Motion) -> np.ndarray:
        val = _take(motion.A, self.cols)
        return val * (_take(motion.V, self.cols) * val < 0)


class Jerk(_PowerLaw):
    kind, power, order, sources = "jerk", 3, 3, ("J",)


class _TorqueBand(JointConstraint):
    """A kind whose value is the torque τ itself (against a fixed or a speed-dependent limit):
    blocked where gravity and friction alone exceed it; affine in the payload mass."""

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        return _affine_band(_take(motion.tau, self.cols), _take(payload.tau1, self.cols),
                            self.limit)


class Effort(_TorqueBand):
    """|τ| ≤ L, τ(x) = s + w·x + i·x²: the band's first exit per sample, in closed form."""

    kind, payload_dependent = "effort", True

    def __init__(self, motion: Motion):
        super().__init__(motion)
        cols, rows = self.cols, motion.rows
        self._motion, self._L = motion, motion.limits.effort[cols]
        self.value = _take(motion.tau, cols)
        self.limit = np.broadcast_to(self._L, self.value.shape)
        s, w, i = self.terms(motion)
        self._x = kernels.band_exit(s[rows], w[rows], i[rows], self._L)

    def scan_requests(self) -> list[ScanRequest]:
        # τ against the limit, and the static torque's peak (no limit): where gravity and
        # friction alone exceed the limit no slowdown helps
        return [ScanRequest(sk.ABS, ("tau",), self._L, self.cols),
                ScanRequest(sk.ABS, ("S",), np.full(len(self.cols), np.inf), self.cols)]

    def blocked(self) -> Blocked | None:
        static = self.scanned(self._motion)[1]
        at, peak, L = static.abs_at, static.abs_peak, self._L
        if not np.any(peak > L):
            return None
        with np.errstate(divide="ignore"):  # a zero (YAML) limit: inf, the worst
            c = int(np.argmax(peak / L))      # the worst pose
        return _static_block(self._motion, int(self.cols[c]), int(at[c]), float(peak[c]),
                             float(L[c]))


class EffortSpeed(_TorqueBand):
    """|τ| ≤ the torque-speed envelope at |q̇|: piecewise the same band, per envelope piece."""

    kind, label, payload_dependent = "effort_speed", "torque-speed envelope", True

    @classmethod
    def applies(cls, model: "RobotModel") -> bool:
        return any(c is not None for c in model.limits.effort_speed_curve)

    def __init__(self, motion: Motion):
        curves_all = motion.limits.effort_speed_curve
        super().__init__(motion, np.array([j for j, cv in enumerate(curves_all) if cv is not None],
                                          dtype=int))
        cols, rows = self.cols, motion.rows
        curves = [curves_all[j] for j in cols]
        npts = np.array([len(cv) for cv in curves])
        sp = np.zeros((len(cols), npts.max()))
        ef = np.zeros_like(sp)
        for c, cv in enumerate(curves):
            sp[c, :len(cv)], ef[c, :len(cv)] = cv[:, 0], cv[:, 1]
        ve = _take(motion.V, cols)
        self.value, self.limit = _take(motion.tau, cols), kernels.envelope_values(ve, sp, ef, npts)
        s, w, i = (X[rows] for X in self.terms(motion))
        self._x = kernels.envelope_exit_min(s, w, i, ve[rows], sp, ef, npts)
        # the envelope at standstill: what gravity and friction alone may use
        self._e0 = [float(np.interp(0.0, cv[:, 0], cv[:, 1])) for cv in curves]
        self._motion = motion

    def scan_requests(self) -> list[ScanRequest]:
        # τ against the envelope (its own array), and the static torque's peak (no limit)
        return [ScanRequest(sk.ABS, ("tau",), self.limit, self.cols),
                ScanRequest(sk.ABS, ("S",), np.full(len(self.cols), np.inf), self.cols)]

    def blocked(self) -> Blocked | None:
        static = self.scanned(self._motion)[1]
        for c, j in enumerate(self.cols):
            if static.abs_peak[c] > self._e0[c]:      # the worst pose
                return _static_block(self._motion, int(j), int(static.abs_at[c]),
                                     float(static.abs_peak[c]), self._e0[c])
        return None


class Power(JointConstraint):
    """|τ·q̇| ≤ L: odd powers of x, (s + w·x + i·x²)·v·x."""

    kind, payload_dependent = "power", True

    def __init__(self, motion: Motion):
        super().__init__(motion)
        v, rows = _take(motion.V, self.cols), motion.rows
        self._motion, self._L = motion, motion.limits.power[self.cols]
        self.limit = np.broadcast_to(self._L, v.shape)
        self._x = kernels.odd_exit(*(X[rows] for X in self.terms(motion)), v[rows], self._L)

    @property
    def value(self) -> np.ndarray:
        """τ·q̇ (formed when asked for: the fused pass forms it sample by sample)."""
        return _take(self._motion.tau, self.cols) * _take(self._motion.V, self.cols)

    def scan_requests(self) -> list[ScanRequest]:
        return [ScanRequest(sk.PRODUCT, ("tau", "V"), self._L, self.cols)]

    def payload_band(self, motion: Motion, payload: PayloadTerms) -> Band | None:
        return _affine_band(_take(motion.tau, self.cols), _take(payload.tau1, self.cols),
                            self.limit, _take(motion.V, self.cols))


class EffortRate(JointConstraint):
    """|dτ/dt| ≤ L, by fourth-order differences inside each segment (τ is smooth there; each
    knot's two sides are one-sided rates of their own segments, never a difference across
    it: :func:`~dyn_node.core.compiled.peak_kernels.segment_rate`); Coulomb
    friction's step at a velocity reversal is left out, and says so."""

    kind, label, payload_dependent = "effort_rate", "effort rate", True

    def __init__(self, motion: Motion):
        super().__init__(motion)
        cols, rows, smp = self.cols, motion.rows, motion.smp
        L = motion.limits.effort_rate[cols]
        dG, dW, dI = (pk.segment_rate(_take(X, cols), smp.first, smp.last, smp.h)
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
        d0 = pk.segment_rate(smooth0, smp.first, smp.last, smp.h)
        d1 = pk.segment_rate(_take(payload.tau1, cols), smp.first, smp.last, smp.h)
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
        S, W, I = self.terms(motion)
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


#: A position within this fraction of its limit's magnitude (at least 1e-9 rad or m) is on it:
#: a quintic ending exactly at a limit evaluates ~1e-15 past it (issue 39).
POSITION_RTOL = 1e-9


def _position_bounds(lim: JointLimits, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The hard bounds the check enforces: each limit widened by POSITION_RTOL of its size."""
    lo, hi = lim.position_lower[cols], lim.position_upper[cols]
    with np.errstate(invalid="ignore"):
        tol_lo = POSITION_RTOL * np.maximum(1.0, np.abs(np.nan_to_num(lo, posinf=0.0, neginf=0.0)))
        tol_hi = POSITION_RTOL * np.maximum(1.0, np.abs(np.nan_to_num(hi, posinf=0.0, neginf=0.0)))
    return lo - tol_lo, hi + tol_hi


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
        self._motion = motion
        # q's exact extremes on every piece (exact_peaks), not its samples
        rng = exact_peaks.position_range(motion, cols)
        self.warnings = self._soft(motion, rng)
        self._peaks, self._violations = self._hard(motion, rng)
        self._blocked = None
        lo, hi = _position_bounds(lim, cols)
        if np.any((rng.late_max > hi) | (rng.late_min < lo)):   # beyond after the start segment
            v0 = max(self._violations, key=lambda v: abs(v.peak_value - v.limit))
            self._blocked = Blocked(v0.joint, timing_free=True)

    @property
    def value(self) -> np.ndarray:
        """q of the limited joints (formed when asked for), each joint's samples contiguous."""
        return np.asfortranarray(_take(self._motion.Q, self.cols))

    def _soft(self, motion: Motion, rng: "exact_peaks.PositionRange") -> list[str]:
        lim, cols = motion.limits, self.cols
        out = []
        for c, where in enumerate(self.where):
            j = cols[c]
            # beyond a soft bound when > 0 (an infinite bound gives −inf, never a warning)
            for bound, q, t, beyond in (
                    (lim.soft_lower[j], rng.q_min[c], rng.t_min[c], lim.soft_lower[j] - rng.q_min[c]),
                    (lim.soft_upper[j], rng.q_max[c], rng.t_max[c], rng.q_max[c] - lim.soft_upper[j])):
                if beyond > 0:
                    out.append(f"{where} enters its soft-limit zone: q = {_fmt(q)} "
                               f"{self.units[c]} beyond {_fmt(bound)} at t = {t:.2f} s")
        return out

    def _hard(self, motion: Motion, rng: "exact_peaks.PositionRange"
              ) -> tuple[list[Peak], list[Violation]]:
        lim, cols = motion.limits, self.cols
        lo, hi = lim.position_lower[cols], lim.position_upper[cols]
        ranged = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
        mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        lo_t, hi_t = _position_bounds(lim, cols)
        over = np.maximum(rng.q_max - hi_t, lo_t - rng.q_min)
        bad = np.flatnonzero(over > 0)
        # beyond a limit by more than the tolerance is a violation; when and how long it is
        # out are of the limit itself
        first, outside = exact_peaks.position_excess(motion, cols[bad], lo[bad], hi[bad])
        peaks, violations = [], []
        for c, where in enumerate(self.where):
            up = rng.q_max[c] - hi[c] >= lo[c] - rng.q_min[c]
            q, t = (rng.q_max[c], rng.t_max[c]) if up else (rng.q_min[c], rng.t_min[c])
            if over[c] > 0:
                n = int(np.flatnonzero(bad == c)[0])
                t0 = first[n] if np.isfinite(first[n]) else t
                violations.append(Violation(where, "position", float(min(t0, t)), float(t),
                                            float(q), float(hi[c] if up else lo[c]),
                                            float(outside[n]), self.units[c]))
            if ranged[c]:
                up = rng.q_max[c] - mid[c] >= mid[c] - rng.q_min[c]
                q, t = (rng.q_max[c], rng.t_max[c]) if up else (rng.q_min[c], rng.t_min[c])
                peaks.append(Peak(where, float(abs(q - mid[c]) / half[c]), float(t), float(q),
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

