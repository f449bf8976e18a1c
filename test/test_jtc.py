"""dyn_sim's goal rules (dyn_node.sim.jtc) against joint_trajectory_controller's own, each test
citing the lines of ros2_controllers it follows: branch jazzy, commit ed360c97d,
``joint_trajectory_controller/include/joint_trajectory_controller/tolerances.hpp`` (tol.hpp),
``src/joint_trajectory_controller.cpp`` (jtc.cpp) and
``src/joint_trajectory_controller_parameters.yaml`` (params.yaml)."""
from __future__ import annotations

import numpy as np
import pytest

from dyn_node.sim import jtc

JOINTS = ["a", "b", "c"]


def defaults(**kw) -> jtc.SegmentTolerances:
    return jtc.default_tolerances(3, **{"trajectory": 0.1, "goal": 0.05, "stopped_velocity": 0.01,
                                        "goal_time": 0.5, **kw})


def test_minus_one_erases_a_default_tolerance():
    """tol.hpp 137–148: a value within float epsilon of -1 erases (0.0 = not enforced); a
    positive value replaces the default; 0 keeps it (153)."""
    tol, why = jtc.goal_tolerances(defaults(), JOINTS,
                                   [("a", -1.0, 0.0, 0.0), ("b", 0.3, 0.0, 0.0), ("c", 0.0, 0.0, 0.0)],
                                   [("a", -1.0 + 1e-8, -1.0, 0.0)], 0.0)
    assert why == ""
    np.testing.assert_array_equal(tol.path.position, [0.0, 0.3, 0.1])
    np.testing.assert_array_equal(tol.goal.position, [0.0, 0.05, 0.05])
    np.testing.assert_array_equal(tol.goal.velocity, [0.0, 0.01, 0.01])
    # an erased path tolerance lets the joint move without restriction (tol.hpp 309: > 0 only)
    assert jtc.monitor(0.1, 1.0, np.array([5.0, 0.0, 0.0]), np.zeros(3), tol, JOINTS) is None


@pytest.mark.parametrize("path, goal", [
    ([("nope", 0.2, 0.0, 0.0)], []),                  # tol.hpp 192–202: unknown joint in path_tolerance
    ([], [("nope", 0.2, 0.0, 0.0)]),                  # tol.hpp 241–251: unknown joint in goal_tolerance
    ([("a", -0.5, 0.0, 0.0)], []),                    # tol.hpp 149–151 + 217–224: illegal negative value
    ([("a", 0.2, 0.0, 0.0)], [("b", 0.0, -2.0, 0.0)]),  # 266–273: after a legal path entry, still defaults
])
def test_unknown_joint_or_illegal_value_uses_the_defaults(path, goal):
    """The whole goal falls back to the controller's defaults (``return default_tolerances``)."""
    d = defaults()
    tol, why = jtc.goal_tolerances(d, JOINTS, path, goal, 0.0)
    assert tol is d and why.endswith("using the default tolerances")


def test_goal_time_zero_keeps_the_default_and_a_zero_default_waits_for_ever():
    """tol.hpp 175–176 with 153: a goal's goal_time_tolerance 0 keeps the default; -1 erases it
    (→ 0); jtc.cpp 394: a goal_time_tolerance of 0 never aborts, whatever the lateness."""
    d = defaults(goal_time=0.5)
    assert jtc.goal_tolerances(d, JOINTS, [], [], 0.0)[0].goal_time == 0.5
    assert jtc.goal_tolerances(d, JOINTS, [], [], 0.25)[0].goal_time == 0.25
    erased = jtc.goal_tolerances(d, JOINTS, [], [], -1.0)[0]
    assert erased.goal_time == 0.0
    off = np.array([0.0, 0.2, 0.0])  # outside b's goal tolerance 0.05
    assert jtc.monitor(1e6, 1.0, off, np.zeros(3), erased, JOINTS) is None
    # with 0.5 s (jtc.cpp 397: time_difference > goal_time_tolerance), 0.5 s late is not yet over
    assert jtc.monitor(1.5, 1.0, off, np.zeros(3), d, JOINTS) is None
    out = jtc.monitor(1.5 + 1e-6, 1.0, off, np.zeros(3), d, JOINTS)
    assert out.code == jtc.GOAL_TOLERANCE_VIOLATED and "outside the goal tolerance: b" in out.text


def test_stopped_velocity_is_the_goal_velocity_tolerance():
    """tol.hpp 113: goal_state_tolerance.velocity = stopped_velocity_tolerance for every joint;
    308–311: |velocity error| above it (> 0) fails; jtc.cpp 495–499: success once within."""
    d = defaults(stopped_velocity=0.01)
    np.testing.assert_array_equal(d.goal.velocity, [0.01] * 3)
    np.testing.assert_array_equal(d.path.velocity, [0.0] * 3)  # tol.hpp 111: position only on the path
    moving = np.array([0.0, 0.0, 0.0101])
    assert jtc.monitor(1.2, 1.0, np.zeros(3), moving, d, JOINTS) is None
    out = jtc.monitor(1.2, 1.0, np.zeros(3), np.array([0.0, 0.0, 0.0099]), d, JOINTS)
    assert (out.code, out.text) == (jtc.SUCCESSFUL, "Goal successfully reached!")
    # stopped_velocity_tolerance 0: velocity not checked at the goal (308–311, "> 0.0")
    out = jtc.monitor(1.2, 1.0, np.zeros(3), np.array([0.0, 0.0, 5.0]), defaults(stopped_velocity=0.0), JOINTS)
    assert out.code == jtc.SUCCESSFUL


def test_per_joint_default_tolerances():
    """params.yaml 239–249: ``constraints.<joint>.trajectory`` and ``.goal`` per joint (default 0:
    not enforced); tol.hpp 111–112 copy them into the path and goal position tolerances."""
    d = jtc.default_tolerances(3, trajectory=[0.1, 0.0, 0.3], goal=[0.0, 0.02, 0.03])
    np.testing.assert_array_equal(d.path.position, [0.1, 0.0, 0.3])
    np.testing.assert_array_equal(d.goal.position, [0.0, 0.02, 0.03])
    # jtc.cpp 379–384: while moving, only the joints with a tolerance can violate it
    assert jtc.monitor(0.5, 1.0, np.array([0.0, 9.0, 0.0]), np.zeros(3), d, JOINTS) is None
    out = jtc.monitor(0.5, 1.0, np.array([0.11, 0.0, 0.0]), np.zeros(3), d, JOINTS)
    assert (out.code, out.text) == (jtc.PATH_TOLERANCE_VIOLATED, "Aborted due to path tolerance violation")


def test_dyn_sim_reads_per_joint_parameters_before_the_uniform_ones():
    """dyn_sim's parameters: constraints.<joint>.<kind> when set (≥ 0), else constraints.<kind>."""
    from dyn_node.ros.sim.action import joint_tolerance_parameters, joint_tolerances

    specs = joint_tolerance_parameters(JOINTS)
    assert [s.name for s in specs[:2]] == ["constraints.a.trajectory", "constraints.a.goal"]
    p = {s.name: s.default for s in specs}
    p.update({"constraints.trajectory": 0.2, "constraints.goal": 0.04,
              "constraints.b.trajectory": 0.0, "constraints.c.goal": 0.5})
    assert joint_tolerances(p, JOINTS, "trajectory") == [0.2, 0.0, 0.2]
    assert joint_tolerances(p, JOINTS, "goal") == [0.04, 0.04, 0.5]
