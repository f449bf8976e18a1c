"""Compiled per-sample loops for the feasibility check (Numba, no rclpy).

The feasibility check reduces every sample of a trajectory to a few numbers per joint (the
first time-scale exit of a torque band, the worst windowed RMS). Written as whole-array NumPy
those reductions make a dozen passes over memory and hold the GIL between them; here each is one
loop over the samples that keeps the running answer in registers and skips what a cheap bound
rules out. ``nogil=True``: a check running in the node's worker thread does not stall the
joint_states callbacks. ``cache=True``: compiled once per machine, not per process.

Arrays are float64; M×m sample arrays are read column by column, so column-major (Fortran)
input is the fast layout.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from dyn_node.core.compiled.jit import _B, _I, _JIT, _M, _V, _f8, _i8, _pair


@njit(**_JIT)
def _tau2_cumulative(tt: np.ndarray, s: np.ndarray, w: np.ndarray, i: np.ndarray, c: int,
                     x: float, E: np.ndarray) -> None:
    """E[n] = trapezoid integral over tt[:n + 1] of τ² for τ = s + w·x + i·x² in column c
    (torque²·s); non-decreasing, since every term added is ≥ 0."""
    t = s[0, c] + x * (w[0, c] + x * i[0, c])
    prev = t * t
    E[0] = 0.0
    for n in range(1, len(tt)):
        t = s[n, c] + x * (w[n, c] + x * i[n, c])
        t2 = t * t
        E[n] = E[n - 1] + (t2 + prev) * (0.5 * (tt[n] - tt[n - 1]))
        prev = t2


@njit(**_JIT)
def _window_at(tt: np.ndarray, E: np.ndarray, n: int, j: int, span: float,
               hold: float) -> tuple[float, int]:
    """(E(tₙ) − E(tₙ − span) + hold·(time of the window before tt[0]), j) for cumulative
    integrals E at samples tt (linear in between, as numpy.interp). ``j``: a sample at or before
    the window start (0 will do); returned moved forward to the last one, within [0, M − 2],
    ready for a later window end."""
    M = len(tt)
    start = tt[n] - span
    while j + 1 <= M - 2 and tt[j + 1] <= start:
        j += 1
    jn = min(j + 1, M - 1)
    h = tt[jn] - tt[j]
    f = 0.0
    if h > 0:
        f = min(max((start - tt[j]) / h, 0.0), 1.0)
    before = tt[0] - start
    return E[n] - (E[j] + f * (E[jn] - E[j])) + (before if before > 0 else 0.0) * hold, j


@njit(**_JIT)
def _last_at_or_before(tt: np.ndarray, j: int, start: float) -> int:
    """Where :func:`_window_at`'s walk from sample j ends for a window starting at ``start``:
    the last sample in [j, M − 2] at or before it (j itself when the next is after it), tt
    non-decreasing."""
    lo, hi = j, len(tt) - 2
    if hi <= lo or tt[lo + 1] > start:
        return j
    # invariant: tt[lo] ≤ start (or lo = j), and every sample after hi is after start or past M − 2
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if tt[mid] <= start:
            lo = mid
        else:
            hi = mid - 1
    return lo


@njit([types.Array(_f8, 2, "C")(_V, _M, _V, _V)], **_JIT)
def windowed(tt: np.ndarray, cum: np.ndarray, window: np.ndarray,
             hold: np.ndarray) -> np.ndarray:
    """Integrals over the trailing window ending at each sample (r×M) from cumulative
    integrals ``cum`` (r×M rows over times tt), window lengths ``window`` (r, s) and values
    ``hold`` (r) integrated before the start: cum(t) − cum(t − window) + hold·(time before
    tt[0])."""
    out = np.empty(cum.shape)
    for r in range(cum.shape[0]):
        j = 0
        for n in range(cum.shape[1]):
            out[r, n], j = _window_at(tt, cum[r], n, j, window[r], hold[r])
    return out


@njit([types.Array(_f8, 2, "C")(_V, _M, _M, _M, _V, _V, _V)], **_JIT)
def rms_windowed(tt: np.ndarray, s: np.ndarray, w: np.ndarray, i: np.ndarray, x: np.ndarray,
                 window: np.ndarray, hold2: np.ndarray) -> np.ndarray:
    """Per column c (m×M out), the integral of τ² (τ = s + w·x + i·x², samples M×m) over the
    trailing window of ``window[c]·x[c]`` (original time, s) ending at each sample; before
    ``tt[0]`` the integrand is ``hold2[c]``. At x = 1: the trajectory's own windowed ∫τ²."""
    M, m = s.shape
    out = np.empty((m, M))
    E = np.empty(M)
    for c in range(m):
        _tau2_cumulative(tt, s, w, i, c, x[c], E)
        j = 0
        for n in range(M):
            out[c, n], j = _window_at(tt, E, n, j, window[c] * x[c], hold2[c])
    return out


