"""Replaying a bag into a running register_node and recording the poses it returns: the part
of ``cegc-replay`` (cegc_ros/tools/replay.py) that ``cegc-eval --through-node``
(cegc_ros/evaluation/through_node.py) reuses, so that evaluation does not import a tool.

:func:`replay_bag` publishes the chosen PointCloud2 messages as stored (serialized CDR, no
decoding) with RELIABLE QoS, paced by the bag's log times or, for a pair bag, in lockstep, and
matches every ``~/pose`` (a stream: ``~/odometry``) and ``~/quality`` to its pair or cloud by
header stamp (:func:`plan_topics`: a pair bag's two topics onto the node's inputs; a sequence
bag's or any recording's cloud topic onto ``cloud``; ``--remap FROM:=TO`` chooses);
:func:`write_records` and :func:`summary` report.
"""

from __future__ import annotations

import csv
import json
import os
import sys
import threading
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cegc_ros.data.bag import (TOPIC_CLOUD, TOPIC_CLOUD_GT,  # the bag layouts played here
                               TOPIC_GT, TOPIC_SOURCE, TOPIC_TARGET)



class ReplayError(Exception):
    """The bag cannot be replayed or the node could not be reached."""


@dataclass
class ReplayRecord:
    """One pair (or, for a cloud stream, one cloud) of the bag and what the node answered.

    T_est / T_gt: (4, 4) row-major nested lists, None when the node published no answer for it
    (dropped, rejected, lost) / the bag has no ground truth for it. A pair: T_target_source from
    ``~/pose`` and ``/cegc/ground_truth``. A stream: T_odom_cloud from ``~/odometry`` and, for a
    sequence bag, the ground truth relative to the first cloud played (the odometry's frame).
    latency_s: from publishing the item's last cloud to receiving its answer (None without).
    loop: which play of the bag (0 first; ``loops`` > 1).
    fitness / ambiguity / rejected: the item's ``~/quality``: a pair's engine fitness and
    ambiguity; a stream cloud's odometry fitness and its global registration's ambiguity (None
    when tracking sufficed); the rejection reason when the node published no pose (odometry)
    for it, e.g. ``ambiguous``, ``empty_cloud``, ``not_registered``. None without a quality
    message (a node that publishes none) or a number in it ("nan").
    method / keyframe: a stream cloud's ``~/quality``: how it was registered (``first``,
    ``icp``, ``global``; ``none`` when not registered) and whether it became the keyframe;
    None for a pair, without a quality message, or (method) when the odometry never took the
    cloud.
    """

    index: int
    stamp_ns: int
    T_est: list[list[float]] | None
    T_gt: list[list[float]] | None
    latency_s: float | None
    loop: int = 0
    fitness: float | None = None
    ambiguity: float | None = None
    rejected: str | None = None
    method: str | None = None
    keyframe: bool | None = None


@dataclass
class ReplayResult:
    records: list[ReplayRecord]
    diagnostics: dict[str, str]          # the node's last /diagnostics key-values ({} if none)
    wall_s: float                        # whole replay, connection excluded
    # The Fast DDS profiles file named when the replay's node was created (None: Fast DDS's
    # defaults). Fast DDS applies it only if that was the process's first ROS node.
    fastdds_profile: str | None = None
    loops: int = 1                       # plays of the bag done
    stream: bool = False                 # one cloud stream (sequential mode), not pairs

    def to_json(self) -> dict[str, Any]:
        return {"records": [asdict(r) for r in self.records], "diagnostics": self.diagnostics,
                "wall_s": self.wall_s, "fastdds_profile": self.fastdds_profile,
                "loops": self.loops}


def _topic(namespace: str, name: str) -> str:
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{name}"


POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"


@dataclass
class TopicPlan:
    """What a replay publishes: bag topic -> topic to publish on, and whether those are the two
    inputs of a pairs-mode node (``pairs``, answered per pair) or one cloud stream."""

    routes: dict[str, str]
    pairs: bool


def parse_remap(text: str) -> tuple[str, str]:
    """``FROM:=TO`` (as ``ros2 bag play --remap`` takes it) -> (FROM, TO); ValueError else."""
    src, sep, dst = text.partition(":=")
    if not sep or not src.strip() or not dst.strip():
        raise ValueError(f"--remap {text!r}: expected FROM:=TO, e.g. /os_cloud_node/points:=cloud")
    return src.strip(), dst.strip()


