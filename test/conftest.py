"""Shared fixtures: an isolated ROS 2 domain per test session, rclpy contexts and child processes.

Every ROS test runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and its own ROS_DOMAIN_ID, so
concurrent test runs on one machine never hear each other. Set DYN_TEST_DOMAIN to pin the domain.
"""
from __future__ import annotations

import contextlib
import os
import signal as _signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import pytest

REPO = Path(__file__).resolve().parents[1]


def _pick_domain() -> int:
    if os.environ.get("DYN_TEST_DOMAIN"):
        return int(os.environ["DYN_TEST_DOMAIN"])
    # 1..100 stays inside the port range Fast DDS maps for localhost participants.
    return 1 + os.getpid() % 100


TEST_DOMAIN = _pick_domain()
os.environ["ROS_DOMAIN_ID"] = str(TEST_DOMAIN)
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.pop("ROS_LOCALHOST_ONLY", None)


@pytest.fixture(scope="session")
def ros_domain() -> int:
    return TEST_DOMAIN


@contextlib.contextmanager
def _context(domain: int) -> Iterator["object"]:
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.fixture
def ros_context(ros_domain: int) -> Iterator["object"]:
    """A fresh rclpy Context initialised on the test domain, shut down afterwards."""
    with _context(ros_domain) as ctx:
        yield ctx


@pytest.fixture(scope="module")
def module_ros_context(ros_domain: int) -> Iterator["object"]:
    """One rclpy Context for a whole test module (nodes that are slow to discover share it)."""
    with _context(ros_domain) as ctx:
        yield ctx


class Collected:
    """Messages collected per key by subscription callbacks, and a condition every callback
    notifies, so a test waits for what it needs instead of sleeping."""

    default_timeout = 10.0

    def __init__(self, keys: Iterable[str] = ()):
        self.cond = threading.Condition()
        self.got: dict[str, list] = {k: [] for k in keys}

    def collector(self, key: str, stamp_receipt: bool = False) -> Callable[[Any], None]:
        """A subscription callback appending to ``got[key]`` ((monotonic time, msg) if asked)."""
        self.got.setdefault(key, [])

        def cb(msg: Any) -> None:
            with self.cond:
                self.got[key].append((time.monotonic(), msg) if stamp_receipt else msg)
                self.cond.notify_all()
        return cb

    def wait(self, pred: Callable[[], bool], timeout: float | None = None) -> bool:
        """Wait on the condition (woken by every collected message) until pred() or the deadline."""
        deadline = time.monotonic() + (self.default_timeout if timeout is None else timeout)
        with self.cond:
            while not pred():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.cond.wait(min(left, 0.05))
        return True


class Spinner:
    """Spins an executor over ``nodes`` on a thread until :meth:`stop`.

    Stopping ends the spin loop and joins the thread *before* the executor is shut down:
    ``Executor.shutdown`` while another thread is inside ``spin_once`` can destroy the guard
    condition that thread is about to trigger (an ``InvalidHandle`` raised in the spin thread)."""

    def __init__(self, ctx: Any, nodes: Iterable[Any]):
        from rclpy.executors import SingleThreadedExecutor

        self.ex = SingleThreadedExecutor(context=ctx)
        for n in nodes:
            self.ex.add_node(n)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.ex.context.ok():
            self.ex.spin_once(timeout_sec=0.05)

    def add_node(self, node: Any) -> None:
        self.ex.add_node(node)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=10.0)
        self.ex.shutdown(timeout_sec=5.0)


def child_env(**extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(TEST_DOMAIN), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    env.update(extra)
    return env


class ChildProcess:
    """A process started in its own session so it and its children can be signalled together."""

    def __init__(self, args: list[str], **popen: object):
        self.args = args
        self.proc = subprocess.Popen(args, start_new_session=True, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, **popen)  # type: ignore[call-overload]

    def signal(self, sig: int) -> None:
        try:
            os.killpg(self.proc.pid, sig)
        except ProcessLookupError:
            pass

    def stop(self, sig: int = _signal.SIGINT, timeout: float = 10.0) -> tuple[int, str, str]:
        """Signal, wait, and return (returncode, stdout, stderr); SIGKILL if it will not exit."""
        if self.proc.poll() is None:
            self.signal(sig)
        try:
            out, err = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.signal(_signal.SIGKILL)
            out, err = self.proc.communicate()
        return self.proc.returncode, out, err


@pytest.fixture
def spawn() -> Iterator["object"]:
    """Start child processes (``spawn([...])``); every one is stopped at teardown."""
    started: list[ChildProcess] = []

    def _spawn(args: list[str], env: dict[str, str] | None = None, **popen: object) -> ChildProcess:
        cp = ChildProcess(args, env=env or child_env(), cwd=str(REPO), **popen)
        started.append(cp)
        return cp

    yield _spawn
    for cp in started:
        cp.stop(timeout=5.0)


def python_cmd(module: str, *args: str) -> list[str]:
    """Command line running ``python -m module args`` with this interpreter."""
    return [sys.executable, "-m", module, *args]
