"""Compiled per-sample loops of the base and grasp laws (Numba, no rclpy).

:mod:`dyn_node.core.check.force_laws` and :mod:`dyn_node.core.check.base_constraints` reduce N×3 wrenches
to a value, a ratio and a time scale (or a payload interval) per sample; in NumPy that is a few
dozen whole-array passes and temporaries per law. Each kernel here is one pass over the samples
with the same arithmetic in the same order, so the results equal the NumPy forms (the tests keep
those as the reference). Conventions as :mod:`dyn_node.core.compiled.kernels`: nogil, cache, NumPy's
x/0, explicit signatures compiled at import (any layout, read-only or not), float64 only.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from dyn_node.core.compiled.jit import _JIT

_f8 = types.float64
_V = types.Array(_f8, 1, "A", readonly=True)
_M = types.Array(_f8, 2, "A", readonly=True)
_C1 = types.Array(_f8, 1, "C")
_C2 = types.Array(_f8, 2, "C")
_pair = types.UniTuple(_f8, 2)


@njit(inline="always", **_JIT)
def _nonfinite_row(X: np.ndarray, n: int) -> bool:
    """Any entry of row n NaN or ±inf: x·0 is NaN exactly then (one sum, no branch per entry)."""
    z = 0.0
    for j in range(X.shape[1]):
        z += X[n, j] * 0.0
    return z != 0.0


@njit(inline="always", **_JIT)
def _dot_row(X: np.ndarray, Y: np.ndarray, n: int) -> float:
    acc = 0.0
    for j in range(X.shape[1]):
        acc += X[n, j] * Y[n, j]
    return acc


@njit(inline="always", **_JIT)
def _norm_scale(A: float, B: float, C: float) -> float:
    """Smallest k with A s² + 2B s + C ≤ 0 on (0, 1/k²] (force_laws._norm_time_scale's case
    analysis, row by row)."""
    if not C <= 0:
        return np.inf
    if A == 0:
        return 0.0
    if not A > 0:
        return np.inf
    sq = math.sqrt(B * B - A * C)
    s_max = (sq - B) / A if B <= 0 else -C / (B + sq)
    return 1.0 / math.sqrt(s_max) if s_max > 0 else np.inf


@njit([types.UniTuple(_C1, 4)(_M, _M, _f8)], **_JIT)
def norm_rows(a: np.ndarray, b: np.ndarray, L: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(|a + b|, |a|, |a + b| / L (0 where the value is 0), k) per row of N×d a, b: the
    :func:`force_laws.norm_law` arrays; NaN in all four where a row holds a non-finite entry."""
    N, d = a.shape
    value, static, ratio, k = (np.empty(N), np.empty(N), np.empty(N), np.empty(N))
    for n in range(N):
        if _nonfinite_row(a, n) or _nonfinite_row(b, n):
            value[n] = static[n] = ratio[n] = k[n] = np.nan
            continue
        v2 = 0.0
        for j in range(d):
            x = a[n, j] + b[n, j]
            v2 += x * x
        an = math.sqrt(_dot_row(a, a, n))
        v = math.sqrt(v2)
        value[n], static[n] = v, an
        ratio[n] = 0.0 if v == 0 else v / L
        k[n] = _norm_scale(_dot_row(b, b, n), _dot_row(a, b, n), (an - L) * (an + L))
    return value, static, ratio, k


