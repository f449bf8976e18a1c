"""The question worker process (dyn_node.core.live.question_process): its answers are the
in-process core's to the bit, a worker that dies answers its pending caller with the reason
and is replaced, and a closed one refuses with the reason."""
from __future__ import annotations

import os
import signal
import threading

import numpy as np
import pinocchio as pin
import pytest

from conftest import Collected
from dyn_node.core.check import questions
from dyn_node.core.live.question_process import QuestionProcess, WorkerFailed
from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.core.robot.model import load_model
from dyn_node.core.robot.settings import Settings
from dyn_node.ros.demo import READY

MODEL = load_model(builtin="panda")
NAMES = list(MODEL.joint_names)
SETTINGS = Settings(robot_model="panda")


@pytest.fixture(scope="module")
def worker():
    proc = QuestionProcess()
    yield proc
    proc.close()


def _path(n: int, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0.0, seconds, n)
    return t, np.array(READY) + 0.2 * np.sin(t[:, None] * np.arange(1, 8) * (6.0 / seconds))


def _question(kind: str, n: int = 200, seconds: float = 20.0, **kw) -> questions.Question:
    """A path through n points (cubic: with velocities, zero at both ends), in reversed joint order."""
    t, P = _path(n, seconds)
    V = np.gradient(P, t, axis=0)
    V[0] = V[-1] = 0.0
    rev = list(reversed(NAMES))  # the request's own joint order, not the model's
    return questions.Question(kind, rev, t, P[:, ::-1].copy(), V[:, ::-1].copy(), None,
                              np.zeros((n, 0)), **kw)


def _timeless(statuses) -> list:
    """Statuses without their compute time (the one value that differs between two runs); values
    by repr, so a NaN equals a NaN."""
    return [(s.name, s.level, s.message,
             {k: repr(v) for k, v in s.values.items() if k != "compute_time_s"}) for s in statuses]


def test_a_check_answer_is_the_in_process_cores(worker):
    q = _question(questions.CHECK)
    got, want = worker.ask(SETTINGS, MODEL, q), questions.answer(Dynamics(MODEL), SETTINGS, q)
    assert isinstance(got, questions.CheckAnswer) and got.error is None and got.feasible
    np.testing.assert_allclose(got.waypoint_effort, want.waypoint_effort, rtol=0, atol=1e-12)
    assert (got.feasible, got.time_scale, got.worst_ratio, got.message) == (
        want.feasible, want.time_scale, want.worst_ratio, want.message)
    assert _timeless(got.statuses) == _timeless(want.statuses)


def test_inverse_dynamics_answer_is_pinocchios_rnea(worker):
    """States with velocities and accelerations: the worker's τ equals the in-process core's and
    Pinocchio's own RNEA plus the URDF's friction (the reference we did not write)."""
    rng = np.random.default_rng(7)
    Q = np.array(READY) + 0.3 * rng.standard_normal((50, 7))
    V, A = rng.standard_normal((50, 7)), rng.standard_normal((50, 7))
    q = questions.Question(questions.INVERSE_DYNAMICS, NAMES, np.zeros(50), Q, V, A, np.zeros((50, 0)))
    got = worker.ask(SETTINGS, MODEL, q)
    np.testing.assert_allclose(got, questions.answer(Dynamics(MODEL), SETTINGS, q), rtol=0, atol=1e-12)
    pm = MODEL.pin_model
    data = pm.createData()
    ref = np.array([pin.rnea(pm, data, Q[i], V[i], A[i]) + np.asarray(pm.damping) * V[i]
                    + np.asarray(pm.friction) * np.sign(V[i]) for i in range(50)])
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-9)


def test_a_retime_answer_is_the_in_process_cores(worker):
    q = _question(questions.RETIME, n=60)
    got, want = worker.ask(SETTINGS, MODEL, q), questions.answer(Dynamics(MODEL), SETTINGS, q)
    assert isinstance(got, questions.RetimeAnswer) and got.feasible
    np.testing.assert_allclose(got.trajectory.times, want.trajectory.times, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.trajectory.positions, want.trajectory.positions, rtol=0, atol=1e-12)
    assert (got.duration_out, got.lower_bound, got.message) == (want.duration_out, want.lower_bound,
                                                                 want.message)
    assert _timeless(got.statuses) == _timeless(want.statuses)


def test_a_malformed_question_is_refused_as_in_process(worker):
    t, P = _path(10, 1.0)
    P[3, 2] = np.nan
    q = questions.Question(questions.INVERSE_DYNAMICS, NAMES, t, P, None, None, None)
    got = worker.ask(SETTINGS, MODEL, q)
    assert got == questions.answer(Dynamics(MODEL), SETTINGS, q)
    assert got == questions.Refusal("non_finite", f"point 3: positions of {NAMES[2]} is nan")


