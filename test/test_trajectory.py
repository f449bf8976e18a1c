"""Trajectory validation and interpolation, checked against independent constructions."""
from __future__ import annotations

import numpy as np
import pytest

from dyn_node.errors import PLANNING_ERROR, TrajectoryError
from dyn_node.core.check.trajectory import Trajectory, clamped_spline_velocities, interpolate, validate_trajectory

J = ("a", "b", "c")


def expect(code, *fragments, **kw):
    args = dict(model_joints=J, names=J, times=[0.0, 1.0], positions=[[0, 0, 0], [1, 1, 1]])
    args.update(kw)
    with pytest.raises(TrajectoryError) as e:
        validate_trajectory(**args)
    assert e.value.code == code, str(e.value)
    assert e.value.failure_label == PLANNING_ERROR
    for f in fragments:
        assert f in str(e.value), str(e.value)


def test_validation_errors():
    expect("empty_names", names=[])
    expect("duplicate_names", "b", names=["a", "b", "b"])
    expect("unknown_joints", "z", names=["a", "b", "c", "z"], positions=[[0] * 4, [1] * 4])
    expect("missing_joints", "c", names=["a", "b"], positions=[[0, 0], [1, 1]])
    expect("empty_points", times=[], positions=[])
    expect("too_few_points", times=[0.5], positions=[[0, 0, 0]])
    expect("length_mismatch", times=[0.0, 1.0, 2.0])
    expect("length_mismatch", "point 1", positions=[[0, 0, 0], [1, 1]])
    expect("length_mismatch", "velocities", velocities=[[0, 0, 0], [1]])
    expect("length_mismatch", accelerations=[[0, 0, 0], [0, 0, 0]])
    expect("non_finite", "b", positions=[[0, 0, 0], [1, np.nan, 1]])
    expect("non_finite", velocities=[[0, 0, 0], [1, np.inf, 1]])
    expect("non_finite", times=[0.0, np.inf])
    expect("bad_times", "negative", times=[-0.1, 1.0])
    expect("bad_times", "point 2", times=[0.0, 1.0, 1.0], positions=[[0] * 3] * 3)
    expect("bad_times", times=[0.0, 2.0, 1.0], positions=[[0] * 3] * 3)


