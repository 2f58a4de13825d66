"""Two cores for one pair: the independent halves of a stage side by side.

The engine's numpy and SciPy stages run on one thread, while the network and Open3D use the
threads they are given. Where a stage does the same work on two clouds that do not depend on
each other (the bound stage's hygiene, grid and stray check of the source and of the target,
cegc_ros/bounding.py), :func:`both` runs the second half on a worker thread while the calling
thread runs the first: numpy's array loops and SciPy's k-d trees release the GIL, so the two
halves share the two cores. The verification's landing search (cegc_ros/refine.py,
``_nearest``) splits its queries the same way. The answers are the same as one after the other
(the same calls on the same inputs; test_parallel), and so are the errors: the first half's is
raised before the second's, as it would have been in turn.

Only where the halves are large: each hand-off costs a wake-up, and beside busy processes a
wake-up waits for a time slice (docs/performance.md: the bound stage of 1.5k-point crops 10 ->
15 ms beside two busy processes; the free-space check's two directions, ~1 ms each, gained
nothing and were left in turn). SciPy's own threads (``workers``) start at every call: the
landing search on them gained nothing idle and cost 60 ms at 300k points beside two busy
processes, where its halves on this module's one worker gain 7 ms idle and are level there.

:func:`query_workers` is the rule for SciPy's own k-d-tree threads (``workers``)."""

from __future__ import annotations

import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, TypeVar

A = TypeVar("A")
R = TypeVar("R")

#: k-d-tree queries of more points than this use every core; smaller ones stay on one thread,
#: where SciPy's per-call thread start-up costs more than it saves (2000 points: 1.5 ms on one
#: thread, 3.9 ms on two beside a busy process; docs/performance.md).
PARALLEL_QUERY_POINTS = 10000


def query_workers(n: int) -> int:
    """SciPy's ``workers`` for a k-d-tree query of n points: -1 (every core) above
    :data:`PARALLEL_QUERY_POINTS`, else 1; 1 inside a half of :func:`both` (the other half
    has the other core)."""
    return -1 if n > PARALLEL_QUERY_POINTS and not _in_half() else 1


def cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()
_half = threading.local()          # .flag: this thread is running a half of both()


def _in_half() -> bool:
    return getattr(_half, "flag", False)


def _worker() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(1, thread_name_prefix="cegc-half",
                                       initializer=lambda: setattr(_half, "flag", True))
        return _pool


def _forget_pool() -> None:
    """In a forked child: the parent's worker thread does not exist there, so work submitted to
    the inherited pool would wait for ever; the child starts its own on first use."""
    global _pool, _pool_lock
    _pool = None
    _pool_lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def both(fn: Callable[[A], R], first: A, second: A, side_by_side: bool = True) -> tuple[R, R]:
    """(fn(first), fn(second)), the second on a worker thread when ``side_by_side`` and this
    process may use two cores or more, else one after the other. ``fn`` must not change state
    the other call reads.
    An exception of the first call is raised (after the second has finished), else the second's.
    Called within a half (nested), both run on the calling thread."""
    if not side_by_side or cores() < 2 or _in_half():
        return fn(first), fn(second)
    later: Future = _worker().submit(fn, second)
    _half.flag = True
    try:
        a = fn(first)
    except BaseException:
        later.exception()                  # wait: nothing of this pair runs on after the raise
        raise
    finally:
        _half.flag = False
    return a, later.result()
