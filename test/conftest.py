"""Shared fixtures: an isolated ROS 2 domain per test session, rclpy contexts and child processes.

Every ROS test runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and its own ROS_DOMAIN_ID, so
concurrent test runs on one machine never hear each other. Set DYN_TEST_DOMAIN to pin the domain.
``DYN_TEST_SHUFFLE=<seed>`` runs the modules, and each module's tests, in an order drawn from the
seed (no test may depend on another's state: this is how that is checked).
"""
from __future__ import annotations

import contextlib
import errno
import math
import os
import random
import signal as _signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import pytest

REPO = Path(__file__).resolve().parents[1]


def shuffled(items: list, seed: str) -> list:
    """``items`` (pytest items, by ``nodeid``) in an order drawn from ``seed``: modules shuffled,
    and the tests inside each; a module's tests stay together, so its module-scoped fixtures
    (nodes, bags) are still set up once."""
    rng = random.Random(seed)
    modules: dict[str, list] = {}
    for item in items:
        modules.setdefault(item.nodeid.split("::", 1)[0], []).append(item)
    order = list(modules)
    rng.shuffle(order)
    for tests in modules.values():
        rng.shuffle(tests)
    return [item for m in order for item in modules[m]]


def pytest_collection_modifyitems(config: Any, items: list) -> None:
    seed = os.environ.get("DYN_TEST_SHUFFLE")
    if seed:
        items[:] = shuffled(items, seed)


def pytest_report_header(config: Any) -> str | None:
    seed = os.environ.get("DYN_TEST_SHUFFLE")
    return f"dyn_node: tests shuffled with DYN_TEST_SHUFFLE={seed}" if seed else None


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
    # DYN_TEST_DOMAIN too: a child that imports this module (a test file run as a child
    # process) then stays on the session's domain instead of picking one from its own pid
    env.update(ROS_DOMAIN_ID=str(TEST_DOMAIN), DYN_TEST_DOMAIN=str(TEST_DOMAIN),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
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


def close_stack(closers: Iterable[Any], procs: Iterable["ChildProcess"], timeout: float = 10.0) -> None:
    """A module fixture's teardown: its observers and clients closed, then its processes stopped."""
    for c in closers:
        c.close()
    for p in procs:
        p.stop(timeout=timeout)


def python_cmd(module: str, *args: str) -> list[str]:
    """Command line running ``python -m module args`` with this interpreter."""
    return [sys.executable, "-m", module, *args]


def kv(status: Any) -> dict[str, str]:
    """The key/value pairs of a diagnostic_msgs/DiagnosticStatus as a dict."""
    return {k.key: k.value for k in status.values}


def t_msg(t: float) -> Any:
    """builtin_interfaces/Time of ``t`` seconds (nanoseconds rounded, never 10⁹)."""
    from builtin_interfaces.msg import Time

    sec = int(math.floor(t))
    return Time(sec=sec, nanosec=min(int(round((t - sec) * 1e9)), 999_999_999))


def t_s(stamp: Any) -> float:
    """Seconds of a builtin_interfaces/Time."""
    return stamp.sec + stamp.nanosec * 1e-9


def js(names: Iterable[str], q: Iterable[float], v: Iterable[float] = (), e: Iterable[float] = (),
       *, stamp: float = 1.0) -> Any:
    """A sensor_msgs/JointState stamped ``stamp`` seconds."""
    from sensor_msgs.msg import JointState

    m = JointState()
    m.header.stamp = t_msg(stamp)
    m.name = list(names)
    m.position = [float(x) for x in q]
    m.velocity = [float(x) for x in v]
    m.effort = [float(x) for x in e]
    return m


class Stepper:
    """An executor over ``nodes`` that the test spins on its own thread, between its own steps
    (publish one message, spin until its answer is in), so nothing runs while it checks."""

    def __init__(self, ctx: Any, nodes: Iterable[Any], *, step_s: float = 0.01):
        from rclpy.executors import SingleThreadedExecutor

        self.ex = SingleThreadedExecutor(context=ctx)
        self.nodes = list(nodes)
        for n in self.nodes:
            self.ex.add_node(n)
        self.step_s = step_s

    def until(self, cond: Callable[[], bool], timeout: float) -> bool:
        """Spin until cond() or the deadline; the last cond(). ``until(lambda: False, t)`` spins
        for t seconds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not cond():
            self.ex.spin_once(timeout_sec=self.step_s)
        return cond()

    def close(self, *, destroy_nodes: bool = True) -> None:
        """Take the nodes off the executor and shut it down; destroy the nodes unless asked not to
        (a node that outlives this executor)."""
        for n in self.nodes:
            self.ex.remove_node(n)
        self.ex.shutdown()
        if destroy_nodes:
            for n in self.nodes:
                n.destroy_node()


class NodeHarness(Collected):
    """An in-process DynNode and a probe node in one namespace, spun on a background thread.

    Each harness lives in its own namespace so concurrent nodes never hear each other's
    joint_states. A subclass creates its publishers and collectors (:meth:`sub`), then calls
    :meth:`start` with the discovery it needs before a test may publish."""

    def __init__(self, ctx: Any, namespace: str, overrides: list[Any], keys: Iterable[str] = ()):
        import rclpy

        from dyn_node.ros.node import DynNode

        super().__init__(keys)
        self.ctx = ctx
        self.ns = namespace
        self.probe = rclpy.create_node("probe", namespace=namespace, context=ctx)
        self.node = DynNode(namespace=namespace, context=ctx, parameter_overrides=overrides)
        self.spinner: Spinner | None = None

    def sub(self, key: str, msg_type: Any, topic: str, qos: Any) -> None:
        """Collect ``topic`` (relative to the namespace unless absolute) into ``got[key]``."""
        self.probe.create_subscription(msg_type, topic, self.collector(key), qos)

    def start(self, discovered: Callable[[], bool]) -> None:
        self.spinner = Spinner(self.ctx, (self.node, self.probe))
        assert self.wait(discovered), "discovery"

    def close(self) -> None:
        if self.spinner is not None:
            self.spinner.stop()
        self.node.destroy_node()
        self.probe.destroy_node()


class FullDisk:
    """A file that accepts ``budget`` bytes, then raises ENOSPC like a full file system."""

    def __init__(self, path: str, budget: int):
        self.f = open(path, "xb")
        self.budget = budget
        self.full_at: float | None = None

    def write(self, data: bytes) -> int:
        if len(data) > self.budget:
            self.full_at = self.full_at or time.monotonic()
            raise OSError(errno.ENOSPC, "No space left on device")
        self.budget -= len(data)
        return self.f.write(data)

    def flush(self) -> None:
        self.f.flush()

    def fileno(self) -> int:
        return self.f.fileno()

    def close(self) -> None:
        self.f.close()
