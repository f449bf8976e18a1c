"""Action-server helpers shared by the gate and dyn_sim's controller face: the canceled end of a
goal that was never asked to cancel, and waits on futures from coroutines on one executor (no
thread per wait, no polling loop)."""
from __future__ import annotations

import heapq
import itertools
import time
from typing import Any, Iterable

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.task import Future


def end_canceled(handle: Any) -> None:
    """CANCELED from EXECUTING (a pre-emption): rcl_action allows CANCELED only from CANCELING, so
    the cancel transition is taken first, as a cancel request would (rclpy has no public call)."""
    if not handle.is_cancel_requested:
        handle._update_state(_rclpy.GoalEvent.CANCEL_GOAL)
    handle.canceled()


def _noop(_f: Any) -> None:
    return None


class Waits:
    """Waits for coroutines run by ``executor`` on ``node`` (which that executor spins), from that
    executor's thread only. Every bounded wait shares one rclpy timer, created once and re-armed
    for the earliest deadline: a timer per wait made each wait create and destroy an rcl timer
    (and change the node's entities) on the goal's path. ``group``: the timer's (reentrant: the
    waiting coroutine's own entity holds a mutually exclusive one)."""

    def __init__(self, node: Any, executor: Any, group: Any = None):
        self.node, self.executor, self.group = node, executor, group
        self._deadlines: list[tuple[float, int, Future]] = []  # heap of (monotonic s, seq, wake)
        self._seq = itertools.count()
        self._armed: float | None = None  # the deadline the timer fires for; None: cancelled
        self._timer = node.create_timer(3600.0, self._fire, callback_group=group)
        self._timer.cancel()

    def future(self) -> Future:
        """A future that wakes the executor when completed from any thread (its done callback is
        scheduled as a task, which triggers the executor's guard condition)."""
        fut = Future(executor=self.executor)
        fut.add_done_callback(_noop)
        return fut

    async def any(self, futures: Iterable[Any], timeout: float | None) -> bool:
        """Until one of ``futures`` is done or ``timeout`` s (None: no limit); whether one is."""
        futures = list(futures)
        if any(f.done() for f in futures):
            return True
        if timeout is not None and timeout <= 0:
            return False
        wake = self.future()

        def fire(_f: Any = None) -> None:
            if not wake.done():
                wake.set_result(True)

        for f in futures:
            f.add_done_callback(fire)
        if timeout is not None:
            self._add(time.monotonic() + timeout, wake)
        await wake
        return any(f.done() for f in futures)

    async def sleep(self, seconds: float) -> None:
        await self.any((), seconds)

    def _add(self, at: float, wake: Future) -> None:
        heapq.heappush(self._deadlines, (at, next(self._seq), wake))
        if self._armed is None or at < self._armed:
            self._arm(at)

    def _arm(self, at: float) -> None:
        self._armed = at
        self._timer.timer_period_ns = max(int((at - time.monotonic()) * 1e9), 1000)
        self._timer.reset()

    def _fire(self) -> None:
        """The timer: wake every wait whose deadline passed, re-arm for the next one still waiting."""
        now = time.monotonic()
        heap = self._deadlines
        while heap and (heap[0][0] <= now or heap[0][2].done()):
            _, _, wake = heapq.heappop(heap)
            if not wake.done():
                wake.set_result(False)
        if heap:
            self._arm(heap[0][0])
        else:
            self._armed = None
            self._timer.cancel()
