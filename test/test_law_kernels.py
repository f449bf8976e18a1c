"""The compiled base and grasp laws (dyn_node.core.compiled.law_kernels, through force_laws and
base_constraints) against the NumPy forms they replace, kept here as the reference: random rows
and the edge cases (zeros, tangency C = 0, s_max = 0, NaN and inf rows, lift-off N ≤ 0, a centre
of pressure on an edge, a band blocked by a zero coefficient)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dyn_node.core.check import base_constraints as BC
from dyn_node.core.check import force_laws as F
from dyn_node.core.compiled import kernels, law_kernels

GRAVITY = np.array([0.0, 0.0, -9.81])
SQUARE = F.SupportPolygon.from_ccw(np.array([[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]]))
HEXAGON = F.SupportPolygon.from_ccw(np.column_stack([np.cos(np.arange(6) * np.pi / 3) * 0.4 + 0.1,
                                                     np.sin(np.arange(6) * np.pi / 3) * 0.3]))


# --- the NumPy reference (the code the kernels replace) ---------------------------------------

def floor_wrench(force: np.ndarray, moment: np.ndarray, *, base_mass: float,
                 base_com: np.ndarray, gravity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The floor's push on the still base (force, moment about the root origin; N×3 each) from
    the base's push on the robot: F − m_b·g and M − c_b × m_b·g."""
    weight, weight_moment = F.base_weight(base_mass=base_mass, base_com=base_com, gravity=gravity)
    return force - weight, moment - weight_moment


