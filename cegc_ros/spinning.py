"""An rclpy executor spun on a background thread, stopped in the one safe order.

``threading.Thread(target=executor.spin)`` followed by ``executor.shutdown()`` races: rclpy
(Jazzy) destroys the executor's guard condition in ``shutdown`` without waiting for the spinning
thread to leave its wait set, and ``destroy_node`` after it can pull a subscription out from under
a callback being dispatched. Under load that surfaced as ``InvalidHandle`` raised in the spin
thread (CI of 2026-12-05). :class:`Spinner` spins in short ``spin_once`` slices and, on
:meth:`Spinner.stop`, ends the loop and joins the thread *before* the executor shuts down, so the
caller may then destroy its nodes and shut the context down.

Used by the replay client (cegc_ros.replay), the node benchmark's probe and the ROS tests.
"""

from __future__ import annotations

import threading
import time
from typing import Any

#: The longest a stop waits for the loop: one ``spin_once`` slice plus a callback in flight (s).
STOP_TIMEOUT_S = 30.0


class Spinner:
    """Spin ``executor`` on a daemon thread until :meth:`stop` (also as a context manager).

    ``slice_s`` bounds each ``spin_once`` wait, so a stop is noticed within it.
    """

    def __init__(self, executor: Any, name: str = "cegc_spin", slice_s: float = 0.05) -> None:
        self.executor = executor
        self._slice_s = float(slice_s)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from rclpy.executors import ExternalShutdownException, ShutdownException

        ex = self.executor
        # Executor.spin's own loop condition: spin_once returns at once without raising once the
        # context or the executor is shut down (some executors swallow both exceptions).
        while not self._stop.is_set() and ex.context.ok() and not getattr(ex, "_is_shutdown", False):
            try:
                ex.spin_once(timeout_sec=self._slice_s)
            except (ExternalShutdownException, ShutdownException):
                return      # the context (or the executor) was shut down from outside

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """End the loop, wait for the thread and the callbacks in flight, then shut the
        executor down. Idempotent.

        RuntimeError if a callback is still running after ``timeout`` s (one that never
        returns): destroying nodes then would race it.
        """
        deadline = time.monotonic() + timeout
        self._stop.set()
        self._thread.join(timeout)
        # A MultiThreadedExecutor runs its callbacks on a pool after spin_once returned; its
        # _futures are the tasks it submitted there, started or still queued. Wait for them
        # (Executor.shutdown means to wait for the work in flight but does not: Jazzy tests
        # _is_shutdown right after setting it), then for rclpy's count of callbacks running.
        pending = list(getattr(self.executor, "_futures", ()))
        tracker = getattr(self.executor, "_work_tracker", None)
        def busy() -> bool:
            return self._thread.is_alive() or any(not f.done() for f in pending)

        while busy() and time.monotonic() < deadline:
            time.sleep(0.005)
        if busy() or (tracker is not None and not tracker.wait(max(0.0, deadline - time.monotonic()))):
            raise RuntimeError(f"the executor's callbacks did not finish within {timeout:g} s "
                               "of the stop (one still running)")
        self.executor.shutdown(timeout_sec=0)

    def __enter__(self) -> Spinner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
