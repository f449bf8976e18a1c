"""The contact/collision state machine on hand-made external-torque sequences."""
from __future__ import annotations

import numpy as np
import pytest

from dyn_node.core.contacts.contact import COLLISION, CONTACT, NONE, ContactDetector, ContactOptions
from dyn_node.core.contacts.observer import WrenchEstimate

NAMES = ("j1", "j2", "j3")
LIMIT = np.array([100.0, 50.0, 10.0])
DT = 0.001


def detector(**kw) -> ContactDetector:
    return ContactDetector(NAMES, LIMIT, units=("N·m", "N·m", "N"), frame="tool",
                           options=ContactOptions(**kw))


def feed(det, t0, samples, dt=DT):
    """Feed τ rows at t0, t0 + dt, …; returns the states."""
    return [det.update(t0 + k * dt, np.asarray(tau, dtype=float)) for k, tau in enumerate(samples)]


def test_a_burst_shorter_than_min_duration_is_ignored():
    det = detector(min_duration_s=0.02)
    over = [6.0, 0.0, 0.0]  # 0.06 of j1's limit: over its 0.05 contact threshold
    # samples over the threshold at 0 … 19 ms span 19 ms: not yet 20 ms
    states = feed(det, 0.0, [over] * 20 + [[0.0, 0.0, 0.0]])
    assert all(s.state == NONE for s in states) and det.history == []
    # a run lasting exactly 20 ms (21 samples) is a contact, starting at its first sample
    states = feed(det, 1.0, [over] * 21)
    assert [s.state for s in states].index(CONTACT) == 20
    assert det.episode.start_s == pytest.approx(1.0)


def test_a_dip_below_the_threshold_restarts_the_duration():
    det = detector(min_duration_s=0.02)
    over, dip = [6.0, 0.0, 0.0], [4.0, 0.0, 0.0]
    states = feed(det, 0.0, [over] * 15 + [dip] + [over] * 15)
    assert all(s.state == NONE for s in states)
    states = feed(det, 0.031, [over] * 6)
    assert states[-1].state == CONTACT
    assert det.episode.start_s == pytest.approx(0.016)


def test_hysteresis_ends_only_below_half_the_contact_threshold_on_every_joint():
    det = detector(min_duration_s=0.0)
    s = feed(det, 0.0, [[6.0, 0.0, 0.0]])[-1]
    assert s.state == CONTACT
    # below the threshold (5 N·m) but above half of it (2.5 N·m): still in contact
    assert feed(det, 0.001, [[3.0, 0.0, 0.0]] * 50)[-1].state == CONTACT
    # j1 released, j3 at 0.3 N (above half of its 0.5 N threshold): still in contact
    assert feed(det, 0.1, [[1.0, 0.0, 0.3]])[-1].state == CONTACT
    end = feed(det, 0.2, [[2.4, 1.2, 0.2]])[-1]
    assert end.state == NONE and end.episode is None
    assert end.ended.end_s == pytest.approx(0.2) and end.ended.start_s == 0.0
    assert end.ended.end_reason == "every joint below half its contact threshold"
    assert det.history == [end.ended]


def test_thresholds_are_per_joint_fractions_of_each_limit():
    det = detector(contact_threshold=[0.05, 0.2, 0.05], min_duration_s=0.0)
    # j2 at 0.1 of its limit: under its own 0.2 threshold
    assert feed(det, 0.0, [[0.0, 5.0, 0.0]])[-1].state == NONE
    # j3 at 0.6 N of 10 N: over 0.05 of its limit
    s = feed(det, 0.001, [[0.0, 5.0, 0.6]])[-1]
    assert s.state == CONTACT
    np.testing.assert_allclose(s.ratios, [0.0, 0.1, 0.06])
    assert [j.joint for j in s.episode.joints] == ["j3"]
    with pytest.raises(ValueError, match="contact_threshold needs 1 or 3 values"):
        detector(contact_threshold=[0.1, 0.2])
    with pytest.raises(ValueError, match="collision_threshold must be ≥ contact_threshold"):
        detector(contact_threshold=0.3, collision_threshold=0.2)


def test_collision_needs_its_own_duration_and_latches_until_the_end():
    det = detector(min_duration_s=0.01)
    states = feed(det, 0.0, [[25.0, 0.0, 0.0]] * 11)  # 0.25: over the 0.20 collision threshold
    assert [s.state for s in states][-2:] == [NONE, COLLISION]
    det2 = detector(min_duration_s=0.01)
    # in contact, then a collision-level spike shorter than the duration: stays contact
    feed(det2, 0.0, [[6.0, 0.0, 0.0]] * 11)
    assert det2.state == CONTACT
    feed(det2, 0.011, [[25.0, 0.0, 0.0]] * 5 + [[6.0, 0.0, 0.0]])
    assert det2.state == CONTACT
    feed(det2, 0.02, [[25.0, 0.0, 0.0]] * 11)
    assert det2.state == COLLISION
    # back under the collision threshold, still in contact: the episode stays a collision
    assert feed(det2, 0.04, [[6.0, 0.0, 0.0]])[-1].state == COLLISION
    end = feed(det2, 0.05, [[0.0, 0.0, 0.0]])[-1]
    assert end.state == NONE and end.ended.level == COLLISION