def floor_edges(force: np.ndarray, moment: np.ndarray, polygon: F.SupportPolygon
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, P = N·p, edges) of a floor wrench (N×3 each): the normal force N = F_z, the centre of
    pressure p = (−M_y, M_x) / N times N, and the columns [N, b_i·N − n_i·P] that are ≥ 0 (N
    > 0) exactly where p stands inside the polygon. Linear in the wrench: so in s, and in the
    payload mass."""
    N, P = force[:, 2], np.column_stack([-moment[:, 1], moment[:, 0]])
    return N, P, np.column_stack([N, N[:, None] * polygon.offsets - P @ polygon.normals.T])


def _finite_rows(*arrays: np.ndarray) -> np.ndarray:
    ok = np.ones(len(arrays[0]), dtype=bool)
    for a in arrays:
        ok &= np.isfinite(a).reshape(len(a), -1).all(axis=1)
    return ok


def _norm_time_scale(a: np.ndarray, b: np.ndarray, L: float) -> np.ndarray:
    A = np.einsum("ij,ij->i", b, b)
    B = np.einsum("ij,ij->i", a, b)
    an = np.linalg.norm(a, axis=1)
    C = (an - L) * (an + L)
    k = np.full(len(a), np.inf)
    k[(C <= 0) & (A == 0)] = 0.0
    m = (C <= 0) & (A > 0)
    Am, Bm, Cm = A[m], B[m], C[m]
    sq = np.sqrt(Bm * Bm - Am * Cm)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_max = np.where(Bm <= 0, (sq - Bm) / Am, -Cm / (Bm + sq))
    k[m] = np.where(s_max > 0, 1.0 / np.sqrt(np.where(s_max > 0, s_max, 1.0)), np.inf)
    return k


def norm_law_ref(a: np.ndarray, b: np.ndarray, L: float) -> tuple[np.ndarray, ...]:
    ok = _finite_rows(a, b)
    with np.errstate(over="ignore", invalid="ignore"):
        value = np.linalg.norm(a + b, axis=1)
        static_value = np.linalg.norm(a, axis=1)
        k = np.full(len(a), np.nan)
        k[ok] = _norm_time_scale(a[ok], b[ok], L)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(value == 0, 0.0, value / L)
    value[~ok] = static_value[~ok] = ratio[~ok] = np.nan
    return value, static_value, ratio, k


def tangential_ref(f: np.ndarray, n: np.ndarray) -> np.ndarray:
    return f - np.outer(f @ n, n)


def _tipping_time_scale(alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    near0 = (alpha > 0) | ((alpha == 0) & (beta >= 0))
    near0[:, 0] = (alpha[:, 0] > 0) | ((alpha[:, 0] == 0) & (beta[:, 0] > 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where(beta < 0, alpha / -beta, np.inf)
        s_max = bound.min(axis=1)
        k = np.where(np.isinf(s_max), 0.0, 1.0 / np.sqrt(s_max))
    return np.where(near0.all(axis=1), k, np.inf)


def tipping_law_ref(Fs, Fd, Ms, Md, polygon, mb, cb) -> tuple[np.ndarray, ...]:
    Fs, Ms = floor_wrench(Fs, Ms, base_mass=mb, base_com=cb, gravity=GRAVITY)
    ok = _finite_rows(Fs, Fd, Ms, Md)
    with np.errstate(invalid="ignore", over="ignore"):
        (Ns, Ps, alpha), (Nd, Pd, beta) = (floor_edges(Fs, Ms, polygon),
                                           floor_edges(Fd, Md, polygon))
        k = np.full(len(Fs), np.nan)
        k[ok] = _tipping_time_scale(alpha[ok], beta[ok])

    def gauge(N: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        up = N > 0
        cop = np.full(P.shape, np.nan)
        cop[up] = P[up] / N[up, None]
        g = np.full(len(N), np.inf)
        with np.errstate(invalid="ignore"):
            g[up] = polygon.gauge(cop[up])
        g[~ok] = np.nan
        return g, cop

    ratio, cop = gauge(Ns + Nd, Ps + Pd)
    static_ratio, _ = gauge(Ns, Ps)
    return k, ratio, static_ratio, np.where(ok, Ns + Nd, np.nan), cop


def linear_band_ref(alpha: np.ndarray, beta: np.ndarray, strict: np.ndarray) -> tuple:
    with np.errstate(divide="ignore", invalid="ignore"):
        root = -alpha / beta
    if np.any((beta == 0) & ((alpha < 0) | (strict & (alpha <= 0)))):
        return math.inf, -math.inf
    return (float(np.max(root[beta > 0], initial=-math.inf)),
            float(np.min(root[beta < 0], initial=math.inf)))


def tipping_band_ref(F1, M1, f1, m1, polygon, mb, cb) -> tuple:
    Ff, Mf = floor_wrench(F1, M1, base_mass=mb, base_com=cb, gravity=GRAVITY)
    alpha = floor_edges(Ff, Mf, polygon)[2]
    beta = floor_edges(f1, m1, polygon)[2]
    strict = np.zeros(alpha.shape, dtype=bool)
    strict[:, 0] = True
    return linear_band_ref(alpha, beta, strict)


def quadratic_norm_band_ref(a: np.ndarray, b: np.ndarray, L: float, *, reach: float = 1e3,
                            grid: int = 100_001) -> tuple:
    """The masses m with |a + m·b| ≤ L at every row, found by scanning m directly (no quadratic
    formula): the feasible points of a grid over [−reach, reach], each end then bisected on the
    predicate to ~1e-15 relative; (inf, −inf) when no grid point is feasible."""
    def ok(m: np.ndarray) -> np.ndarray:
        m = np.atleast_1d(m)
        return np.all(np.linalg.norm(a[None] + m[:, None, None] * b[None], axis=2) <= L, axis=1)

    ms = np.linspace(-reach, reach, grid)
    good = np.concatenate([ok(chunk) for chunk in np.array_split(ms, 200)])
    if not good.any():
        return math.inf, -math.inf
    idx = np.flatnonzero(good)
    assert np.all(np.diff(idx) == 1), "the feasible masses are one interval"
    assert 0 < idx[0] and idx[-1] < grid - 1, "the band lies inside the scanned range"

    def edge(inside: float, outside: float) -> float:
        for _ in range(200):
            mid = 0.5 * (inside + outside)
            if mid in (inside, outside):
                break
            inside, outside = (mid, outside) if ok(mid)[0] else (inside, mid)
        return inside

    return edge(ms[idx[0]], ms[idx[0] - 1]), edge(ms[idx[-1]], ms[idx[-1] + 1])


def _same(x, y) -> None:
    """Equal to 1e-12 relative, NaN and ±inf at the same places (the arithmetic order is the
    same; a BLAS product may round its last bit differently)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    assert x.shape == y.shape
    np.testing.assert_array_equal(np.isnan(x), np.isnan(y))
    np.testing.assert_array_equal(np.where(np.isinf(x), x, 0), np.where(np.isinf(y), y, 0))
    np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-300)


# --- norm and grasp -----------------------------------------------------------------------------

