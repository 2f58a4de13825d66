"""Small ROS-free pieces of the node: the one-slot mailbox, throttled logging, thinning, and the
job / offer records that the modes hand to the worker (here, so that the modes and the worker
import them from one place and not from each other)."""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np


class Mailbox:
    """A one-slot hand-over between the executor and the worker: the newest item wins."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Any = None
        self._closed = False

    def put(self, item: Any) -> Any:
        """Leave ``item`` for the worker; returns the item it replaced (dropped) or None."""
        with self._cond:
            replaced, self._item = self._item, item
            self._cond.notify()
            return replaced

    def get(self, timeout: float | None = None) -> Any:
        """The waiting item (emptying the slot), or None once closed / after ``timeout``."""
        with self._cond:
            self._cond.wait_for(lambda: self._item is not None or self._closed, timeout)
            if self._closed:
                return None
            item, self._item = self._item, None
            return item

    def take(self) -> Any:
        """Empty the slot without waiting; returns the item that was waiting, if any."""
        with self._cond:
            item, self._item = self._item, None
            return item

    def close(self) -> Any:
        """Wake the worker for good; returns the item that was still waiting, if any."""
        with self._cond:
            self._closed = True
            item, self._item = self._item, None
            self._cond.notify_all()
            return item

    @property
    def closed(self) -> bool:
        return self._closed


class ThrottledLog:
    """Logs each kind of message at once, then at most once per ``period`` s with a count."""

    def __init__(self, emit: Callable[[str], None], period: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._emit = emit
        self.period = period
        self._clock = clock
        self._lock = threading.Lock()     # called from the executor and the worker
        self._last: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()

    def __call__(self, kind: str, text: str) -> bool:
        """Log ``text`` unless ``kind`` was logged less than ``period`` ago; True if logged."""
        with self._lock:
            now = self._clock()
            last = self._last.get(kind)
            if last is not None and now - last < self.period:
                self._suppressed[kind] += 1
                return False
            more = self._suppressed.pop(kind, 0)
            self._last[kind] = now
        self._emit(f"{text} ({more} more like this since the last report)" if more else text)
        return True


def percentiles_ms(samples: Sequence[float], qs: Sequence[float] = (50, 90, 99)) -> list[float]:
    """Percentiles (ms) of durations given in seconds; NaN when there are none."""
    if not samples:
        return [float("nan")] * len(qs)
    return [float(v) * 1e3 for v in np.percentile(np.asarray(samples, np.float64), qs)]


def thin(xyz: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` rows of (N, 3) ``xyz`` by a uniform stride (order kept)."""
    n = xyz.shape[0]
    if n <= max_points:
        return xyz
    return xyz[:: math.ceil(n / max_points)]


@dataclass
class Job:
    """One registration for the worker: ``source`` onto ``target`` (both PointCloud2).

    The outputs carry the source's stamp and the target's frame.
    """

    source: Any
    target: Any
    received: float      # time.monotonic() when the job was complete (the latency's start)


@dataclass
class Offer:
    """What one incoming message produced."""

    job: Job | None = None
    unpaired: list[str] = field(default_factory=list)   # one line per cloud given up on, by side
    unpaired_sides: list[str] = field(default_factory=list)