def test_no_estimate_ends_the_episode_and_says_why():
    det = detector(min_duration_s=0.0)
    feed(det, 0.0, [[6.0, 0.0, 0.0]])
    s = det.update(0.01, None, reason="effort not measured")
    assert not s.available and s.reason == "effort not measured" and s.state == NONE
    assert s.ended.end_reason == "no estimate: effort not measured" and s.ended.end_s == 0.01
    # the run is forgotten: a new contact needs its own duration again
    det3 = detector(min_duration_s=0.02)
    feed(det3, 0.0, [[6.0, 0.0, 0.0]] * 15)
    det3.update(0.015, None, reason="gap")
    assert feed(det3, 0.016, [[6.0, 0.0, 0.0]] * 15)[-1].state == NONE


def _wrench(f):
    return WrenchEstimate(frame="tool", wrench=np.array([*f, 0.0, 0.0, 0.0]), sigma_min=0.3, damping=0.0,
                          singular=False, misfit=0.0, determined=True)


def test_episode_peaks_and_message():
    det = ContactDetector(("panda_joint2", "panda_joint4"), [87.0, 87.0], frame="panda_link8",
                          options=ContactOptions(min_duration_s=0.0))
    det.update(1.00, np.array([9.0, 10.0]), _wrench((0.0, 0.0, 20.0)))
    det.update(1.05, np.array([-9.02, -14.1]), _wrench((0.0, 38.0, 0.0)))
    s = det.update(1.12, np.array([2.0, 19.0]), _wrench((0.0, 0.0, 30.0)))
    ep = s.episode
    assert ep.level == COLLISION  # 19/87 = 0.218 > 0.20, with a zero min duration
    assert ep.peak_force_n == pytest.approx(38.0)
    np.testing.assert_allclose(ep.peak_wrench, [0.0, 38.0, 0.0, 0.0, 0.0, 0.0])
    assert [(j.joint, j.torque) for j in ep.joints] == [("panda_joint4", 19.0), ("panda_joint2", 9.02)]
    assert ep.peak_ratio == pytest.approx(19.0 / 87.0)
    assert ep.message(1.12) == ("collision: 38 N at panda_link8 (panda_joint4 19 N·m of 87, "
                                "panda_joint2 9.02 N·m of 87), 0.12 s")
    without = ContactDetector(("a",), [10.0], units=("N",), options=ContactOptions(min_duration_s=0.0))
    without.update(0.0, np.array([0.7]))
    assert without.episode.message(0.5) == "contact: a 0.7 N of 10, 0.50 s"


def test_an_infinite_limit_never_triggers_and_bad_options_are_refused():
    det = ContactDetector(("a", "b"), [np.inf, 10.0], options=ContactOptions(min_duration_s=0.0))
    assert det.update(0.0, np.array([1e6, 0.0])).state == NONE
    assert det.update(0.001, np.array([0.0, 0.6])).state == CONTACT
    zero = ContactDetector(("a", "b"), [0.0, 10.0], options=ContactOptions(min_duration_s=0.0))
    assert zero.update(0.0, np.array([0.0, 0.0])).state == NONE
    s = zero.update(0.001, np.array([1e-6, 0.0]))
    assert s.state == COLLISION and s.ratios[0] == np.inf  # a zero limit: any torque is over both
    nan = zero.update(0.002, np.array([np.nan, 0.0]))
    assert not nan.available and nan.ended is not None and nan.reason == "external-torque estimate not finite"
    with pytest.raises(ValueError, match="tau_ext needs 2 values"):
        zero.update(0.003, np.zeros(3))
    with pytest.raises(ValueError, match="min_duration_s"):
        ContactDetector(("a",), [1.0], options=ContactOptions(min_duration_s=-1.0))
    with pytest.raises(ValueError, match="release_fraction"):
        ContactDetector(("a",), [1.0], options=ContactOptions(release_fraction=0.0))
    with pytest.raises(ValueError, match="effort_limit"):
        ContactDetector(("a",), [np.nan])


def test_history_limit_keeps_the_latest_episodes_and_counts_all():
    """A long-running node keeps only the latest ended episodes; ``ended`` counts every one."""
    d = ContactDetector(["j"], [10.0], options=ContactOptions(min_duration_s=0.0, history_limit=2))
    t = 0.0
    for k in range(5):
        for tau in (1.0, 0.0):  # over 5 % of 10, then below half of it: one episode each
            d.update(t, np.array([tau]))
            t += 0.001
    assert d.ended == 5 and len(d.history) == 2
    assert [e.start_s for e in d.history] == pytest.approx([0.006, 0.008])
