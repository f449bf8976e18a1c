"""TOPP-RA's reachability passes (toppra 0.6.10's algorithm, seidel wrapper semantics), compiled.

TOPP-RA's own passes are a Python loop over the grid's stages with two small LPs per stage; on a
1000-step grid that loop is most of its time, and the retimer runs it two or three times. Here
the same two passes run in one compiled loop each:

- backward (controllable sets): the stage's polygon in (u, x) = (s̈, ṡ²) is the stage's rows
  a·u + b·x + c ≤ 0, the next stage's rows with x → x + 2Δu (TOPP-RA's "interpolation"
  discretisation), x + 2Δu in the next stage's set, 0 ≤ x ≤ xmax and TOPP-RA's own variable
  bounds |u|, |x| ≤ 1e8. Its projection onto x is computed exactly (Fourier–Motzkin: every pair
  of a lower and an upper bound on u gives a bound on x), which is what TOPP-RA's two LPs per
  stage (max x, min x) compute up to its solver's 1e-10 feasibility tolerance.
- forward: from x₀, at each stage the largest u the stage's rows allow at that x with
  x + 2Δu in the next set, then x' = max(x + 2Δu − 1e-8, 0.9999(x + 2Δu)) clamped into the
  next set, and on a numerically empty interval x reduced by max(1e-8, 0.1 %) up to 1000 times:
  toppra's ``compute_parameterization`` step for step.

``test_retime_topp`` checks both against TOPP-RA called directly.
"""
from __future__ import annotations

import numpy as np
from numba import njit, types

from dyn_node.core.compiled.jit import _JIT, _M, _V, _f8, _i8

#: TOPP-RA's bounds on every stage's u and x (its seidel wrapper's VAR_MIN/VAR_MAX)
VAR_MAX = 1e8
#: toppra's constants: TINY (the forward step's back-off), its retries on a failed step
_TINY = 1e-8
_MAX_TRIES = 1000


@njit(**_JIT)
def _span(al, be, ce, k, lo, hi):   # pragma: no cover (compiled)
    """[lo, hi] ∩ the projection onto x of {(u, x): al·u + be·x + ce ≤ 0 (first k rows)}
    (Fourier–Motzkin; u bounded only by the rows given); lo > hi: empty."""
    for p in range(k):
        if al[p] == 0.0:
            if be[p] > 0.0:
                hi = min(hi, -ce[p] / be[p])
            elif be[p] < 0.0:
                lo = max(lo, -ce[p] / be[p])
            elif ce[p] > 0.0:
                return 1.0, 0.0
    for p in range(k):
        if al[p] <= 0.0:
            continue
        for q in range(k):
            if al[q] >= 0.0:
                continue
            # u ≤ −(b_p x + c_p)/a_p and u ≥ −(b_q x + c_q)/a_q meet where
            # x (a_p b_q − a_q b_p) ≤ a_q c_p − a_p c_q (both sides × a_p·(−a_q) > 0)
            kx = al[p] * be[q] - al[q] * be[p]
            r = al[q] * ce[p] - al[p] * ce[q]
            if kx > 0.0:
                hi = min(hi, r / kx)
            elif kx < 0.0:
                lo = max(lo, r / kx)
            elif r < 0.0:
                return 1.0, 0.0
    return lo, hi


@njit(**_JIT)
def _interval(a0, b0, c0, a1, b1, c1, d, xlo, xhi, klo, khi):   # pragma: no cover (compiled)
    """[lo, hi] of x over one stage's polygon (lo > hi: empty): rows (a0, b0, c0) at the
    stage, (a1 + 2d·b1, b1, c1) of the next (none when d < 0), x + 2d·u in [klo, khi] (d ≥ 0),
    |u| ≤ VAR_MAX, x in [xlo, xhi]."""
    m = a0.shape[0]
    n = 2 * m + 4
    al = np.empty(n)
    be = np.empty(n)
    ce = np.empty(n)
    k = 0
    for j in range(m):
        al[k], be[k], ce[k] = a0[j], b0[j], c0[j]
        k += 1
    if d >= 0.0:
        for j in range(m):
            al[k], be[k], ce[k] = a1[j] + 2.0 * d * b1[j], b1[j], c1[j]
            k += 1
        al[k], be[k], ce[k] = 2.0 * d, 1.0, -khi
        al[k + 1], be[k + 1], ce[k + 1] = -2.0 * d, -1.0, klo
        k += 2
    al[k], be[k], ce[k] = 1.0, 0.0, -VAR_MAX
    al[k + 1], be[k + 1], ce[k + 1] = -1.0, 0.0, -VAR_MAX
    k += 2
    return _span(al, be, ce, k, xlo, xhi)


