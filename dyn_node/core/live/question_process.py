"""The question worker process: the question services' answers computed outside the node's process.

Why a process. The node answers joint_states (gravity torques every few milliseconds) on a
thread of its own, and every thread of a Python process shares one interpreter lock (GIL). A
20,000-point check or a retime computed on a thread of the node takes turns with it: whatever
holds the lock there (a Pinocchio or NumPy call, a garbage collection over the request's
hundreds of thousands of objects, a kernel being loaded) holds joint_states too, so the bound
on their pause depended on every library call the core makes. Measured with the computation on
a thread (test_services.py, 20,000-point checks): gravity torques paused 34-65 ms in most
attempts and 89-146 ms in about one in three (raw gaps; 261-528 ms before the collector was
tamed). A process has its own lock: the computation there cannot hold joint_states, whatever it
costs or calls. What stays in the node is the conversion between messages and arrays (rclpy's,
in small steps the lock switches between). On a saturated machine the operating system's
scheduling still pauses any process (docs/node.md has the figures of both designs).

How. :class:`QuestionProcess` starts ``python -m dyn_node.core.live.question_process FD`` with one
end of a socket pair (a plain subprocess: no ``multiprocessing`` start method re-imports the
node's main module in the child) and talks to it with pickled tuples over a
:class:`multiprocessing.connection.Connection`:

- ``("model", token, model)``: the node's :class:`RobotModel` itself (pickled, ~60 kB, sent once
  per model): the worker computes with the very model the node has, not a rebuilt one;
- ``("ask", job, token, settings, question)`` → ``(job, "answer", answer)``, the answer of
  :func:`dyn_node.core.check.questions.answer`, the function the node would call in-process (so
  the numbers are the same bits), or ``(job, "error", message)`` when it raised.

The worker answers each kind on a thread of its own, with a Dynamics per thread kept while the
model and friction setting stay (so an inverse-dynamics call never waits behind a retime). The
node sends at most one question per kind at a time (its lanes, each a bounded queue), so nothing
queues unbounded here. When the worker dies (killed, out of memory), every pending question is
answered with the exit status (:class:`WorkerFailed`; the node's reason ``worker_failed``), never left waiting, and a new worker is
started (at most one start per ``RESTART_MIN_INTERVAL_S``). The worker ignores SIGINT (the node
decides when it ends) and exits when the node's end of the socket closes, the node's death
included. Pure (no rclpy).
"""
from __future__ import annotations

import itertools
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:  # imported where used: the worker lowers its priority before its heavy imports
    from dyn_node.core.check import questions
    from dyn_node.core.robot.model import RobotModel
    from dyn_node.core.robot.settings import Settings

#: a worker that dies at once (a broken environment) is not restarted in a tight loop
RESTART_MIN_INTERVAL_S = 1.0
#: how long a question asked while the worker restarts waits for the new one
RESTART_WAIT_S = RESTART_MIN_INTERVAL_S + 10.0
#: the worker's scheduling priority relative to the node (nice increment): on a machine short of
#: cores the node's joint_states thread wins the CPU over a long computation (seen: the node's
#: threads descheduled for 116 ms while the worker computed at the same priority, load 4-6 on 2 cores)
WORKER_NICE = 10
#: models the worker keeps (a question in flight may use the previous one)
MODELS_KEPT = 4


class WorkerFailed(Exception):
    """The worker could not answer (it died, or is closed): the message says why."""


class QuestionError(RuntimeError):
    """The computation raised in the worker (a bug, not the request's fault): its type and message."""


class _Pending:
    __slots__ = ("done", "outcome", "sent")

    def __init__(self) -> None:
        self.done = threading.Event()
        self.outcome: tuple[str, Any] | None = None
        self.sent = False