def test_validation_reorders_and_detects_mode():
    names = ["c", "a", "b"]
    t = validate_trajectory(J, names, [0.0, 1.0], [[3, 1, 2], [6, 4, 5]],
                            velocities=[[0.3, 0.1, 0.2], [0, 0, 0]])
    np.testing.assert_array_equal(t.positions, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(t.velocities[0], [0.1, 0.2, 0.3])
    assert t.accelerations is None and t.natural_interpolation == "cubic"
    assert t.n_points == 2 and t.duration == 1.0
    t2 = validate_trajectory(J, J, [0.0, 1.0], [[0] * 3] * 2, velocities=[[], []],
                             accelerations=[[], []])
    assert t2.velocities is None and t2.natural_interpolation == "spline"
    t3 = validate_trajectory(J, J, [0.0, 1.0], [[0] * 3] * 2, [[0] * 3] * 2, [[0] * 3] * 2)
    assert t3.natural_interpolation == "quintic"
    assert validate_trajectory(J, J, [0.2], [[0, 0, 0]], min_points=1).n_points == 1
    # the controller's own choice differs only for positions-only trajectories (linear, not spline)
    assert (t.jtc_interpolation, t2.jtc_interpolation, t3.jtc_interpolation) == \
        ("cubic", "linear", "quintic")


def random_traj(n=6, nj=3, seed=0, vel=True, acc=True):
    rng = np.random.default_rng(seed)
    times = np.concatenate([[0.0], np.cumsum(rng.uniform(0.2, 1.5, n - 1))])
    return Trajectory(times=times, positions=rng.uniform(-2, 2, (n, nj)),
                      velocities=rng.uniform(-1, 1, (n, nj)) if vel else None,
                      accelerations=rng.uniform(-3, 3, (n, nj)) if acc else None)


def one_sided(pp, t, h=1e-7):
    """Values just left and right of t (for continuity checks)."""
    return pp.evaluate(np.array([t - h])), pp.evaluate(np.array([t + h]))


def test_array_rows_validate_as_the_same_rows_as_lists():
    """N×k arrays (a message's rows, convert.trajectory_arrays) take a path without a loop over the
    rows: the same trajectory as the rows given as lists, and the same errors."""
    rng = np.random.default_rng(3)
    names = ["c", "a", "b"]
    p, v, a = (rng.normal(size=(4, 3)) for _ in range(3))
    times = [0.0, 0.5, 1.0, 1.5]
    fast = validate_trajectory(J, names, times, p, v, a)
    slow = validate_trajectory(J, names, times, p.tolist(), v.tolist(), a.tolist())
    for f in ("times", "positions", "velocities", "accelerations"):
        np.testing.assert_array_equal(getattr(fast, f), getattr(slow, f))
    assert fast.positions[0].tolist() == [p[0, 1], p[0, 2], p[0, 0]]  # model order a, b, c
    assert fast.fields is None and slow.fields is None
    bad = p.copy()
    bad[2, 1] = np.nan
    for rows in (bad, bad.tolist()):
        expect("non_finite", "point 2: positions of a is nan", names=names, times=times, positions=rows)
    for rows in (np.zeros((4, 2)), np.zeros((4, 2)).tolist()):
        expect("length_mismatch", "point 0: 2 positions for 3 joints", names=names, times=times, positions=rows)


@pytest.mark.parametrize("mode,order", [("quintic", 2), ("cubic", 1), ("spline", 2), ("linear", 0)])
def test_interpolation_hits_waypoints_and_is_continuous(mode, order):
    traj = random_traj(seed=3)
    pp = interpolate(traj, mode)
    q, qd, qdd, _ = pp.evaluate(traj.times)
    np.testing.assert_allclose(q, traj.positions, rtol=0, atol=1e-12)
    if mode in ("quintic", "cubic"):
        np.testing.assert_allclose(qd, traj.velocities, rtol=0, atol=1e-11)
    if mode == "quintic":
        np.testing.assert_allclose(qdd, traj.accelerations, rtol=0, atol=1e-10)
    if mode == "spline":
        np.testing.assert_allclose(qd[[0, -1]], 0.0, rtol=0, atol=1e-12)
    for t in traj.times[1:-1]:
        left, right = one_sided(pp, t)
        for d in range(order + 1):
            np.testing.assert_allclose(left[d], right[d], rtol=0, atol=1e-5 * 10**d)
    # Derivatives are consistent with each other (finite differences on one segment).
    t = np.linspace(traj.times[1], traj.times[2], 2001)[1:-1]  # strictly inside one segment
    q, qd, qdd, qddd = pp.evaluate(t)
    np.testing.assert_allclose(np.gradient(q, t, axis=0)[1:-1], qd[1:-1], atol=1e-5)
    if mode != "linear":
        np.testing.assert_allclose(np.gradient(qd, t, axis=0)[1:-1], qdd[1:-1], atol=1e-4)
        np.testing.assert_allclose(np.gradient(qdd, t, axis=0)[1:-1], qddd[1:-1], atol=1e-3)


def test_cubic_acceleration_jumps_so_continuity_check_can_fail():
    traj = random_traj(seed=4)
    pp = interpolate(traj, "cubic")
    left, right = one_sided(pp, traj.times[2])
    assert np.abs(left[2] - right[2]).max() > 1e-3


def test_linear_mode():
    traj = random_traj(seed=5, vel=False, acc=False)
    pp = interpolate(traj, "linear")
    t = 0.3 * traj.times[1] + 0.7 * traj.times[2]
    q, qd, qdd, _ = pp.evaluate(t)
    slope = (traj.positions[2] - traj.positions[1]) / (traj.times[2] - traj.times[1])
    np.testing.assert_allclose(q[0], traj.positions[1] + slope * (t - traj.times[1]), atol=1e-12)
    np.testing.assert_allclose(qd[0], slope, atol=1e-12)
    np.testing.assert_array_equal(qdd, 0.0)


def test_hold_outside_range():
    traj = random_traj(seed=6)
    traj = Trajectory(times=traj.times + 0.5, positions=traj.positions,
                      velocities=traj.velocities, accelerations=traj.accelerations)
    pp = interpolate(traj)
    q, qd, qdd, qddd = pp.evaluate(np.array([0.0, 0.4, traj.times[-1] + 0.1, traj.times[-1] + 10]))
    np.testing.assert_allclose(q[:2], traj.positions[[0, 0]], atol=1e-12)
    np.testing.assert_allclose(q[2:], traj.positions[[-1, -1]], atol=1e-12)
    for d in (qd, qdd, qddd):
        np.testing.assert_array_equal(d, 0.0)
    single = Trajectory(times=np.array([0.3]), positions=np.array([[1.0, 2.0]]))
    q, qd, _, _ = interpolate(single).evaluate(np.array([0.0, 0.3, 5.0]))
    np.testing.assert_array_equal(q, [[1.0, 2.0]] * 3)
    np.testing.assert_array_equal(qd, 0.0)


def dense_clamped_spline(t, p):
    """Independent solution: unknown cubic coefficients per segment from a dense linear system.

    Conditions: each segment interpolates both ends; q̇ and q̈ continuous at interior knots;
    q̇ = 0 at both ends. Returns knot velocities."""
    n = len(t)
    s = n - 1
    A = np.zeros((4 * s, 4 * s))
    b = np.zeros(4 * s)
    row = 0
    for i in range(s):
        h = t[i + 1] - t[i]
        A[row, 4 * i:4 * i + 4] = [1, 0, 0, 0]
        b[row] = p[i]
        row += 1
        A[row, 4 * i:4 * i + 4] = [1, h, h**2, h**3]
        b[row] = p[i + 1]
        row += 1
        if i < s - 1:
            A[row, 4 * i:4 * i + 4] = [0, 1, 2 * h, 3 * h**2]
            A[row, 4 * i + 5] = -1
            row += 1
            A[row, 4 * i:4 * i + 4] = [0, 0, 2, 6 * h]
            A[row, 4 * i + 6] = -2
            row += 1
    A[row, 1] = 1
    row += 1
    h = t[-1] - t[-2]
    A[row, 4 * (s - 1):] = [0, 1, 2 * h, 3 * h**2]
    c = np.linalg.solve(A, b).reshape(s, 4)
    return np.append(c[:, 1], 0.0)


@pytest.mark.parametrize("n", [2, 3, 4, 9, 40])
def test_clamped_spline_against_dense_solve(n):
    rng = np.random.default_rng(n)
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.05, 2.0, n - 1))])
    p = rng.uniform(-3, 3, (n, 2))
    v = clamped_spline_velocities(t, p)
    for j in range(2):
        np.testing.assert_allclose(v[:, j], dense_clamped_spline(t, p[:, j]), rtol=0, atol=1e-9)
    # C² at every interior knot: each segment's polynomial evaluated at its own end (s = T)
    # against the next segment's start, plus a one-sided numerical check.
    traj = Trajectory(times=t, positions=p)
    pp = interpolate(traj, "spline")
    c, T = pp.coeffs, np.diff(t)[:, None]
    for d, end in ((0, c[:, 0] + c[:, 1] * T + c[:, 2] * T**2 + c[:, 3] * T**3),
                   (1, c[:, 1] + 2 * c[:, 2] * T + 3 * c[:, 3] * T**2),
                   (2, 2 * c[:, 2] + 6 * c[:, 3] * T)):
        start = c[1:, 0] if d == 0 else (c[1:, 1] if d == 1 else 2 * c[1:, 2])
        np.testing.assert_allclose(end[:-1], start, rtol=1e-10, atol=1e-9)
    for tk in t[1:-1]:
        left, right = one_sided(pp, tk, 1e-9)
        np.testing.assert_allclose(left[2], right[2], rtol=0, atol=1e-4)