def plan_topics(connections: dict[str, str], remaps: list[tuple[str, str]], namespace: str,
                source_topic: str, target_topic: str) -> TopicPlan:
    """Choose what to publish from a bag's ``connections`` (topic -> message type).

    With ``remaps`` (FROM, TO): exactly those topics, each a PointCloud2, published on TO (a
    relative TO is resolved in the node's namespace, as a node's inputs are). Without: a pair
    bag's /cegc/source and /cegc/target onto the node's two inputs; a sequence bag's
    /cegc/cloud, or a bag's one PointCloud2 topic, onto ``<namespace>/cloud`` (sequential
    mode). Every other topic is skipped unread (custom message types need no definitions).
    """
    def resolve(name: str) -> str:
        return name if name.startswith("/") else _topic(namespace, name)
    clouds = sorted(t for t, kind in connections.items() if kind == POINTCLOUD2)
    if remaps:
        routes = {}
        for src, dst in remaps:
            if src not in connections:
                raise ReplayError(f"--remap {src}:={dst}: the bag has no topic {src} "
                                  f"(PointCloud2 topics: {', '.join(clouds) or 'none'})")
            if connections[src] != POINTCLOUD2:
                raise ReplayError(f"--remap {src}:={dst}: {src} is {connections[src]}, only "
                                  f"PointCloud2 topics are replayed")
            routes[src] = resolve(dst)
        return TopicPlan(routes, set(routes.values()) == {source_topic, target_topic})
    if {TOPIC_SOURCE, TOPIC_TARGET} <= set(connections):
        return TopicPlan({TOPIC_SOURCE: source_topic, TOPIC_TARGET: target_topic}, True)
    if TOPIC_CLOUD in connections:
        return TopicPlan({TOPIC_CLOUD: resolve("cloud")}, False)
    if len(clouds) == 1:
        return TopicPlan({clouds[0]: resolve("cloud")}, False)
    raise ReplayError(f"the bag has {len(clouds)} PointCloud2 topics"
                      + (f" ({', '.join(clouds)}): choose with --remap FROM:=TO" if clouds
                         else f" (its topics: {', '.join(sorted(connections)) or 'none'})"))


