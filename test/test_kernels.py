"""The compiled kernels against references we did not write: numpy.roots for the polynomial
roots, a direct trapezoid windowed integral for the RMS pass."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dyn_node.core.compiled import kernels as K
from dyn_node.core.compiled import rigid_kernels


def _real_roots(coeffs) -> list[float]:
    r = np.roots(coeffs)
    return sorted(float(x.real) for x in r if abs(x.imag) <= 1e-9 * max(1.0, abs(x)))


@pytest.mark.parametrize("seed", range(4))
def test_cubic_roots_agree_with_numpy_roots(seed):
    rng = np.random.default_rng(seed)
    checked = 0
    for _ in range(400):
        # spread magnitudes, and some with three real roots close together
        a, b, c, d = rng.normal(size=4) * 10.0 ** rng.uniform(-3, 3, 4)
        if rng.random() < 0.3:
            r = rng.normal(size=3)
            a, b, c, d = np.poly(r) * rng.uniform(0.1, 10)
        got = sorted(x for x in K.cubic_roots(a, b, c, d) if not math.isnan(x))
        ref = _real_roots([a, b, c, d])
        if len(ref) != len(got):   # a double root at the edge of real: both are defensible
            continue
        scale = max(1.0, max(abs(x) for x in ref))
        assert np.allclose(got, ref, rtol=1e-7, atol=1e-7 * scale), (a, b, c, d, got, ref)
        checked += 1
    assert checked > 380


def test_degenerate_polynomials():
    assert K.cubic_roots(0.0, 1.0, -3.0, 2.0)[1:] in ((2.0, 1.0), (1.0, 2.0))  # quadratic
    assert math.isnan(K.cubic_roots(0.0, 1.0, -3.0, 2.0)[0])
    assert K.quadratic_roots(0.0, 2.0, -4.0) == (pytest.approx(np.nan, nan_ok=True), 2.0)
    assert all(math.isnan(x) for x in K.quadratic_roots(1.0, 0.0, 1.0))   # no real root


def test_first_exits_are_the_least_positive_crossing():
    # |2 + x + x²| = 8 at x = 2; |−x³| = 27 at x = 3
    assert K.quadratic_exit(2.0, 1.0, 1.0, 8.0) == pytest.approx(2.0, rel=1e-15)
    assert K.cubic_exit(0.0, 0.0, -1.0, 27.0) == pytest.approx(3.0, rel=1e-15)
    assert K.quadratic_exit(1.0, 0.0, 0.0, 8.0) == math.inf        # never grows
    # a column starting outside its band exits at 0
    s = np.asfortranarray([[1.0], [9.0]])
    assert K.band_exit(s, s * 0, s * 0 + 1, np.array([8.0]))[0] == 0.0


def test_abs_peak_is_numpy_argmax_of_abs():
    X = np.asfortranarray(np.random.default_rng(3).normal(size=(500, 4)))
    X[7, 1] = X[9, 1] = 50.0                      # a tie: the first one, as numpy.argmax
    at, peak = K.abs_peak(X)
    np.testing.assert_array_equal(at, np.argmax(np.abs(X), axis=0))
    np.testing.assert_array_equal(peak, np.abs(X).max(axis=0))
    X[3, 2] = np.nan
    at, peak = K.abs_peak(X)
    assert at[2] == 3 and np.isnan(peak[2])
    assert K.abs_peak(np.zeros((0, 2)))[1].tolist() == [0.0, 0.0]


def test_envelope_values_are_numpy_interp_of_the_speed():
    rng = np.random.default_rng(11)
    v = np.asfortranarray(rng.normal(scale=3.0, size=(400, 3)))
    v[0] = 0.0
    v[1] = [1.0, -2.5, 4.0]                       # exactly on curve points
    curves = [np.array([[0.0, 80.0], [3.0, 40.0]]),
              np.array([[0.5, 10.0], [1.0, 9.0], [2.5, 2.0], [6.0, 1.0]]),
              np.array([[1.0, 5.0], [4.0, 5.0], [5.0, 0.5]])]
    npts = np.array([len(c) for c in curves])
    sp = np.zeros((3, npts.max()))
    ef = np.zeros_like(sp)
    for c, cv in enumerate(curves):
        sp[c, :len(cv)], ef[c, :len(cv)] = cv[:, 0], cv[:, 1]
    got = K.envelope_values(v, sp, ef, npts)
    want = np.stack([np.interp(np.abs(v[:, c]), cv[:, 0], cv[:, 1])
                     for c, cv in enumerate(curves)], axis=1)
    np.testing.assert_array_equal(got, want)      # the same arithmetic, to the last bit
    assert got.flags.f_contiguous


@pytest.mark.parametrize("seed", range(4))
def test_rms_windows_match_a_direct_windowed_integral(seed):
    rng = np.random.default_rng(50 + seed)
    M, m = 800, 3
    t = np.sort(rng.uniform(0.0, 2.0, M))
    t[0] = 0.0
    t[300] = t[299]                         # a waypoint twice, as the sampler makes it
    s, w, i = (np.asfortranarray(rng.normal(size=(M, m))) for _ in range(3))
    x = rng.uniform(0.3, 2.0, m)
    window = rng.uniform(0.05, 0.8, m)
    hold2 = rng.uniform(0.0, 2.0, m)
    every = K.rms_windowed(t, s, w, i, x, window, hold2)
    got = K.rms_worst(t, s, w, i, x, window, hold2, np.ones(m, dtype=bool))
    for c in range(m):
        f = (s[:, c] + w[:, c] * x[c] + i[:, c] * x[c] ** 2) ** 2
        E = np.concatenate(([0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(t))))
        start = t - window[c] * x[c]
        inside = E - np.interp(start, t, E) + np.maximum(t[0] - start, 0.0) * hold2[c]
        np.testing.assert_allclose(every[c], inside, rtol=1e-10, atol=1e-12 * inside.max())
        assert got[c] == pytest.approx(inside.max(), rel=1e-10)
        assert got[c] == every[c].max()       # the pruned search finds the very maximum
    only = K.rms_worst(t, s, w, i, x, window, hold2, np.array([False, True, False]))
    assert math.isnan(only[0]) and math.isnan(only[2]) and only[1] == got[1]


def test_segment_rate_is_exact_for_quartics_and_stays_inside_segments():
    from dyn_node.core.check.feasibility import _sample
    from dyn_node.core.compiled import peak_kernels as pk
    # 10, 1, 2 and 14 steps: fourth order, the chord, second order, fourth order
    smp = _sample(np.array([0.0, 0.5, 0.53, 0.63, 1.2]), 0.05, 10_000)
    t, seg = smp.t, smp.seg
    # a different quartic per segment, so a difference across a knot would show
    F = np.stack([(1 + seg) * t ** 4 - 2 * t ** 3 + 3 * t, -2 * t ** 2 + seg * t], axis=1)
    D = pk.segment_rate(np.asfortranarray(F), smp.first, smp.last, smp.h)
    exact = np.stack([4 * (1 + seg) * t ** 3 - 6 * t ** 2 + 3, -4 * t + seg], axis=1)
    steps = (smp.last - smp.first)[seg]
    np.testing.assert_allclose(D[steps >= 4], exact[steps >= 4], rtol=1e-9, atol=1e-9)
    # two steps: second order, exact for the quadratic column
    np.testing.assert_allclose(D[steps == 2, 1], exact[steps == 2, 1], rtol=1e-9, atol=1e-9)
    # a one-step segment gets the chord slope at both ends
    f, l_ = smp.first[1], smp.last[1]
    assert l_ - f == 1
    np.testing.assert_allclose(D[[f, l_]], np.repeat((F[l_] - F[f])[None] / smp.h[f], 2, 0))




@pytest.mark.parametrize("name", ["panda", "ur5", "planar_2link", "tree"])
def test_gravity_rows_agree_with_pinocchio(name):
    """The gravity kernel against Pinocchio's computeGeneralizedGravity, state by state: the
    built-in arms, and a branching tree with aligned and unaligned revolute and prismatic axes, a
    fixed joint merged into its parent and a continuous joint, carrying a payload under a tilted
    gravity vector."""
    from robots import BRANCHED_URDF
    import pinocchio as pin

    from dyn_node.core.robot.dynamics import gravity_tables
    from dyn_node.core.robot.model import Payload, load_model

    if name == "tree":
        model = load_model(urdf=BRANCHED_URDF, payload=Payload(1.5, (0.02, -0.03, 0.05), "f"),
                           gravity=(1.1, -2.3, -9.5))
        kinds = {model.pin_model.joints[i].shortname() for i in range(1, model.pin_model.njoints)}
        assert kinds == {"JointModelRZ", "JointModelRX", "JointModelRY", "JointModelPX",
                         "JointModelRevoluteUnaligned", "JointModelPrismaticUnaligned"}
    else:
        model = load_model(builtin=name)
    pm = model.pin_model
    rng = np.random.default_rng(7)
    Q = rng.uniform(-2.5, 2.5, (200, pm.nv))
    tables = gravity_tables(pm)
    assert tables is not None
    out = np.full((len(Q), pm.nv), np.nan)
    rigid_kernels.gravity_rows(Q, *tables, out)
    data = pm.createData()
    ref = np.array([pin.computeGeneralizedGravity(pm, data, q) for q in Q])
    assert np.abs(ref).max() > 1.0          # the states load every joint
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-11)
    empty = np.empty((0, pm.nv))
    rigid_kernels.gravity_rows(Q[:0], *tables, empty)    # no state: nothing written, no error
