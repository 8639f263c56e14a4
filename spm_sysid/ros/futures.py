"""Work off the executor, awaited by a coroutine on it: one helper, no polling.

A coroutine on the node's executor (the action, the Trigger, an automatic
identification) awaits an rclpy :class:`~rclpy.task.Future`; the work runs on a
thread (reading a user's path, waiting for the worker process) or is answered by
another thread (the worker's reader). :class:`Pending` is that future with the
one way to settle it from any thread -- first settlement wins -- and the
executor woken at once (a guard condition), so nothing sleeps and polls.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from rclpy.task import Future

__all__ = ["Pending"]


class Pending:
    """An rclpy Future settled from any thread, first settlement winning.

    Parameters
    ----------
    wake : callable
        Wakes the executor (``guard_condition.trigger``) so the awaiting coroutine
        resumes at once.
    """

    def __init__(self, wake: Callable[[], None]) -> None:
        self.future = Future()
        self._wake = wake
        self._lock = threading.Lock()

    def settle(self, value: Any = None, exc: BaseException | None = None) -> bool:
        """Give the result (or the error); False when it was settled already."""
        with self._lock:
            if self.future.done():
                return False
            if exc is None:
                self.future.set_result(value)
            else:
                self.future.set_exception(exc)
        self._wake()
        return True

    @classmethod
    def run(cls, fn: Callable[[], Any], wake: Callable[[], None], *,
            timeout: float | None = None,
            on_timeout: Callable[[], BaseException] | None = None) -> Pending:
        """``fn()`` on a thread; its value or its error (or ``on_timeout()`` after ``timeout``)."""
        pending = cls(wake)

        def work() -> None:
            try:
                pending.settle(fn())
            except BaseException as exc:  # noqa: BLE001 - handed to the awaiting coroutine
                pending.settle(exc=exc)

        threading.Thread(target=work, daemon=True, name="off-executor").start()
        if timeout is not None and timeout > 0 and on_timeout is not None:
            timer = threading.Timer(timeout, lambda: pending.settle(exc=on_timeout()))
            timer.daemon = True
            timer.start()
            pending.future.add_done_callback(lambda _: timer.cancel())
        return pending
