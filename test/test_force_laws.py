"""The per-sample constraint laws (dyn_node.core.check.force_laws): closed forms worked by hand, and the
time-scale contract by brute force: each sample is re-evaluated directly at stretched timings
(|a + b/k²| ≤ L, the centre of pressure tested with matplotlib's point-in-polygon), never
through the laws' own algebra."""
from __future__ import annotations

import math

import numpy as np
import pytest
from matplotlib.path import Path as MplPath

from dyn_node.core.check import force_laws as F

G0 = 9.81
GRAVITY = np.array([0.0, 0.0, -G0])
SQUARE = F.SupportPolygon.from_ccw(np.array([[-0.3, -0.3], [0.3, -0.3], [0.3, 0.3], [-0.3, 0.3]]))
# above k_max·1.001 the sampled stretches: 1.001·k up to 10⁴·k
ABOVE = 1.001 * np.geomspace(1.0, 1e4, 120)
BELOW = np.linspace(0.97, 1.0, 31, endpoint=False)


def _contract(feasible, k: float, *, very_slow: float = 1e6) -> None:
    """feasible(k′) for the law's k: every sampled k′ ≥ 1.001·k feasible and some k′ in
    [0.97·k, k) not (k > 0); k = 0: feasible over a wide range; k = inf: the still limit
    (k′ = very_slow) infeasible."""
    if k == 0:
        assert all(feasible(x) for x in np.geomspace(1e-3, 1e3, 60))
    elif math.isinf(k):
        assert not feasible(very_slow)
    else:
        assert all(feasible(k * x) for x in ABOVE), k
        assert not all(feasible(k * x) for x in BELOW), k


# --- speed, acceleration and energy ------------------------------------------------------------

def test_speed_law_is_linear_in_one_over_k():
    r = F.speed_law(np.array([0.0, 0.1, 0.25, 0.5]), 0.25)
    assert r.ratio.tolist() == [0.0, 0.4, 1.0, 2.0]
    assert r.time_scale.tolist() == [0.0, 0.4, 1.0, 2.0]
    for v, k in zip(r.value, r.time_scale):
        _contract(lambda kk, v=v: v / kk <= 0.25, k)
    assert r.max_time_scale == 2.0 and r.peak_index == 3


def test_acceleration_and_energy_law_goes_as_s():
    r = F.acceleration_law(np.array([0.0, 2.5, 10.0, 40.0]), 10.0)
    assert r.ratio.tolist() == [0.0, 0.25, 1.0, 4.0]
    assert r.time_scale.tolist() == [0.0, 0.5, 1.0, 2.0]
    for v, k in zip(r.value, r.time_scale):
        _contract(lambda kk, v=v: v / kk**2 <= 10.0, k)


def test_power_laws_reject_what_they_cannot_mean():
    with pytest.raises(ValueError):
        F.speed_law(np.array([-0.1]), 1.0)
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError):
            F.acceleration_law(np.array([1.0]), bad)
    r = F.speed_law(np.array([math.nan, 1.0]), 2.0)
    assert math.isnan(r.time_scale[0]) and r.time_scale[1] == 0.5
    assert math.isnan(r.max_time_scale)     # a NaN sample is never hidden by the maximum


# --- |static + s·dynamic| ≤ L --------------------------------------------------------------------