def _scan_bag(bag_path: Path, remaps: list[tuple[str, str]], namespace: str, source_topic: str,
              target_topic: str, start_offset: float = 0.0
              ) -> tuple[TopicPlan, list[tuple[int, str, bytes]], dict[int, np.ndarray]]:
    """The plan, the chosen cloud messages (log time ns, bag topic, raw CDR) in log order from
    ``start_offset`` s after the bag's first message on, and the ground truth by stamp (a pair
    bag's T_target_source; a sequence bag's T_world_cloud made relative to the first cloud)."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import Reader

    from cegc_ros.data.bag import BagError
    from msg_adapters.nav import time_to_ns
    from msg_adapters.pose import pose_to_matrix

    if not bag_path.exists():
        raise BagError(f"bag {bag_path} does not exist")
    clouds: list[tuple[int, str, bytes]] = []
    gt: dict[int, np.ndarray] = {}
    try:
        with Reader(bag_path) as reader:
            plan = plan_topics({c.topic: c.msgtype for c in reader.connections}, remaps,
                               namespace, source_topic, target_topic)
            gt_topic = TOPIC_GT if plan.pairs else TOPIC_CLOUD_GT
            wanted = set(plan.routes) | {gt_topic}
            conns = [c for c in reader.connections if c.topic in wanted]
            first = reader.start_time
            for conn, log_ns, raw in reader.messages(connections=conns):
                if log_ns - first < start_offset * 1e9:
                    continue
                raw = bytes(raw)
                if conn.topic == gt_topic:
                    msg = deserialize_message(raw, PoseStamped)
                    gt[time_to_ns(msg.header.stamp)] = pose_to_matrix(msg.pose)
                else:
                    clouds.append((int(log_ns), conn.topic, raw))
    except (BagError, ReplayError):
        raise
    except Exception as err:
        raise BagError(f"cannot read bag {bag_path}: {type(err).__name__}: {err}") from err
    if not plan.pairs and gt and clouds:
        # A stream's answers are odometry poses in the first played cloud's frame.
        from msg_adapters.point_cloud2_cdr import header_stamp_ns
        first_gt = gt.get(header_stamp_ns(clouds[0][2]))
        gt = {} if first_gt is None else {k: np.linalg.inv(first_gt) @ T for k, T in gt.items()}
    return plan, clouds, gt


def replay_bag(bag_path: str | Path, rate: float = 1.0, *, lockstep: bool = False,
               timeout: float = 10.0, connect_timeout: float = 30.0,
               node_name: str = "register_node", node_namespace: str = "/",
               source_topic: str | None = None, target_topic: str | None = None,
               pose_topic: str | None = None, pair_timeout: float = 30.0,
               progress: bool = False, fastdds_profile: str = "default",
               remaps: list[tuple[str, str]] | None = None,
               start_offset: float = 0.0, loops: int = 1) -> ReplayResult:
    """Publish a bag's clouds into a running register_node and collect its answers.

    Args:
        bag_path: a rosbag2 directory (sqlite3 or mcap): a pair bag of ``cegc-make-bag``, a
            sequence bag, or any recording (:func:`plan_topics` says what is published).
        remaps: (FROM, TO) topic remaps, as ``ros2 bag play --remap``; they choose the topics.
        start_offset: skip the bag's first ``start_offset`` seconds (log time).
        rate: playback speed factor on the bag's log times (ignored with ``lockstep``).
        lockstep: wait for the node's answer to each item (a pair; or a cloud of a stream)
            before publishing the next.
        loops: plays of the bag (as ``ros2 bag play --loop``; 0: until interrupted, and then
            the completed plays are returned). Before
            each play after the first the node's ``~/reset`` is called (when it offers one), so
            a sequential-mode node takes the repeated stamps as a new odometry.
        timeout: after the last item of a play, wait at most this long (s) for outstanding
            answers.
        connect_timeout: wait at most this long (s) for the node's topics to match.
        node_name, node_namespace: where the node runs (its topics are derived from them).
        source_topic, target_topic, pose_topic: explicit topic names (override the above).
            A stream is answered on ``<node>/odometry`` (nav_msgs/Odometry, sequential mode).
        pair_timeout: with ``lockstep``, the longest wait (s) for the node's answer to one
            item (its pose or odometry, or a counted rejection): past it, or as soon as the
            node's subscription to the inputs is gone (the node died), ReplayError.
        fastdds_profile: Fast DDS profiles file of the publishing node, as
            :func:`cegc_ros.paths.fastdds_profile` takes it: ``"default"`` (the user's
            FASTRTPS_DEFAULT_PROFILES_FILE if set, else the shipped profile for huge clouds),
            ``"none"`` or a path. Takes effect only if no ROS node was created in this process
            before (Fast DDS reads its profiles once per process).

    Returns:
        A :class:`ReplayResult`, one record per item (by stamp) in bag order, per play.

    Raises:
        cegc_ros.data.bag.BagError: unreadable bag or missing topics.
        ReplayError: the node's topics never matched within ``connect_timeout``; with
            ``lockstep``, the node went away or did not answer an item within ``pair_timeout``.
        FileNotFoundError: ``fastdds_profile`` names no file.
    """
    if not rate > 0:
        raise ValueError(f"rate must be > 0, got {rate}")
    if loops < 0:
        raise ValueError(f"loops must be >= 0 (0: until interrupted), got {loops}")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    from cegc_ros.paths import fastdds_profile as profile_env
    from cegc_ros.spinning import Spinner
    from msg_adapters.nav import time_to_ns
    from msg_adapters.point_cloud2_cdr import header_stamp_ns
    from msg_adapters.pose import pose_to_matrix

    if start_offset < 0:
        raise ValueError(f"start offset must be >= 0, got {start_offset}")
    src_topic = source_topic or _topic(node_namespace, "source_cloud")
    tgt_topic = target_topic or _topic(node_namespace, "target_cloud")
    plan, clouds, gt = _scan_bag(Path(bag_path), list(remaps or []), node_namespace, src_topic,
                                 tgt_topic, start_offset)
    node_path = _topic(node_namespace, node_name)
    out_topic = pose_topic or (f"{node_path}/pose" if plan.pairs else f"{node_path}/odometry")
    per_item = 2 if plan.pairs else 1        # messages that make one answerable item
    item = "pair" if plan.pairs else "cloud"
    n_items = len(clouds) // per_item

    context = rclpy.Context()                   # own context: callers may run rclpy too
    rclpy.init(context=context)
    lock = threading.Lock()
    answers: dict[int, tuple[np.ndarray, float]] = {}   # stamp -> (T_est, receive time)
    quality: dict[int, dict[str, str]] = {}             # stamp -> ~/quality key-values
    diag: dict[str, str] = {}
    answered = threading.Condition(lock)
    status_name = f"{node_path}: registration"      # the node's full name
    node = executor = spinner = None
    try:
        with profile_env(fastdds_profile) as profile:   # read when the participant is made
            node = rclpy.create_node("cegc_replay", context=context)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        pubs = {bag_topic: node.create_publisher(PointCloud2, out, qos)
                for bag_topic, out in plan.routes.items()}

        def on_answer(msg: Any) -> None:
            now = time.monotonic()
            stamp = time_to_ns(msg.header.stamp)
            T = pose_to_matrix(msg.pose if plan.pairs else msg.pose.pose)
            with answered:
                answers[stamp] = (T, now)
                answered.notify_all()

        def on_quality(msg: Any) -> None:
            for st in msg.status[:1]:
                with answered:
                    quality[time_to_ns(msg.header.stamp)] = {kv.key: kv.value for kv in st.values}
                    answered.notify_all()

        def done(stamp: int) -> bool:
            """The node answered the item: a pose, or a quality message saying it has none."""
            return stamp in answers or quality.get(stamp, {}).get("published") == "false"

        def settled(stamp: int) -> bool:
            """Answered, and its quality message in too when the node publishes them (it comes
            on a topic of its own, so it may arrive after the pose)."""
            return done(stamp) and (stamp in quality or not quality)

        def on_diag(msg: Any) -> None:
            for st in msg.status:
                if st.name == status_name:
                    with answered:
                        diag.clear()
                        diag.update({kv.key: kv.value for kv in st.values})
                        answered.notify_all()

        node.create_subscription(PoseStamped if plan.pairs else Odometry, out_topic, on_answer,
                                 100)
        node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
        # Both modes publish one per finished item (pairs mode: per pair; sequential: per
        # cloud); an older node or a stand-in may publish none, then `settled` waits for none.
        node.create_subscription(DiagnosticArray, f"{node_path}/quality", on_quality, 100)
        reset = node.create_client(Trigger, f"{node_path}/reset")
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        spinner = Spinner(executor, name="cegc_replay_spin")

        end = time.monotonic() + connect_timeout
        while not (all(p.get_subscription_count() for p in pubs.values())
                   and node.count_publishers(out_topic)):
            if time.monotonic() > end:
                raise ReplayError(f"no register_node answered within {connect_timeout} s "
                                  f"(publishing {', '.join(plan.routes.values())}; listening "
                                  f"{out_topic})")
            time.sleep(0.05)
        base: int | None = None    # the node's pairs_done before this replay (lockstep)
        if lockstep:
            with answered:
                if answered.wait_for(lambda: "pairs_done" in diag, min(connect_timeout, 5.0)):
                    base = int(diag["pairs_done"])

        records: list[ReplayRecord] = []
        sent = 0                            # items sent over all plays (for pairs_done)
        log0 = clouds[0][0] if clouds else 0

        def play_once(play: int) -> None:
            """Publish the bag once; append its records (one per item, in bag order)."""
            nonlocal sent
            with answered:
                answers.clear()
                quality.clear()
            published: dict[int, float] = {}    # stamp -> publish time of the item's last cloud
            order: list[int] = []
            pending: dict[int, set[str]] = {}   # stamp -> topics published so far
            bar = _progress(n_items, progress, item)
            t_play = time.monotonic()
            try:
                for log_ns, topic, raw in clouds:
                    stamp = header_stamp_ns(raw)
                    if not lockstep:
                        delay = t_play + (log_ns - log0) / 1e9 / rate - time.monotonic()
                        if delay > 0:
                            time.sleep(delay)
                    if lockstep and pending.get(stamp) is None and order:
                        _wait_answer(answered, answers, diag, order[-1],
                                     None if base is None else base + sent, pair_timeout,
                                     pubs, len(order), n_items, item, quality)
                    pubs[topic].publish(raw)
                    seen = pending.setdefault(stamp, set())
                    seen.add(topic)
                    if len(seen) == per_item:
                        published[stamp] = time.monotonic()
                        order.append(stamp)
                        sent += 1
                        bar.update(1)
                if lockstep and order:
                    _wait_answer(answered, answers, diag, order[-1],
                                 None if base is None else base + sent, pair_timeout,
                                 pubs, len(order), n_items, item, quality)
                    if base is not None:    # diagnostics that count every item of this play
                        with answered:
                            answered.wait_for(lambda: int(diag.get("pairs_done", "-1"))
                                              >= base + sent, timeout)
                    with answered:
                        answered.wait_for(lambda: all(settled(s) for s in order if done(s)), timeout)
                if not lockstep:
                    with answered:
                        answered.wait_for(lambda: all(settled(s) for s in order), timeout)
            finally:
                bar.close()
            with lock:
                for stamp in order:
                    got = answers.get(stamp)
                    T_gt = gt.get(stamp)
                    q = quality.get(stamp, {})
                    records.append(ReplayRecord(
                        index=len(records), stamp_ns=stamp,
                        T_est=None if got is None else got[0].tolist(),
                        T_gt=None if T_gt is None else T_gt.tolist(),
                        latency_s=None if got is None else got[1] - published[stamp],
                        loop=play, fitness=_number(q.get("fitness")),
                        ambiguity=_number(q.get("ambiguity")),
                        rejected=q.get("reason") if q.get("published") == "false" else None,
                        method=q.get("method") or None,
                        keyframe=_BOOLS.get(q.get("keyframe", ""))))

        t_start = time.monotonic()
        play = 0
        try:
            while loops == 0 or play < loops:
                if play > 0:
                    _call_reset(reset, node_path)
                play_once(play)
                play += 1
        except KeyboardInterrupt:
            # --loop ends with Ctrl-C: the plays completed so far are the result (the one cut
            # short is left out); a bounded replay, or one before its first play, re-raises.
            if loops != 0 or play == 0:
                raise
        wall = time.monotonic() - t_start
        with lock:
            last_diag = dict(diag)
        return ReplayResult(records, last_diag, wall, profile, loops=play, stream=not plan.pairs)
    finally:
        # Always, also after an error: a spin thread still inside rcl when the interpreter
        # exits aborts the process ("terminate called without an active exception").
        stuck: RuntimeError | None = None
        if spinner is not None:
            try:
                spinner.stop()
            except RuntimeError as err:
                stuck = err
        elif executor is not None:
            executor.shutdown(timeout_sec=2.0)
        # A callback still running after the stop keeps the node alive (destroying it would race
        # that callback: Spinner.stop); the context still shuts down. The stop's error raises
        # after a replay that succeeded; after one that failed, the replay's own error goes on,
        # the stop's added to it as a note.
        if node is not None and stuck is None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
        if stuck is not None:
            failed = sys.exc_info()[1]
            if failed is None:
                raise stuck
            failed.add_note(f"then stopping the spin thread failed: {stuck}")


#: How long a replay waits for the node's ``~/reset`` service between plays (s).
RESET_TIMEOUT_S = 5.0


def _call_reset(client: Any, node_path: str) -> None:
    """Call the node's ``~/reset`` before a repeated play; ReplayError when it has none or
    refuses (the repeated stamps would be refused as going back in time)."""
    from std_srvs.srv import Trigger

    if not client.wait_for_service(timeout_sec=RESET_TIMEOUT_S):
        raise ReplayError(f"a repeated play needs {node_path}/reset (std_srvs/Trigger) to "
                          f"start over; no such service answered within {RESET_TIMEOUT_S:g} s")
    done = threading.Event()
    future = client.call_async(Trigger.Request())
    future.add_done_callback(lambda _f: done.set())
    if not done.wait(RESET_TIMEOUT_S) or future.result() is None or not future.result().success:
        raise ReplayError(f"{node_path}/reset did not succeed before the repeated play")


#: How often a lockstep wait checks that the node is still there (s).
ALIVE_CHECK_S = 0.25


def _wait_answer(cond: threading.Condition, poses: dict[int, Any], diag: dict[str, str],
                 stamp: int, done_target: int | None, limit: float, pubs: dict[str, Any],
                 n_sent: int, n_total: int, item: str = "pair",
                 quality: dict[int, dict[str, str]] | None = None) -> None:
    """Wait until the node answered item ``stamp``: its pose (odometry), a ``~/quality``
    message saying it published none (``quality``: stamp -> key-values), or pairs_done >=
    done_target on /diagnostics (a node without ~/quality). ReplayError when no node
    subscribes to the inputs any more, or after ``limit`` s."""
    def answered() -> bool:
        return (stamp in poses
                or (quality is not None and quality.get(stamp, {}).get("published") == "false")
                or (done_target is not None
                    and int(diag.get("pairs_done", "-1")) >= done_target))
    end = time.monotonic() + limit
    with cond:
        while not answered():
            if not all(p.get_subscription_count() for p in pubs.values()):
                raise ReplayError(f"register_node went away (nothing subscribes to "
                                  f"{', '.join(p.topic_name for p in pubs.values())} any more) "
                                  f"after {n_sent} of {n_total} {item}s were sent, "
                                  f"{len(poses)} answered with a pose")
            left = end - time.monotonic()
            if left <= 0:
                raise ReplayError(f"register_node did not answer {item} {n_sent} of {n_total} "
                                  f"within --wait {limit:g} s ({len(poses)} poses so far)")
            cond.wait(min(ALIVE_CHECK_S, left))


class _NoBar:
    def update(self, _n: int) -> None: ...
    def close(self) -> None: ...


def _progress(total: int, enabled: bool, unit: str = "pair") -> Any:
    if not enabled:
        return _NoBar()
    from tqdm import tqdm
    return tqdm(total=total, unit=unit, desc="replay")


#: ~/quality's ``keyframe`` values.
_BOOLS = {"true": True, "false": False}


def _number(text: str | None) -> float | None:
    """A ~/quality value as a float; None when absent or not a number ("nan", "")."""
    try:
        value = float(text) if text else None
    except ValueError:
        return None
    return value if value is not None and np.isfinite(value) else None


def write_records(result: ReplayResult, path: str | Path, meta: dict[str, Any]) -> None:
    """Write records as JSON (with ``meta`` and the node's diagnostics) or CSV (one row/pair)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".csv":
        with path.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["index", "loop", "stamp_ns", "latency_s"] + [f"est_{i}{j}" for i in range(4)
                                                              for j in range(4)]
                       + [f"gt_{i}{j}" for i in range(4) for j in range(4)]
                       + ["fitness", "ambiguity", "rejected", "method", "keyframe"])
            for r in result.records:
                est = np.asarray(r.T_est).ravel().tolist() if r.T_est else [""] * 16
                gt = np.asarray(r.T_gt).ravel().tolist() if r.T_gt else [""] * 16
                keyframe = None if r.keyframe is None else str(r.keyframe).lower()
                w.writerow([r.index, r.loop, r.stamp_ns, "" if r.latency_s is None else r.latency_s]
                           + est + gt + ["" if v is None else v
                                         for v in (r.fitness, r.ambiguity, r.rejected, r.method,
                                                   keyframe)])
    else:
        path.write_text(json.dumps({"meta": meta, **result.to_json()}, indent=1))