def _norm_rows(rng: np.random.Generator, n: int, L: float) -> tuple[np.ndarray, np.ndarray]:
    a = rng.normal(size=(n, 3)) * L * rng.uniform(0.2, 1.5, (n, 1))
    b = rng.normal(size=(n, 3)) * L * 10.0 ** rng.uniform(-2, 1, (n, 1))
    # edges: zeros, no motion, tangency |a| = L with b inward / along / outward (s_max = 0),
    # NaN and inf rows, b opposing a (a feasible band in between)
    a[0], b[0] = 0.0, 0.0
    b[1] = 0.0
    a[2:5] = [L * 0.6, L * 0.8, 0.0]
    b[2], b[3], b[4] = -a[2], [0.0, 0.0, 1.0], a[4]
    a[5, 1], b[6, 2], a[7, 0], b[8, 0] = np.nan, np.nan, np.inf, -np.inf
    b[9:20] = -2.5 * a[9:20]
    return a, b


@pytest.mark.parametrize("seed", range(3))
def test_norm_law_equals_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    L = 40.0
    a, b = _norm_rows(rng, 400, L)
    r = F.norm_law(a, b, L)
    for got, ref in zip((r.value, r.static_value, r.ratio, r.time_scale), norm_law_ref(a, b, L)):
        _same(got, ref)
    # the edge rows hold the cases named
    assert r.time_scale[0] == 0.0 and r.ratio[0] == 0.0
    assert r.time_scale[3] == math.inf and r.time_scale[4] == math.inf       # s_max = 0, C > 0
    assert 0 < r.time_scale[2] < math.inf
    assert all(math.isnan(r.time_scale[i]) and math.isnan(r.value[i]) for i in range(5, 9))
    assert np.count_nonzero(np.isinf(r.time_scale)) > 20
    assert np.count_nonzero(np.isfinite(r.time_scale) & (r.time_scale > 0)) > 100


def test_norm_law_zero_limit_and_layouts_equal_reference():
    rng = np.random.default_rng(5)
    a, b = _norm_rows(rng, 60, 1.0)
    a[20:30] = 0.0                                       # C = 0 at L = 0: only A = 0 is feasible
    b[25:30] = 0.0
    for L in (0.0, 1.0):
        ref = norm_law_ref(a, b, L)
        fa, fb = np.asfortranarray(a), b[::-1][::-1].copy()
        fa.setflags(write=False)
        r = F.norm_law(fa, fb, L)
        for got, x in zip((r.value, r.static_value, r.ratio, r.time_scale), ref):
            _same(got, x)
    r0 = F.norm_law(a, b, 0.0)
    assert np.all(r0.time_scale[25:30] == 0.0) and np.all(np.isinf(r0.time_scale[20:25]))
    # d = 6 (any width) and the strided slice the base kinds pass
    w = rng.normal(size=(30, 6))
    r = F.norm_law(w[:, :3], w[:, 3:], 2.0)
    _same(r.time_scale, norm_law_ref(w[:, :3], w[:, 3:], 2.0)[3])


@pytest.mark.parametrize("seed", range(2))
def test_grasp_slip_law_equals_numpy_reference(seed):
    rng = np.random.default_rng(20 + seed)
    n = 300
    R = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
    acc = rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-1, 1.5, (n, 1))
    acc[3] = np.nan
    g_ref = np.einsum("nji,j->ni", R, GRAVITY)
    a_ref = np.einsum("nji,nj->ni", R, acc)
    _same(F.gravity_in_frame(R, GRAVITY), g_ref)
    np.testing.assert_allclose(F.gravity_in_frame(R, GRAVITY)[7], R[7].T @ GRAVITY, rtol=1e-14)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    force = F.payload_grasp_force(1.7, a_ref, g_ref)
    _same(F.tangential(force.static, axis), tangential_ref(force.static, axis))
    r = F.grasp_slip_law(force, normal_axis=axis, limit=20.0)
    ref = norm_law_ref(tangential_ref(force.static, axis), tangential_ref(force.dynamic, axis),
                       20.0)
    for got, x in zip((r.value, r.static_value, r.ratio, r.time_scale), ref):
        _same(got, x)
    assert math.isnan(r.time_scale[3])


def test_grasp_force_rotation_equals_einsum():
    rng = np.random.default_rng(3)
    R = np.linalg.qr(rng.normal(size=(40, 3, 3)))[0]
    acc = rng.normal(size=(40, 3))
    point = type("P", (), {"linear_acceleration": acc})()
    f = BC.grasp_force(point, R, GRAVITY, 2.0)
    _same(f.dynamic, 2.0 * np.einsum("nji,nj->ni", R, acc))
    _same(f.static, -2.0 * np.einsum("nji,j->ni", R, GRAVITY))


