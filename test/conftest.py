"""Shared fixtures: an isolated ROS 2 domain per test session, rclpy contexts and child processes.

Every ROS test runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and its own ROS_DOMAIN_ID, so
concurrent test runs on one machine never hear each other. Set DYN_TEST_DOMAIN to pin the domain.
"""
from __future__ import annotations

import os
import signal as _signal
import subprocess
import sys
from pathlib import Path
from typing import Iterator

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


@pytest.fixture
def ros_context(ros_domain: int) -> Iterator["object"]:
    """A fresh rclpy Context initialised on the test domain, shut down afterwards."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)


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