def summary(result: ReplayResult) -> dict[str, Any]:
    """Counts (rejections by reason; a stream's clouds by registration method and its new
    keyframes, from ~/quality), latency percentiles and median errors (with ground truth)."""
    recs = result.records
    with_pose = [r for r in recs if r.T_est is not None]
    out: dict[str, Any] = {"clouds" if result.stream else "pairs": len(recs),
                           "poses": len(with_pose), "wall_s": round(result.wall_s, 3)}
    if result.loops != 1:
        out["loops"] = result.loops
    rejected = Counter(r.rejected for r in recs if r.rejected)
    if rejected:                          # by the node's reason (~/quality)
        out["rejected"] = dict(sorted(rejected.items()))
    methods = Counter(r.method for r in recs if r.method)
    if methods:                           # a stream's: first / icp / global / none
        out["methods"] = dict(sorted(methods.items()))
        out["keyframes"] = sum(bool(r.keyframe) for r in recs)
    lat = [r.latency_s for r in with_pose if r.latency_s is not None]
    if lat:
        p50, p90 = np.percentile(lat, [50, 90])
        out.update(latency_p50_ms=round(p50 * 1e3, 1), latency_p90_ms=round(p90 * 1e3, 1))
    both = [r for r in with_pose if r.T_gt is not None]
    if both:
        from cegc_ros.metrics import pair_errors
        err = pair_errors(np.array([r.T_gt for r in both]), np.array([r.T_est for r in both]))
        out.update(median_rot_error_deg=round(float(np.median(err.rot_error_deg)), 3),
                   median_trans_error=round(float(np.median(err.trans_error)), 4))
    return out
