"""dyn_node.core.check.questions: a Question (arrays) answered by the core functions the node,
dyn-check and the audit use, as the plain picklable answers the worker process sends back."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from dyn_node.core.check import on_demand, questions
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import load_model
from dyn_node.core.robot.settings import Settings
from dyn_node.errors import TrajectoryError
from dyn_node.ros.demo import READY

MODEL = load_model(builtin="panda")
NAMES = list(MODEL.joint_names)
DYN = Dynamics(MODEL)
SETTINGS = Settings(robot_model="panda")


def _path(n: int = 40, seconds: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0.0, seconds, n)
    return t, np.array(READY) + 0.1 * np.sin(t[:, None] * np.arange(1, 8) * 0.3)


def test_a_check_answer_holds_the_outcomes_numbers():
    t, P = _path()
    got = questions.answer(DYN, SETTINGS, questions.Question(questions.CHECK, NAMES, t, P, None, None, None))
    want = on_demand.check(DYN, SETTINGS, NAMES, t, P, start_unknown=on_demand.START_NOT_REQUESTED).result
    assert isinstance(got, questions.CheckAnswer) and got.error is None
    assert (got.feasible, got.time_scale, got.worst_joint, got.worst_constraint, got.worst_ratio,
            got.time_scale_joint, got.message) == (
        want.feasible, want.time_scale, want.worst_joint, want.worst_constraint, want.worst_ratio,
        want.time_scale_joint, want.message)
    np.testing.assert_array_equal(got.waypoint_effort, want.waypoint_effort)
    # what crosses the process boundary: the answer survives pickling unchanged
    back = pickle.loads(pickle.dumps(got))
    np.testing.assert_array_equal(back.waypoint_effort, got.waypoint_effort)
    assert back.message == got.message


def test_a_rejected_check_carries_the_error_and_statuses():
    t, P = _path()
    P[5, 3] = np.inf
    got = questions.answer(DYN, SETTINGS, questions.Question(questions.CHECK, NAMES, t, P, None, None, None))
    assert got.error is not None and got.error.code == "non_finite" and not got.feasible
    assert got.waypoint_effort is None and got.statuses[0].level == 2


def test_rows_of_unequal_length_are_refused_naming_the_point():
    rows = [list(READY), list(READY)[:6], list(READY)]
    q = questions.Question(questions.INVERSE_DYNAMICS, NAMES, [0.0, 0.0, 0.0], rows, None, None, None)
    assert questions.answer(DYN, SETTINGS, q) == questions.Refusal(
        "length_mismatch", "point 1: 6 positions for 7 joints")


def test_a_malformed_path_is_refused_before_the_retimer():
    t, P = _path()
    t[3] = t[2]  # times must increase
    got = questions.answer(DYN, SETTINGS, questions.Question(questions.RETIME, NAMES, t, P, None, None, None))
    with pytest.raises(TrajectoryError) as exc:
        on_demand.validated(NAMES, NAMES, t, P)
    assert isinstance(got, questions.Refusal) and got.message == str(exc.value)
    assert got.reason == exc.value.code


def test_an_unknown_kind_raises():
    t, P = _path(5)
    with pytest.raises(ValueError, match="unknown question kind 'nope'"):
        questions.answer(DYN, SETTINGS, questions.Question("nope", NAMES, t, P, None, None, None))