# --- tipping ------------------------------------------------------------------------------------

def _reaction_rows(rng: np.random.Generator, n: int, polygon: F.SupportPolygon):
    m = 15.0
    c = np.column_stack([rng.uniform(-0.6, 0.6, (n, 2)), rng.uniform(0.2, 1.0, n)])
    c[::2, :2] *= 2.5                    # every other robot CoM far out: statically tipped
    Fs = np.tile(-m * GRAVITY, (n, 1)) + rng.normal(size=(n, 3)) * 5
    Ms = np.cross(c, Fs)
    Fd = rng.normal(size=(n, 3)) * m * 10.0 ** rng.uniform(-0.5, 1.5, (n, 1))
    Md = np.cross(c, Fd) + rng.normal(size=(n, 3)) * 5
    Md[:n // 4] = -2.0 * Ms[:n // 4] * rng.uniform(1.0, 3.0, (n // 4, 1))   # band cases
    Fd[:n // 4] = 0.0
    # lift-off: static N ≤ 0 (robot pulled up), N = 0 exactly with Nd > 0 and < 0, NaN and inf
    Fs[n // 4, 2], Fs[n // 4 + 1, 2] = -500.0, 0.0
    Fd[n // 4 + 1, 2], Fd[n // 4 + 2, 2] = 3.0, -1e4
    Fs[n // 4 + 3, 2] = 0.0
    Fd[n // 4 + 3, 2] = -1.0
    Ms[n // 4 + 4, 0], Fd[n // 4 + 5, 1], Md[n // 4 + 6, 2] = np.nan, np.inf, -np.inf
    # no wrench at all (N = 0 with mb = 0 at every k: lift-off, the strict normal column)
    Fs[n // 4 + 9] = Fd[n // 4 + 9] = Ms[n // 4 + 9] = Md[n // 4 + 9] = 0.0
    # centre of pressure on the centroid and exactly on the square's x = 0.3 edge (mb = 0)
    Ms[n // 4 + 7] = np.cross(np.append(polygon.centroid, 0), Fs[n // 4 + 7])
    Fs[n // 4 + 8], Ms[n // 4 + 8], Fd[n // 4 + 8], Md[n // 4 + 8] = (
        [0, 0, 100.0], [0, -30.0, 0], [0, 0, 10.0], [0, -3.0, 0])
    return Fs, Fd, Ms, Md


@pytest.mark.parametrize("polygon", [SQUARE, HEXAGON], ids=["square", "hexagon"])
@pytest.mark.parametrize("mb", [0.0, 20.0])
def test_tipping_law_equals_numpy_reference(polygon, mb):
    rng = np.random.default_rng(int(mb) + len(polygon.offsets))
    n = 400
    Fs, Fd, Ms, Md = _reaction_rows(rng, n, polygon)
    cb = np.array([0.02, -0.03, 0.1])
    r = F.tipping_law(F.ScaledWrench(Fs, Fd, Ms, Md), polygon=polygon, base_mass=mb,
                      base_com=cb, gravity=GRAVITY)
    ref = tipping_law_ref(Fs, Fd, Ms, Md, polygon, mb, cb)
    got = (r.time_scale, r.ratio, r.static_value, r.normal_force, r.centre_of_pressure)
    for g, x in zip(got, ref):
        _same(g, x)
    np.testing.assert_array_equal(r.value, r.ratio)
    i = n // 4
    assert math.isinf(r.time_scale[i]) and math.isinf(r.static_value[i])    # lifted off still
    assert all(math.isnan(r.time_scale[j]) for j in (i + 4, i + 5, i + 6))
    assert math.isinf(r.time_scale[i + 9]) == (mb == 0)
    finite = np.isfinite(r.time_scale) & (r.time_scale > 0)
    assert np.count_nonzero(finite) > 30 and np.count_nonzero(np.isinf(r.time_scale)) > 30


def test_tipping_on_the_edge_and_on_the_centroid():
    rng = np.random.default_rng(1)
    Fs, Fd, Ms, Md = _reaction_rows(rng, 40, SQUARE)
    r = F.tipping_law(F.ScaledWrench(Fs, Fd, Ms, Md), polygon=SQUARE, base_mass=0.0,
                      base_com=np.zeros(3), gravity=GRAVITY)
    assert r.ratio[18] == 1.0 and r.static_value[18] == 1.0      # x = 0.3 at every k
    assert r.time_scale[18] == 0.0                                # alpha = 0, beta = 0: holds
    assert r.static_value[17] == pytest.approx(0.0, abs=1e-15)


@pytest.mark.parametrize("seed", range(3))
def test_tipping_payload_band_equals_numpy_reference(seed):
    rng = np.random.default_rng(40 + seed)
    n = 300
    F1 = np.tile(-12.0 * GRAVITY, (n, 1)) + rng.normal(size=(n, 3)) * 10
    M1 = np.cross(np.column_stack([rng.uniform(-0.1, 0.1, (n, 2)), np.full(n, 0.5)]), F1)
    a_c = rng.normal(size=(n, 3)) * 2.0
    c = np.column_stack([rng.uniform(-0.4, 0.4, (n, 2)), np.full(n, 0.8)])
    f1 = a_c - GRAVITY
    m1 = np.cross(c, f1)
    cb = np.array([0.0, 0.01, 0.1])
    for poly in (SQUARE, HEXAGON):
        weight = F.base_weight(base_mass=8.0, base_com=cb, gravity=GRAVITY)
        got = law_kernels.tipping_mass_band(F1, M1, f1, m1, *weight, poly.normals, poly.offsets)
        ref = tipping_band_ref(F1, M1, f1, m1, poly, 8.0, cb)
        _same(got, ref)
        assert ref[0] < ref[1] and math.isfinite(ref[0]) and math.isfinite(ref[1])
    # a zero per-kg row: blocked where a column is < 0, or N ≤ 0 (strict); free where N > 0 and
    # the edges ≥ 0 (the base's weight at the origin: CoP at the origin); NaN roots are sticky
    weight = F.base_weight(base_mass=8.0, base_com=np.zeros(3), gravity=GRAVITY)
    for Na, blocked in ((0.0, True), (-1.0, True), (1.0, False), (math.nan, False)):
        f, m, FF, MM = f1.copy(), m1.copy(), F1.copy(), M1.copy()
        f[5] = m[5] = MM[5] = 0.0
        FF[5] = [0.0, 0.0, Na - 8.0 * 9.81]
        got = law_kernels.tipping_mass_band(FF, MM, f, m, *weight, SQUARE.normals,
                                            SQUARE.offsets)
        with np.errstate(invalid="ignore"):
            ref = tipping_band_ref(FF, MM, f, m, SQUARE, 8.0, np.zeros(3))
        _same(got, ref)
        assert (got == (math.inf, -math.inf)) == blocked, Na
    f = f1.copy()
    f[9, 2] = np.nan
    got = law_kernels.tipping_mass_band(F1, M1, f, m1, *weight, SQUARE.normals, SQUARE.offsets)
    assert np.isnan(got).tolist() == [False, False]   # beta NaN: no root, no block
    FF = F1.copy()
    FF[9, 2] = np.nan
    got = law_kernels.tipping_mass_band(FF, M1, f1, m1, *weight, SQUARE.normals, SQUARE.offsets)
    _same(got, tipping_band_ref(FF, M1, f1, m1, SQUARE, 8.0, np.zeros(3)))
    assert math.isnan(got[0])


def test_quadratic_norm_band_equals_a_direct_scan_of_the_mass():
    rng = np.random.default_rng(8)
    a, b = _norm_rows(rng, 200, 30.0)
    a, b = a[9:], b[9:]
    # rows 0-10 here have b = −2.5·a: a band around m = 0.4 even where all rows leave none
    for rows, L in ((slice(None), 300.0), (slice(0, 11), 30.0), (slice(None), 30.0),
                    (slice(None), 0.0)):
        got = BC._quadratic_norm_band(a[rows], b[rows], L)
        ref = quadratic_norm_band_ref(a[rows], b[rows], L)
        if math.isinf(ref[0]):
            assert got[0] > got[1], (L, got)          # empty: no scanned mass holds
        else:
            np.testing.assert_allclose(got, ref, rtol=1e-9, atol=0)
            assert ref[0] < ref[1]


# --- power law and the per-kg payload wrench ---------------------------------------------------

@pytest.mark.parametrize("power", [1, 2, 3])
def test_power_law_equals_numpy_reference(power):
    rng = np.random.default_rng(power)
    v = np.abs(rng.normal(size=500)) * 10.0 ** rng.uniform(-3, 3, 500)
    v[:4] = [0.0, np.nan, np.inf, 2.5]
    r = F.power_law(v, 2.5, power=power)
    _same(r.ratio, v / 2.5)
    _same(r.time_scale, (v / 2.5) ** (1.0 / power))
    assert r.time_scale[3] == 1.0 and r.time_scale[0] == 0.0 and math.isnan(r.time_scale[1])
    with pytest.raises(ValueError, match="magnitudes"):
        F.power_law(np.array([1.0, -1e-300]), 1.0, power=power)


def test_payload_wrench_and_base_weight_equal_np_cross():
    rng = np.random.default_rng(4)
    c, a = rng.normal(size=(2, 100, 3))
    point = type("P", (), {"position": c, "linear_acceleration": a})()
    f, m = BC.unit_payload_wrench(point, GRAVITY)
    _same(f, a - GRAVITY)
    _same(m, np.cross(c, a - GRAVITY))
    w, wm = F.base_weight(base_mass=7.5, base_com=[0.1, -0.2, 0.3], gravity=[0.5, -0.4, -9.8])
    _same(w, 7.5 * np.array([0.5, -0.4, -9.8]))
    _same(wm, np.cross([0.1, -0.2, 0.3], w))


# --- compilation ----------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["norm_rows", "norm_band_terms", "tangential", "rotate_back",
                                  "tipping_rows", "centre_of_pressure", "tipping_mass_band",
                                  "power_rows", "payload_wrench_rows"])
def test_kernels_are_compiled_once_and_never_recompile(name):
    kernel = getattr(law_kernels, name)
    assert len(kernel.signatures) == 1 and not kernel._can_compile
    with pytest.raises(TypeError):
        kernel(*([np.zeros((2, 3), dtype=np.float32)] * len(kernel.signatures[0])))


def test_task_reaction_matches_pinocchio_force_action():
    """law_kernels.task_reaction (the mounting's share of a task wrench, at the base frame) equals
    Pinocchio's Force moved by SE3 actions: world = oMf·W, base = oMrᵀ·world, with the frame
    origin o = position − R·point, over random poses, a point off the origin and a tilted,
    offset base frame."""
    import pinocchio as pin

    rng = np.random.default_rng(28)
    N = 40
    R = np.stack([pin.rpy.rpyToMatrix(*rng.uniform(-np.pi, np.pi, 3)) for _ in range(N)])
    position = rng.normal(size=(N, 3))
    point, W = np.array([0.02, -0.01, 0.1]), rng.normal(size=6) * 20.0
    R0, r0 = pin.rpy.rpyToMatrix(0.1, -0.2, 0.3), np.array([0.3, -0.1, 0.05])
    got = law_kernels.task_reaction(R.reshape(N, 9), position, point, W, R0, r0)
    oMr = pin.SE3(R0, r0)
    for n in range(N):
        oMf = pin.SE3(R[n], position[n] - R[n] @ point)
        want = oMr.actInv(oMf.act(pin.Force(W[:3], W[3:])))
        np.testing.assert_allclose(got[n], np.concatenate([want.linear, want.angular]),
                                   rtol=0, atol=1e-12)
    assert np.abs(got).max() > 1.0      # a zero result would pass the comparison trivially


def test_row_squares_are_the_rows_squared_norms():
    """law_kernels.row_squares: |x|² and |x| per row (closed forms on Pythagorean rows, and
    np.linalg.norm on random rows of very different sizes, within an ulp or two)."""
    X = np.array([[3.0, 4.0, 12.0], [0.0, 0.0, 0.0], [-2.0, 3.0, 6.0]])
    np.testing.assert_array_equal(law_kernels.row_squares(X, True), [13.0, 0.0, 7.0])
    np.testing.assert_array_equal(law_kernels.row_squares(X, False), [169.0, 0.0, 49.0])
    rng = np.random.default_rng(5)
    Y = rng.normal(size=(500, 3)) * rng.lognormal(sigma=4.0, size=(500, 1))
    np.testing.assert_allclose(law_kernels.row_squares(Y, True), np.linalg.norm(Y, axis=1),
                               rtol=1e-15, atol=0)
    assert np.isnan(law_kernels.row_squares(np.array([[np.nan, 1.0, 0.0]]), True)[0])