@njit([types.Array(_f8, 1, "C")(_V, _M, _M, _M, _V, _V, _V, _B)], **_JIT)
def rms_worst(tt: np.ndarray, s: np.ndarray, w: np.ndarray, i: np.ndarray, x: np.ndarray,
              window: np.ndarray, hold2: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """The largest value of :func:`rms_windowed` per column c with ``sel[c]`` (NaN for the
    others).

    Exact, without visiting every window end: the windows ending on a sparse grid are
    integrated first; since E (the integral of τ² from the start) never decreases, the windows
    ending between grid points a < b integrate at most E(t_b) − E(t_a − span) (+ the hold part
    of a's window), and only the gaps where that bound reaches the grid's maximum are
    integrated end by end.
    """
    M, m = s.shape
    out = np.full(m, np.nan)
    E = np.empty(M)
    stride = max(1, M // 256)
    grid = np.append(np.arange(0, M - 1, stride), M - 1)
    at_grid = np.empty(len(grid))
    start_grid = np.empty(len(grid), dtype=np.int64)
    for c in range(m):
        if not sel[c]:
            continue
        _tau2_cumulative(tt, s, w, i, c, x[c], E)
        span, hold = window[c] * x[c], hold2[c]
        worst = -np.inf
        j = 0
        for g in range(len(grid)):
            # the grid's window starts are ~stride samples apart: found by bisection, where
            # _window_at would walk there sample by sample (the same sample either way)
            j = _last_at_or_before(tt, j, tt[grid[g]] - span)
            start_grid[g] = j
            at_grid[g], j = _window_at(tt, E, grid[g], j, span, hold)
            worst = max(worst, at_grid[g])
        # the interpolated window start can round either way: skip only gaps clearly below
        slack = 1e-12 * abs(worst)
        for g in range(len(grid) - 1):
            a, b = grid[g], grid[g + 1]
            if b - a < 2 or at_grid[g] + (E[b] - E[a]) < worst - slack:
                continue
            j = start_grid[g]
            for n in range(a + 1, b):
                value, j = _window_at(tt, E, n, j, span, hold)
                worst = max(worst, value)
        out[c] = worst
    return out


# --- roots -------------------------------------------------------------------------------------

@njit([_pair(_f8, _f8, _f8)], **_JIT)
def quadratic_roots(a: float, b: float, c: float) -> tuple[float, float]:
    """Real roots of a·x² + b·x + c (NaN where none), stable form; a = 0 gives the linear root."""
    disc = b * b - 4 * a * c
    if not disc >= 0:
        return np.nan, np.nan
    sq = math.sqrt(disc)
    q = -0.5 * (b + (sq if b >= 0 else -sq))
    r1 = q / a if a != 0 else np.nan
    if q != 0:
        r2 = c / q
    elif a == 0 and b != 0:
        r2 = -c / b
    else:
        r2 = np.nan
    return r1, r2


@njit(**_JIT)
def _polish(a: float, b: float, c: float, d: float, x: float) -> float:
    # two Newton steps on the cubic: the closed forms lose digits when roots are close
    for _ in range(2):
        f = ((a * x + b) * x + c) * x + d
        fp = (3 * a * x + 2 * b) * x + c
        step = f / fp if fp != 0 else 0.0
        if math.isfinite(step):
            x = x - step
    return x


@njit([types.UniTuple(_f8, 3)(_f8, _f8, _f8, _f8)], **_JIT)
def cubic_roots(a: float, b: float, c: float, d: float) -> tuple[float, float, float]:
    """Real roots of a·x³ + b·x² + c·x + d (d ≠ 0), NaN where none; degree drops where a = 0.

    The largest-magnitude real root comes from Cardano / the trigonometric form; it is deflated
    out and the remaining quadratic solved stably; every root is then polished by Newton steps.
    """
    if a == 0:
        r2, r3 = quadratic_roots(b, c, d)
        return np.nan, _polish(a, b, c, d, r2), _polish(a, b, c, d, r3)
    B, C, D = b / a, c / a, d / a
    p = C - B * B / 3
    q = 2 * B * B * B / 27 - B * C / 3 + D
    disc = (q / 2) ** 2 + (p / 3) ** 3
    if disc > 0:
        # one real root: avoid cancellation by adding magnitudes
        w = -q / 2 - (1.0 if q >= 0 else -1.0) * math.sqrt(disc)
        t = np.cbrt(w)
        big = (t - p / (3 * t) if t != 0 else 0.0) - B / 3
    else:
        # three real roots (trigonometric form); the largest in magnitude
        r = 2 * math.sqrt(max(-p / 3, 0.0))
        arg = 3 * q / (p * (r if r != 0 else 1.0)) if p < 0 else 0.0
        phi = math.acos(min(max(arg, -1.0), 1.0)) / 3
        x0 = r * math.cos(phi) - B / 3
        x1 = r * math.cos(phi - 2 * math.pi / 3) - B / 3
        x2 = r * math.cos(phi - 4 * math.pi / 3) - B / 3
        if abs(x0) >= max(abs(x1), abs(x2)):
            big = x0
        elif abs(x1) >= abs(x2):
            big = x1
        else:
            big = x2
    if big == 0:
        return _polish(a, b, c, d, big), np.nan, np.nan
    # backward deflation by the large root
    qc = -d / big
    qb = (qc - c) / big
    qa = (qb - b) / big
    r2, r3 = quadratic_roots(qa, qb, qc)
    return _polish(a, b, c, d, big), _polish(a, b, c, d, r2), _polish(a, b, c, d, r3)


@njit(**_JIT)
def _least_positive(x: float, best: float) -> float:
    return x if (x > 0 and x < best) else best    # x < best ≤ inf: finite; NaN fails


@njit([_f8(_f8, _f8, _f8, _f8)], **_JIT)
def quadratic_exit(c0: float, c1: float, c2: float, limit: float) -> float:
    """Smallest x > 0 where |c0 + c1·x + c2·x²| reaches ``limit``; inf if none."""
    best = np.inf
    for sign in (1.0, -1.0):
        r1, r2 = quadratic_roots(sign * c2, sign * c1, sign * c0 - limit)
        best = _least_positive(r1, best)
        best = _least_positive(r2, best)
    return best


@njit([_f8(_f8, _f8, _f8, _f8)], **_JIT)
def cubic_exit(c1: float, c2: float, c3: float, limit: float) -> float:
    """Smallest x > 0 where |c1·x + c2·x² + c3·x³| reaches ``limit`` (> 0); inf if none."""
    best = np.inf
    for sign in (1.0, -1.0):
        r1, r2, r3 = cubic_roots(sign * c3, sign * c2, sign * c1, -limit)
        best = _least_positive(r1, best)
        best = _least_positive(r2, best)
        best = _least_positive(r3, best)
    return best


# --- per-column first exits (time scale x = 1/k) ------------------------------------------------

@njit(**_JIT)
def _argmax_abs(X: np.ndarray, c: int) -> int:
    # numpy.argmax(|X[:, c]|): the first largest, or the first NaN
    best, at = -1.0, 0
    for n in range(X.shape[0]):
        a = abs(X[n, c])
        if a > best or (a != a and best == best):
            best, at = a, n
    return at


@njit([types.Array(_f8, 1, "C")(_M, _M, _M, _V)], **_JIT)
def band_exit(s: np.ndarray, w: np.ndarray, i: np.ndarray, L: np.ndarray) -> np.ndarray:
    """Per column c, the smallest first exit x > 0 over samples (M×m) of
    |s + w·x + i·x²| ≤ L[c]; 0 where |s| > L[c] somewhere (outside already at x = 0), inf where
    no sample ever leaves.

    |s| + |w|·x + |i|·x² bounds the torque, so a sample can only exit before the best exit x_b
    found so far if that bound reaches L at x_b: roots are solved only for those. The first x_b
    comes from the samples with the largest |s|, |w| and |i|.
    """
    M, m = s.shape
    out = np.empty(m)
    for c in range(m):
        Lc = L[c]
        outside = False
        for n in range(M):
            if abs(s[n, c]) > Lc:
                outside = True
                break
        if outside:
            out[c] = 0.0
            continue
        best = np.inf
        for n in (_argmax_abs(s, c), _argmax_abs(w, c), _argmax_abs(i, c)):
            best = min(best, quadratic_exit(s[n, c], w[n, c], i[n, c], Lc))
        for n in range(M):
            aw, ai = abs(w[n, c]), abs(i[n, c])
            if best < np.inf:
                xb = best * (1 + 1e-9)
                if (ai * xb + aw) * xb + abs(s[n, c]) < Lc:
                    continue
            elif aw + ai == 0:
                continue
            x = quadratic_exit(s[n, c], w[n, c], i[n, c], Lc)
            if x < best:
                best = x
        out[c] = best
    return out


@njit([types.Array(_f8, 1, "C")(_M, _M, _M, _M, _V)], **_JIT)
def odd_exit(c1: np.ndarray, c2: np.ndarray, c3: np.ndarray, scale: np.ndarray,
             L: np.ndarray) -> np.ndarray:
    """Per column c, the smallest first exit x > 0 over samples (M×m) of
    |(c1·x + c2·x² + c3·x³)·scale| ≤ L[c] (L > 0); inf where no sample ever leaves. ``scale``
    (M×m, may be a broadcast view): e.g. the joint speed, for power.

    In k = 1/x the bound |c1|x + |c2|x² + |c3|x³ ≤ L reads p(k) = L·k³ − |c1|k² − |c2|k − |c3|
    ≥ 0; p has one positive root, which bounds the sample's exact k from above and exceeds the
    best k found so far exactly when p(k_best) < 0: roots are solved only for those samples.
    """
    M, m = c1.shape
    out = np.empty(m)
    for c in range(m):
        Lc = L[c]
        best = np.inf
        big = np.zeros(3)
        seeds = np.zeros(3, dtype=np.int64)
        for n in range(M):
            f = abs(scale[n, c])
            for q, X in enumerate((c1, c2, c3)):
                a = abs(X[n, c]) * f
                if a > big[q]:
                    big[q], seeds[q] = a, n
        for n in seeds:
            f = scale[n, c]
            best = min(best, cubic_exit(c1[n, c] * f, c2[n, c] * f, c3[n, c] * f, Lc))
        for n in range(M):
            f = scale[n, c]
            a1, a2, a3 = c1[n, c] * f, c2[n, c] * f, c3[n, c] * f
            A, B, C = abs(a1), abs(a2), abs(a3)
            if best < np.inf:
                kb = 1.0 / best / (1 + 1e-9)
                if ((Lc * kb - A) * kb - B) * kb - C >= 0:
                    continue
            elif A + B + C == 0:
                continue
            x = cubic_exit(a1, a2, a3, Lc)
            if x < best:
                best = x
        out[c] = best
    return out


@njit([types.Tuple((types.Array(_i8, 1, "C"), types.Array(_f8, 1, "C")))(_M)], **_JIT)
def abs_peak(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column of X (M×m): the first sample of the largest |X| and that value; (0, 0) for
    an empty column; NaN propagates as in numpy.max."""
    M, m = X.shape
    at = np.zeros(m, dtype=np.int64)
    peak = np.zeros(m)
    if M:
        for c in range(m):
            at[c] = _argmax_abs(X, c)
            peak[c] = abs(X[at[c], c])
    return at, peak


# --- torque-speed envelope -----------------------------------------------------------------------

@njit([_f8(_f8, _f8, _f8, _f8)], **_JIT)
def band_exit_bound(s: float, w: float, i: float, L: float) -> float:
    """Lower bound on the first exit x of |s + w·x + i·x²| ≤ L: the root of
    |s| + |w|·x + |i|·x² = L (0 where |s| ≥ L already, inf where nothing grows)."""
    room = L - abs(s)
    if not room > 0:
        return 0.0
    aw = abs(w)
    d = aw + math.sqrt(aw * aw + 4 * abs(i) * room)
    return 2 * room / d if d > 0 else np.inf


@njit(**_JIT)
def _interp(x: float, sp: np.ndarray, ef: np.ndarray, P: int) -> float:
    # numpy.interp on the first P points: held constant outside them
    if not x > sp[0]:
        return ef[0]
    if x >= sp[P - 1]:
        return ef[P - 1]
    j = 0
    while sp[j + 1] <= x:
        j += 1
    return ef[j] + (x - sp[j]) * ((ef[j + 1] - ef[j]) / (sp[j + 1] - sp[j]))


@njit(**_JIT)
def _speed_to_x(point: float, v: float) -> float:
    # the x at which speed v·x reaches a curve point
    if v > 0:
        return point / v
    return np.inf if point > 0 else 0.0


@njit([_f8(_f8, _f8, _f8, _f8, _V, _V, _i8)], **_JIT)
def envelope_exit(s: float, w: float, i: float, speed: float, sp: np.ndarray, ef: np.ndarray,
                  P: int) -> float:
    """First x > 0 where |s + w·x + i·x²| reaches the envelope E(|speed|·x), E piecewise linear
    through (sp, ef)[:P] and held constant outside: one quadratic per piece and sign, a root
    counting only inside its piece's range of x; inf if none."""
    v = abs(speed)
    best = np.inf
    for piece in range(P + 1):
        # piece 0: before the first point, piece P: after the last (constant there); piece p in
        # between: from point p − 1 to point p
        if piece == 0 or piece == P:
            e0, slope, s0 = (ef[0] if piece == 0 else ef[P - 1]), 0.0, 0.0
        else:
            m = piece - 1
            e0, s0 = ef[m], sp[m]
            slope = (ef[m + 1] - ef[m]) / (sp[m + 1] - sp[m])
        lo = 0.0 if piece == 0 else _speed_to_x(sp[piece - 1], v)
        hi = np.inf if piece == P else _speed_to_x(sp[piece], v)
        for sign in (1.0, -1.0):
            r1, r2 = quadratic_roots(sign * i, sign * w - slope * v, sign * s - e0 + slope * s0)
            for x in (r1, r2):
                if x >= lo and x <= hi and x > 0 and x < best:
                    best = x
    return best


@njit([types.Array(_f8, 2, "F")(_M, _M, _M, _I)], **_JIT)
def envelope_values(v: np.ndarray, sp: np.ndarray, ef: np.ndarray, npts: np.ndarray) -> np.ndarray:
    """The torque-speed envelope of column c (points sp[c, :npts[c]], ef[c, :npts[c]], as
    numpy.interp: held constant outside them) at each sample's speed |v| (M×m, column-major)."""
    M, m = v.shape
    out = np.empty((m, M)).T
    for c in range(m):
        P, spc, efc = npts[c], sp[c], ef[c]
        for n in range(M):
            out[n, c] = _interp(abs(v[n, c]), spc, efc, P)
    return out


@njit(**_JIT)
def _floor(speed: float, sp: np.ndarray, ef: np.ndarray, prefix: np.ndarray, P: int) -> float:
    # the envelope's minimum over speeds [0, speed]
    at = _interp(speed, sp, ef, P)
    k = -1
    while k + 1 < P and sp[k + 1] <= speed:
        k += 1
    return min(prefix[k], at) if k >= 0 else ef[0]


@njit([types.Array(_f8, 1, "C")(_M, _M, _M, _M, _M, _M, _I)], **_JIT)
def envelope_exit_min(s: np.ndarray, w: np.ndarray, i: np.ndarray, v: np.ndarray,
                      sp: np.ndarray, ef: np.ndarray, npts: np.ndarray) -> np.ndarray:
    """Per column c, the smallest first exit x over samples (M×m) of |s + w·x + i·x²| from the
    envelope of column c (points sp[c, :npts[c]], ef[c, :npts[c]]) at speed |v|·x; inf if no
    sample leaves.

    Below the best exit x_b found so far the envelope is at least its minimum over speeds
    [0, |v|·x_b], so a sample that stays inside the band |τ| ≤ that floor until x_b (checked by
    a bound, then by the band's exact exit) cannot leave the envelope earlier: only the others
    are solved piece by piece. The first x_b is the least exit of the samples with the largest
    |s|, |w| and |i|.
    """
    M, m = s.shape
    out = np.empty(m)
    slack = 1 + 1e-9     # rounding in a bound must never rule out the true first exit
    for c in range(m):
        P = npts[c]
        spc, efc = sp[c], ef[c]
        prefix = np.empty(P)
        prefix[0] = efc[0]
        for k in range(1, P):
            prefix[k] = min(prefix[k - 1], efc[k])
        e_min = max(prefix[P - 1], 1e-300)
        best = np.inf
        for n in (_argmax_abs(s, c), _argmax_abs(w, c), _argmax_abs(i, c)):
            best = min(best, envelope_exit(s[n, c], w[n, c], i[n, c], v[n, c], spc, efc, P))
        for n in range(M):
            sn, wn, inn, av = s[n, c], w[n, c], i[n, c], abs(v[n, c])
            limit = best * slack
            # the envelope never falls below its overall minimum: most samples stop here, where
            # the bound |s| + |w|·x + |i|·x² is still below it at x = limit
            if limit < np.inf and (abs(inn) * limit + abs(wn)) * limit + abs(sn) < e_min:
                continue
            fl = _floor(av * best if av > 0 else 0.0, spc, efc, prefix, P)
            if not band_exit_bound(sn, wn, inn, fl) < limit:
                continue
            if abs(sn) < fl and not quadratic_exit(sn, wn, inn, fl) < limit:
                continue
            x = envelope_exit(sn, wn, inn, v[n, c], spc, efc, P)
            if x < best:
                best = x
        out[c] = best
    return out


# --- payload margin ------------------------------------------------------------------------------

@njit([_pair(_M, _M, _M, _M)], **_JIT)
def affine_band(a: np.ndarray, b: np.ndarray, scale: np.ndarray,
                L: np.ndarray) -> tuple[float, float]:
    """The interval of m with |(a + m·b)·scale| ≤ L at every element (M×m arrays, ``scale``
    and ``L`` may be broadcast views): (lo, hi), lo > hi when none. An element with b·scale = 0
    constrains nothing unless it is outside already (then no m helps)."""
    lo, hi = -np.inf, np.inf
    M, m = a.shape
    for c in range(m):
        for n in range(M):
            sa, sb, lim = a[n, c] * scale[n, c], b[n, c] * scale[n, c], L[n, c]
            if sb == 0:
                if abs(sa) > lim:
                    return np.inf, -np.inf
                continue
            ab = abs(sb)
            sgn = sa if sb > 0 else -sa
            t = (lim - sgn) / ab
            if t < hi:
                hi = t
            t = (-lim - sgn) / ab
            if t > lo:
                lo = t
    return lo, hi


@njit([_pair(_M, _M, _M)], **_JIT)
def quadratic_band(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[float, float]:
    """The interval of m with A·m² + 2B·m + C ≤ 0 at every element (r×M arrays, A ≥ 0: a
    windowed ∫(a0 + m·a1)² minus its limit): (lo, hi), lo > hi when none. Roots in the stable
    form of :func:`quadratic_roots`; where A = 0 the element constrains nothing unless C > 0."""
    lo, hi = -np.inf, np.inf
    r, M = A.shape
    for k in range(r):
        for n in range(M):
            a, c = A[k, n], C[k, n]
            r1, r2 = quadratic_roots(a, 2 * B[k, n], c)
            if math.isnan(r1) and c > 0:
                return np.inf, -np.inf
            if not a > 0:
                continue
            up = r2 if math.isnan(r1) else (r1 if math.isnan(r2) else max(r1, r2))
            dn = r2 if math.isnan(r1) else (r1 if math.isnan(r2) else min(r1, r2))
            if up < hi:
                hi = up
            if dn > lo:
                lo = dn
    return lo, hi


# --- torque terms --------------------------------------------------------------------------------

@njit(**_JIT)
def _sign(v: float) -> float:
    # numpy.sign: 0 at 0, NaN at NaN
    return 1.0 if v > 0 else (-1.0 if v < 0 else (0.0 if v == 0 else v))


_F2 = types.Array(_f8, 2, "F")


@njit([types.UniTuple(_F2, 4)(_M, _M, _M, _M, _V, _V)], **_JIT)
def split_terms(G: np.ndarray, F: np.ndarray, V: np.ndarray, A: np.ndarray,
                damping: np.ndarray, coulomb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """From rigid-body gravity G and full RNEA F (nv×N, one state per column, as Pinocchio's
    batch writes them), velocities V and accelerations A (N×nv): static = G + coulomb·sign(v),
    viscous = damping·v, inertial = F − G and the full torque F + friction (N·m), each N×nv
    column-major (every joint's samples contiguous). A state at rest (v = a = 0) has no inertial
    part: F − G there is only the rounding between two gravity routes, and read as an inertial
    term it would give a held pose a spurious time scale."""
    nv, N = G.shape
    still = np.empty(N, dtype=np.bool_)
    for n in range(N):
        rest = True
        for j in range(nv):
            if V[n, j] != 0.0 or A[n, j] != 0.0:
                rest = False
                break
        still[n] = rest
    S = np.empty((nv, N)).T
    W = np.empty((nv, N)).T
    I = np.empty((nv, N)).T
    tau = np.empty((nv, N)).T
    for j in range(nv):
        d, cf = damping[j], coulomb[j]
        for n in range(N):
            v = V[n, j]
            s = G[j, n] + cf * _sign(v)
            w = d * v
            i = F[j, n] - G[j, n]
            S[n, j], W[n, j] = s, w
            I[n, j] = 0.0 if still[n] else i
            tau[n, j] = s + w + i
    return S, W, I, tau




_T4 = types.Array(_f8, 4, "C", readonly=True)
_C3 = types.Array(_f8, 3, "C")


@njit([_C3(_T4, _I, _V)], **_JIT)
def piecewise_eval(tables: np.ndarray, seg: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Every tabulated derivative of a piecewise polynomial at M samples, as D×M×nv (each
    derivative row-major M×nv): ``tables[d, k, p, j]`` is derivative d's coefficient of sᵖ on
    segment k for column j, ``seg`` each sample's segment and ``s`` its time from the segment's
    start. Horner per sample, all derivatives in one pass over the samples."""
    D, _, P, nv = tables.shape
    out = np.empty((D, len(s), nv))
    for n in range(len(s)):
        k, x = seg[n], s[n]
        for d in range(D):
            row = out[d, n]
            c = tables[d, k]
            # the columns side by side: independent chains, so the multiply-adds overlap
            for j in range(nv):
                row[j] = c[P - 1, j]
            for p in range(P - 2, -1, -1):
                for j in range(nv):
                    row[j] = row[j] * x + c[p, j]
    return out


@njit([types.Array(_i8, 2, "C")(_M, _I)], **_JIT)
def bin_peaks(val: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Per bin b of samples [edges[b], edges[b + 1]) (edges strictly increasing) and per column
    of ``val`` (M×m): the first sample of the bin's largest |val| (NaN counts as inf), B×m."""
    m = val.shape[1]
    out = np.empty((len(edges) - 1, m), dtype=np.int64)
    for c in range(m):
        for b in range(len(edges) - 1):
            best, where = -1.0, edges[b]
            for n in range(edges[b], edges[b + 1]):
                v = abs(val[n, c])
                if v != v:
                    v = np.inf
                if v > best:
                    best, where = v, n
            out[b, c] = where
    return out
