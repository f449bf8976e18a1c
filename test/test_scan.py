"""The fused peak scan (constraints.scan → scan_kernels.peak_scan) against per-kind NumPy
written here: each channel's largest ratio and its sample, first exceedance, time over the
limit and largest magnitude from r0 on, for every way a channel forms its value."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from dyn_node.core.check import constraints as C
from dyn_node.core.check import feasibility as F
from dyn_node.core.compiled import scan_kernels as sk

M, NV = 997, 4


def _motion(seed: int, r0: int) -> SimpleNamespace:
    rng = np.random.default_rng(seed)
    X = {k: np.asfortranarray(rng.normal(size=(M, NV)) * s)
         for k, s in (("V", 2.0), ("A", 5.0), ("J", 50.0), ("tau", 30.0), ("S", 20.0))}
    X["V"][100, 1] = X["V"][700, 1] = 40.0            # a tie: the first one counts
    X["A"][r0 + 3, 2] = 1e3 if r0 else 0.0            # the largest after r0 only
    t = np.cumsum(rng.uniform(5e-4, 2e-3, M))
    weight = np.gradient(t)
    return SimpleNamespace(**X, smp=SimpleNamespace(t=t, weight=weight), r0=r0)


def _reference(x: np.ndarray, L: np.ndarray, weight: np.ndarray, r0: int) -> dict:
    """One channel in NumPy: x (M) its signed value, L (M) its limit per sample."""
    v = np.abs(x)
    # one positive limit for all samples: the largest ratio is at the largest |x| (which also
    # names the sample under an infinite limit, where every ratio is 0)
    constant = bool(np.all(L == L[0])) and L[0] > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        r = v if constant else np.where(L > 0, v / L, np.where(v > 0, np.inf, 0.0))
    ranked = np.where(np.isnan(r), -np.inf, r)        # a NaN ratio is never the largest
    at = int(np.argmax(ranked))
    if constant:
        ranked = ranked / L[0]
    over = v > L
    tail = v[r0:]
    a = r0 + int(np.argmax(tail)) if len(tail) else r0   # numpy.argmax: the first NaN wins
    return dict(peak_at=at, ratio=ranked[at], value=v[at], limit=L[at],
                first=int(np.argmax(over)) if over.any() else -1,
                above=float(weight[over].sum()),
                abs_at=a, abs_peak=float(tail.max()) if len(tail) else 0.0)


def _check(answer: C.Scanned, values: np.ndarray, L: np.ndarray, motion) -> None:
    for c in range(values.shape[1]):
        ref = _reference(values[:, c], L[:, c], motion.smp.weight, motion.r0)
        assert answer.peak_at[c] == ref["peak_at"], c
        assert answer.first[c] == ref["first"], c
        assert answer.abs_at[c] == ref["abs_at"], c
        for key in ("ratio", "value", "limit", "abs_peak"):
            got, want = float(getattr(answer, key)[c]), float(ref[key])
            assert got == want or (math.isnan(got) and math.isnan(want)), (c, key, got, want)
        # Σ weight in sample order here, pairwise in NumPy
        assert answer.above[c] == pytest.approx(ref["above"], rel=1e-12, abs=0.0), c


@pytest.mark.parametrize("r0", [0, 40])
def test_every_channel_kind_matches_numpy(r0):
    m = _motion(3, r0)
    cols = np.array([0, 1, 2, 3])
    half = np.array([1.0, 3.0, 0.5, 2.0])     # some columns over their limit, some not
    own = np.asfortranarray(np.random.default_rng(9).normal(size=(M, 3)))
    own[5, 1] = np.nan                         # a NaN in a kind's own array
    rate = [np.asfortranarray(np.random.default_rng(s).normal(size=(M, 2))) for s in (1, 2, 3)]
    envelope = np.asfortranarray(np.abs(np.random.default_rng(4).normal(30.0, 5.0, size=(M, 2))))
    envelope[11, 0] = 0.0                      # a zero limit at one sample
    requests = [
        C.ScanRequest(sk.ABS, ("V",), half * 2.0, cols),
        C.ScanRequest(sk.DECEL, ("A", "V"), half * 5.0, cols),
        C.ScanRequest(sk.PRODUCT, ("tau", "V"), half * 60.0, cols),
        C.ScanRequest(sk.ABS, ("S",), np.full(2, np.inf), cols[2:]),
        C.ScanRequest(sk.ABS, (own,), np.array([1.0, 1.5, 0.0])),
        C.ScanRequest(sk.SUM3, tuple(rate), np.array([2.0, 2.5])),
        C.ScanRequest(sk.ABS, ("tau",), envelope, cols[1:3]),
        C.ScanRequest(sk.ABS, ("J",), np.array([-1.0, 0.0]), cols[:2]),   # limits ≤ 0
    ]
    got = C.scan(m, requests)
    V, A, tau = m.V, m.A, m.tau
    full = lambda L: np.broadcast_to(L, (M, len(L)))  # noqa: E731
    _check(got[0], V, full(half * 2.0), m)
    _check(got[1], np.where(V * A < 0, A, 0.0), full(half * 5.0), m)
    _check(got[2], tau * V, full(half * 60.0), m)
    _check(got[3], m.S[:, 2:], full(np.full(2, np.inf)), m)
    _check(got[4], own, full(np.array([1.0, 1.5, 0.0])), m)
    _check(got[5], rate[0] + rate[1] + rate[2], full(np.array([2.0, 2.5])), m)
    _check(got[6], tau[:, 1:3], envelope, m)
    _check(got[7], m.J[:, :2], full(np.array([-1.0, 0.0])), m)
    # the cases the fused pass shortcuts are there: a violation, a NaN, the tie
    assert got[0].first[1] >= 0 and got[0].peak_at[1] == 100
    assert math.isnan(got[4].abs_peak[1]) == (r0 <= 5) and not math.isnan(got[4].ratio[1])


def test_one_scan_for_all_equals_each_request_alone():
    m = _motion(5, 0)
    requests = [C.ScanRequest(sk.ABS, ("V",), np.ones(NV), np.arange(NV)),
                C.ScanRequest(sk.PRODUCT, ("tau", "V"), np.full(2, 50.0), np.array([3, 0]))]
    together = C.scan(m, requests)
    for r, answer in zip(requests, together):
        alone = C.scan(m, [r])[0]
        for key, x in vars(answer).items():
            np.testing.assert_array_equal(x, getattr(alone, key))


def test_the_checks_joint_peaks_are_numpys_on_its_own_samples():
    """Through check_trajectory: velocity, deceleration and power peaks (ratio and time) from
    NumPy over the check's samples and torque, at limits the trajectory stays within."""
    from benchmarks.feasibility_bench import every_limit_kind, trajectory
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.robot.model import load_model

    model = load_model(builtin="panda").with_limits(None)
    limits = every_limit_kind(model)
    for entry in limits["joint_limits"].values():
        entry.update(has_deceleration_limits=True, max_deceleration=12.0)
    model = model.with_limits(limits)
    dyn = Dynamics(model)
    traj = trajectory(model)
    opts = F.FeasibilityOptions(sample_period=0.002, compute_payload_margin=False)
    r = F.check_trajectory(dyn, traj, opts)
    pp = F.interpolate(traj, traj.natural_interpolation)
    smp = F._sample(traj.times, opts.sample_period, opts.max_samples)
    Q, V, A = F._evaluate(pp.coeffs, pp.breaks, smp, 3)
    tau = dyn.rnea_batch(Q, V, A)
    lim = model.limits
    for kind, value, L in (("velocity", V, lim.velocity),
                           ("deceleration", np.where(V * A < 0, A, 0.0), lim.deceleration),
                           ("power", tau * V, lim.power)):
        assert np.all(np.isfinite(L)), kind
        ratio = np.abs(value) / L
        for j, name in enumerate(model.joint_names):
            n = int(np.argmax(ratio[:, j]))
            e = r.per_joint[name][kind]
            if kind == "power":
                assert e["ratio"] == pytest.approx(ratio[n, j], rel=1e-9), (kind, name)
                assert e["time_s"] == pytest.approx(smp.t[n], abs=1e-12), (kind, name)
            else:
                # the kinematic kinds' peaks are exact on each piece (test_exact_peaks): at
                # least the samples', and scipy's extremum of the piecewise polynomial
                assert e["ratio"] >= ratio[n, j] * (1 - 1e-12), (kind, name)
                assert e["ratio"] == pytest.approx(_scipy_peak(pp, j, kind) / L[j], rel=1e-9)


def _scipy_peak(pp, j: int, kind: str) -> float:
    """|q̇| or the deceleration's largest |q̈| (q̇·q̈ < 0) of joint j from scipy's PPoly: at the
    knots and the roots of the next derivative (and of q̇, for the deceleration)."""
    from scipy.interpolate import PPoly

    poly = PPoly(pp.coeffs[:, ::-1, j].T, pp.breaks)
    v, a = poly.derivative(1), poly.derivative(2)
    t = np.concatenate([pp.breaks, a.roots(extrapolate=False), poly.derivative(3).roots(
        extrapolate=False), v.roots(extrapolate=False)])
    t = t[np.isfinite(t)]
    if kind == "velocity":
        return float(np.max(np.abs(v(t))))
    # the deceleration's supremum: |q̈| where q̇·q̈ < 0 or q̇ stops (either side of a knot)
    tl = np.concatenate([t, t - 1e-12, t + 1e-12])
    tl = tl[(tl >= pp.breaks[0]) & (tl <= pp.breaks[-1])]
    return float(np.max(np.abs(a(tl)) * (v(tl) * a(tl) < 0)))
