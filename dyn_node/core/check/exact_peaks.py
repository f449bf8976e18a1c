"""Exact peaks of the kinematic kinds, and how densely the torque kinds sample each piece.

Position, velocity, acceleration, deceleration and jerk are polynomials on each piece of the
executed trajectory (:class:`~dyn_node.core.check.trajectory.PiecewisePolynomial`, degree ≤ 5),
so their peaks are taken exactly: per piece, the largest value at its two ends (both one-sided
values of every knot) and at the roots of the next derivative inside it
(:mod:`dyn_node.core.compiled.peak_kernels`); nothing between samples can hide one. The torque
kinds (not polynomial) are sampled: every piece on its own, both knot sides included, with at
least :func:`min_steps` steps so that a piece shorter than the sample period is sampled inside
too. The method is in docs/limits.md ("How peaks are found").
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dyn_node.core.check.constraints import Motion, Peak, Samples, Violation
from dyn_node.core.check.trajectory import PiecewisePolynomial
from dyn_node.core.compiled import peak_kernels as pk

#: Steps per piece at least, by the piece's polynomial degree (index): a linear piece's torque
#: is nearly linear; a quadratic's or higher needs ≥ 4 steps for the fourth-order effort-rate
#: differences, which resolve a torque peak at the piece's ends exactly.
MIN_STEPS_BY_DEGREE = (1, 2, 4, 4, 4, 4)
#: Steps at least in a piece whose |q̈| or |q⃛| peaks inside it from zero at its ends (a
#: rest-to-rest quintic's inertial torque peaks at s = 0.21 T): uniform steps miss such a peak
#: by ~1/n² of it, 0.1 % at 32 steps and 0.04 % at 48 (docs/limits.md). A peak rising a fraction
#: r over the larger end is missed by ~r/n²: it gets ⌈48·√r⌉ steps, the same resolution (a
#: retimed answer's 4 ms pieces rise little: 48 each made its check 10× the sampling's cost).
INNER_PEAK_STEPS = 48


def piece_degrees(pp: PiecewisePolynomial) -> np.ndarray:
    """Each piece's degree (the highest power with a non-zero coefficient for any joint)."""
    nz = np.any(pp.coeffs != 0.0, axis=2)                       # K × P
    P = nz.shape[1]
    return np.where(nz.any(axis=1), P - 1 - np.argmax(nz[:, ::-1], axis=1), 0)


def min_steps(pp: PiecewisePolynomial) -> np.ndarray:
    """Per piece, the fewest sample steps the torque kinds take on it: by its degree, and
    ⌈:data:`INNER_PEAK_STEPS` · √r⌉ where some joint's acceleration or jerk peaks inside it a
    fraction r above the piece's ends (by more than 0.1 %: the ends are samples anyway)."""
    table = np.asarray(MIN_STEPS_BY_DEGREE)
    least = table[np.minimum(piece_degrees(pp), len(table) - 1)]
    rise = np.maximum(pk.inner_rise(pp.coeffs, pp.breaks, 2, 1e-3),
                      pk.inner_rise(pp.coeffs, pp.breaks, 3, 1e-3))
    inner = np.ceil(INNER_PEAK_STEPS * np.sqrt(rise)).astype(least.dtype)
    return np.where(rise > 0.0, np.maximum(least, inner), least)


def sampling_warnings(smp: Samples, least: np.ndarray, period: float) -> list[str]:
    """What the sample budget cost: long segments sampled coarser than ``period``, short ones
    with fewer steps than ``least`` (their torque peaks less resolved; the kinematic kinds'
    stay exact)."""
    out = []
    steps = np.diff(smp.first, append=len(smp.t)) - 1
    coarse = smp.h[smp.last] > period * (1 + 1e-9)
    if np.any(coarse):
        out.append(f"{int(coarse.sum())} long segment(s) sampled with "
                   f"{int(steps[coarse].min())} steps (up to {smp.h.max() * 1e3:.3g} ms) "
                   f"instead of {period * 1e3:.3g} ms, to bound memory")
    few = steps < least
    if np.any(few):
        out.append(f"{int(few.sum())} short segment(s) sampled with {int(steps[few].min())} "
                   f"step(s) instead of {int(least[few].max())}, to bound memory (torque peaks "
                   "inside them less resolved)")
    return out