class QuestionProcess:
    """The node's side of the worker: :meth:`ask` blocks the calling thread (a lane) until the
    worker answers. Thread-safe; starts the worker at once (it loads while the node starts)."""

    def __init__(self, *, log: Callable[[str], None] = lambda line: None):
        self._log = log
        self._lock = threading.Lock()        # the bookkeeping below
        # sends (a large question takes a while): apart, so the reader never waits behind one
        self._send_lock = threading.Lock()
        self._pending: dict[int, _Pending] = {}
        self._jobs = itertools.count(1)
        self._model_tokens = itertools.count(1)
        self._model: RobotModel | None = None  # the last model sent to the current worker
        self._token = 0
        self._closed = False
        self.restarts = 0
        self._started_at = 0.0
        # set while a worker is up: a question asked during a restart waits for the new one
        # (sent to the ended one it would be lost or refused)
        self._up = threading.Event()
        self._up.set()
        self._proc, self._conn = self._start()
        self._reader = threading.Thread(target=self._read_loop, name="dyn_node_question_reader",
                                        daemon=True)
        self._reader.start()

    @property
    def pid(self) -> int:
        """The current worker's process id."""
        return self._proc.pid

    def in_flight(self) -> int:
        """Questions sent to the worker (whole) and not answered yet."""
        with self._lock:
            return sum(p.sent for p in self._pending.values())

    def _start(self) -> tuple[subprocess.Popen, Connection]:
        ours, theirs = socket.socketpair()
        self._started_at = time.monotonic()
        try:
            proc = subprocess.Popen([sys.executable, "-m", __name__, str(theirs.fileno())],
                                    pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL)
        finally:
            theirs.close()
        return proc, Connection(ours.detach())

    def preload(self, model: RobotModel) -> None:
        """Send ``model`` now: the worker loads the compiled kernels with it before the first
        question (otherwise that question waits for them)."""
        with self._send_lock:
            with self._lock:
                if self._closed or model is self._model:
                    return
                conn = self._conn
                self._token, self._model = next(self._model_tokens), model
                token = self._token
            try:
                conn.send(("model", token, model))
            except (OSError, ValueError):  # gone: the reader restarts it, the first ask resends
                pass

    def ask(self, settings: Settings, model: RobotModel, question: questions.Question) -> Any:
        """The worker's answer to ``question`` (as :func:`questions.answer` returns it) with
        ``model`` and ``settings``; raises :class:`WorkerFailed` when the worker cannot answer."""
        pending = _Pending()
        deadline = time.monotonic() + RESTART_WAIT_S
        while True:
            if not self._up.wait(max(0.0, deadline - time.monotonic())):
                raise WorkerFailed(f"the question worker did not come back within {RESTART_WAIT_S:g} s")
            self._send_lock.acquire()
            with self._lock:
                up = self._up.is_set()
            if up:
                break
            self._send_lock.release()   # a restart began meanwhile: wait for it
        try:
            with self._lock:
                if self._closed:
                    raise WorkerFailed("the question worker is closed")
                job = next(self._jobs)
                self._pending[job] = pending
                conn, send_model = self._conn, model is not self._model
                if send_model:
                    self._token, self._model = next(self._model_tokens), model
                token = self._token
            try:
                if send_model:
                    conn.send(("model", token, model))
                conn.send(("ask", job, token, settings, question))
                pending.sent = True
            except (OSError, ValueError) as exc:  # the worker is gone: the reader restarts it
                with self._lock:
                    self._pending.pop(job, None)
                raise WorkerFailed(f"the question worker is not reachable ({exc}); it is being "
                                   "restarted") from exc
        finally:
            self._send_lock.release()
        pending.done.wait()
        status, value = pending.outcome
        if status == "answer":
            return value
        raise (QuestionError if status == "error" else WorkerFailed)(value)

    def _read_loop(self) -> None:
        while True:
            conn = self._conn
            try:
                while True:
                    job, status, value = conn.recv()
                    with self._lock:
                        pending = self._pending.pop(job, None)
                    if pending is not None:
                        pending.outcome = (status, value)
                        pending.done.set()
            except (EOFError, OSError):
                pass
            except Exception as exc:  # noqa: BLE001 - an unreadable answer: replace the worker
                self._log(f"question worker's answer unreadable ({exc!r}); restarting it")
                self._proc.kill()
            if not self._restart():
                return
            conn.close()  # the ended worker's (the new one has its own)

    def _restart(self) -> bool:
        """After the worker's end: fail what it held, start another unless closed."""
        proc = self._proc
        try:
            code = proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
        why = f"signal {-code}" if code < 0 else f"exit code {code}"
        with self._lock:
            self._up.clear()   # questions from now on wait for the new worker
            failed, self._pending = self._pending, {}
            closing = self._closed
            self._model = None
            for pending in failed.values():
                pending.outcome = ("failed", f"the question worker process ended ({why}) while "
                                   "answering" + ("" if closing else "; it is being restarted"))
                pending.done.set()
            if closing:
                self._up.set()   # waiters see it closed
                return False
            self._log(f"question worker process ended ({why}); restarting it")
            wait = RESTART_MIN_INTERVAL_S - (time.monotonic() - self._started_at)
        if wait > 0:
            threading.Event().wait(wait)
        with self._send_lock, self._lock:
            self._up.set()
            if self._closed:
                return False
            self._proc, self._conn = self._start()
            self._model = None  # the new worker has none yet
            self.restarts += 1
        return True

    def close(self, timeout: float = 1.0) -> None:
        """End the worker (questions in progress raise :class:`WorkerFailed`)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._up.set()   # a question waiting for a restart sees it closed
            conn, proc = self._conn, self._proc
        if self._send_lock.acquire(timeout=timeout):  # not inside another thread's message
            try:
                conn.send(("close",))
            except (OSError, ValueError):
                pass
            finally:
                self._send_lock.release()
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:  # busy in a long computation: no need to wait for it
            proc.kill()
        self._reader.join(timeout=timeout + 5.0)
        conn.close()


# --- the worker's side (runs in the child process) ----------------------------------------------
class _Worker:
    def __init__(self, conn: Connection):
        self.conn = conn
        self.send_lock = threading.Lock()
        self.models: dict[int, RobotModel] = {}
        self.lanes: dict[str, _KindThread] = {}

    def serve(self) -> None:
        while True:
            try:
                msg = self.conn.recv()
            except (EOFError, OSError):
                return  # the node is gone
            if msg[0] == "close":
                return
            if msg[0] == "model":
                if not self.models:  # the first: load the compiled kernels before a question needs them
                    threading.Thread(target=_warm_up, args=(msg[2],), daemon=True).start()
                self.models[msg[1]] = msg[2]
                for old in sorted(self.models)[:-MODELS_KEPT]:
                    del self.models[old]
                continue
            _, job, token, settings, question = msg
            lane = self.lanes.get(question.kind)
            if lane is None:
                lane = self.lanes[question.kind] = _KindThread(self)
            lane.put((job, self.models.get(token), token, settings, question))

    def reply(self, job: int, status: str, value: Any) -> None:
        with self.send_lock:
            self.conn.send((job, status, value))


class _KindThread:
    """One kind's jobs, in order, with a Dynamics of its own (rebuilt when the model changes)."""

    def __init__(self, worker: _Worker):
        self.worker = worker
        self.jobs: list[tuple] = []
        self.cond = threading.Condition()
        self.key: tuple | None = None
        self.dynamics: Any = None
        threading.Thread(target=self._loop, daemon=True).start()

    def put(self, job: tuple) -> None:
        with self.cond:
            self.jobs.append(job)
            self.cond.notify()

    def _loop(self) -> None:
        from dyn_node.core.check import questions
        while True:
            with self.cond:
                while not self.jobs:
                    self.cond.wait()
                job, model, token, settings, question = self.jobs.pop(0)
            try:
                if model is None:
                    raise RuntimeError(f"model {token} unknown to the question worker")
                dyn = self._dynamics(model, token, settings)
                self.worker.reply(job, "answer", questions.answer(dyn, settings, question))
            except Exception as exc:  # the node answers internal_error with it
                self.worker.reply(job, "error", f"{type(exc).__name__}: {exc}")

    def _dynamics(self, model: RobotModel, token: int, settings: Settings) -> Any:
        from dyn_node.core.robot.dynamics import Dynamics, DynamicsOptions
        key = (token, settings.include_friction)
        if key != self.key:
            self.dynamics = Dynamics(model, DynamicsOptions(include_friction=settings.include_friction))
            self.key = key
        return self.dynamics


def _warm_up(model: RobotModel) -> None:
    from dyn_node.core.check import questions
    from dyn_node.core.robot.dynamics import Dynamics
    from dyn_node.core.robot.settings import Settings
    try:
        questions.warm_up(Dynamics(model), Settings())
    except Exception:  # a model the defaults do not suit: the first question loads them instead
        pass


def main(argv: list[str]) -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the node ends its worker (close or EOF)
    try:
        os.nice(WORKER_NICE)
    except OSError:  # not permitted here: same priority as the node
        pass
    conn = Connection(int(argv[0]))
    # loaded before the first question: the feasibility check's and the retimer's modules
    from dyn_node.core.check import feasibility  # noqa: F401
    try:
        import dyn_node.retime  # noqa: F401
    except ImportError:  # answered retimer_unavailable when asked
        pass
    _Worker(conn).serve()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))


__all__ = ["QuestionProcess", "WorkerFailed", "QuestionError"]