def test_norm_law_closed_forms():
    a = np.array([[1.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [2.0, 0, 0],
                  [2.0, 0, 0], [2.0, 0, 0], [1.0, 0, 0]])
    b = np.array([[3.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, 0, 0], [-1.0, 0, 0], [1.0, 0, 0],
                  [0, 1.0, 0], [-5.0, 0, 0], [-3.0, 0, 0]])
    r = F.norm_law(a, b, 2.0)
    expected = [
        math.sqrt(3.0),        # 1 + 3s ≤ 2: s ≤ 1/3
        3.0 ** -0.25,          # 1 + s² ≤ 4: s ≤ √3
        math.inf,              # 3 − s ≤ 2 needs s ≥ 1: a band [1, 5], never near the still pose
        0.0,                   # no dynamic term, static inside
        0.5,                   # on the limit, moving inward: |2 − s| ≤ 2 for s ≤ 4
        math.inf,              # on the limit, moving outward at once
        math.inf,              # on the limit, tangent: 4 + s² > 4 for every s > 0
        math.sqrt(5.0 / 4.0),  # |2 − 5s| ≤ 2 for s ≤ 4/5
        1.0,                   # |1 − 3s| ≤ 2 for s ≤ 1: the far root, through zero
    ]
    np.testing.assert_allclose(r.time_scale, expected, rtol=1e-15)
    np.testing.assert_allclose(r.value, np.linalg.norm(a + b, axis=1), rtol=1e-15)
    np.testing.assert_allclose(r.static_value, [1, 1, 3, 1, 2, 2, 2, 2, 1], rtol=1e-15)
    np.testing.assert_allclose(r.ratio, r.value / 2.0, rtol=1e-15)


def test_norm_law_zero_limit_and_no_motion():
    still, moving = np.array([[0.0, 0], [0.0, 0], [1.0, 0]]), np.array([[0.0, 0], [1.0, 0], [0.0, 0]])
    r = F.norm_law(still, moving, 0.0)
    assert r.time_scale.tolist() == [0.0, math.inf, math.inf]
    assert r.ratio.tolist() == [0.0, math.inf, math.inf]


def _random_cases(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, float]:
    L = 10.0
    a = rng.normal(size=(n, 3))
    a *= (L * rng.uniform(0.0, 1.5, n) / np.linalg.norm(a, axis=1))[:, None]
    b = rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-1, 2, (n, 1))
    # gravity-opposed dynamic terms: static over the limit, a band of mid-range k inside it
    band = slice(0, n // 4)
    a[band] = np.array([0, 0, 1.0]) * L * rng.uniform(1.1, 2.0, (n // 4, 1))
    b[band] = -a[band] * rng.uniform(0.5, 20.0, (n // 4, 1)) + rng.normal(size=(n // 4, 3)) * 0.5
    # exactly on the limit statically
    edge = slice(n // 4, n // 4 + 20)
    a[edge] = np.array([0, L, 0.0])
    return a, b, L


@pytest.mark.parametrize("seed", range(3))
def test_norm_law_time_scale_contract_by_brute_force(seed):
    rng = np.random.default_rng(seed)
    a, b, L = _random_cases(rng, 400)
    r = F.norm_law(a, b, L)
    kinds = {"inf": 0, "finite": 0, "band": 0}
    for ai, bi, k in zip(a, b, r.time_scale):
        def feasible(kk, ai=ai, bi=bi):
            return bool(np.linalg.norm(ai + bi / kk**2) <= L)
        _contract(feasible, k)
        if math.isinf(k):
            kinds["inf"] += 1
            grid = np.geomspace(1e-2, 1e3, 2000)
            kinds["band"] += any(feasible(x) for x in grid)
        else:
            kinds["finite"] += 1
    # every kind of case actually occurred (band: feasible mid-range k yet k = inf)
    assert kinds["finite"] > 100 and kinds["inf"] > 100 and kinds["band"] > 50, kinds


def test_norm_law_nan_rows_are_nan_not_feasible():
    a = np.array([[math.nan, 0, 0], [1.0, 0, 0]])
    b = np.array([[0.0, 0, 0], [0, 0, math.inf]])
    r = F.norm_law(a, b, 5.0)
    assert np.isnan(r.time_scale).all() and np.isnan(r.ratio).all()


def test_norm_law_rejects_mismatched_shapes():
    with pytest.raises(ValueError):
        F.norm_law(np.zeros((3, 3)), np.zeros((2, 3)), 1.0)


# --- grasp -----------------------------------------------------------------------------------

# frame axes in root axes (columns): x_f = x, y_f = z (up), z_f = −y; exact, so no rounding
R_UP = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])


def _translating_payload(mass: float, a_world: np.ndarray) -> F.GraspForce:
    """A point mass at the frame origin, frame translating only (no ω, no α): a_com = Rᵀ·a."""
    n = len(a_world)
    R = np.broadcast_to(R_UP, (n, 3, 3))
    return F.payload_grasp_force(mass, np.einsum("nji,nj->ni", R, a_world),
                                 F.gravity_in_frame(R, GRAVITY))


def test_grasp_point_mass_closed_form_horizontal_normal():
    # grip normal z_f = root −y (horizontal): gravity and an x acceleration A are both tangential
    m, mu, grip, faces, A = 1.5, 0.5, 40.0, 2, 20.0
    L = mu * grip * faces
    f = _translating_payload(m, np.array([[A, 0, 0], [0, -A, 0], [0, 0, 0]]))
    r = F.grasp_slip_law(f, normal_axis=np.array([0, 0, 2.0]), limit=L)
    # |m·(A·s, g0)| ≤ L ⇔ s ≤ √(L² − (m g0)²) / (m A); acceleration along the normal: no slip
    s_max = math.sqrt(L**2 - (m * G0) ** 2) / (m * A)
    np.testing.assert_allclose(r.time_scale, [1 / math.sqrt(s_max), 0.0, 0.0], rtol=1e-14)
    np.testing.assert_allclose(r.value, [m * math.hypot(A, G0), m * G0, m * G0], rtol=1e-14)
    np.testing.assert_allclose(r.static_value, m * G0, rtol=1e-14)


def test_grasp_point_mass_closed_form_vertical_normal():
    # grip normal y_f = root z: gravity is carried by the normal force; slip only from A·s
    m, L, A = 2.0, 10.0, 20.0
    f = _translating_payload(m, np.array([[A, 0, 0]]))
    r = F.grasp_slip_law(f, normal_axis=np.array([0, 1.0, 0]), limit=L)
    assert r.static_value[0] == 0.0
    assert r.time_scale[0] == pytest.approx(math.sqrt(m * A / L), rel=1e-15)


def test_grasp_force_is_mass_times_acceleration_minus_gravity():
    rng = np.random.default_rng(3)
    a, g = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    f = F.payload_grasp_force(0.7, a, g)
    np.testing.assert_allclose(f.static + f.dynamic, 0.7 * (a - g), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(f.dynamic, 0.7 * a)
    with pytest.raises(ValueError):
        F.payload_grasp_force(-1.0, a, g)


def test_gravity_in_frame_is_the_transposed_rotation():
    rng = np.random.default_rng(4)
    Q, _ = np.linalg.qr(rng.normal(size=(6, 3, 3)))
    got = F.gravity_in_frame(Q, GRAVITY)
    for Ri, gi in zip(Q, got):
        np.testing.assert_allclose(Ri @ gi, GRAVITY, atol=1e-14)   # back in root axes


def test_grasp_band_heavy_payload_lowered_fast_is_no_slowdown():
    # m g0 = 29.4 N over 20 N; lowering at 2g..4g unloads the grip mid-range, yet the still pose
    # slips, so no time scale makes the whole motion feasible
    m, L = 3.0, 20.0
    f = _translating_payload(m, np.array([[0, 0, -3 * G0]]))
    r = F.grasp_slip_law(f, normal_axis=np.array([0, 0, 1.0]), limit=L)
    assert math.isinf(r.time_scale[0])
    feasible = [abs(m * G0 * (1 - 3 / k**2)) <= L for k in np.geomspace(0.5, 100, 400)]
    assert any(feasible) and not feasible[-1]


# --- tipping ---------------------------------------------------------------------------------

def _point_mass_reaction(m: float, c: np.ndarray, a: np.ndarray) -> F.ScaledWrench:
    """The base's wrench on a point-mass robot at c (root frame) accelerating by s·a: m·(s·a − g)
    at c, as moment about the root origin."""
    Fs, Fd = np.atleast_2d(-m * GRAVITY), np.atleast_2d(m * a)
    return F.ScaledWrench(Fs, Fd, np.cross(c, Fs), np.cross(c, Fd))


def test_tipping_hand_computed():
    # robot 10 kg at (0.1, 0, 0.5), base 20 kg at (0, 0, 0.1), square ±0.3 m; the robot's mass
    # accelerates along +x at a_x = 8 g0, which moves the CoP towards −x. Moments about the CoP
    # line (by hand): p_x(s) = (10·0.1·g0 − 10·0.5·a_x·s) / (30·g0)
    m, c, ax = 10.0, np.array([0.1, 0, 0.5]), 8 * G0
    react = _point_mass_reaction(m, c, np.array([ax, 0, 0]))
    r = F.tipping_law(react, polygon=SQUARE, base_mass=20.0, base_com=np.array([0, 0, 0.1]),
                      gravity=GRAVITY)
    px = (10 * 0.1 * G0 - 10 * 0.5 * ax) / (30 * G0)               # −1.3 m at k = 1
    np.testing.assert_allclose(r.centre_of_pressure[0], [px, 0.0], atol=1e-15)
    assert r.normal_force[0] == pytest.approx(30 * G0, rel=1e-15)
    assert r.ratio[0] == pytest.approx(1.3 / 0.3, rel=1e-14)
    # edge x = −0.3: 10·0.1·g0 − 5·ax·s ≥ −0.3·30·g0 ⇔ s ≤ 10 g0 / (5 ax) = 1/4 → k = 2
    assert r.time_scale[0] == pytest.approx(2.0, rel=1e-14)
    assert r.static_value[0] == pytest.approx((0.1 / 3) / 0.3, rel=1e-14)


def test_tipping_lift_off_bounds_k_through_the_normal_force():
    # robot above the centroid plunging down at 3.5 g: N = 30 g0 − 10·3.5 g0·s > 0 ⇔ s < 6/7;
    # the CoP stays at the centroid until lift-off
    react = _point_mass_reaction(10.0, np.array([0, 0, 0.5]), np.array([0, 0, -3.5 * G0]))
    r = F.tipping_law(react, polygon=SQUARE, base_mass=20.0, base_com=np.zeros(3),
                      gravity=GRAVITY)
    assert r.time_scale[0] == pytest.approx(math.sqrt(7 / 6), rel=1e-14)
    assert r.normal_force[0] == pytest.approx(-5 * G0, rel=1e-14)
    assert math.isinf(r.ratio[0]) and np.isnan(r.centre_of_pressure[0]).all()
    assert r.static_value[0] == 0.0            # at rest the CoP is the centroid


def test_tipping_without_any_normal_force_is_lift_off_at_every_k():
    # nothing presses on the floor at any timing (N ≡ 0, no moment): the edge inequalities
    # b_i·N − n_i·P ≥ 0 all hold with equality, only the strict N > 0 rejects it
    zero = np.zeros((1, 3))
    r = F.tipping_law(F.ScaledWrench(zero, zero, zero, zero), polygon=SQUARE, base_mass=0.0,
                      base_com=np.zeros(3), gravity=GRAVITY)
    assert math.isinf(r.time_scale[0]) and math.isinf(r.ratio[0])


def test_tipping_gauge_known_points():
    pts = np.array([[-0.45, 0.0], [0.3, 0.3], [0.15, 0.3], [0.0, 0.0], [0.06, -0.03]])
    np.testing.assert_allclose(SQUARE.gauge(pts), [1.5, 1.0, 1.0, 0.0, 0.2], rtol=1e-14)
    tri = F.SupportPolygon.from_ccw(np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 3.0]]))
    np.testing.assert_allclose(tri.centroid, [1.0, 1.0], rtol=1e-15)
    # from the centroid (1, 1) towards (2, 2): the hypotenuse x + y = 3 at (1.5, 1.5)
    assert tri.gauge(np.array([[2.0, 2.0]]))[0] == pytest.approx(2.0, rel=1e-14)


def _random_polygon(rng: np.random.Generator) -> F.SupportPolygon:
    """Convex: points on an ellipse at jittered, increasing angles (counter-clockwise)."""
    n = int(rng.integers(3, 9))
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(0, 0.5 * np.pi / n, n)
    r = rng.uniform(0.3, 0.5)
    pts = np.column_stack([np.cos(ang), 0.7 * np.sin(ang)]) * r + rng.uniform(-0.05, 0.05, 2)
    return F.SupportPolygon.from_ccw(pts)


def _floor_cop(react: F.ScaledWrench, i: int, s: float, mb: float, cb: np.ndarray):
    """(normal force, CoP) of the floor on the base directly from the balance of the still base."""
    Fr = react.force_static[i] + s * react.force_dynamic[i]
    Mr = react.moment_static[i] + s * react.moment_dynamic[i]
    W = mb * GRAVITY
    Ff, Mf = Fr - W, Mr - np.cross(cb, W)
    N = Ff[2]
    # Mf = p × Ff + τ_z ẑ with p = (x, y, 0): Mf_x = y·N, Mf_y = −x·N
    return N, np.array([-Mf[1] / N, Mf[0] / N]) if N > 0 else None


@pytest.mark.parametrize("seed", range(3))
def test_tipping_time_scale_contract_by_brute_force(seed):
    rng = np.random.default_rng(10 + seed)
    poly = _random_polygon(rng)
    path = MplPath(poly.vertices)
    n, m = 160, 15.0
    mb, cb = rng.uniform(0, 30), np.append(poly.centroid + rng.uniform(-0.05, 0.05, 2), 0.1)
    # robot CoM over the polygon (statically standing) in half the rows, well outside in the rest
    c = np.column_stack([rng.uniform(-0.2, 0.2, (n, 2)), rng.uniform(0.2, 1.0, n)])
    c[:n // 2, :2] = rng.uniform(0.6, 1.0, (n // 2, 2)) * rng.choice([-1, 1], (n // 2, 2))
    Fs = np.tile(-m * GRAVITY, (n, 1)) + rng.normal(size=(n, 3)) * 5
    Ms = np.cross(c, Fs)
    Fd = rng.normal(size=(n, 3)) * m * 10.0 ** rng.uniform(-0.5, 1.5, (n, 1))
    Md = np.cross(c, Fd) + rng.normal(size=(n, 3)) * 5
    # band cases: CoP statically outside, pulled back inside by the dynamic moment mid-range
    # (it cancels the robot's static moment at s = 1/(2u): the CoP is then the base's)
    band = slice(0, n // 4)
    Md[band] = -2.0 * Ms[band] * rng.uniform(1.0, 3.0, (n // 4, 1))
    Fd[band] = 0.0
    react = F.ScaledWrench(Fs, Fd, Ms, Md)
    r = F.tipping_law(react, polygon=poly, base_mass=mb, base_com=cb, gravity=GRAVITY)
    counts = {"finite": 0, "inf": 0, "band": 0}
    for i, k in enumerate(r.time_scale):
        def feasible(kk, i=i):
            N, p = _floor_cop(react, i, 1.0 / kk**2, mb, cb)
            return p is not None and bool(path.contains_point(p))
        _contract(feasible, k)
        # the gauge at k = 1 agrees with the independent point-in-polygon test
        inside = feasible(1.0)
        assert (r.ratio[i] < 1) == inside or abs(r.ratio[i] - 1) < 1e-9
        if math.isinf(k):
            counts["inf"] += 1
            counts["band"] += any(feasible(x) for x in np.geomspace(0.05, 100, 300))
        else:
            counts["finite"] += 1
    assert counts["finite"] > 30 and counts["inf"] > 30 and counts["band"] > 15, counts


def test_tipping_centre_of_pressure_matches_the_direct_balance():
    rng = np.random.default_rng(7)
    n = 50
    react = F.ScaledWrench(*(rng.normal(size=(n, 3)) * 50 + np.array([0, 0, 300.0]) * (j == 0)
                             for j in range(4)))
    cb = np.array([0.05, -0.02, 0.3])
    r = F.tipping_law(react, polygon=SQUARE, base_mass=12.0, base_com=cb, gravity=GRAVITY)
    for i in range(n):
        N, p = _floor_cop(react, i, 1.0, 12.0, cb)
        assert r.normal_force[i] == pytest.approx(N, rel=1e-12)
        if p is None:
            assert math.isinf(r.ratio[i])
        else:
            np.testing.assert_allclose(r.centre_of_pressure[i], p, rtol=1e-12, atol=1e-12)


def test_tipping_nan_rows_are_nan():
    react = _point_mass_reaction(10.0, np.array([0, 0, 0.5]), np.array([math.nan, 0, 0]))
    r = F.tipping_law(react, polygon=SQUARE, base_mass=0.0, base_com=np.zeros(3), gravity=GRAVITY)
    assert math.isnan(r.time_scale[0]) and math.isnan(r.ratio[0])
