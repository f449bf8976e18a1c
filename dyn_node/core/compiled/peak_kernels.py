"""Compiled exact extrema of piecewise polynomials (Numba, no rclpy): the kinematic kinds' peaks.

A trajectory's position, velocity, acceleration and jerk are polynomials of degree ≤ 5 on each
piece, so their peaks need no sampling: the extrema of a piece's derivative polynomial lie at its
ends or at the real roots of the next derivative inside it. Roots are isolated without any
closed form: the roots of a polynomial are separated by those of its derivative, so going up the
chain of derivatives (linear first) every root lies in a bracket where the polynomial is
monotone, found there by safeguarded Newton steps (bisection when Newton leaves the bracket) to
the last bit. Coefficients are ascending (``coeffs[k, p, j]`` multiplies sᵖ, s the time from
piece k's start, for column j), zero-padded: a linear and a quintic piece sit in one table.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from dyn_node.core.compiled.jit import _I, _JIT, _V, _f8, _i8

#: coefficients per piece at most (degree 5: quintic interpolation)
MAXP = 6

_T3 = types.Array(_f8, 3, "A", readonly=True)


@njit(**_JIT)
def _horner(c: np.ndarray, n: int, x: float) -> float:
    """Σ c[p]·xᵖ over the first n coefficients."""
    acc = 0.0
    for p in range(n - 1, -1, -1):
        acc = acc * x + c[p]
    return acc


@njit(**_JIT)
def _chain(src: np.ndarray, k: int, j: int, order: int, D: np.ndarray) -> int:
    """D[i] = derivative ``order + i`` of column j of piece k (ascending coefficients); returns
    the degree of D[0] (−1 when identically zero), trailing zero coefficients dropped."""
    P = src.shape[1]
    for i in range(MAXP):
        for p in range(MAXP):
            D[i, p] = 0.0
    for p in range(P):
        D[0, p] = src[k, p, j]
    for _ in range(order):          # differentiate in place
        for p in range(MAXP - 1):
            D[0, p] = (p + 1) * D[0, p + 1]
        D[0, MAXP - 1] = 0.0
    deg = MAXP - 1
    while deg >= 0 and D[0, deg] == 0.0:
        deg -= 1
    for i in range(1, max(deg, 0) + 1):
        for p in range(MAXP - 1):
            D[i, p] = (p + 1) * D[i - 1, p + 1]
    return deg


@njit(**_JIT)
def _solve(c: np.ndarray, dc: np.ndarray, n: int, a: float, b: float, fa: float) -> float:
    """The root of the polynomial c (n coefficients, derivative dc) in [a, b], where it is
    monotone and changes sign (fa = c(a)): Newton kept inside the shrinking bracket."""
    lo, hi = a, b
    up = fa < 0.0               # c increases through the root
    x = 0.5 * (lo + hi)
    for _ in range(200):
        f = _horner(c, n, x)
        if f == 0.0:
            return x
        if (f < 0.0) == up:
            lo = x
        else:
            hi = x
        d = _horner(dc, n - 1, x)
        xn = x - f / d if d != 0.0 else 0.5 * (lo + hi)
        if not (lo < xn < hi):
            xn = 0.5 * (lo + hi)
        if xn == x or hi - lo <= 4e-16 * max(abs(lo), abs(hi)):
            return xn
        x = xn
    return x


@njit(**_JIT)
def _roots(D: np.ndarray, deg: int, T: float, out: np.ndarray) -> int:
    """The real roots of D[0] (degree ``deg``, derivatives below it in D) inside (0, T), in
    ascending order, into ``out``; returns their count. An identically zero or constant
    polynomial has none."""
    if deg <= 0:
        return 0
    crit = np.empty(MAXP)
    nc = 0
    for level in range(deg - 1, -1, -1):       # the linear derivative first, then up the chain
        c = D[level]
        n = deg - level + 1
        nr = 0
        a, fa = 0.0, _horner(c, n, 0.0)
        for i in range(nc + 1):
            b = crit[i] if i < nc else T
            fb = _horner(c, n, b)
            if fa == 0.0 and a > 0.0:
                out[nr] = a             # a root of the derivative too (a double root)
                nr += 1
            elif fa * fb < 0.0:
                out[nr] = _solve(c, D[level + 1], n, a, b, fa)
                nr += 1
            a, fa = b, fb
        for i in range(nr):
            crit[i] = out[i]
        nc = nr
    return nc


@njit(**_JIT)
def _piece_range(D: np.ndarray, deg: int, T: float,
                 roots: np.ndarray) -> tuple[float, float, float, float]:
    """(max, its s, min, its s) of D[0] over [0, T]: at the ends or the roots of D[1] inside."""
    f0 = _horner(D[0], deg + 1, 0.0) if deg >= 0 else 0.0
    hi, t_hi, lo, t_lo = f0, 0.0, f0, 0.0
    nr = _roots(D[1:], deg - 1, T, roots) if deg >= 2 else 0
    for i in range(nr + 1):
        s = roots[i] if i < nr else T
        f = _horner(D[0], deg + 1, s) if deg >= 0 else 0.0
        if f > hi:
            hi, t_hi = f, s
        if f < lo:
            lo, t_lo = f, s
    return hi, t_hi, lo, t_lo


@njit(**_JIT)
def _ends(src: np.ndarray, k: int, j: int, order: int, T: float) -> tuple[float, float, float]:
    """Derivative ``order`` of column j on piece k: its value at s = 0 and at s = T, and R, a
    bound of |value(s) − value(0)| on [0, T] (Σ |coefficient|·Tᵖ beyond the constant)."""
    f0, fT, R, tp = 0.0, 0.0, 0.0, 1.0
    for p in range(order, src.shape[1]):
        fac = 1.0
        for i in range(p - order + 1, p + 1):
            fac *= i
        c = fac * src[k, p, j]
        if p == order:
            f0 = c
        else:
            R += abs(c) * tp
        fT += c * tp
        tp *= T
    return f0, fT, R


_C1 = types.Array(_f8, 1, "C")


@njit([types.UniTuple(_C1, 6)(_T3, _V, _i8, _I, _i8)], **_JIT)
def column_range(coeffs: np.ndarray, breaks: np.ndarray, order: int, cols: np.ndarray,
                 seg0: int) -> tuple[np.ndarray, ...]:
    """Per column c (joint cols[c]) of derivative ``order``: its largest value and the time
    (on the breaks' clock), its smallest and that time, over every piece; and its largest and
    smallest from piece ``seg0`` on. The ends of every piece first; then only the pieces whose
    bound (value at the start ± R) could beat them are solved for their insides."""
    K, m = coeffs.shape[0], len(cols)
    hi, t_hi, lo, t_lo = np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    law_hi, law_lo = np.full(m, -np.inf), np.full(m, np.inf)
    D = np.empty((MAXP, MAXP))
    roots = np.empty(MAXP)
    for c in range(m):
        j = cols[c]
        h, th, l, tl = -np.inf, breaks[0], np.inf, breaks[0]
        for k in range(K):
            f0, fT, _ = _ends(coeffs, k, j, order, breaks[k + 1] - breaks[k])
            for f, t in ((f0, breaks[k]), (fT, breaks[k + 1])):
                if f > h:
                    h, th = f, t
                if f < l:
                    l, tl = f, t
                if k >= seg0:
                    law_hi[c], law_lo[c] = max(law_hi[c], f), min(law_lo[c], f)
        for k in range(K):
            T = breaks[k + 1] - breaks[k]
            f0, _, R = _ends(coeffs, k, j, order, T)
            top, bottom = (law_hi[c], law_lo[c]) if k >= seg0 else (h, l)
            if f0 + R <= top and f0 - R >= bottom:
                continue              # its inside cannot beat the ends already seen
            ph, sh, pl, sl = _piece_range(D, _chain(coeffs, k, j, order, D), T, roots)
            if ph > h:
                h, th = ph, breaks[k] + sh
            if pl < l:
                l, tl = pl, breaks[k] + sl
            if k >= seg0:
                law_hi[c], law_lo[c] = max(law_hi[c], ph), min(law_lo[c], pl)
        hi[c], t_hi[c], lo[c], t_lo[c] = h, th, l, tl
    return hi, t_hi, lo, t_lo, law_hi, law_lo


@njit(**_JIT)
def _decel_at(DV: np.ndarray, dv: int, DA: np.ndarray, da: int, s: float, stop: bool) -> float:
    """|q̈| at s when it decelerates there (q̇·q̈ < 0), or where q̇ reaches 0 from a deceleration
    (``stop``: the supremum of a deceleration phase that ends in a stop); else 0."""
    v = _horner(DV[0], dv + 1, s) if dv >= 0 else 0.0
    a = _horner(DA[0], da + 1, s) if da >= 0 else 0.0
    return abs(a) if (v * a < 0.0 or stop) else 0.0


@njit(**_JIT)
def _stops_at(DV: np.ndarray, dv: int, s: float) -> bool:
    """q̇ = 0 exactly at s (a stop exactly on a piece's end: the sign test alone misses it;
    a stop a rounding error before or after the end is a root inside or a deceleration)."""
    return (_horner(DV[0], dv + 1, s) if dv >= 0 else 0.0) == 0.0


@njit(**_JIT)
def _piece_decel(DV: np.ndarray, dv: int, DA: np.ndarray, da: int, T: float,
                 r: np.ndarray) -> tuple[float, float]:
    """The supremum of |q̈| where q̇·q̈ < 0 on one piece and its s. Candidates: both ends, the
    extrema of q̈ inside (roots of q⃛) and the stops inside (roots of q̇, approached from a
    deceleration whenever q̈ ≠ 0 there); a piece ending at q̇ = 0 with q̈ ≠ 0 decelerates
    into its end."""
    best, s_best = _decel_at(DV, dv, DA, da, 0.0, False), 0.0
    f = _decel_at(DV, dv, DA, da, T, _stops_at(DV, dv, T))
    if f > best:
        best, s_best = f, T
    for stop in range(2):
        n = _roots(DV, dv, T, r) if stop else _roots(DA[1:], da - 1, T, r)
        for i in range(n):
            f = _decel_at(DV, dv, DA, da, r[i], stop == 1)
            if f > best:
                best, s_best = f, r[i]
    return best, s_best


@njit([types.UniTuple(_C1, 3)(_T3, _V, _I, _i8)], **_JIT)
def column_deceleration(coeffs: np.ndarray, breaks: np.ndarray, cols: np.ndarray,
                        seg0: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per column: the supremum of |q̈| where |q̇| decreases (q̇·q̈ < 0) over every piece, its
    time, and the same from piece ``seg0`` on. Pieces whose |q̈| bound (|q̈(0)| + R) cannot beat
    the best so far are skipped; the others solved (:func:`_piece_decel`)."""
    K, m = coeffs.shape[0], len(cols)
    val, at, law = np.zeros(m), np.full(m, breaks[0]), np.zeros(m)
    DV, DA = np.empty((MAXP, MAXP)), np.empty((MAXP, MAXP))
    r = np.empty(MAXP)
    for c in range(m):
        j = cols[c]
        for k in range(K):
            T = breaks[k + 1] - breaks[k]
            a0, _, R = _ends(coeffs, k, j, 2, T)
            if abs(a0) + R <= (law[c] if k >= seg0 else val[c]):
                continue
            dv = _chain(coeffs, k, j, 1, DV)
            best, s = _piece_decel(DV, dv, DA, _chain(coeffs, k, j, 2, DA), T, r)
            if best > val[c]:
                val[c], at[c] = best, breaks[k] + s
            if k >= seg0:
                law[c] = max(law[c], best)
    return val, at, law


@njit(**_JIT)
def _cuts(D: np.ndarray, deg: int, level: float, T: float, cuts: np.ndarray, nc: int,
          r: np.ndarray) -> int:
    """Append the roots of D[0] − level inside (0, T) to cuts[nc:]; returns the new count
    (an infinite level: none)."""
    if not math.isfinite(level):
        return nc
    D[0, 0] -= level
    n = _roots(D, deg if deg > 0 else 0, T, r)
    D[0, 0] += level
    for i in range(n):
        cuts[nc + i] = r[i]
    return nc + n


@njit(**_JIT)
def _over(D: np.ndarray, deg: int, DV: np.ndarray, dv: int, s: float, lower: float,
          upper: float, decel: bool) -> bool:
    x = _horner(D[0], deg + 1, s) if deg >= 0 else 0.0
    if not (x > upper or x < lower):
        return False
    return not decel or x * (_horner(DV[0], dv + 1, s) if dv >= 0 else 0.0) < 0.0


@njit([types.UniTuple(types.Array(_f8, 1, "C"), 2)(_T3, _V, _i8, _I, _V, _V, types.boolean)],
      **_JIT)
def excess(coeffs: np.ndarray, breaks: np.ndarray, order: int, cols: np.ndarray,
           lower: np.ndarray, upper: np.ndarray, decel: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per column: the first time (s, on the breaks' clock; NaN if never) and the total time
    that derivative ``order`` lies above upper[c] or below lower[c] (with ``decel``: only where
    q̇·q̈ < 0, order 2). Each piece is cut at the roots of the derivative − each bound (and of
    q̇) and each part tested inside."""
    K, m = coeffs.shape[0], len(cols)
    first, total = np.full(m, np.nan), np.zeros(m)
    D, DV = np.empty((MAXP, MAXP)), np.empty((MAXP, MAXP))
    cuts, r = np.empty(4 * MAXP), np.empty(MAXP)
    for c in range(m):
        for k in range(K):
            T = breaks[k + 1] - breaks[k]
            deg = _chain(coeffs, k, cols[c], order, D)
            dv = _chain(coeffs, k, cols[c], 1, DV)
            nc = _cuts(D, deg, upper[c], T, cuts, 0, r)
            nc = _cuts(D, deg, lower[c], T, cuts, nc, r)
            if decel:
                nc = _cuts(DV, dv, 0.0, T, cuts, nc, r)
            part = np.sort(cuts[:nc])
            a = 0.0
            for i in range(nc + 1):
                b = part[i] if i < nc else T
                if b > a and _over(D, deg, DV, dv, 0.5 * (a + b), lower[c], upper[c], decel):
                    total[c] += b - a
                    if math.isnan(first[c]):
                        first[c] = breaks[k] + a
                a = b
    return first, total


_F2 = types.Array(_f8, 2, "F")
_MA = types.Array(_f8, 2, "A", readonly=True)


@njit(**_JIT)
def _rate5(F: np.ndarray, f: int, l_: int, c: int, h: float, D: np.ndarray) -> None:
    """Fourth-order differences over samples f..l_ (≥ 4 steps of h), exact for quartics:
    central inside, five-point one-sided at both ends and their neighbours."""
    for n in range(f + 2, l_ - 1):
        D[n, c] = (F[n - 2, c] - 8 * F[n - 1, c] + 8 * F[n + 1, c] - F[n + 2, c]) / (12 * h)
    D[f, c] = (-25 * F[f, c] + 48 * F[f + 1, c] - 36 * F[f + 2, c] + 16 * F[f + 3, c]
               - 3 * F[f + 4, c]) / (12 * h)
    D[f + 1, c] = (-3 * F[f, c] - 10 * F[f + 1, c] + 18 * F[f + 2, c] - 6 * F[f + 3, c]
                   + F[f + 4, c]) / (12 * h)
    D[l_, c] = (25 * F[l_, c] - 48 * F[l_ - 1, c] + 36 * F[l_ - 2, c] - 16 * F[l_ - 3, c]
                + 3 * F[l_ - 4, c]) / (12 * h)
    D[l_ - 1, c] = (3 * F[l_, c] + 10 * F[l_ - 1, c] - 18 * F[l_ - 2, c] + 6 * F[l_ - 3, c]
                    - F[l_ - 4, c]) / (12 * h)


@njit(**_JIT)
def _rate3(F: np.ndarray, f: int, l_: int, c: int, h: float, D: np.ndarray) -> None:
    """Second-order differences over samples f..l_ (2 or 3 steps); one step: the chord."""
    if l_ - f >= 2:
        for n in range(f + 1, l_):
            D[n, c] = (F[n + 1, c] - F[n - 1, c]) / (2 * h)
        D[f, c] = (-3 * F[f, c] + 4 * F[f + 1, c] - F[f + 2, c]) / (2 * h)
        D[l_, c] = (3 * F[l_, c] - 4 * F[l_ - 1, c] + F[l_ - 2, c]) / (2 * h)
    else:
        D[f, c] = D[l_, c] = (F[l_, c] - F[f, c]) / h


@njit([_F2(_MA, _I, _I, _V)], **_JIT)
def segment_rate(F: np.ndarray, first: np.ndarray, last: np.ndarray,
                 h: np.ndarray) -> np.ndarray:
    """d/dt of samples F (M×m, per second) inside each segment (samples first[k]..last[k],
    step h), never across a knot: each knot's two sides are one-sided values of their own
    segments. Fourth order where a segment has ≥ 4 steps (exact for a quartic in time: the
    inertial torque of a short quintic piece), second order with 2–3. Column-major M×m."""
    M, m = F.shape
    D = np.empty((m, M)).T
    for c in range(m):
        for k in range(len(first)):
            f, l_ = first[k], last[k]
            if l_ - f >= 4:
                _rate5(F, f, l_, c, h[f], D)
            else:
                _rate3(F, f, l_, c, h[f], D)
    return D


@njit([_V(_T3, _V, _i8, _f8)], **_JIT)
def inner_rise(coeffs: np.ndarray, breaks: np.ndarray, order: int, margin: float) -> np.ndarray:
    """Per piece: how far some column's |derivative ``order``| peaks inside it above its larger
    end, as a fraction of that peak (0 where no peak exceeds (1 + margin) × the larger end: the
    samples at the ends resolve it)."""
    K, nv = coeffs.shape[0], coeffs.shape[2]
    out = np.zeros(K)
    D = np.empty((MAXP, MAXP))
    roots = np.empty(MAXP)
    for k in range(K):
        T = breaks[k + 1] - breaks[k]
        for j in range(nv):
            f0, fT, R = _ends(coeffs, k, j, order, T)
            top = max(abs(f0), abs(fT))
            end = (1.0 + margin) * top
            if abs(f0) + R <= end:
                continue
            hi, _, lo, _ = _piece_range(D, _chain(coeffs, k, j, order, D), T, roots)
            peak = max(hi, -lo)
            if peak > end:
                out[k] = max(out[k], (peak - top) / peak)
    return out
