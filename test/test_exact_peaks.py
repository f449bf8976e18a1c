"""Exact peaks (dyn_node.core.check.exact_peaks, compiled.peak_kernels): the kinematic kinds'
extrema on each polynomial piece against scipy's PPoly roots, the torque kinds at both knot sides
and inside short pieces against a dense evaluation by Pinocchio, and the between-samples findings
of issue 36 as regression tests (dyn-check, core.check.on_demand.check)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest
from scipy.interpolate import PPoly

from dyn_node.audit.check import main as dyn_check
from dyn_node.core.check import exact_peaks, on_demand
from dyn_node.core.check import feasibility as F
from dyn_node.core.check.trajectory import PiecewisePolynomial, validate_trajectory
from dyn_node.core.compiled import peak_kernels as pk
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import load_model
from dyn_node.core.robot.settings import Settings

PANDA = load_model(builtin="panda")
NAMES = list(PANDA.joint_names)
NV = PANDA.nv
HOME = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.6, 0.8])
#: libfranka's limits on every joint (the issue's findings were made with these)
FRANKA = {"acceleration": 15.0, "jerk": 7500.0, "effort_rate": 1000.0}
KINEMATIC = {"velocity": 1, "acceleration": 2, "jerk": 3}


def franka_model(**extra):
    lim = {n: dict(has_acceleration_limits=True, max_acceleration=FRANKA["acceleration"],
                   has_jerk_limits=True, max_jerk=FRANKA["jerk"],
                   max_effort_rate=FRANKA["effort_rate"], **extra) for n in NAMES}
    return PANDA.with_limits({"joint_limits": lim})


def random_pieces(rng, n: int, shortest: float = 1e-4, longest: float = 0.03) -> PiecewisePolynomial:
    """n pieces of random lengths (log-uniform), each linear, cubic, quintic or a rest-to-rest
    quintic (zero-padded), from a pose near HOME with velocities ~1 rad/s and accelerations ~10
    rad/s² whatever the length (so short pieces carry large jerks), independent of their
    neighbours (every knot a step in some derivative)."""
    T = np.exp(rng.uniform(np.log(shortest), np.log(longest), n))
    coeffs = np.zeros((n, 6, NV))
    for k in range(n):
        deg = rng.choice([1, 3, 5, 6])           # 6: a rest-to-rest quintic (q̈ peaks inside)
        coeffs[k, 0] = HOME + rng.uniform(-0.3, 0.3, NV)
        if deg == 6:
            # up to 10 rad/s² at its peak, 10/√3·Δ/T²
            delta = rng.uniform(-10.0, 10.0, NV) * T[k] ** 2 * np.sqrt(3) / 10
            coeffs[k, 3:] = np.outer([10, -15, 6] / T[k] ** np.arange(3, 6), delta)
            continue
        coeffs[k, 1] = rng.uniform(-1.0, 1.0, NV)
        for p in range(2, deg + 1):
            coeffs[k, p] = rng.uniform(-10.0, 10.0, NV) / (p * (p - 1) * T[k] ** (p - 2))
    return PiecewisePolynomial(np.concatenate(([0.0], np.cumsum(T))), coeffs)


def scipy_range(pp: PiecewisePolynomial, k: int, j: int, order: int) -> tuple[float, float]:
    """Max and min of derivative ``order`` of joint j on piece k: at the ends and at the roots
    of the next derivative (scipy's PPoly.solve), evaluated by scipy."""
    T = pp.breaks[k + 1] - pp.breaks[k]
    poly = PPoly(pp.coeffs[k, ::-1, j][:, None], [0.0, T]).derivative(order) if order else \
        PPoly(pp.coeffs[k, ::-1, j][:, None], [0.0, T])
    cand = np.concatenate(([0.0, T], poly.derivative().roots(extrapolate=False)))
    vals = poly(cand[np.isfinite(cand)])
    return float(vals.max()), float(vals.min())


def test_column_range_is_scipys_extremum_on_every_piece():
    pp = random_pieces(np.random.default_rng(3), 60)
    cols = np.arange(NV)
    for order in range(4):
        for k in range(len(pp.coeffs)):
            one = pp.coeffs[k:k + 1]
            hi, t_hi, lo, t_lo, law_hi, law_lo = pk.column_range(one, pp.breaks[k:k + 2], order,
                                                                 cols, 0)
            np.testing.assert_array_equal([hi, lo], [law_hi, law_lo])
            for j in range(NV):
                want_hi, want_lo = scipy_range(pp, k, j, order)
                scale = max(abs(want_hi), abs(want_lo), 1e-300)
                assert abs(hi[j] - want_hi) <= 1e-9 * scale, (order, k, j)
                assert abs(lo[j] - want_lo) <= 1e-9 * scale, (order, k, j)
                # reached where reported
                at = np.polyval(np.polyder(one[0, ::-1, j], order),
                                [t_hi[j] - pp.breaks[k], t_lo[j] - pp.breaks[k]])
                np.testing.assert_allclose(at, [hi[j], lo[j]], rtol=0, atol=1e-9 * scale)
        # all pieces at once (the ends first, then the insides that could beat them), and from
        # piece 5 on
        hi, t_hi, lo, t_lo, law_hi, law_lo = pk.column_range(pp.coeffs, pp.breaks, order, cols, 5)
        for j in range(NV):
            each = np.array([scipy_range(pp, k, j, order) for k in range(len(pp.coeffs))])
            scale = np.abs(each).max()
            assert abs(hi[j] - each[:, 0].max()) <= 1e-9 * scale
            assert abs(lo[j] - each[:, 1].min()) <= 1e-9 * scale
            assert abs(law_hi[j] - each[5:, 0].max()) <= 1e-9 * scale
            assert abs(law_lo[j] - each[5:, 1].min()) <= 1e-9 * scale


def test_roots_of_a_quintic_with_close_and_double_roots():
    """(s − 0.2)²(s − 0.2001)(s − 0.7)(s − 5) on [0, 1]: negative on [0, 0.2001) (touching 0 at
    the double root 0.2, 1e-4 from a simple one) and on (0.7, 1]: 0.5001 s below zero."""
    coeffs = np.zeros((1, 6, 1))
    coeffs[0, :, 0] = np.poly([0.2, 0.2, 0.2001, 0.7, 5.0])[::-1]        # ascending
    first, total = pk.excess(coeffs, np.array([0.0, 1.0]), 0, np.array([0]),
                             np.array([0.0]), np.array([np.inf]), False)
    # 1e-8: the conditioning of the root beside the double one (p′ ≈ 2.4e-8 there) times the
    # rounding of the coefficients themselves
    assert first[0] == 0.0 and total[0] == pytest.approx(0.5001, abs=1e-8)
    hi, t_hi, lo, t_lo, *_ = pk.column_range(coeffs, np.array([0.0, 1.0]), 0, np.array([0]), 0)
    want_hi, want_lo = scipy_range(PiecewisePolynomial(np.array([0.0, 1.0]), coeffs), 0, 0, 0)
    assert hi[0] == pytest.approx(want_hi, rel=1e-12) and lo[0] == pytest.approx(want_lo, rel=1e-12)


def _truth(pp: PiecewisePolynomial, per_piece_min: int = 400, rate_hz: float = 1e5):
    """q, q̇, q̈, q⃛ on every piece on its own (both knot sides), at ≥ 100 kHz and ≥
    ``per_piece_min`` points per piece, by numpy's polyval; τ = Pinocchio's RNEA plus the
    model's viscous damping, dτ/dt from Pinocchio's RNEA derivatives."""
    pm = PANDA.pin_model
    data = pm.createData()
    damping = np.asarray(pm.damping)
    rows = []
    for k in range(len(pp.coeffs)):
        T = pp.breaks[k + 1] - pp.breaks[k]
        s = np.linspace(0.0, T, max(per_piece_min, int(np.ceil(T * rate_hz)) + 1))
        d = [np.stack([np.polyval(np.polyder(pp.coeffs[k, ::-1, j], o), s) for j in range(NV)], 1)
             for o in range(4)]
        rows.append((pp.breaks[k] + s, *d))
    t, q, v, a, jk = (np.concatenate(x) for x in zip(*rows))
    tau, rate = np.empty_like(q), np.empty_like(q)
    for n in range(len(t)):
        tau[n] = pin.rnea(pm, data, q[n], v[n], a[n]) + damping * v[n]
        dq, dv, M = pin.computeRNEADerivatives(pm, data, q[n], v[n], a[n])
        M = np.triu(M) + np.triu(M, 1).T
        rate[n] = dq @ v[n] + dv @ a[n] + M @ jk[n] + damping * a[n]
    return t, q, v, a, jk, tau, rate


def _check_pieces(model, pp: PiecewisePolynomial) -> F.FeasibilityResult:
    """The check of exactly these pieces: their knots as the waypoints, the pieces standing in for
    the execution model's polynomials (the interpolation is not what is tested here, nor are the
    velocity steps between random pieces: test_execution.py)."""
    import dataclasses

    from dyn_node.core.check.execution import execute

    traj = validate_trajectory(NAMES, NAMES, pp.breaks, np.zeros((len(pp.breaks), NV)))
    ex = dataclasses.replace(execute(traj), pp=pp, velocity_steps=())
    return F._check(Dynamics(model), ex, F.FeasibilityOptions(compute_payload_margin=False))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_property_check_peak_at_least_the_dense_truth(seed):
    """Random pieces (mixed degrees, lengths 0.1–30 ms): every kinematic kind's peak is scipy's
    exact extremum (1e-9), every torque kind's at least the dense truth − 0.1 %."""
    rng = np.random.default_rng(seed)
    pp = random_pieces(rng, 24)
    curve = [[0.0, 200.0], [10.0, 100.0]]
    model = franka_model(max_power=1e4, effort_speed_curve=curve)
    r = _check_pieces(model, pp)
    t, q, v, a, jk, tau, rate = _truth(pp)
    lim = model.limits
    for j, name in enumerate(NAMES):
        e = r.per_joint[name]
        for kind, order in KINEMATIC.items():
            exact = max(max(abs(x) for x in scipy_range(pp, k, j, order))
                        for k in range(len(pp.coeffs)))
            assert e[kind]["value"] == pytest.approx(exact, rel=1e-9), (kind, name)
        env = np.interp(np.abs(v[:, j]), *np.array(curve).T)
        for kind, ratio in (("effort", np.abs(tau[:, j]) / lim.effort[j]),
                            ("power", np.abs(tau[:, j] * v[:, j]) / lim.power[j]),
                            ("effort_speed", np.abs(tau[:, j]) / env),
                            ("effort_rate", np.abs(rate[:, j]) / lim.effort_rate[j])):
            assert e[kind]["ratio"] >= ratio.max() * (1 - 1e-3), (kind, name, e[kind]["ratio"],
                                                                  ratio.max())


def _rest_to_rest(d: float, T: float, joint: int = 0):
    """Two points: HOME, then joint moved by d, at rest with zero acceleration (a quintic)."""
    q1 = HOME.copy()
    q1[joint] += d
    z = np.zeros(NV)
    return [0.0, T], [HOME, q1], [z, z], [z, z]


def _write(tmp_path, name: str, times, positions, velocities, accelerations) -> str:
    from dyn_node.audit.trajectory_files import TrajectoryFile, format_trajectory

    path = tmp_path / f"{name}.json"
    tf = TrajectoryFile(path=str(path), joint_names=NAMES, times=list(map(float, times)),
                        positions=[list(map(float, p)) for p in positions],
                        velocities=[list(map(float, p)) for p in velocities],
                        accelerations=[list(map(float, p)) for p in accelerations], format="json")
    path.write_text(format_trajectory(tf))
    return str(path)


@pytest.mark.parametrize("d, T, kind, peak", [
    (0.1, 0.5e-3, "velocity", 15 / 8 * 0.1 / 0.5e-3),                  # 375 rad/s
    (2.2e-3, 2e-3, "acceleration", 10 / np.sqrt(3) * 2.2e-3 / 2e-3**2)])  # 3,175 rad/s²
def test_short_rest_to_rest_moves_are_infeasible(tmp_path, capsys, d, T, kind, peak):
    """Issue 36: a segment shorter than the sample period was sampled at its ends only (at rest)
    and a 2 ms one at its middle (q̈ = 0): both passed as FEASIBLE."""
    times, pos, vel, acc = _rest_to_rest(d, T)
    limits = tmp_path / "franka.yaml"
    limits.write_text("joint_limits:\n" + "".join(
        f"  {n}:\n    has_acceleration_limits: true\n    max_acceleration: 15.0\n"
        f"    has_jerk_limits: true\n    max_jerk: 7500.0\n    max_effort_rate: 1000.0\n"
        for n in NAMES))
    path = _write(tmp_path, kind, times, pos, vel, acc)
    code = dyn_check([path, "--robot-model", "panda", "--limits", str(limits)])
    out = capsys.readouterr().out
    assert code == 1 and "INFEASIBLE" in out
    dyn = Dynamics(franka_model())
    outcome = on_demand.check(dyn, Settings(robot_model="panda"), NAMES, times, pos, vel, acc)
    res = outcome.result
    assert not res.feasible
    e = res.per_joint["panda_joint1"][kind]
    assert e["value"] == pytest.approx(peak, rel=1e-9)
    assert e["ratio"] > 1.0 and any(v.kind == kind and v.joint == "panda_joint1"
                                    for v in res.violations)


def test_tiny_move_reports_the_exact_effort_rate():
    """Issue 36: 1e-9 rad over 0.5 ms answered with 2 points reported a fraction of the effort
    rate (one difference over the whole segment, the torque back where it started); its peak,
    M·q⃛ at either end, is reported as Pinocchio's RNEA derivatives give it."""
    times, pos, vel, acc = _rest_to_rest(1e-9, 0.5e-3)
    traj = validate_trajectory(NAMES, NAMES, times, pos, vel, acc)
    r = F.check_trajectory(Dynamics(franka_model()), traj)
    pp = F.interpolate(traj, "quintic")
    t, *_, rate = _truth(pp, per_piece_min=2001)
    want = np.abs(rate) / FRANKA["effort_rate"]
    for j, name in enumerate(NAMES):
        e = r.per_joint[name]["effort_rate"]
        assert e["ratio"] == pytest.approx(want[:, j].max(), rel=1e-6), name
        # at either end (the same |M·q⃛| at both, to rounding): the truth there is the peak
        at = int(np.argmin(np.abs(t - e["time_s"])))
        assert e["time_s"] in (0.0, 0.5e-3) and want[at, j] == pytest.approx(e["ratio"], rel=1e-6)


def test_effort_rate_peak_just_before_a_knot():
    """A retimer-like answer: a 10 ms quintic reaching a hard acceleration (40 rad/s²) at a knot,
    where its jerk (and so the effort rate) is largest, on the knot's left side; the next piece
    starts with a much smaller one. The check reports that one-sided peak, at the knot."""
    z = np.zeros(NV)
    q1, q2 = HOME.copy(), HOME.copy()
    q1[0] += 0.0015
    q2[0] += 0.0015 + 0.5 * 0.45 * 0.06
    v1, a1 = z.copy(), z.copy()
    v1[0], a1[0] = 0.45, 40.0
    traj = validate_trajectory(NAMES, NAMES, [0.0, 0.01, 0.07], [HOME, q1, q2], [z, v1, z],
                               [z, a1, z])
    r = F.check_trajectory(Dynamics(franka_model()), traj)
    pp = F.interpolate(traj, "quintic")
    t, *_, rate = _truth(pp, per_piece_min=2001)
    n = int(np.argmax(np.abs(rate[:, 0])))
    assert n == 2000 and t[n] == 0.01          # the construction: the peak is the knot's left side
    assert np.abs(rate[2001:, 0]).max() < 0.5 * np.abs(rate[n, 0])   # the right side far lower
    e = r.per_joint["panda_joint1"]["effort_rate"]
    assert e["time_s"] == pytest.approx(0.01, abs=1e-12)
    assert e["value"] == pytest.approx(np.abs(rate[n, 0]), rel=1e-6)


def test_position_bump_between_samples_on_7200_segments():
    """Issue 36: 10 s of 7,200 quintic segments along panda_joint1's upper limit (inside it at
    every point), one of which bulges 1e-4 rad over it between 1 ms samples: infeasible, the
    bulge's exact peak reported."""
    hi = float(PANDA.limits.position_upper[0])
    times = np.linspace(0.0, 10.0, 7201)
    pos = np.tile(HOME, (7201, 1))
    pos[:, 0] = hi - 3.95e-4
    vel, acc = np.zeros_like(pos), np.zeros_like(pos)
    T = times[1] - times[0]
    # segment 3000: leaves at q̇ = c, returns at rest; bulge peak found by scipy below
    c = 1.8
    vel[3000, 0] = c
    traj = validate_trajectory(NAMES, NAMES, times, pos, vel, acc)
    pp = F.interpolate(traj, "quintic")
    top, _ = scipy_range(pp, 3000, 0, 0)
    assert 0.9e-4 < top - hi < 1.1e-4                # ~1e-4 rad over the limit
    r = F.check_trajectory(Dynamics(PANDA), traj)
    smp = F._sample(pp.breaks, 0.001, 250_000)     # 1 ms steps, as the check sampled it
    Q = F._evaluate(pp.coeffs, pp.breaks, smp, 1)[0]
    assert Q[:, 0].max() < hi                      # those samples stay inside the limit
    assert not r.feasible
    (v,) = [v for v in r.violations if v.kind == "position"]
    assert v.joint == "panda_joint1" and v.peak_value == pytest.approx(top, rel=1e-12)
    assert times[3000] < v.first_time_s < v.peak_time_s < times[3001]


def test_min_steps_by_degree_inner_peaks_and_budget():
    pp = random_pieces(np.random.default_rng(5), 40)
    deg = exact_peaks.piece_degrees(pp)
    nz = [max(p for p in range(6) if np.any(pp.coeffs[k, p] != 0)) for k in range(40)]
    assert deg.tolist() == nz
    least = exact_peaks.min_steps(pp)
    # ⌈INNER_PEAK_STEPS·√r⌉ where some joint's |q̈| or |q⃛| peaks inside a fraction r above the
    # piece's ends, by more than 0.1 % (scipy)
    for k in range(40):
        rise = 0.0
        for j in range(NV):
            for order in (2, 3):
                ends = np.abs(np.polyval(np.polyder(pp.coeffs[k, ::-1, j], order),
                                         [0.0, pp.breaks[k + 1] - pp.breaks[k]])).max()
                peak = max(map(abs, scipy_range(pp, k, j, order)))
                if peak > (1 + 1e-3) * ends:
                    rise = max(rise, (peak - ends) / peak)
        inner = int(np.ceil(exact_peaks.INNER_PEAK_STEPS * np.sqrt(rise)))
        want = max(exact_peaks.MIN_STEPS_BY_DEGREE[deg[k]], inner)
        assert least[k] == want, (k, rise)
    assert 0 < np.sum(least > max(exact_peaks.MIN_STEPS_BY_DEGREE)) < 40
    smp = F._sample(pp.breaks, 1e-3, 250_000, least)
    steps = np.diff(smp.first, append=len(smp.t)) - 1
    assert np.all(steps >= least) and np.all(steps >= np.ceil(np.diff(pp.breaks) / 1e-3 - 1e-9))
    # a tight budget takes steps from the pieces with most, and says so
    tight = F._sample(pp.breaks, 1e-3, 400, least)
    cut = np.diff(tight.first, append=len(tight.t)) - 1
    assert len(smp.t) > 400 >= len(tight.t) and np.all(cut >= 1)
    warn = exact_peaks.sampling_warnings(tight, least, 1e-3)
    assert any("short segment(s)" in w for w in warn)
