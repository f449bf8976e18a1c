"""The process entry pattern shared by dyn_node and dyn_sim (Jazzy's main() with safe signals).

SIGINT and SIGTERM only set an event. rclpy's own handlers shut the context down (or raise
KeyboardInterrupt) wherever the executor happens to be, and while it is converting an incoming
message that surfaces as a pybind11 RuntimeError and a traceback: at 1 kHz that is most of the
time. The executor spins on a thread of its own and blocks until there is work; the main thread
polls the event every 0.1 s (Python runs signal handlers on the main thread only, between
bytecodes, and the kernel may hand the signal to any thread). Polling with the executor instead
cost ten wait-set rebuilds a second, each holding the GIL for ~0.6 ms with dyn_node's ~30
entities, which its joint_states thread then waited for.
"""
from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
from typing import Callable, NoReturn

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions


def spin_until_signalled(make_node: Callable[[], Node], args: list[str] | None, program: str,
                         fatal: tuple[type[BaseException], ...] = (),
                         describe: Callable[[BaseException], str] = str,
                         fatal_code: int | Callable[[BaseException], int] = 2) -> int:
    """Init rclpy, build the node, spin until SIGINT/SIGTERM, then destroy it and shut down.

    Exceptions of the ``fatal`` types raised while building or spinning (configuration the
    program cannot run with) print one line ``<program>: <describe(exc)>`` on stderr instead of a
    traceback and make the return value ``fatal_code`` (or ``fatal_code(exc)``); otherwise 0.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node = None
    code = 0
    try:
        node = make_node()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        # work for the executor, so that its spin_once returns (its own wake() only rebuilds)
        wake = node.create_guard_condition(lambda: None)
        failure: list[BaseException] = []
        spinner = threading.Thread(target=_spin, args=(executor, stop, failure), name=f"{program} executor",
                                   daemon=True)
        spinner.start()
        while not stop.wait(0.1):  # back in the interpreter: a signal another thread took runs here
            pass
        wake.trigger()
        spinner.join()
        if failure:
            raise failure[0]
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except fatal as exc:
        print(f"{program}: {describe(exc)}", file=sys.stderr, flush=True)
        code = fatal_code(exc) if callable(fatal_code) else fatal_code
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


def _spin(executor: SingleThreadedExecutor, stop: threading.Event, failure: list[BaseException]) -> None:
    """Spin until ``stop`` (then woken by the main thread); what a callback raised, or the
    context's shutdown, is handed to the main thread in ``failure``."""
    try:
        while not stop.is_set() and rclpy.ok():
            executor.spin_once()
    except BaseException as exc:
        failure.append(exc)
    finally:
        stop.set()


def end_process(code: int) -> NoReturn:
    """Exit with ``code`` without the interpreter's finalization, once
    :func:`spin_until_signalled` has returned: the node is destroyed (its bag finalised), rclpy
    is shut down (its log files flushed), so nothing is left that needs it.

    Finalization cost 0.6–0.9 s here, 0.4 s of it Numba's compiled kernels alone, and longer on
    a busy machine; and it would tear C++ runtimes down under a feasibility check that
    destroy_node abandoned (a daemon thread in compiled code).
    """
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # a closed or broken pipe: nothing more can be said on it
            pass
    try:
        ctypes.CDLL(None).fflush(None)   # C stdio too (rcutils logs through it)
    except Exception:
        pass
    os._exit(code)