@njit([_i8(_M, _M, _M, _V, _V, _V, types.Array(_f8, 2, "C"), _i8, _f8)], **_JIT)
def controllable(A, B, C, xmax, deltas, cap, K, top, rounding):   # pragma: no cover (compiled)
    """TOPP-RA's controllable sets K[top], …, K[0] (K[top + 1] given), each clamped to
    [0, cap]; a lower end above the cap by at most ``rounding`` is set to it. Returns the stage
    found empty (K at and below it NaN), or −1."""
    for i in range(top, -1, -1):
        lo, hi = _interval(A[i], B[i], C[i], A[i + 1], B[i + 1], C[i + 1], deltas[i],
                           0.0, min(xmax[i], VAR_MAX), K[i + 1, 0], K[i + 1, 1])
        lo = max(lo, 0.0)
        hi = min(hi, cap[i])
        if lo > hi and lo <= hi + rounding:
            lo = hi
        if not (lo <= hi):
            K[: i + 1, :] = np.nan
            return i
        K[i, 0] = lo
        K[i, 1] = hi
    return -1


@njit(**_JIT)
def _narrow(a, rhs, lo, hi):   # pragma: no cover (compiled)
    """[lo, hi] ∩ {u: a·u ≤ rhs}."""
    if a > 0.0:
        return lo, min(hi, rhs / a)
    if a < 0.0:
        return max(lo, rhs / a), hi
    return lo, hi


@njit([types.Array(_f8, 1, "C")(_M, _M, _M, _V, _M, _f8)], **_JIT)
def forward(A, B, C, deltas, K, x0):   # pragma: no cover (compiled)
    """TOPP-RA's forward pass: x = ṡ² at every grid point from x0 (NaN from a failed stage)."""
    n = deltas.shape[0]
    m = A.shape[1]
    xs = np.full(n + 1, np.nan)
    xs[0] = x0
    i = 0
    tries = 0
    while i < n:
        x = xs[i]
        d = deltas[i]
        # u's interval at this x: the stage's rows, the next stage's (x' = x + 2d·u), the set
        ulo = max(-VAR_MAX, (K[i + 1, 0] - x) / (2.0 * d))
        uhi = min(VAR_MAX, (K[i + 1, 1] - x) / (2.0 * d))
        for j in range(m):
            ulo, uhi = _narrow(A[i, j], -(B[i, j] * x + C[i, j]), ulo, uhi)
            ulo, uhi = _narrow(A[i + 1, j] + 2.0 * d * B[i + 1, j],
                               -(B[i + 1, j] * x + C[i + 1, j]), ulo, uhi)
        if not (ulo <= uhi):
            if tries >= _MAX_TRIES:
                return xs
            xs[i] = max(x - _TINY, 0.999 * x)
            tries += 1
            continue
        tries = 0
        xn = x + 2.0 * d * uhi
        xn = max(xn - _TINY, 0.9999 * xn)
        xs[i + 1] = min(K[i + 1, 1], max(K[i + 1, 0], xn))
        i += 1
    return xs


# --- the certified lower bound's passes (dyn_node/retime/bound.py): each stage's relaxed rows
# α·ū + β·x_i + γ ≤ 0 hold for the true samples x_i = x(s_i) and the stage's mean ū, u free

@njit(**_JIT)
def _outward(lo, hi):   # pragma: no cover (compiled)
    """An interval widened by rounding's worth (1e-10 relative): the bound's sets contain the
    exact ones."""
    return max(0.0, lo - 1e-10 * abs(lo) - 1e-12), hi + 1e-10 * abs(hi) + 1e-12


