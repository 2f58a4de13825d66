"""cegc_ros.spinning.Spinner: a stop waits for the spin thread and the callbacks in flight before
the executor shuts down (rclpy's own shutdown does not wait, and nodes destroyed then raced a
dispatching callback: InvalidHandle in the spin thread under load)."""

from __future__ import annotations

import threading
import time
import warnings

import pytest
import ros_helpers as rh   # first: pins DDS to this machine before rclpy starts

rclpy = pytest.importorskip("rclpy")

from cegc_ros.spinning import Spinner  # noqa: E402


@pytest.fixture
def context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def _timer_node(context, callback):
    node = rclpy.create_node("spinning_test", context=context)
    node.create_timer(0.01, callback)
    return node


def test_stop_waits_for_the_callback_in_flight_and_nothing_runs_after_it(context):
    from rclpy.executors import MultiThreadedExecutor

    started, finished = threading.Event(), threading.Event()
    calls = []

    def slow() -> None:
        calls.append(time.monotonic())
        if not started.is_set():
            started.set()
            time.sleep(0.3)
            finished.set()

    node = _timer_node(context, slow)
    ex = MultiThreadedExecutor(num_threads=2, context=context)
    ex.add_node(node)
    spinner = Spinner(ex)
    assert started.wait(10.0), "the timer never fired"
    spinner.stop()
    # The first callback was sleeping on the pool when stop began; stop returned after it.
    assert finished.is_set()
    assert not spinner.running
    n = len(calls)
    time.sleep(0.1)                 # ten timer periods: nothing dispatches any more
    assert len(calls) == n
    node.destroy_node()
    spinner.stop()                  # idempotent


def test_stop_waits_for_callbacks_still_queued_on_the_pool(context):
    """One pool thread, two timers of their own callback groups: a task is usually queued behind
    the one running when the stop comes; none may start after stop returned."""
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
    from rclpy.executors import MultiThreadedExecutor

    lock = threading.Lock()
    count = {"started": 0, "finished": 0}

    def work() -> None:
        with lock:
            count["started"] += 1
        time.sleep(0.03)
        with lock:
            count["finished"] += 1

    node = rclpy.create_node("spinning_queue", context=context)
    for _ in range(2):
        node.create_timer(0.005, work, callback_group=MutuallyExclusiveCallbackGroup())
    for _ in range(5):                       # five stops, each with a fresh executor
        with warnings.catch_warnings():      # one pool thread on purpose: a queue behind it
            warnings.simplefilter("ignore", UserWarning)
            ex = MultiThreadedExecutor(num_threads=1, context=context)
        ex.add_node(node)
        spinner = Spinner(ex)
        start = count["started"]
        assert rh.wait_for(lambda: count["started"] >= start + 6, 10.0), "the timers never fired"
        spinner.stop()
        with lock:
            after_stop = dict(count)
        assert after_stop["started"] == after_stop["finished"]
        time.sleep(0.1)
        assert count == after_stop, "a callback ran after stop() returned"
    node.destroy_node()


def test_stop_refuses_while_a_callback_never_returns(context):
    from rclpy.executors import MultiThreadedExecutor

    release, entered = threading.Event(), threading.Event()

    def stuck() -> None:
        entered.set()
        release.wait(10.0)

    node = _timer_node(context, stuck)
    ex = MultiThreadedExecutor(num_threads=2, context=context)
    ex.add_node(node)
    spinner = Spinner(ex)
    assert entered.wait(10.0), "the timer never fired"
    with pytest.raises(RuntimeError, match="did not finish within 0.2 s"):
        spinner.stop(timeout=0.2)
    release.set()
    spinner.stop()
    node.destroy_node()


def test_a_single_threaded_executor_runs_its_callbacks_until_stopped(context):
    from rclpy.executors import SingleThreadedExecutor

    calls = []
    node = _timer_node(context, lambda: calls.append(1))
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(node)
    with Spinner(ex) as spinner:
        assert rh.wait_for(lambda: len(calls) >= 5, 10.0)
    assert not spinner.running
    n = len(calls)
    time.sleep(0.1)
    assert len(calls) == n
    node.destroy_node()
