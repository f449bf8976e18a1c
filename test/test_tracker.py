"""The controller tracker follows what the controller executes (the execution model), not the
message: the segment from the robot's state to a first point due ahead, a past stamp's cut, and
a refused trajectory that leaves the running one in place. References are closed forms."""
from __future__ import annotations

import numpy as np
import pytest

from dyn_node.core.check.execution import Timing
from dyn_node.core.check.start_segment import StartState
from dyn_node.core.check.trajectory import validate_trajectory
from dyn_node.core.live.monitor import Monitor
from dyn_node.core.live.tracker import ControllerTracker
from dyn_node.core.robot.model import load_model
from dyn_node.core.robot.settings import Settings

PANDA = load_model(builtin="panda")
NAMES = PANDA.joint_names
Q0 = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.6, 0.8])
ZERO = np.zeros(7)


def _rest(q: np.ndarray) -> StartState:
    return StartState(positions=q, velocities=ZERO, age_s=0.0)


def _quintic_rest(times, positions):
    n = len(times)
    return validate_trajectory(NAMES, NAMES, times, positions, [ZERO] * n, [ZERO] * n)


def test_a_first_point_due_ahead_is_reached_through_the_start_segment():
    """Robot at rest at Q0, first point Q0 + 0.2 due 0.5 s after receipt: the controller moves
    there on a rest-to-rest quintic, whose midpoint is exactly half way (10τ³ − 15τ⁴ + 6τ⁵ = ½)."""
    s = Settings(tracking_tolerance=0.01)
    tr, mon = ControllerTracker(PANDA, s), Monitor(PANDA, s)
    ex = tr.follow(_quintic_rest([0.5, 1.0], [Q0 + 0.2, Q0 + 0.3]), timing=Timing(0.0, 2.0),
                   start=_rest(Q0))
    assert ex.start_segment
    np.testing.assert_allclose(tr.reference(2.0), Q0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(tr.reference(2.25), Q0 + 0.1, rtol=0, atol=1e-14)
    np.testing.assert_allclose(tr.reference(2.5), Q0 + 0.2, rtol=0, atol=1e-14)
    np.testing.assert_allclose(tr.reference(3.0), Q0 + 0.3, rtol=0, atol=1e-14)
    assert tr.reference(1.99) is None and tr.reference(3.01) is None
    # a robot still at Q0 a tenth into the start segment is tracking (the reference is 3.5 mrad
    # away), not idle; one that stayed put to its middle is deviating
    assert tr.update(mon.process(NAMES, Q0, [], [], 2.05, 2.05), 2.05) and tr.state == "tracking"
    assert tr.update(mon.process(NAMES, Q0, [], [], 2.25, 2.25), 2.25) and tr.state == "deviating"


def test_a_past_stamp_starts_inside_and_ends_at_stamp_plus_duration():
    """Positions only, stamped 0.4 s before its receipt: the controller is at t = 0.4 of the
    linear interpolation on receipt and done at stamp + 1 s."""
    tr = ControllerTracker(PANDA, Settings())
    traj = validate_trajectory(NAMES, NAMES, [0.0, 1.0], [Q0, Q0 + 0.2])
    tr.follow(traj, timing=Timing(1.6, 2.0), start=_rest(Q0))
    np.testing.assert_allclose(tr.reference(2.0), Q0 + 0.08, rtol=0, atol=1e-14)
    np.testing.assert_allclose(tr.reference(2.3), Q0 + 0.14, rtol=0, atol=1e-14)
    np.testing.assert_allclose(tr.reference(2.6), Q0 + 0.2, rtol=0, atol=1e-14)
    assert tr.reference(2.61) is None and tr.reference(1.95) is None


def test_a_refused_trajectory_leaves_the_running_one():
    """A trajectory whose stamped end is already past is refused by the controller
    (``ends_in_past``): the tracker keeps following the one the controller still runs."""
    tr = ControllerTracker(PANDA, Settings())
    tr.follow(_quintic_rest([0.0, 2.0], [Q0, Q0 + 0.2]), timing=Timing(0.0, 10.0), start=_rest(Q0))
    late = tr.follow(_quintic_rest([0.0, 0.5], [Q0, Q0 - 0.2]), timing=Timing(9.0, 10.5),
                     start=_rest(Q0))
    assert [c for c, _ in late.refusals] == ["ends_in_past"]
    np.testing.assert_allclose(tr.reference(11.0), Q0 + 0.1, rtol=0, atol=1e-14)


def test_samples_stamped_before_a_new_plan_arrived_are_judged_by_the_old_one():
    """The controller runs the old trajectory until the new one arrives: a sample stamped before
    the new plan's receipt (and handed in after it) is compared with the old plan."""
    tr = ControllerTracker(PANDA, Settings())
    tr.follow(_quintic_rest([0.0, 2.0], [Q0, Q0 + 0.2]), timing=Timing(0.0, 10.0), start=_rest(Q0))
    tr.follow(_quintic_rest([0.0, 1.0], [Q0 + 0.1, Q0 - 0.2]), timing=Timing(0.0, 11.0),
              start=_rest(Q0 + 0.1))
    np.testing.assert_allclose(tr.reference(10.5), Q0 + 0.2 * (10 * 0.25**3 - 15 * 0.25**4 + 6 * 0.25**5),
                               rtol=0, atol=1e-14)
    np.testing.assert_allclose(tr.reference(11.5), Q0 - 0.05, rtol=0, atol=1e-14)
    assert tr.reference(12.5) is None   # the old plan (to 12 s) was replaced at 11 s


def test_a_single_point_ahead_is_a_start_segment_then_held():
    tr = ControllerTracker(PANDA, Settings())
    tr.follow(validate_trajectory(NAMES, NAMES, [1.0], [Q0 + 0.4], min_points=1),
              timing=Timing(0.0, 5.0), start=_rest(Q0))
    # positions only at the point: the segment from the state is linear (T 279-280)
    np.testing.assert_allclose(tr.reference(5.5), Q0 + 0.2, rtol=0, atol=1e-14)
    np.testing.assert_allclose(tr.reference(6.0), Q0 + 0.4, rtol=0, atol=1e-14)
    assert tr.reference(6.0 + 1e-6) is None


@pytest.mark.parametrize("stamp, receipt, at", [(0.0, 10.0, 10.5), (9.7, 10.0, 10.2)])
def test_without_a_state_the_first_point_is_the_start(stamp, receipt, at):
    """No joint_states known: the message's own interpolation from its first point, which is
    due at the stamp (or on receipt for a zero stamp); half way 0.5 s after that origin."""
    tr = ControllerTracker(PANDA, Settings())
    tr.follow(_quintic_rest([0.0, 1.0], [Q0, Q0 + 0.2]), timing=Timing(stamp, receipt))
    np.testing.assert_allclose(tr.reference(at), Q0 + 0.1, rtol=0, atol=1e-14)


def test_the_lock_is_held_only_to_replace_the_plan():
    """The node's joint_states lock is taken to swap the plan in (the old plan still in place on
    entry), never for a trajectory the controller refuses."""
    tr = ControllerTracker(PANDA, Settings())
    seen: list = []

    class Lock:
        def __enter__(self):
            seen.append(tr.reference(10.5))

        def __exit__(self, *exc):
            return False

    tr.follow(_quintic_rest([0.0, 1.0], [Q0, Q0 + 0.2]), timing=Timing(0.0, 10.0), lock=Lock())
    tr.follow(_quintic_rest([0.0, 0.5], [Q0, Q0 - 0.2]), timing=Timing(8.0, 10.5), lock=Lock())
    assert len(seen) == 1 and seen[0] is None   # entered once, before the first plan was in
    np.testing.assert_allclose(tr.reference(10.5), Q0 + 0.1, rtol=0, atol=1e-14)