def test_interpolation_mode_needs_its_data():
    traj = random_traj(seed=7, vel=False, acc=False)
    with pytest.raises(TrajectoryError) as e:
        interpolate(traj, "cubic")
    assert e.value.code == "length_mismatch"
    with pytest.raises(TrajectoryError):
        interpolate(random_traj(seed=7, acc=False), "quintic")
    with pytest.raises(ValueError):
        interpolate(traj, "bezier")  # type: ignore[arg-type]


def _hermite(t0: float, q: float, v: float, a: float | None, q1: float, v1: float,
             a1: float | None) -> np.ndarray:
    """Polynomial coefficients (increasing powers) on [0, t0] from the boundary conditions,
    by a dense linear solve (independent of trajectory._quintic/_cubic)."""
    deg = 5 if a is not None else 3
    rows, rhs = [], []
    for t, vals in ((0.0, (q, v, a)), (t0, (q1, v1, a1))):
        for d, val in enumerate(vals[:3 if a is not None else 2]):
            rows.append([np.prod(np.arange(p - d + 1, p + 1)) * t ** (p - d) if p >= d else 0.0
                         for p in range(deg + 1)])
            rhs.append(val)
    return np.linalg.solve(np.array(rows, dtype=float), np.array(rhs, dtype=float))


@pytest.mark.parametrize("mode", ["quintic", "cubic", "spline"])
def test_from_current_state_prepends_the_measured_state_as_the_controller_does(mode):
    """joint_trajectory_controller starts from the current state (measured q, q̇, q̈ = 0) at
    t = 0 and reaches the first point at its time_from_start, interpolating by what the points
    give; the points after the first move exactly as without the start state."""
    from dyn_node.core.check.trajectory import from_current_state

    t = np.array([0.4, 1.0, 1.7])
    P = np.array([[0.2, -0.1, 0.5], [0.6, 0.3, 0.1], [0.9, 0.0, -0.2]])
    V = np.array([[0.3, -0.2, 0.1], [0.5, 0.1, -0.4], [0.0, 0.0, 0.0]])
    Acc = np.array([[1.0, -2.0, 0.5], [0.2, 0.4, -1.0], [0.0, 0.0, 0.0]])
    traj = Trajectory(times=t, positions=P, velocities=None if mode == "spline" else V,
                      accelerations=Acc if mode == "quintic" else None)
    qm, vm = np.array([-0.3, 0.4, 0.2]), np.array([-1.5, 0.8, 0.0])
    work = from_current_state(traj, qm, vm)
    assert work.natural_interpolation == ("quintic" if mode == "quintic" else "cubic")
    np.testing.assert_array_equal(work.times, [0.0, 0.4, 1.0, 1.7])
    pp, own = interpolate(work), interpolate(traj)
    # the first point's velocity: given, or the spline's own (clamped: zero at the ends)
    v1 = V[0] if mode != "spline" else np.zeros(3)
    ts = np.linspace(0.0, 0.4, 41)
    q, qd, qdd, _ = pp.evaluate(ts)
    for j in range(3):
        c = _hermite(0.4, qm[j], vm[j], 0.0 if mode == "quintic" else None, P[0, j], v1[j],
                     Acc[0, j] if mode == "quintic" else None)
        np.testing.assert_allclose(q[:, j], np.polyval(c[::-1], ts), rtol=0, atol=1e-12)
        np.testing.assert_allclose(qd[:, j], np.polyval(np.polyder(c[::-1]), ts), rtol=0, atol=1e-11)
    np.testing.assert_allclose(qd[0], vm, rtol=0, atol=1e-12)
    if mode == "quintic":
        np.testing.assert_allclose(qdd[0], 0.0, rtol=0, atol=1e-12)
    later = np.linspace(0.4, 1.7, 27)
    for a, b in zip(pp.evaluate(later), own.evaluate(later)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    with pytest.raises(ValueError):
        from_current_state(Trajectory(times=np.array([0.0, 1.0]), positions=P[:2]), qm, vm)