@njit(**_JIT)
def _rows(Al, Be, Ga, i, extra_a, extra_b, lo, hi, al, be, ce):   # pragma: no cover
    """Stage i's rows into al, be, ce, then x + extra_a·u within [lo, hi] (skipped where
    infinite); the number of rows."""
    m = Al.shape[1]
    for j in range(m):
        al[j], be[j], ce[j] = Al[i, j] + extra_b * Be[i, j], Be[i, j], Ga[i, j]
    k = m
    if hi < np.inf:
        al[k], be[k], ce[k] = extra_a, 1.0, -hi
        k += 1
    if lo > -np.inf:
        al[k], be[k], ce[k] = -extra_a, -1.0, lo
        k += 1
    return k


@njit([_i8(_M, _M, _M, _V, _V, types.Array(_f8, 2, "C"))], **_JIT)
def relaxed_backward(Al, Be, Ga, xmax, deltas, K):   # pragma: no cover (compiled)
    """The controllable sets K[N-1], …, K[0] (K[N] given) of the relaxed stages: x_i in
    [0, xmax_i] and x_i + 2Δū in K[i+1]. Returns the stage found empty (K at and below it
    NaN), or −1."""
    n = deltas.shape[0]
    m = Al.shape[1]
    al, be, ce = np.empty(m + 2), np.empty(m + 2), np.empty(m + 2)
    for i in range(n - 1, -1, -1):
        d = deltas[i]
        k = _rows(Al, Be, Ga, i, 2.0 * d, 0.0, K[i + 1, 0], K[i + 1, 1], al, be, ce)
        lo, hi = _span(al, be, ce, k, 0.0, xmax[i])
        if not (lo <= hi):
            K[: i + 1, :] = np.nan
            return i
        K[i, 0], K[i, 1] = _outward(lo, hi)
    return -1


@njit([_i8(_M, _M, _M, _M, _V, types.Array(_f8, 2, "C"))], **_JIT)
def relaxed_forward(Al, Be, Ga, K, deltas, R):   # pragma: no cover (compiled)
    """The reachable sets R[1..N] from R[0] within the controllable sets: at stage i the next
    y = x_i + 2Δū with x_i = y − 2Δū in R[i], so each row becomes (α − 2Δβ)·ū + β·y + γ ≤ 0.
    Returns the stage whose next set is empty (R NaN beyond it), or −1."""
    n = deltas.shape[0]
    m = Al.shape[1]
    al, be, ce = np.empty(m + 2), np.empty(m + 2), np.empty(m + 2)
    for i in range(n):
        d = deltas[i]
        k = _rows(Al, Be, Ga, i, -2.0 * d, -2.0 * d, R[i, 0], R[i, 1], al, be, ce)
        lo, hi = _span(al, be, ce, k, K[i + 1, 0], K[i + 1, 1])
        if not (lo <= hi):
            R[i + 1:, :] = np.nan
            return i
        R[i + 1, 0], R[i + 1, 1] = _outward(lo, hi)
    return -1


@njit([types.void(_M, _M, _M, _M, types.Array(_f8, 1, "C"))], **_JIT)
def stage_ceiling(Alo, Ahi, B, C, X):   # pragma: no cover (compiled)
    """X[i] lowered to the largest x that some u allows on stage i's rows taken at their most
    permissive over the stage: a·u ≥ Alo·u for u ≥ 0, ≥ Ahi·u for u ≤ 0 (a in [Alo, Ahi]),
    b·x ≥ B·x, c ≥ C; 0 where no (u, x ≥ 0) meets them (no motion does)."""
    n, m = Alo.shape
    al, be, ce = np.empty(m + 1), np.empty(m + 1), np.empty(m + 1)
    for i in range(n):
        best = -1.0
        for side in (1.0, -1.0):
            for j in range(m):
                al[j] = Alo[i, j] if side > 0 else Ahi[i, j]
                be[j], ce[j] = B[i, j], C[i, j]
            al[m], be[m], ce[m] = -side, 0.0, 0.0
            lo, hi = _span(al, be, ce, m + 1, 0.0, X[i])
            if lo <= hi:
                best = max(best, hi)
        X[i] = max(best, 0.0)
