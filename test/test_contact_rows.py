"""ContactDetector.update_rows against the per-sample update()/unavailable() loop, row by row."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dyn_node.core.contacts.contact import COLLISION, ContactDetector, ContactEpisode, ContactOptions
from dyn_node.core.contacts.observer import WrenchEstimate

NOT_FINITE = "external-torque estimate not finite"


def _estimate(w: np.ndarray) -> WrenchEstimate:
    return WrenchEstimate(frame="tool", wrench=w, sigma_min=0.3, damping=0.0, singular=False,
                          misfit=0.0, determined=True)


def reference(det: ContactDetector, t, tau, wrench, has, unavailable) -> list[ContactEpisode]:
    """The per-row loop update_rows must reproduce: the ended episodes, in order."""
    out = []
    for k in range(len(t)):
        if k in unavailable:
            st = det.unavailable(t[k], unavailable[k])
        else:
            st = det.update(t[k], tau[k], _estimate(wrench[k]) if has[k] else None)
        if st.ended is not None:
            out.append(st.ended)
    return out


def same_episode(a: ContactEpisode | None, b: ContactEpisode | None) -> None:
    if a is None or b is None:
        assert a is b
        return
    fields = ("start_s", "level", "frame", "end_s", "end_reason")
    assert [getattr(a, f) for f in fields] == [getattr(b, f) for f in fields]
    assert a.joints == b.joints  # names, torques, ratios, limits, units, and their order
    if a.peak_wrench is None or b.peak_wrench is None:
        assert a.peak_wrench is b.peak_wrench
    else:
        assert a.peak_wrench.dtype == b.peak_wrench.dtype
        assert np.array_equal(a.peak_wrench, b.peak_wrench, equal_nan=True)
    fa, fb = a.peak_force_n, b.peak_force_n
    assert (fa is None) == (fb is None) and type(fa) is type(fb)
    if fa is not None:
        assert fa == fb or (math.isnan(fa) and math.isnan(fb))


def same_state(a: ContactDetector, b: ContactDetector) -> None:
    same_episode(a.episode, b.episode)
    same_episode(a._candidate, b._candidate)
    assert a._over_contact.since == b._over_contact.since
    assert a._over_collision.since == b._over_collision.since
    assert a.ended == b.ended and len(a.history) == len(b.history)
    for x, y in zip(a.history, b.history):
        same_episode(x, y)


def random_case(rng: np.random.Generator):
    """A detector configuration and rows mixing quiet rows, bursts under and over the contact
    and collision levels, rows without estimate or with a non-finite one, rows without
    wrench, repeated stamps; values on a coarse grid so ratios and forces tie."""
    nv = int(rng.choice([1, 2, 3, 7]))
    limit = rng.choice([10.0, 10.0, 50.0, 87.0], size=nv)  # repeated limits: equal ratios
    if nv > 1 and rng.random() < 0.25:
        limit[rng.integers(nv)] = 0.0  # any torque is over both levels; never released
    if nv > 1 and rng.random() < 0.2:
        limit[rng.integers(nv)] = np.inf  # never over
    if rng.random() < 0.5:
        contact = 0.05
    else:
        contact = rng.choice([0.03, 0.05, 0.1], size=nv)
    collision = np.asarray(contact) * rng.choice([1.0, 2.0, 4.0])
    opts = ContactOptions(contact_threshold=contact, collision_threshold=collision,
                          min_duration_s=float(rng.choice([0.0, 0.0, 0.002, 0.005])),
                          release_fraction=float(rng.choice([0.5, 1.0])),
                          history_limit=rng.choice([None, 1, 2]))
    names = [f"j{i}" for i in range(nv)]
    kw = dict(units=["N·m"] * nv, frame="tool", options=opts)
    det_a, det_b = ContactDetector(names, limit, **kw), ContactDetector(names, limit, **kw)

    n = int(rng.integers(1, 400))
    # per segment a level (in units of the contact level) held for a few rows
    levels = np.array([0.0, 0.2, 0.7, 1.0, 1.5, 3.0, 6.0])
    tau = np.empty((n, nv))
    k = 0
    while k < n:
        m = int(rng.integers(1, 30))
        lv = levels[rng.choice(len(levels), p=[.25, .15, .15, .1, .15, .1, .1])]
        q = lv * np.asarray(contact) * np.where(np.isfinite(limit) & (limit > 0), limit, 10.0)
        jitter = rng.choice([1.0, 1.0, 1.1, 1.3], size=(min(m, n - k), nv))  # coarse: ties
        jitter *= rng.random(size=(min(m, n - k), nv)) < rng.choice([0.3, 1.0])  # some joints quiet
        tau[k:k + m] = q * jitter * rng.choice([-1.0, 1.0], size=jitter.shape)
        k += m
    dt = rng.choice([0.0, 0.0005, 0.001, 0.001, 0.001], size=n)  # 0: repeated stamps
    t = 100.0 + np.cumsum(dt)
    unavailable = {}
    for k in np.flatnonzero(rng.random(n) < rng.choice([0.0, 0.01, 0.05])):
        tau[k] = rng.choice([np.nan, 1e9, -3.0])  # anything: must not be read
        unavailable[int(k)] = str(rng.choice(["effort not measured", "gap"]))
    for k in np.flatnonzero(rng.random(n) < rng.choice([0.0, 0.01])):
        if int(k) not in unavailable:
            tau[k, rng.integers(nv)] = rng.choice([np.nan, np.inf, -np.inf])
    # wrenches on a grid: [3, 4, 0] and [0, 5, 0] have the same force, different rows
    grid = np.array([[3.0, 4.0, 0.0], [0.0, 5.0, 0.0], [0.0, 0.0, 5.0], [6.0, 8.0, 0.0],
                     [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    wrench = np.zeros((n, 6))
    wrench[:, :3] = grid[rng.integers(len(grid), size=n)]
    wrench[:, 3:] = rng.integers(-2, 3, size=(n, 3))
    has = rng.random(n) < rng.choice([0.0, 0.5, 1.0])
    force = np.full(n, np.nan)  # read only where has
    for k in np.flatnonzero(has):
        force[k] = _estimate(wrench[k]).force_n
    return det_a, det_b, t, tau, force, wrench, has, unavailable


def run_chunks(det, rng, t, tau, force, wrench, has, unavailable) -> list[ContactEpisode]:
    out, k, n = [], 0, len(t)
    while k < n:
        e = min(n, k + int(rng.choice([1, 2, 7, 50, 1000])))
        local = {r - k: why for r, why in unavailable.items() if k <= r < e}
        out += det.update_rows(t[k:e], tau[k:e], force[k:e], wrench[k:e], has[k:e], local)
        k = e
    return out


def test_update_rows_equals_the_per_row_loop_on_random_sequences():
    rng = np.random.default_rng(20261202)
    seen = dict(ended=0, collisions=0, by_release=0, by_no_estimate=0, not_finite=0,
                tied_joints=0, open_at_end=0, candidate_at_end=0, wrench=0, trimmed=0)
    for _ in range(400):
        det_a, det_b, t, tau, force, wrench, has, unavailable = random_case(rng)
        got = run_chunks(det_a, rng, t, tau, force, wrench, has, unavailable)
        want = reference(det_b, t, tau, wrench, has, unavailable)
        assert len(got) == len(want)
        for x, y in zip(got, want):
            same_episode(x, y)
        same_state(det_a, det_b)
        for ep in want + ([det_b.episode] if det_b.episode else []):
            seen["collisions"] += ep.level == COLLISION
            seen["wrench"] += ep.peak_wrench is not None
            ratios = [j.ratio for j in ep.joints]
            seen["tied_joints"] += len(set(ratios)) < len(ratios)
        seen["ended"] += len(want)
        seen["by_release"] += sum(e.end_reason.startswith("every joint") for e in want)
        seen["by_no_estimate"] += sum(e.end_reason.startswith("no estimate: ") for e in want)
        seen["not_finite"] += sum(e.end_reason == f"no estimate: {NOT_FINITE}" for e in want)
        seen["open_at_end"] += det_b.episode is not None
        seen["candidate_at_end"] += det_b._candidate is not None
        seen["trimmed"] += det_b.ended > len(det_b.history)
    # the data exercises what it claims to (else this test could pass on nothing)
    assert seen["ended"] > 500 and seen["collisions"] > 100, seen
    print(seen)
    assert min(seen.values()) > 5, seen


def test_update_rows_after_and_before_per_row_updates():
    """The state update_rows starts from may be left by update() (an open episode, a
    candidate, an open collision run), and update() goes on from the state it leaves."""
    rng = np.random.default_rng(7)
    for _ in range(150):
        det_a, det_b, t, tau, force, wrench, has, unavailable = random_case(rng)
        n = len(t)
        a, b = sorted(rng.integers(0, n + 1, size=2))
        parts = [(0, a, False), (a, b, True), (b, n, False)]
        got, want = [], reference(det_b, t, tau, wrench, has, unavailable)
        for lo, hi, batched in parts:
            local = {r - lo: why for r, why in unavailable.items() if lo <= r < hi}
            args = (t[lo:hi], tau[lo:hi], force[lo:hi], wrench[lo:hi], has[lo:hi], local)
            if batched:
                got += det_a.update_rows(*args)
            else:
                got += reference(det_a, args[0], args[1], args[3], args[4], local)
        assert len(got) == len(want)
        for x, y in zip(got, want):
            same_episode(x, y)
        same_state(det_a, det_b)


def _split_everywhere(make, t, tau):
    """update_rows on rows [0, a) and [a, n) for every a, against the per-row loop."""
    n = len(t)
    force, wrench, has = np.zeros(n), np.zeros((n, 6)), np.zeros(n, bool)
    ref = make()
    want = reference(ref, t, tau, wrench, has, {})
    for a in range(n + 1):
        det = make()
        got = det.update_rows(t[:a], tau[:a], force[:a], wrench[:a], has[:a], {})
        got += det.update_rows(t[a:], tau[a:], force[a:], wrench[a:], has[a:], {})
        assert len(got) == len(want)
        for x, y in zip(got, want):
            same_episode(x, y)
        same_state(det, ref)
    return ref


def test_a_collision_run_carried_across_calls_escalates_as_row_by_row():
    """In contact, then over the collision level for exactly min_duration_s, then back to
    contact: a collision whichever row the calls are split at (the run's start is carried)."""
    def make():
        return ContactDetector(["a", "b"], [10.0, 10.0], options=ContactOptions(
            contact_threshold=0.05, collision_threshold=0.2, min_duration_s=0.005))
    rows = [[1.0, 0.0]] * 8 + [[3.0, 0.0]] * 6 + [[1.0, 0.0]] * 5 + [[0.0, 0.0]] * 2
    t = np.arange(len(rows)) * 0.001
    ref = _split_everywhere(make, t, np.array(rows))
    assert ref.ended == 1 and ref.history[0].level == COLLISION
    # one row shorter: stays a contact
    rows = [[1.0, 0.0]] * 8 + [[3.0, 0.0]] * 5 + [[1.0, 0.0]] * 5 + [[0.0, 0.0]] * 2
    ref = _split_everywhere(make, t[:len(rows)], np.array(rows))
    assert ref.ended == 1 and ref.history[0].level != COLLISION


def test_escalation_at_exactly_min_duration_less_the_stamp_slack():
    """A collision run lasting exactly min_duration_s − STAMP_RESOLUTION_S (in float seconds)
    escalates; one ulp less does not; the same with rows in one call or split."""
    from dyn_node.core.contacts.contact import STAMP_RESOLUTION_S

    def make():
        return ContactDetector(["a"], [10.0], options=ContactOptions(
            contact_threshold=0.05, collision_threshold=0.2, min_duration_s=0.004))
    edge = 0.004 - STAMP_RESOLUTION_S
    for last, level in ((edge, COLLISION), (np.nextafter(edge, 0.0), "contact")):
        t = np.array([-0.01, -0.005, 0.0, last, last])
        tau = np.array([[1.0], [1.0], [3.0], [3.0], [1.0]])
        ref = _split_everywhere(make, t, tau)
        assert ref.episode.level == level


def _counting(monkeypatch) -> dict:
    calls = {"update": 0, "unavailable": 0}
    for name in calls:
        orig = getattr(ContactDetector, name)

        def wrapped(self, *a, _orig=orig, _name=name, **kw):
            calls[_name] += 1
            return _orig(self, *a, **kw)
        monkeypatch.setattr(ContactDetector, name, wrapped)
    return calls


def _franka() -> ContactDetector:
    return ContactDetector([f"panda_joint{i}" for i in range(1, 8)],
                           [87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0], frame="panda_link8",
                           options=ContactOptions(min_duration_s=0.02))


def test_quiet_rows_take_the_fast_path(monkeypatch):
    """10,000 quiet rows (and a few without estimate) cost no per-row Python step."""
    n = 10_000
    rng = np.random.default_rng(1)
    t = np.arange(n) * 0.001
    tau = rng.normal(0.0, 0.05, size=(n, 7))  # far under 5 % of the limits (0.6 N·m)
    calls = _counting(monkeypatch)
    det = _franka()
    assert det.update_rows(t, tau, np.zeros(n), np.zeros((n, 6)), np.zeros(n, bool),
                           {10: "gap", 5000: "gap"}) == []
    assert calls == {"update": 0, "unavailable": 0}
    assert det.episode is None and det.ended == 0


def test_a_long_collision_is_folded_not_stepped(monkeypatch):
    """10,000 rows of one collision: only the rows before it lasts min_duration_s, and the
    row that ends it, go through update(); the episode is the per-row loop's."""
    n = 10_000
    rng = np.random.default_rng(2)
    t = np.arange(n) * 0.001
    tau = rng.normal(0.0, 0.05, size=(n, 7))
    tau[100:9_000, 3] = 30.0 + rng.normal(0.0, 2.0, size=8_900)  # over 20 % of 87 N·m
    wrench = rng.normal(0.0, 10.0, size=(n, 6))
    force = np.array([_estimate(w).force_n for w in wrench])
    has = np.ones(n, bool)
    ref = _franka()
    want = reference(ref, t, tau, wrench, has, {})
    calls = _counting(monkeypatch)
    det = _franka()
    got = det.update_rows(t, tau, force, wrench, has, {})
    assert calls["update"] <= 25 and calls["unavailable"] == 0, calls
    assert len(got) == len(want) == 1 and got[0].level == COLLISION
    same_episode(got[0], want[0])
    same_state(det, ref)


def test_update_rows_refuses_bad_shapes_and_rows():
    det = _franka()
    z = np.zeros
    with pytest.raises(ValueError, match="tau needs shape"):
        det.update_rows(z(3), z((3, 6)), z(3), z((3, 6)), z(3, bool), {})
    with pytest.raises(ValueError, match="force_n, wrench, has_wrench"):
        det.update_rows(z(3), z((3, 7)), z(3), z((3, 3)), z(3, bool), {})
    with pytest.raises(ValueError, match="unavailable row 3"):
        det.update_rows(z(3), z((3, 7)), z(3), z((3, 6)), z(3, bool), {3: "gap"})
    assert det.update_rows(z(0), z((0, 7)), z(0), z((0, 6)), z(0, bool), {}) == []