@njit([types.UniTuple(_C1, 3)(_M, _M, _f8)], **_JIT)
def norm_band_terms(a: np.ndarray, b: np.ndarray, L: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(|b|², a·b, |a|² − L² as (|a| − L)(|a| + L)) per row: |a + m·b|² − L² in m."""
    N = a.shape[0]
    A, B, C = np.empty(N), np.empty(N), np.empty(N)
    for n in range(N):
        an = math.sqrt(_dot_row(a, a, n))
        A[n], B[n], C[n] = _dot_row(b, b, n), _dot_row(a, b, n), (an - L) * (an + L)
    return A, B, C


@njit([types.Tuple((_C1, _C1, types.boolean))(_V, _f8, types.int64)], **_JIT)
def power_rows(v: np.ndarray, L: float, power: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """(v / L, (v / L)^(1/power), whether any v < 0) for :func:`force_laws.power_law`; the
    powers 1 and 2 exactly as NumPy's ``**`` does them (identity, sqrt)."""
    N = len(v)
    ratio, k, negative = np.empty(N), np.empty(N), False
    for n in range(N):
        r = v[n] / L
        negative |= v[n] < 0
        ratio[n] = r
        k[n] = r if power == 1 else (math.sqrt(r) if power == 2 else r ** (1.0 / power))
    return ratio, k, negative


@njit([types.UniTuple(_C2, 2)(_M, _M, _V)], **_JIT)
def payload_wrench_rows(position: np.ndarray, acceleration: np.ndarray, gravity: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """(a − g, c × (a − g)) per row of N×3 point positions c and accelerations a."""
    N = position.shape[0]
    f, m = np.empty((N, 3)), np.empty((N, 3))
    for n in range(N):
        f0, f1, f2 = (acceleration[n, 0] - gravity[0], acceleration[n, 1] - gravity[1],
                      acceleration[n, 2] - gravity[2])
        c0, c1, c2 = position[n, 0], position[n, 1], position[n, 2]
        f[n, 0], f[n, 1], f[n, 2] = f0, f1, f2
        m[n, 0], m[n, 1], m[n, 2] = c1 * f2 - c2 * f1, c2 * f0 - c0 * f2, c0 * f1 - c1 * f0
    return f, m


@njit([_C1(_M, types.boolean)], **_JIT)
def row_squares(X: np.ndarray, root: bool) -> np.ndarray:
    """|x|² per row of N×3 X (its square root with ``root``), summed as (x₀² + x₂²) + x₁²: the
    order NumPy's einsum("ij,ij->i") takes here, so the task laws' values did not move."""
    N = X.shape[0]
    out = np.empty(N)
    for n in range(N):
        a, b, c = X[n, 0], X[n, 1], X[n, 2]
        s = (a * a + c * c) + b * b
        out[n] = math.sqrt(s) if root else s
    return out


@njit([_C2(_M, _M, _V, _V, _M, _V)], **_JIT)
def task_reaction(R: np.ndarray, position: np.ndarray, point: np.ndarray, W: np.ndarray,
                  R0: np.ndarray, r0: np.ndarray) -> np.ndarray:
    """Per sample (N×9 row-major frame-to-world R, N×3 world ``position`` of the frame's
    ``point``): the wrench W ([force; torque], frame axes, at the frame origin) in world axes,
    its moment taken about the world origin then about r0, both in the axes of R0 (N×6)."""
    N = R.shape[0]
    out = np.empty((N, 6))
    for n in range(N):
        Rn = R[n]
        ox = position[n, 0] - (Rn[0] * point[0] + Rn[1] * point[1] + Rn[2] * point[2])
        oy = position[n, 1] - (Rn[3] * point[0] + Rn[4] * point[1] + Rn[5] * point[2])
        oz = position[n, 2] - (Rn[6] * point[0] + Rn[7] * point[1] + Rn[8] * point[2])
        fx = Rn[0] * W[0] + Rn[1] * W[1] + Rn[2] * W[2]
        fy = Rn[3] * W[0] + Rn[4] * W[1] + Rn[5] * W[2]
        fz = Rn[6] * W[0] + Rn[7] * W[1] + Rn[8] * W[2]
        # n = R·T + o × f − r0 × f
        nx = Rn[0] * W[3] + Rn[1] * W[4] + Rn[2] * W[5] + (oy * fz - oz * fy)
        ny = Rn[3] * W[3] + Rn[4] * W[4] + Rn[5] * W[5] + (oz * fx - ox * fz)
        nz = Rn[6] * W[3] + Rn[7] * W[4] + Rn[8] * W[5] + (ox * fy - oy * fx)
        nx, ny, nz = (nx - (r0[1] * fz - r0[2] * fy), ny - (r0[2] * fx - r0[0] * fz),
                      nz - (r0[0] * fy - r0[1] * fx))
        for i in range(3):
            out[n, i] = R0[0, i] * fx + R0[1, i] * fy + R0[2, i] * fz
            out[n, 3 + i] = R0[0, i] * nx + R0[1, i] * ny + R0[2, i] * nz
    return out


@njit([_C2(_M, _V)], **_JIT)
def tangential(f: np.ndarray, n: np.ndarray) -> np.ndarray:
    """f − (f·n)·n per row of N×3 f, for the unit axis n."""
    N = f.shape[0]
    out = np.empty((N, 3))
    for i in range(N):
        fn = f[i, 0] * n[0] + f[i, 1] * n[1] + f[i, 2] * n[2]
        for j in range(3):
            out[i, j] = f[i, j] - fn * n[j]
    return out


@njit([_C2(_M, _M)], **_JIT)
def rotate_back(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rᵀ·v per sample for N×9 row-major rotations R and N×3 (or 1×3, shared) vectors v."""
    N = R.shape[0]
    out = np.empty((N, 3))
    shared = v.shape[0] == 1
    for n in range(N):
        r = 0 if shared else n
        for i in range(3):
            out[n, i] = R[n, i] * v[r, 0] + R[n, 3 + i] * v[r, 1] + R[n, 6 + i] * v[r, 2]
    return out


@njit(inline="always", **_JIT)
def _edge(N: float, P0: float, P1: float, normals: np.ndarray, offsets: np.ndarray,
          i: int) -> float:
    """b_i·N − n_i·P: ≥ 0 where the centre of pressure P/N (N > 0) is inside edge i."""
    return N * offsets[i] - (P0 * normals[i, 0] + P1 * normals[i, 1])


@njit(inline="always", **_JIT)
def _gauge(N: float, P0: float, P1: float, normals: np.ndarray, centroid: np.ndarray,
           reach: np.ndarray) -> float:
    """SupportPolygon.gauge of the centre of pressure P/N; inf at lift-off (N ≤ 0)."""
    if not N > 0:
        return np.inf
    d0, d1 = P0 / N - centroid[0], P1 / N - centroid[1]
    g, nan = -np.inf, False
    for i in range(len(reach)):
        x = (d0 * normals[i, 0] + d1 * normals[i, 1]) / reach[i]
        nan |= x != x                   # NaN wins, as in np.max; no branch in the loop
        g = x if x > g else g
    return np.nan if nan else (g if g > 0.0 else 0.0)


@njit(inline="always", **_JIT)
def _tipping_scale(Ns: float, Ps0: float, Ps1: float, Nd: float, Pd0: float, Pd1: float,
                   normals: np.ndarray, offsets: np.ndarray) -> float:
    """force_laws' tipping time scale for one sample: columns [N, edges] of alpha (static) and
    beta (dynamic) must be ≥ 0 (N > 0) near s = 0⁺, then s ≤ min alpha / −beta over beta < 0."""
    near0 = Ns > 0 or (Ns == 0 and Nd > 0)
    s_max = Ns / -Nd if Nd < 0 else np.inf
    for i in range(len(offsets)):
        al = _edge(Ns, Ps0, Ps1, normals, offsets, i)
        be = _edge(Nd, Pd0, Pd1, normals, offsets, i)
        near0 = near0 and (al > 0 or (al == 0 and be >= 0))
        bound = al / -be if be < 0 else np.inf
        if not math.isnan(s_max) and (math.isnan(bound) or bound < s_max):
            s_max = bound          # NaN sticky, as np.min
    if not near0:
        return np.inf
    return 0.0 if math.isinf(s_max) else 1.0 / math.sqrt(s_max)


@njit([types.UniTuple(_C1, 4)(_M, _M, _M, _M, _V, _V, _M, _V, _V, _V)], **_JIT)
def tipping_rows(Fs: np.ndarray, Fd: np.ndarray, Ms: np.ndarray, Md: np.ndarray,
                 weight: np.ndarray, weight_moment: np.ndarray, normals: np.ndarray,
                 offsets: np.ndarray, centroid: np.ndarray, reach: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(k, gauge at k = 1, still gauge, normal force N at k = 1) per sample of the reaction
    F = Fs + s·Fd, M = Ms + s·Md on the robot; the floor's wrench subtracts the base's
    ``weight`` and its moment ``weight_moment`` (c_b × m_b·g) from the static part. NaN in all
    four where a row (after that subtraction) holds a non-finite entry."""
    N = Fs.shape[0]
    k, ratio, still, normal = np.empty(N), np.empty(N), np.empty(N), np.empty(N)
    for n in range(N):
        fs2 = Fs[n, 2] - weight[2]
        ms0, ms1 = Ms[n, 0] - weight_moment[0], Ms[n, 1] - weight_moment[1]
        z = 0.0                  # as _nonfinite_row, of the floor wrench's static part too
        for j in range(3):
            z += (Fs[n, j] - weight[j]) * 0.0 + (Ms[n, j] - weight_moment[j]) * 0.0
            z += Fd[n, j] * 0.0 + Md[n, j] * 0.0
        if z != 0.0:
            k[n] = ratio[n] = still[n] = normal[n] = np.nan
            continue
        Ps0, Ps1, Pd0, Pd1 = -ms1, ms0, -Md[n, 1], Md[n, 0]
        k[n] = _tipping_scale(fs2, Ps0, Ps1, Fd[n, 2], Pd0, Pd1, normals, offsets)
        N1 = fs2 + Fd[n, 2]
        normal[n] = N1
        ratio[n] = _gauge(N1, Ps0 + Pd0, Ps1 + Pd1, normals, centroid, reach)
        still[n] = _gauge(fs2, Ps0, Ps1, normals, centroid, reach)
    return k, ratio, still, normal


@njit([_C2(_M, _M, _M, _M, _V, _V)], **_JIT)
def centre_of_pressure(Fs: np.ndarray, Fd: np.ndarray, Ms: np.ndarray, Md: np.ndarray,
                       weight: np.ndarray, weight_moment: np.ndarray) -> np.ndarray:
    """The floor's centre of pressure (−M_y, M_x) / N at k = 1 per sample (N×2; NaN where
    N = F_z ≤ 0), arguments as :func:`tipping_rows`; rows with non-finite entries included."""
    N = Fs.shape[0]
    cop = np.empty((N, 2))
    for n in range(N):
        Nz = (Fs[n, 2] - weight[2]) + Fd[n, 2]
        if Nz > 0:
            cop[n, 0] = (-(Ms[n, 1] - weight_moment[1]) + -Md[n, 1]) / Nz
            cop[n, 1] = ((Ms[n, 0] - weight_moment[0]) + Md[n, 0]) / Nz
        else:
            cop[n, 0] = cop[n, 1] = np.nan
    return cop


@njit(inline="always", **_JIT)
def _band_update(al: float, be: float, strict: bool, lo: float, hi: float
                 ) -> tuple[bool, float, float]:
    """One element of base_constraints._linear_band: (blocked, lo, hi), NaN roots sticky as in
    np.max / np.min."""
    if be == 0:
        return al < 0 or (strict and al <= 0), lo, hi
    root = -al / be
    if be > 0 and not math.isnan(lo) and (math.isnan(root) or root > lo):
        lo = root
    elif be < 0 and not math.isnan(hi) and (math.isnan(root) or root < hi):
        hi = root
    return False, lo, hi


@njit([_pair(_M, _M, _M, _M, _V, _V, _M, _V)], **_JIT)
def tipping_mass_band(F: np.ndarray, M: np.ndarray, f1: np.ndarray, m1: np.ndarray,
                      weight: np.ndarray, weight_moment: np.ndarray, normals: np.ndarray,
                      offsets: np.ndarray) -> tuple[float, float]:
    """The interval of extra payload m with N > 0 and every edge ≥ 0 at every sample, for the
    reaction (F, M) at k = 1 and (f1, m1) per kg (lo > hi when none): the floor wrench's
    columns alpha + m·beta, alpha from (F − weight, M − weight_moment), beta from (f1, m1)."""
    lo, hi, blocked = -np.inf, np.inf, False
    for n in range(F.shape[0]):
        Na = F[n, 2] - weight[2]
        Pa0, Pa1 = -(M[n, 1] - weight_moment[1]), M[n, 0] - weight_moment[0]
        Nb, Pb0, Pb1 = f1[n, 2], -m1[n, 1], m1[n, 0]
        b, lo, hi = _band_update(Na, Nb, True, lo, hi)
        blocked = blocked or b
        for i in range(len(offsets)):
            b, lo, hi = _band_update(_edge(Na, Pa0, Pa1, normals, offsets, i),
                                     _edge(Nb, Pb0, Pb1, normals, offsets, i), False, lo, hi)
            blocked = blocked or b
    return (np.inf, -np.inf) if blocked else (lo, hi)