def test_a_killed_worker_answers_its_caller_and_is_replaced(monkeypatch):
    """SIGKILL while a 20,000-point check is in the worker: the caller gets WorkerFailed naming
    the signal (not silence), and the next question is answered by a new worker. The restart is
    held back here (3 s between starts), so that question is asked while no worker is up: it
    waits for the new one (sent to the ended one it was refused: CI, 2026-12-06)."""
    from dyn_node.core.live import question_process

    monkeypatch.setattr(question_process, "RESTART_MIN_INTERVAL_S", 3.0)
    proc = QuestionProcess()
    try:
        first_pid = proc.pid
        assert proc.ask(SETTINGS, MODEL, _question(questions.CHECK, n=20)).error is None
        outcome: list = []
        done = threading.Event()

        def ask_long() -> None:
            try:
                outcome.append(proc.ask(SETTINGS, MODEL, _question(questions.CHECK, 20000, 20.0)))
            except WorkerFailed as exc:
                outcome.append(exc)
            done.set()

        threading.Thread(target=ask_long, daemon=True).start()
        assert Collected().wait(lambda: proc.in_flight() == 1, 30.0)
        os.kill(first_pid, signal.SIGKILL)
        assert done.wait(30.0), "the caller was left waiting"
        assert isinstance(outcome[0], WorkerFailed), outcome
        assert str(outcome[0]) == ("the question worker process ended (signal 9) while answering; "
                                   "it is being restarted")
        q = _question(questions.CHECK, n=20)
        got = proc.ask(SETTINGS, MODEL, q)  # waits for the new worker to load
        assert proc.pid != first_pid and proc.restarts == 1
        assert got.message == questions.answer(Dynamics(MODEL), SETTINGS, q).message
    finally:
        proc.close()


#: a worker double: answers every question with bytes that are no pickle
_UNREADABLE = """
import sys
from multiprocessing.connection import Connection
conn = Connection(int(sys.argv[1]))
while True:
    msg = conn.recv()
    if msg[0] == "ask":
        conn.send_bytes(b"no pickle")
"""


@pytest.mark.timeout(120)
def test_an_unreadable_answer_replaces_the_worker(monkeypatch):
    """The first worker is a double whose answer cannot be unpickled: the reader says so, kills
    and replaces it, the caller gets WorkerFailed with the reason (not silence: without the
    reader's catch its thread ends and the caller waits forever), the next question is answered
    by a real worker."""
    import socket
    import subprocess
    import sys
    from multiprocessing.connection import Connection

    real_start, doubles = QuestionProcess._start, []

    def start(self):
        if doubles:
            return real_start(self)
        ours, theirs = socket.socketpair()
        self._started_at = 0.0   # no hold-back before the restart
        try:
            proc = subprocess.Popen([sys.executable, "-c", _UNREADABLE, str(theirs.fileno())],
                                    pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL)
        finally:
            theirs.close()
        doubles.append(proc)
        return proc, Connection(ours.detach())

    monkeypatch.setattr(QuestionProcess, "_start", start)
    lines: list[str] = []
    proc = QuestionProcess(log=lines.append)
    try:
        assert proc.pid == doubles[0].pid
        with pytest.raises(WorkerFailed) as failed:
            proc.ask(SETTINGS, MODEL, _question(questions.CHECK, n=20))
        assert str(failed.value) == ("the question worker process ended (signal 9) while "
                                     "answering; it is being restarted")
        assert lines[0].startswith("question worker's answer unreadable (UnpicklingError(")
        assert lines[0].endswith("); restarting it")
        q = _question(questions.CHECK, n=20)
        got = proc.ask(SETTINGS, MODEL, q)
        assert proc.pid != doubles[0].pid and proc.restarts == 1 and len(doubles) == 1
        assert got.message == questions.answer(Dynamics(MODEL), SETTINGS, q).message
    finally:
        proc.close()


def test_a_closed_worker_refuses_with_the_reason():
    proc = QuestionProcess()
    proc.close()
    with pytest.raises(WorkerFailed, match="^the question worker is closed$"):
        proc.ask(SETTINGS, MODEL, _question(questions.CHECK, n=20))
    assert proc.in_flight() == 0


def test_an_exception_in_the_worker_reaches_the_caller(worker):
    """A computation that raises (here a kind the core does not know) is QuestionError with the
    worker's type and message; the worker stays up and answers the next question."""
    from dyn_node.core.live.question_process import QuestionError

    pid = worker.pid
    with pytest.raises(QuestionError, match="^ValueError: unknown question kind 'nope'$"):
        worker.ask(SETTINGS, MODEL, _question("nope", n=5))
    assert worker.ask(SETTINGS, MODEL, _question(questions.CHECK, n=20)).error is None
    assert worker.pid == pid