@dataclass(frozen=True)
class ExactPeaks:
    """One kind's exact peaks per column: the largest |value| over every piece, with its time,
    and the largest over the pieces the time-scale laws cover (from the first law piece)."""

    value: np.ndarray        # |value| at the peak, per column
    time_s: np.ndarray
    law_peak: np.ndarray     # the largest |value| from piece seg0 on


def _first_law_piece(motion: Motion) -> int:
    """The first piece the per-sample laws cover (1 after a start segment that does not
    stretch with k, else 0)."""
    return int(motion.smp.seg[motion.r0]) if motion.r0 < len(motion.smp.seg) else 0


def magnitude_peaks(motion: Motion, order: int, cols: np.ndarray) -> ExactPeaks:
    """|q⁽ᵒʳᵈᵉʳ⁾| (velocity 1, acceleration 2, jerk 3) exactly, per column of ``cols``."""
    pp = motion.pieces
    hi, t_hi, lo, t_lo, law_hi, law_lo = pk.column_range(pp.coeffs, pp.breaks, order, cols,
                                                         _first_law_piece(motion))
    up = hi >= -lo
    return ExactPeaks(np.where(up, hi, -lo), np.where(up, t_hi, t_lo),
                      np.maximum(law_hi, -law_lo))


def deceleration_peaks(motion: Motion, cols: np.ndarray) -> ExactPeaks:
    """The supremum of |q̈| where q̇·q̈ < 0 exactly, per column of ``cols``."""
    pp = motion.pieces
    return ExactPeaks(*pk.column_deceleration(pp.coeffs, pp.breaks, cols,
                                              _first_law_piece(motion)))


def report(kind: str, motion: Motion, peaks: ExactPeaks, cols: np.ndarray, L: np.ndarray,
           where: tuple[str, ...], units: list[str], order: int) -> tuple[list[Peak], list[Violation]]:
    """The peak per place and the violations (first time and time over the limit exact too)
    of a kind whose |value| is checked against the constant limits L."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(peaks.value > 0, peaks.value / L, 0.0)
    peaks_out = [Peak(w, float(ratio[c]), float(peaks.time_s[c]), float(peaks.value[c]),
                      float(L[c])) for c, w in enumerate(where)]
    bad = np.flatnonzero(peaks.value > L)
    violations = []
    if len(bad):
        pp = motion.pieces
        first, total = pk.excess(pp.coeffs, pp.breaks, order, cols[bad], -L[bad], L[bad],
                                 kind == "deceleration")
        for n, c in enumerate(bad):
            # a peak only just over the limit may have no part over it the roots resolve
            t0 = first[n] if math.isfinite(first[n]) else peaks.time_s[c]
            violations.append(Violation(where[c], kind, float(min(t0, peaks.time_s[c])),
                                        float(peaks.time_s[c]), float(peaks.value[c]),
                                        float(L[c]), float(total[n]), units[c]))
    return peaks_out, violations


@dataclass(frozen=True)
class PositionRange:
    """Per column, q's exact largest and smallest value with their times, over every piece and
    (``late_*``) over the pieces after a start segment."""

    q_max: np.ndarray
    t_max: np.ndarray
    q_min: np.ndarray
    t_min: np.ndarray
    late_max: np.ndarray
    late_min: np.ndarray


def position_range(motion: Motion, cols: np.ndarray) -> PositionRange:
    pp = motion.pieces
    return PositionRange(*pk.column_range(pp.coeffs, pp.breaks, 0, cols, _first_law_piece(motion)))


def position_excess(motion: Motion, cols: np.ndarray, lower: np.ndarray, upper: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per column, the first time q leaves [lower, upper] (NaN: never) and the time outside."""
    pp = motion.pieces
    return pk.excess(pp.coeffs, pp.breaks, 0, cols, lower, upper, False)
