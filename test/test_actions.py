"""dyn_node.ros.actions.Waits: bounded waits of coroutines on one executor share one timer,
re-armed for the earliest deadline; a wait ends when one of its futures is done or at its deadline."""
from __future__ import annotations

import threading
import time

import pytest


@pytest.fixture
def waits(ros_context):
    """A Waits on a node spun by a SingleThreadedExecutor on a thread of its own, and ``run(coro)``:
    the coroutine as a task on that executor, its result once done (20 s at most)."""
    from rclpy.callback_groups import ReentrantCallbackGroup
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from dyn_node.ros.actions import Waits

    node = Node("waits_test", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    w = Waits(node, executor, ReentrantCallbackGroup())
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()

    def run(*coros):
        done = threading.Event()
        tasks = [executor.create_task(c) for c in coros]
        left = [len(tasks)]
        lock = threading.Lock()

        def one(_t) -> None:
            with lock:
                left[0] -= 1
                if left[0] == 0:
                    done.set()

        for t in tasks:
            t.add_done_callback(one)
        assert done.wait(20.0), "the waits did not end within 20 s"
        return [t.result() for t in tasks]

    try:
        yield w, node, run
    finally:
        stop.set()
        thread.join(5.0)
        executor.shutdown(timeout_sec=2.0)
        node.destroy_node()


def test_deadlines_fire_in_order_on_one_timer(waits):
    """Three waits started together with timeouts 0.3, 0.1, 0.2 s end at their own deadlines (each
    at or after it, in deadline order), all on the one timer Waits made at its start."""
    w, node, run = waits
    ended: dict[float, float] = {}
    t0 = time.monotonic()

    async def wait(timeout: float) -> bool:
        got = await w.any((w.future(),), timeout)
        ended[timeout] = time.monotonic() - t0
        return got

    assert len(list(node.timers)) == 1
    assert run(wait(0.3), wait(0.1), wait(0.2)) == [False, False, False]
    assert sorted(ended, key=ended.get) == [0.1, 0.2, 0.3]
    assert all(ended[t] >= t for t in ended)
    timers = list(node.timers)
    assert len(timers) == 1 and timers[0].is_canceled()  # nothing left to wait for


def test_a_future_done_first_ends_its_wait_and_later_deadlines_still_fire(waits):
    """A future completed from another thread ends a 30 s wait at once (True); its stale deadline
    does not hold back a later, shorter wait, which still ends at its own deadline (False)."""
    w, _, run = waits
    fut = w.future()

    async def long_wait() -> tuple[bool, float]:
        t = time.monotonic()
        got = await w.any((fut,), 30.0)
        return got, time.monotonic() - t

    async def short_wait() -> tuple[bool, float]:
        t = time.monotonic()
        got = await w.any((w.future(),), 0.2)
        return got, time.monotonic() - t

    setter = threading.Timer(0.1, lambda: fut.set_result("x"))  # another thread, as the check worker
    setter.start()
    [(got, took)] = run(long_wait())
    setter.join()
    assert got is True and took < 10.0
    [(got, took)] = run(short_wait())
    assert got is False and 0.2 <= took < 10.0


def test_done_futures_and_zero_timeouts_return_at_once(waits):
    w, _, run = waits
    done = w.future()
    done.set_result(1)

    async def both() -> tuple[bool, bool, bool]:
        return (await w.any((done,), 30.0), await w.any((w.future(),), 0.0), await w.any((), -1.0))

    assert run(both()) == [(True, False, False)]
