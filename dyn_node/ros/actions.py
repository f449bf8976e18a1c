"""Action-server helpers shared by the gate and dyn_sim's controller face: the canceled end of a
goal that was never asked to cancel, and waits on futures from coroutines on one executor (no
thread per wait, no polling loop)."""
from __future__ import annotations

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
    """Waits for coroutines run by ``executor`` on ``node`` (which that executor spins); timers in
    ``group`` (reentrant: the waiting coroutine's own entity holds a mutually exclusive one)."""

    def __init__(self, node: Any, executor: Any, group: Any = None):
        self.node, self.executor, self.group = node, executor, group

    def future(self) -> Future:
        """A future that wakes the executor when completed from any thread (its done callback is
        scheduled as a task, which triggers the executor's guard condition)."""
        fut = Future(executor=self.executor)
        fut.add_done_callback(_noop)
        return fut

    async def any(self, futures: Iterable[Any], timeout: float | None) -> bool:
        """Until one of ``futures`` is done or ``timeout`` s (None: no limit); whether one is."""
        futures = list(futures)
        wake = self.future()

        def fire(_f: Any = None) -> None:
            if not wake.done():
                wake.set_result(True)

        for f in futures:
            f.add_done_callback(fire)
        timer = None
        if timeout is not None:
            if timeout <= 0:
                return any(f.done() for f in futures)
            timer = self.node.create_timer(timeout, fire, callback_group=self.group)
        try:
            await wake
        finally:
            if timer is not None:
                timer.cancel()
                self.node.destroy_timer(timer)
        return any(f.done() for f in futures)

    async def sleep(self, seconds: float) -> None:
        await self.any((), seconds)
