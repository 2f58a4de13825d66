"""Approximate-time pairing of two message streams by their stamps (ROS-free).

``message_filters`` is not available to this package, so the node pairs its ``source_cloud``
and ``target_cloud`` topics with this small pairer instead. Each stream keeps a bounded buffer
of messages that have not found a partner yet. When a message arrives, the buffered message
of the *other* stream whose stamp is closest to it is taken as its partner, provided the two
stamps differ by at most ``slop``; otherwise the message waits in its own buffer. Stamps may
arrive in any order: the search is by stamp, not by arrival. A full buffer drops its oldest
stamp, which is then reported as unpaired and counted.

All stamps are integer nanoseconds; ``slop`` is given in seconds like the ROS parameter.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from typing import Generic, Literal, TypeVar

M = TypeVar("M")
Side = Literal["source", "target"]
SIDES: tuple[Side, Side] = ("source", "target")


@dataclass(frozen=True)
class Stamped(Generic[M]):
    """One message waiting in a buffer, with the stamp (ns) it is paired by."""

    stamp_ns: int
    msg: M
    side: Side


@dataclass(frozen=True)
class MatchedPair(Generic[M]):
    """A source message and a target message whose stamps differ by at most the slop."""

    source: Stamped[M]
    target: Stamped[M]

    @property
    def dt_ns(self) -> int:
        """Target stamp minus source stamp, in ns."""
        return self.target.stamp_ns - self.source.stamp_ns


@dataclass
class AddResult(Generic[M]):
    """What one :meth:`ApproximatePairer.add` call produced."""

    pair: MatchedPair[M] | None = None
    # Messages pushed out of a full buffer by this call: they will never be paired.
    unpaired: list[Stamped[M]] = field(default_factory=list)


@dataclass
class PairerStats:
    """Counters since construction (or :meth:`ApproximatePairer.reset_stats`)."""

    received: dict[str, int] = field(default_factory=lambda: {"source": 0, "target": 0})
    paired: int = 0
    # Oldest messages dropped from a full buffer, per stream (each is an unpaired message).
    dropped: dict[str, int] = field(default_factory=lambda: {"source": 0, "target": 0})


class ApproximatePairer(Generic[M]):
    """Pairs source and target messages whose stamps lie within ``slop_s`` seconds.

    Not thread-safe: call it from one thread (the node calls it from its executor).
    """

    def __init__(self, slop_s: float, buffer_size: int) -> None:
        self._buffers: dict[str, list[Stamped[M]]] = {"source": [], "target": []}  # sorted by stamp
        self.stats = PairerStats()
        self.slop_s = slop_s
        self.buffer_size = buffer_size

    # -- settings (may change between calls: the node's sync.* parameters are dynamic) --------
    @property
    def slop_s(self) -> float:
        return self._slop_ns / 1e9

    @slop_s.setter
    def slop_s(self, value: float) -> None:
        if not value >= 0.0:
            raise ValueError(f"slop must be >= 0 s, got {value}")
        self._slop_ns = round(value * 1e9)

    @property
    def buffer_size(self) -> int:
        return self._buffer_size

    @buffer_size.setter
    def buffer_size(self, value: int) -> None:
        if value < 1:
            raise ValueError(f"buffer size must be >= 1, got {value}")
        self._buffer_size = int(value)
        # Shrinking takes effect on the next add(), which reports what it drops.

    # -- use ----------------------------------------------------------------------------------
    def add(self, side: Side, stamp_ns: int, msg: M) -> AddResult[M]:
        """Offer one message; returns the pair it completed (if any) and what fell out."""
        if side not in SIDES:
            raise ValueError(f"side must be 'source' or 'target', got {side!r}")
        self.stats.received[side] += 1
        item = Stamped(int(stamp_ns), msg, side)
        other = self._buffers["target" if side == "source" else "source"]
        result: AddResult[M] = AddResult()

        best = self._closest(other, item.stamp_ns)
        if best is not None:
            partner = other.pop(best)
            self.stats.paired += 1
            source, target = (item, partner) if side == "source" else (partner, item)
            result.pair = MatchedPair(source, target)
        else:
            own = self._buffers[side]
            keys = [s.stamp_ns for s in own]
            own.insert(bisect.bisect_right(keys, item.stamp_ns), item)
        for s in SIDES:
            result.unpaired.extend(self._trim(s))
        return result

    def pending(self, side: Side) -> list[Stamped[M]]:
        """Messages of one stream still waiting for a partner, oldest stamp first."""
        return list(self._buffers[side])

    def flush(self) -> list[Stamped[M]]:
        """Empty both buffers and return what was in them (all unpaired), sorted by stamp."""
        out = sorted(self._buffers["source"] + self._buffers["target"], key=lambda s: s.stamp_ns)
        self._buffers = {"source": [], "target": []}
        return out

    # -- internals ----------------------------------------------------------------------------
    def _closest(self, buf: list[Stamped[M]], stamp_ns: int) -> int | None:
        """Index of the buffered message closest in stamp, if within the slop (ties: older)."""
        if not buf:
            return None
        keys = [s.stamp_ns for s in buf]
        i = bisect.bisect_left(keys, stamp_ns)
        candidates = [j for j in (i - 1, i) if 0 <= j < len(buf)]
        j = min(candidates, key=lambda k: (abs(keys[k] - stamp_ns), keys[k]))
        return j if abs(keys[j] - stamp_ns) <= self._slop_ns else None

    def _trim(self, side: Side) -> list[Stamped[M]]:
        buf = self._buffers[side]
        excess = len(buf) - self._buffer_size
        if excess <= 0:
            return []
        dropped, self._buffers[side] = buf[:excess], buf[excess:]
        self.stats.dropped[side] += excess
        return dropped
