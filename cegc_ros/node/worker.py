"""The worker: one thread between the node's mailbox and the engine.

The executor leaves each job in a one-slot :class:`~cegc_ros.node.support.Mailbox` (the
newest wins: a job still waiting when a newer one arrives is dropped and counted). The
worker takes it, turns both clouds into points (rejecting bad ones with a reason), hands
them to the engine (a process of its own, see :mod:`cegc_ros.node.engine_process`), checks
the result and passes it to the node's ``publish``. Every job ends in exactly one of:
a published pose (``pairs_out``), a rejection (``rejected.<reason>``), or nothing else:
``pairs_done`` counts them all; after each, ``report`` hears how it ended (``~/quality``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from cegc_ros.node.engine_process import EngineDied, EngineStartError
from cegc_ros.node.support import Job
from cegc_ros.node.stats import NodeStats, Rejected
from cegc_ros.node.support import Mailbox, ThrottledLog, thin


#: How often an idle worker looks for deferred work (a reset, an initial pose), in seconds.
IDLE_POLL_S = 0.1
#: Frame names (the last path component, so "robot1/map" too) that say a cloud is not in its
#: sensor's frame: such clouds are counted (``map_frames.<side>``) and a warning names the
#: settings that assume sensor frames (preprocess.normals 'sensor', engine.free_space).
MAP_FRAMES = ("map", "odom", "world", "earth")


class RegistrationWorker:
    """Runs jobs on the engine, one at a time, on a thread of its own.

    Args:
        engine: an EngineProcess / InlineEngine (started).
        stats: the node's counters.
        log: throttled warnings (kind, text).
        settings: returns the node's current sections (dict name -> config dataclass); a
            section object is replaced whole on change, never mutated.
        publish: called with (job, result) for a result worth publishing; raises Rejected
            when it cannot be turned into a pose.
        on_result: the mode's hook, after publish.
        info: logs one line that is not a warning (engine restarts).
        report: called once per finished job with (job, its result or None: what
            :meth:`process` returned or the Rejected carried, the Rejected that stopped it or
            None), after publish or the rejection.
    """

    def __init__(self, engine: Any, stats: NodeStats, log: ThrottledLog,
                 settings: Callable[[], dict[str, Any]], publish: Callable[[Job, Any], None],
                 on_result: Callable[[Job, Any], None] = lambda job, result: None,
                 info: Callable[[str], None] = print,
                 report: Callable[[Job, Any, Rejected | None], None] = lambda job, result, rej: None
                 ) -> None:
        self.engine = engine
        self.stats = stats
        self._log = log
        self._settings = settings
        self._publish = publish
        self._on_result = on_result
        self._info = info
        self._report = report
        self._mailbox = Mailbox()
        self._deferred: list[Callable[[], None]] = []   # run by the worker thread, between jobs
        self._deferred_lock = threading.Lock()
        self._engine_dirty = False
        self._last_frames: dict[str, str] = {}
        self._thread = threading.Thread(target=self._run, name="cegc_worker", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def submit(self, job: Job) -> None:
        """Leave a job for the worker (executor thread); the one it replaces is counted."""
        self.stats.add("pairs_in")
        if self._mailbox.put(job) is not None:
            self.stats.add("pairs_dropped")
            self._log("dropped", "registration is slower than the input: the waiting pair "
                      "was replaced by a newer one")

    def clear_pending(self) -> bool:
        """Drop the job waiting in the mailbox, if any (``~/reset``); True if one was."""
        return self._mailbox.take() is not None

    def defer(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` in the worker thread after the job in progress, before the next one
        (within IDLE_POLL_S when idle): state the worker owns changes only there."""
        with self._deferred_lock:
            self._deferred.append(fn)

    def _run_deferred(self) -> None:
        with self._deferred_lock:
            todo, self._deferred = self._deferred, []
        for fn in todo:
            fn()

    def engine_settings_changed(self) -> None:
        """preprocess.* / engine.* changed: the engine gets them with the next job."""
        self._engine_dirty = True

    def stop(self, timeout: float = 10.0) -> bool:
        """Take no more jobs; wait up to ``timeout`` s for the one in progress. True if the
        thread ended (False: the engine is still busy; closing the engine ends it)."""
        self._mailbox.close()
        if self._thread.is_alive():
            self._thread.join(timeout)
        return not self._thread.is_alive()

    # -- the thread -----------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            job = self._mailbox.get(IDLE_POLL_S)
            self._run_deferred()
            if job is None:
                if self._mailbox.closed:
                    return
                continue
            self.stats.busy = True
            result, rejected = None, None
            try:
                result = self.process(job)
            except Rejected as rej:
                result, rejected = rej.result, rej
            except Exception as err:  # noqa: BLE001  the node must outlive any bad pair
                rejected = Rejected("engine_error", f"{type(err).__name__}: {err}")
            finally:
                if rejected is not None:
                    self._reject(rejected.reason, str(rejected))
                self.stats.add("pairs_done")
                self.stats.busy = False
            try:
                self._report(job, result, rejected)
            except Exception as err:  # noqa: BLE001  the pose (or the rejection) stands
                self.stats.add("output_errors")
                self._log("output_error", f"~/quality not published: {type(err).__name__}: {err}")

    def _reject(self, reason: str, detail: str) -> None:
        self.stats.reject(reason)
        self._log(reason, f"pair rejected ({reason}): {detail}")

    def process(self, job: Job) -> Any:
        """One job, start to end: the engine's result, published; raises Rejected with the
        reason it gives no pose (and the result, when the engine gave one)."""
        cfg = self._settings()
        src_xyz = self.points("source", job.source, cfg["input"].max_points, cfg["preprocess"])
        tgt_xyz = self.points("target", job.target, cfg["input"].max_points, cfg["preprocess"])
        update = None
        if self._engine_dirty:
            self._engine_dirty = False
            update = (cfg["preprocess"], cfg["engine"])
        t0 = time.perf_counter()
        try:
            result = self.engine.register(src_xyz, tgt_xyz, update)
        except ValueError as err:
            raise Rejected("too_few_points", f"engine refused the pair: {err}") from err
        except EngineDied as err:
            if self._mailbox.closed:     # the node is shutting down and closed the engine
                raise Rejected("engine_error", "the node stopped during the registration") \
                    from err
            self._restart(err)
            raise Rejected("engine_error", str(err)) from err
        self.stats.engine_time(time.perf_counter() - t0)
        for side, dropped in zip(("source", "target"), getattr(result, "dropped", ())):
            if dropped.isolated:                     # found by the engine, after its voxel grid
                self.stats.add(f"dropped.isolated.{side}", dropped.isolated)
        if not result.valid:
            raise Rejected("invalid_result", f"engine result invalid: {result.reason}", result)
        self.stats.last_fitness = float(result.fitness)
        self.stats.last_ambiguity = float(result.ambiguity)
        min_fitness = cfg["output"].min_fitness
        if result.fitness < min_fitness:
            raise Rejected("low_fitness", f"fitness {result.fitness:.3f} < "
                           f"output.min_fitness {min_fitness:.3f}", result)
        max_ambiguity = cfg["output"].max_ambiguity
        if result.ambiguity > max_ambiguity:
            raise Rejected("ambiguous", f"ambiguity {result.ambiguity:.3f} > "
                           f"output.max_ambiguity {max_ambiguity:.3f}: another alignment "
                           f"explains the clouds nearly as well", result)
        return self.deliver(job, result)

    def deliver(self, job: Job, result: Any) -> Any:
        """Publish an accepted ``result`` and tell the mode (``on_result``); a Rejected from
        publish leaves carrying the result, for ``report``."""
        try:
            self._publish(job, result)
        except Rejected as rej:
            rej.result = result
            raise
        self._on_result(job, result)
        return result

    def _restart(self, err: Exception) -> None:
        self.stats.add("engine_restarts")
        self._info(f"{err}; starting the engine again")
        try:
            self.engine.restart()
        except EngineStartError as start_err:
            self._log("engine_start", f"the engine did not start again: {start_err}")

    def points(self, side: str, msg: Any, max_points: int, preprocess: Any = None) -> np.ndarray:
        """Usable (N, 3) float32 points of one input cloud (finite, not a no-return (0, 0, 0),
        within ``preprocess.min_range`` / ``max_range``: cegc_ros.bounding.clean_points, each
        drop counted as ``dropped.<reason>.<side>``), at most ``max_points``; Rejected with the
        reason when there are none to use."""
        from cegc_ros.bounding import clean_points
        from msg_adapters.point_cloud2 import cloud_to_xyz

        try:
            frame = msg.header.frame_id
        except AttributeError as err:
            raise Rejected("malformed_cloud", f"{side} cloud has no header") from err
        if not frame:
            raise Rejected("missing_frame", f"{side} cloud has an empty header.frame_id")
        last = self._last_frames.get(side)
        if last is not None and last != frame:
            self.stats.add(f"frame_changes.{side}")
            self._log(f"frame_change.{side}", f"{side} cloud frame changed from {last!r} "
                      f"to {frame!r}; following the new frame")
        self._last_frames[side] = frame
        if preprocess is not None and preprocess.normals == "sensor" and frame.rsplit("/", 1)[-1] in MAP_FRAMES:
            self.stats.add(f"map_frames.{side}")
            self._log(f"map_frame.{side}", f"{side} cloud is in frame {frame!r}, a map frame by its "
                      f"name: preprocess.normals 'sensor' and engine.free_space assume each cloud "
                      f"in its sensor's frame; for clouds in a map frame set preprocess.normals "
                      f"to 'centroid' and engine.free_space to 0")
        try:
            xyz = cloud_to_xyz(msg)  # (N, 3) float32, finite only
        except ValueError as err:
            raise Rejected("malformed_cloud", f"{side} cloud: {err}") from err
        n_msg = int(msg.width) * int(msg.height)
        dropped = {"non_finite": n_msg - xyz.shape[0]}
        if preprocess is not None:
            xyz, d = clean_points(xyz, preprocess.min_range, preprocess.max_range)
            dropped.update(no_return=d.no_return, out_of_range=d.out_of_range)
        for reason, n in dropped.items():
            if n > 0:
                self.stats.add(f"dropped.{reason}.{side}", n)
        if xyz.shape[0] == 0:
            raise Rejected("empty_cloud", f"{side} cloud has no usable points ({n_msg} points "
                           f"in the message: {dropped.get('non_finite', 0)} non-finite, "
                           f"{dropped.get('no_return', 0)} at (0, 0, 0), "
                           f"{dropped.get('out_of_range', 0)} out of range)")
        min_points = self.engine.info.min_points
        if xyz.shape[0] < min_points:
            raise Rejected("too_few_points", f"{side} cloud has {xyz.shape[0]} finite "
                           f"points, the engine needs at least {min_points}")
        if xyz.shape[0] > max_points:
            self.stats.add("thinned_clouds")
            self._log("thinned", f"{side} cloud of {xyz.shape[0]} points thinned to "
                      f"input.max_points = {max_points} by a uniform stride")
            xyz = thin(xyz, max_points)
        return xyz
