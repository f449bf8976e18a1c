"""The feasibility check's fused peak scan (Numba, no rclpy).

Every limited kind reduces its value per sample to the same few numbers per column: the sample
of the largest ratio to its limit, the first sample over it and the time spent over it, and for
the time scale the largest magnitude over the samples the laws cover. Done kind by kind that is
a dozen calls, each a pass over memory, and values such as q̇·q̈ or τ·q̇ formed as whole arrays
first. :func:`peak_scan` takes every kind's columns at once (``channels``): each channel forms
its value sample by sample from the check's own arrays (no temporary array) and keeps the
running answers in registers, bit for bit what the per-kind loops it replaced gave (the ratio
peak, first exceedance and time over of each kind, and
:func:`~dyn_node.core.compiled.kernels.abs_peak` of its value).
"""
from __future__ import annotations

import numpy as np
from numba import njit, types

from dyn_node.core.compiled.jit import _JIT, _M, _V, _f8, _i8

#: how a channel forms its value x from its sources a, b, c (columns of V, A, J, τ, S or P)
ABS, DECEL, PRODUCT, SUM3 = range(4)
#: columns of a channel row: op, source and column of a, b and c, the per-sample limit's
#: column of P (−1: the constant limit)
CHANNEL_COLUMNS = 8

_IC = types.Array(_i8, 1, "C")
_FC = types.Array(_f8, 1, "C")
_CH = types.Array(_i8, 2, "C", readonly=True)


@njit(inline="always", **_JIT)
def _pick(s: int, V: np.ndarray, A: np.ndarray, J: np.ndarray, tau: np.ndarray, S: np.ndarray,
          P: np.ndarray) -> np.ndarray:
    # source s: 0 q̇, 1 q̈, 2 q⃛, 3 τ, 4 the static torque, 5 the pool of the kinds' own arrays
    if s == 0:
        return V
    if s == 1:
        return A
    if s == 2:
        return J
    if s == 3:
        return tau
    return S if s == 4 else P


@njit(inline="always", **_JIT)
def _value(op: int, X0: np.ndarray, c0: int, X1: np.ndarray, c1: int, X2: np.ndarray, c2: int,
           n: int) -> float:
    # the operations of the kinds' NumPy forms, in their order: a·(b·a < 0) (deceleration,
    # b = q̇), a·b (power), (a + b) + c
    x = X0[n, c0]
    if op == DECEL:
        return x * (1.0 if X1[n, c1] * x < 0 else 0.0)
    if op == PRODUCT:
        return x * X1[n, c1]
    if op == SUM3:
        return x + X1[n, c1] + X2[n, c2]
    return x


@njit(inline="always", **_JIT)
def _channel(op: int, constant: bool, X0: np.ndarray, c0: int, X1: np.ndarray, c1: int,
             X2: np.ndarray, c2: int, L0: float, P: np.ndarray, lc: int, weight: np.ndarray,
             r0: int) -> tuple[float, int, int, float, float, int]:
    """One channel's pass: (best ratio, its sample, first sample over, time over, largest |x|
    from r0 on, its sample), as :func:`peak_scan` describes. Called with ``op`` and
    ``constant`` as literals, so that each inlined copy is a loop without those branches."""
    M = X0.shape[0]
    # one positive limit: the largest ratio is at the largest magnitude (no division)
    scaled = constant and M > 0 and L0 > 0
    best, where, first, over, abest, aat = -np.inf, 0, -1, 0.0, -1.0, r0
    for n in range(M):
        v = abs(_value(op, X0, c0, X1, c1, X2, c2, n))
        lim = L0 if constant else P[n, lc]
        r = v if scaled else (v / lim if lim > 0 else (np.inf if v > 0 else 0.0))
        if r > best:
            best, where = r, n
        if v > lim:
            if first < 0:
                first = n
            over += weight[n]
        if n >= r0 and (v > abest or (v != v and abest == abest)):
            abest, aat = v, n
    return (best / L0 if scaled else best), where, first, over, abest, aat


@njit(inline="always", **_JIT)
def _largest(op: int, X0: np.ndarray, c0: int, X1: np.ndarray, c1: int, X2: np.ndarray,
             c2: int, start: int) -> tuple[float, bool]:
    """(largest |x| from sample ``start`` on, NaN ignored; whether a NaN was seen): four
    running maxima side by side, so that no compare waits on the one before."""
    M = X0.shape[0]
    m0 = m1 = m2 = m3 = -1.0
    nan = False
    n = start
    while n + 4 <= M:
        v0 = abs(_value(op, X0, c0, X1, c1, X2, c2, n))
        v1 = abs(_value(op, X0, c0, X1, c1, X2, c2, n + 1))
        v2 = abs(_value(op, X0, c0, X1, c1, X2, c2, n + 2))
        v3 = abs(_value(op, X0, c0, X1, c1, X2, c2, n + 3))
        m0, m1 = (v0 if v0 > m0 else m0), (v1 if v1 > m1 else m1)
        m2, m3 = (v2 if v2 > m2 else m2), (v3 if v3 > m3 else m3)
        nan |= (v0 != v0) | (v1 != v1) | (v2 != v2) | (v3 != v3)
        n += 4
    while n < M:
        v0 = abs(_value(op, X0, c0, X1, c1, X2, c2, n))
        m0 = v0 if v0 > m0 else m0
        nan |= v0 != v0
        n += 1
    return max(max(m0, m1), max(m2, m3)), nan


