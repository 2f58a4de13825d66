"""The node's counters and latency windows, and the /diagnostics key-values built from them."""

from __future__ import annotations

import threading
from collections import Counter, deque
from typing import Any

from cegc_ros.node.support import percentiles_ms

#: Why a pair produced no pose: the keys of the ``rejected.*`` diagnostics counters.
REJECT_REASONS = (
    "malformed_cloud",   # missing x/y/z fields, data shorter than the layout, bad field types
    "empty_cloud",       # no finite points at all
    "too_few_points",    # fewer finite points than the engine's minimum
    "missing_frame",     # empty header.frame_id: outputs would have no frame
    "invalid_result",    # the engine judged its result invalid (reason logged)
    "low_fitness",       # fitness < output.min_fitness
    "ambiguous",         # ambiguity > output.max_ambiguity
    "engine_error",      # the engine raised, or its process died; logged with the reason
)

#: Counters shown on /diagnostics (0 until counted), in this order.
COUNTERS = (
    "messages_in.source", "messages_in.target", "pairs_in", "pairs_out", "pairs_dropped",
    "pairs_rejected", "pairs_done", "unpaired.source", "unpaired.target",
    "frame_changes.source", "frame_changes.target", "map_frames.source", "map_frames.target",
    "thinned_clouds", "take_errors",
    "output_errors", "covariance_fallbacks", "engine_restarts", "resets",
) + tuple(f"rejected.{r}" for r in REJECT_REASONS)
#: Input hygiene (cegc_ros.bounding.clean_points): points dropped from each cloud, by reason;
#: ``dropped.<reason>.<side>`` (source, target; cloud in sequential mode).
DROP_REASONS = ("non_finite", "no_return", "out_of_range", "isolated")
COUNTERS += tuple(f"dropped.{r}.{side}" for r in DROP_REASONS for side in ("source", "target"))


class Rejected(Exception):
    """A pair that produces no pose; ``reason`` is one of :data:`REJECT_REASONS`; ``result``:
    the job's result when there was one (the engine's, a check on it rejected the pair; in
    sequential mode the odometry's frame), else None."""

    def __init__(self, reason: str, detail: str, result: Any = None) -> None:
        super().__init__(detail)
        self.reason = reason
        self.result = result


def _number(obj: Any, name: str) -> str:
    """``obj.<name>`` with 4 decimals; "nan" where there is none (``obj`` None included)."""
    value = getattr(obj, name, None)
    return "nan" if value is None else f"{float(value):.4f}"


def quality_values(result: Any, rejected: Rejected | None) -> dict[str, str]:
    """The ``~/quality`` key-values of one finished pair: whether its pose went out, why not,
    and the engine's measures of it ("nan" / "" where the engine gave no result); ``draws``: the
    draws of the network points the pair took (2: engine.redraw_ambiguity)."""
    corr = getattr(result, "correspondences", None)
    total = (getattr(result, "timings", None) or {}).get("total")
    draws = getattr(result, "draws", None)
    return {
        "published": str(rejected is None).lower(),
        "reason": "" if rejected is None else rejected.reason,
        "fitness": _number(result, "fitness"),
        "ambiguity": _number(result, "ambiguity"),
        "correspondences": "" if corr is None else str(len(corr)),
        "engine_ms": "nan" if total is None else f"{1e3 * float(total):.1f}",
        "draws": "" if draws is None else str(int(draws)),
    }


def odometry_quality_values(frame: Any, rejected: Rejected | None) -> dict[str, str]:
    """The ``~/quality`` key-values of one cloud in sequential mode. ``frame``: the odometry's
    FrameResult (cegc_ros/sequential/odometry.py), None when the cloud never reached it.

    :func:`quality_values` of the global registration (``ambiguity``, ``correspondences``,
    ``engine_ms``: "nan" / "" when it did not run), with the odometry's own ``fitness`` and
    ``overlap`` (of the accepted, or last tried, registration) in place of the engine's, how the
    cloud was registered (``method``: first / icp / global; none when rejected; "" without a
    frame), whether it became the ``keyframe``, and the ``detail``: the rejection's, or the
    odometry's note on a published cloud (why global registration or a new keyframe).
    """
    values = quality_values(getattr(frame, "registration", None), rejected)
    values.update(fitness=_number(frame, "fitness"), overlap=_number(frame, "overlap"),
                  method=getattr(frame, "method", ""),
                  keyframe=str(bool(getattr(frame, "new_keyframe", False))).lower(),
                  detail=str(rejected) if rejected is not None else frame.reason)
    return values


class NodeStats:
    """Thread-safe counters (executor and worker both write) and the recent latencies."""

    def __init__(self, window: int) -> None:
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self._latency: deque[float] = deque(maxlen=window)       # pair complete -> pose out (s)
        self._engine_time: deque[float] = deque(maxlen=window)   # engine call (s)
        self.last_fitness = float("nan")
        self.last_ambiguity = float("nan")
        self.busy = False

    def add(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.counts[key] += n

    def count(self, key: str) -> int:
        with self._lock:
            return self.counts[key]

    def reject(self, reason: str) -> None:
        with self._lock:
            self.counts["pairs_rejected"] += 1
            self.counts[f"rejected.{reason}"] += 1

    def engine_time(self, seconds: float) -> None:
        with self._lock:
            self._engine_time.append(seconds)

    def pose_out(self, latency_s: float) -> None:
        with self._lock:
            self.counts["pairs_out"] += 1
            self._latency.append(latency_s)

    def set_window(self, window: int) -> None:
        with self._lock:
            if self._latency.maxlen != window:
                self._latency = deque(self._latency, maxlen=window)
                self._engine_time = deque(self._engine_time, maxlen=window)

    def values(self, extra: dict[str, Any] | None = None) -> dict[str, str]:
        """The /diagnostics key-values: every counter, latency percentiles, ``extra``."""
        with self._lock:
            counts = Counter(self.counts)
            lat = list(self._latency)
            eng = list(self._engine_time)
        values = {k: str(counts.get(k, 0)) for k in COUNTERS}
        values.update({k: str(v) for k, v in sorted(counts.items())       # sequential: .cloud
                       if k.startswith(("dropped.", "map_frames.")) and k not in values})
        for q, v in zip((50, 90, 99), percentiles_ms(lat)):
            values[f"latency_p{q}_ms"] = f"{v:.1f}"
        values["latency_max_ms"] = f"{max(lat) * 1e3:.1f}" if lat else "nan"
        values["engine_p50_ms"] = f"{percentiles_ms(eng, (50,))[0]:.1f}"
        values["last_fitness"] = f"{self.last_fitness:.4f}"
        values["last_ambiguity"] = f"{self.last_ambiguity:.4f}"
        values["busy"] = str(self.busy).lower()
        values.update({k: str(v) for k, v in (extra or {}).items()})
        return values