@njit(inline="always", **_JIT)
def _fast_channel(op: int, X0: np.ndarray, c0: int, X1: np.ndarray, c1: int, X2: np.ndarray,
                  c2: int, L0: float, weight: np.ndarray, r0: int
                  ) -> tuple[bool, float, int, int, float, float, int]:
    """:func:`_channel` for a positive constant limit and no NaN, in passes that need no
    branch per sample: the largest |x| (:func:`_largest`), the first sample reaching it, and
    only where it exceeds the limit the exceedance. First: False when a NaN was seen (the
    caller then takes :func:`_channel`)."""
    M = X0.shape[0]
    big, nan = _largest(op, X0, c0, X1, c1, X2, c2, 0)
    if nan or M == 0:
        return False, 0.0, 0, -1, 0.0, 0.0, 0
    where = 0
    while abs(_value(op, X0, c0, X1, c1, X2, c2, where)) != big:
        where += 1
    first, over = -1, 0.0
    if big > L0:
        for n in range(M):
            if abs(_value(op, X0, c0, X1, c1, X2, c2, n)) > L0:
                first = n if first < 0 else first
                over += weight[n]
    abest, aat = big, where
    if r0 > 0:
        abest, aat = _largest(op, X0, c0, X1, c1, X2, c2, r0)[0], r0
        if abest < 0:           # no sample left: abs_peak's (0, 0)
            abest = -1.0
        else:
            while abs(_value(op, X0, c0, X1, c1, X2, c2, aat)) != abest:
                aat += 1
    return True, big / L0, where, first, over, abest, aat


@njit([types.Tuple((_IC, _FC, _IC, _FC, _FC, _FC, _IC, _FC))(
    _M, _M, _M, _M, _M, _M, _V, types.int64, _CH, _V)], **_JIT)
def peak_scan(V: np.ndarray, A: np.ndarray, J: np.ndarray, tau: np.ndarray, S: np.ndarray,
              P: np.ndarray, weight: np.ndarray, r0: int, channels: np.ndarray, limit: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                         np.ndarray, np.ndarray]:
    """Per channel k (a row of ``channels``, see CHANNEL_COLUMNS) over the M samples (sources
    M×·, any layout; ``weight`` the time each sample stands for, s): with x its value and L its
    limit (``limit[k]``, or column ``channels[k, 7]`` of P per sample),

    (first sample of the largest ratio |x|/L (a zero limit: inf if |x| > 0, else 0), that ratio,
    first sample with |x| > L (−1: none), Σ weight over those, |x| and L at the largest ratio,
    first sample of the largest |x| from sample r0 on (NaN first, as numpy.argmax), that |x|
    (0 when no sample is left)); the last two as
    :func:`~dyn_node.core.compiled.kernels.abs_peak` of the same values."""
    M = len(weight)
    K = channels.shape[0]
    peak_at, first, abs_at = (np.zeros(K, dtype=np.int64), np.full(K, -1, dtype=np.int64),
                              np.zeros(K, dtype=np.int64))
    ratio, above, value, lim_at, abs_peak = (np.zeros(K), np.zeros(K), np.zeros(K), np.zeros(K),
                                             np.zeros(K))
    for k in range(K):
        op, lc = channels[k, 0], channels[k, 7]
        X0 = _pick(channels[k, 1], V, A, J, tau, S, P)
        X1 = _pick(channels[k, 3], V, A, J, tau, S, P)
        X2 = _pick(channels[k, 5], V, A, J, tau, S, P)
        c0, c1, c2 = channels[k, 2], channels[k, 4], channels[k, 6]
        L0 = limit[k]
        res = (False, 0.0, 0, -1, 0.0, 0.0, 0)
        if lc < 0 and L0 > 0:
            if op == ABS:
                res = _fast_channel(ABS, X0, c0, X1, c1, X2, c2, L0, weight, r0)
            elif op == DECEL:
                res = _fast_channel(DECEL, X0, c0, X1, c1, X2, c2, L0, weight, r0)
            elif op == PRODUCT:
                res = _fast_channel(PRODUCT, X0, c0, X1, c1, X2, c2, L0, weight, r0)
            else:
                res = _fast_channel(SUM3, X0, c0, X1, c1, X2, c2, L0, weight, r0)
        if res[0]:
            out = (res[1], res[2], res[3], res[4], res[5], res[6])
        elif op == ABS and lc < 0:
            out = _channel(ABS, True, X0, c0, X1, c1, X2, c2, L0, P, lc, weight, r0)
        elif op == ABS:
            out = _channel(ABS, False, X0, c0, X1, c1, X2, c2, L0, P, lc, weight, r0)
        elif op == DECEL:
            out = _channel(DECEL, lc < 0, X0, c0, X1, c1, X2, c2, L0, P, lc, weight, r0)
        elif op == PRODUCT:
            out = _channel(PRODUCT, lc < 0, X0, c0, X1, c1, X2, c2, L0, P, lc, weight, r0)
        else:
            out = _channel(SUM3, lc < 0, X0, c0, X1, c1, X2, c2, L0, P, lc, weight, r0)
        ratio[k], where, first[k], above[k], abest, abs_at[k] = out
        peak_at[k] = where
        if M:
            value[k] = abs(_value(op, X0, c0, X1, c1, X2, c2, where))
            lim_at[k] = L0 if lc < 0 else P[where, lc]
        abs_peak[k] = abest if abest >= 0 or abest != abest else 0.0
    return peak_at, ratio, first, above, value, lim_at, abs_at, abs_peak
