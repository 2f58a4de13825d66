"""Registration pairs stored as rosbag2 files (sqlite3 or mcap), via the ``rosbags`` library.

Sequence bags (one cloud topic with ground-truth poses, for sequential mode): the section
"Sequence bags" below (:func:`write_sequence`, :func:`read_sequence`).

Layout of a pair bag (one pair = messages sharing one header stamp; pairs 0.5 s apart):

=====================  ==============================  ==============================
topic                  type                            content
=====================  ==============================  ==============================
/cegc/source           sensor_msgs/msg/PointCloud2     float32 x y z, frame cegc_source
/cegc/target           sensor_msgs/msg/PointCloud2     float32 x y z, frame cegc_target
/cegc/ground_truth     geometry_msgs/msg/PoseStamped   T_target_source, frame cegc_target
/cegc/pair_info        std_msgs/msg/String             JSON: protocol, seed, index, overlap, ...
=====================  ==============================  ==============================

Ground truth and info are optional when reading. PointCloud2 bytes are decoded with numpy, so
this module needs neither rclpy nor a ROS installation.
"""

from __future__ import annotations

import itertools
import json
import sqlite3
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

TOPIC_SOURCE = "/cegc/source"
TOPIC_TARGET = "/cegc/target"
TOPIC_GT = "/cegc/ground_truth"
TOPIC_INFO = "/cegc/pair_info"
FRAME_SOURCE = "cegc_source"
FRAME_TARGET = "cegc_target"
PAIR_SPACING_NS = 500_000_000
START_NS = 1_700_000_000 * 10**9           # first pair's stamp (fixed: bags are reproducible)

_TYPES = {TOPIC_SOURCE: "sensor_msgs/msg/PointCloud2",
          TOPIC_TARGET: "sensor_msgs/msg/PointCloud2",
          TOPIC_GT: "geometry_msgs/msg/PoseStamped",
          TOPIC_INFO: "std_msgs/msg/String"}
STORAGES = ("sqlite3", "mcap")

# PointField datatypes -> numpy (sensor_msgs/PointField constants).
_FIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


class BagError(Exception):
    """A bag that cannot be written or read as a pair bag; the message names the problem."""


@dataclass
class BagPair:
    """One pair read back from a bag.

    source: (N, 3) float32 ; target: (M, 3) float32 (finite points only, own frames).
    T_target_source: (4, 4) float64 mapping source into target, or None without ground truth.
    stamp_ns: the pair's header stamp in nanoseconds ; info: the pair_info JSON ({} if absent).
    """

    source: np.ndarray
    target: np.ndarray
    T_target_source: np.ndarray | None
    stamp_ns: int
    info: dict[str, Any] = field(default_factory=dict)


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


# --------------------------------------------------------------------------------------------
# Message conversion (rosbags message classes; numpy only)
# --------------------------------------------------------------------------------------------

def _header(ts: Any, stamp_ns: int, frame_id: str) -> Any:
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = ts.types["std_msgs/msg/Header"]
    return Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame_id)


def xyz_to_pointcloud2(ts: Any, xyz: np.ndarray, header: Any) -> Any:
    """(N, 3) points -> unorganised little-endian float32 x y z PointCloud2 (rosbags class)."""
    xyz = np.ascontiguousarray(np.asarray(xyz, dtype="<f4").reshape(-1, 3))
    PointField = ts.types["sensor_msgs/msg/PointField"]
    fields = [PointField(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate("xyz")]
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=len(xyz), fields=fields, is_bigendian=False,
        point_step=12, row_step=12 * len(xyz), data=xyz.view(np.uint8).reshape(-1),
        is_dense=bool(np.isfinite(xyz).all()))


def pointcloud2_to_xyz(msg: Any) -> np.ndarray:
    """PointCloud2 (any point layout with x, y, z fields) -> (N, 3) float32, finite points only.

    Organised clouds come out in row-major order (row 0 first). Raises BagError on a layout that
    does not fit its data.
    """
    names = {f.name: f for f in msg.fields}
    missing = [n for n in "xyz" if n not in names]
    if missing:
        raise BagError(f"PointCloud2 has no field(s) {missing}; fields are {sorted(names)}")
    order = ">" if msg.is_bigendian else "<"
    formats = []
    for n in "xyz":
        f = names[n]
        if f.datatype not in _FIELD_DTYPES:
            raise BagError(f"PointCloud2 field {n!r} has unknown datatype {f.datatype}")
        formats.append(order + _FIELD_DTYPES[f.datatype])
        if f.offset + np.dtype(formats[-1]).itemsize > msg.point_step:
            raise BagError(f"PointCloud2 field {n!r} at offset {f.offset} exceeds point_step "
                           f"{msg.point_step}")
    n_points = int(msg.height) * int(msg.width)
    data = np.asarray(msg.data, dtype=np.uint8)
    if n_points == 0:
        return np.zeros((0, 3), np.float32)
    if msg.row_step < msg.point_step * msg.width or len(data) < msg.row_step * msg.height:
        raise BagError(f"PointCloud2 data has {len(data)} bytes, expected {msg.row_step} x "
                       f"{msg.height} rows of {msg.width} points x {msg.point_step} bytes")
    dtype = np.dtype({"names": list("xyz"), "formats": formats,
                      "offsets": [names[n].offset for n in "xyz"], "itemsize": msg.point_step})
    rows = data[:msg.row_step * msg.height].reshape(msg.height, msg.row_step)
    rows = rows[:, :msg.point_step * msg.width]
    pts = np.ascontiguousarray(rows).view(dtype).reshape(-1)            # (H * W,) structured
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float32)
    return xyz[np.isfinite(xyz).all(axis=1)]


def matrix_to_pose_stamped(ts: Any, T: np.ndarray, header: Any) -> Any:
    """(4, 4) rigid transform -> geometry_msgs/PoseStamped (rosbags class)."""
    from scipy.spatial.transform import Rotation

    T = np.asarray(T, dtype=np.float64)
    q = Rotation.from_matrix(T[:3, :3]).as_quat()                      # x y z w
    Point = ts.types["geometry_msgs/msg/Point"]
    Quaternion = ts.types["geometry_msgs/msg/Quaternion"]
    pose = ts.types["geometry_msgs/msg/Pose"](
        position=Point(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
    return ts.types["geometry_msgs/msg/PoseStamped"](header=header, pose=pose)


def pose_to_matrix(pose: Any) -> np.ndarray:
    """geometry_msgs/Pose -> (4, 4) float64; raises BagError on a non-unit quaternion."""
    from scipy.spatial.transform import Rotation

    o, p = pose.orientation, pose.position
    q = np.array([o.x, o.y, o.z, o.w], dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or abs(norm - 1.0) > 1e-3:
        raise BagError(f"ground-truth quaternion has norm {norm:.6g}, expected 1")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
    T[:3, 3] = [p.x, p.y, p.z]
    return T


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"{type(x).__name__} is not JSON serialisable")


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------

def write_pairs(path: str | Path, pairs: Iterable[Any], storage: str = "sqlite3",
                protocol: str | None = None, seed: int | None = None,
                start_ns: int = START_NS, spacing_ns: int = PAIR_SPACING_NS) -> int:
    """Write pairs into a new rosbag2 directory ``path``; returns the number of pairs written.

    ``pairs``: iterable of objects with ``source`` (N, 3), ``target`` (M, 3),
    ``T_target_source`` ((4, 4) or None: no ground-truth message) and ``info`` (dict), e.g.
    :class:`cegc_ros.data.protocols.Pair` or :class:`BagPair`. Pair k gets header stamp
    ``start_ns + k * spacing_ns`` on all its messages (and as bag log time). ``protocol`` and
    ``seed``, when given, are written into every pair_info JSON. Raises BagError if ``path``
    exists, the storage is unknown, or rosbags refuses to write.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer, WriterError

    if storage not in STORAGES:
        raise BagError(f"unknown storage {storage!r}; expected one of {STORAGES}")
    path = Path(path)
    if path.exists():
        raise BagError(f"{path} exists already; rosbag2 writes new bags only")
    ts = _typestore()
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    count = 0
    try:
        with Writer(path, version=9, storage_plugin=plugin) as writer:
            conns = {t: writer.add_connection(t, _TYPES[t], typestore=ts)
                     for t in (TOPIC_SOURCE, TOPIC_TARGET, TOPIC_INFO)}
            for k, pair in enumerate(pairs):
                stamp = int(start_ns + k * spacing_ns)
                h_src, h_tgt = _header(ts, stamp, FRAME_SOURCE), _header(ts, stamp, FRAME_TARGET)
                msgs = [(TOPIC_SOURCE, xyz_to_pointcloud2(ts, pair.source, h_src)),
                        (TOPIC_TARGET, xyz_to_pointcloud2(ts, pair.target, h_tgt))]
                if pair.T_target_source is not None:
                    if TOPIC_GT not in conns:
                        conns[TOPIC_GT] = writer.add_connection(TOPIC_GT, _TYPES[TOPIC_GT],
                                                                typestore=ts)
                    msgs.append((TOPIC_GT, matrix_to_pose_stamped(ts, pair.T_target_source, h_tgt)))
                info = dict(pair.info)
                if protocol is not None:
                    info["protocol"] = protocol
                if seed is not None:
                    info["seed"] = int(seed)
                info.setdefault("index", k)
                String = ts.types["std_msgs/msg/String"]
                msgs.append((TOPIC_INFO, String(data=json.dumps(info, default=_jsonable))))
                for topic, msg in msgs:
                    writer.write(conns[topic], stamp, ts.serialize_cdr(msg, _TYPES[topic]))
                count += 1
    except WriterError as err:
        raise BagError(f"cannot write bag {path}: {err}") from err
    return count


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

def _read_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that mean 'this storage is broken', as raised by rosbags and its backends."""
    import apsw                     # rosbags' sqlite3 backend (a rosbags dependency)
    from rosbags.rosbag2 import ReaderError
    from rosbags.serde import SerdeError
    return (ReaderError, SerdeError, apsw.Error, sqlite3.Error, struct.error, EOFError, OSError,
            ValueError, KeyError, IndexError)


_Item = TypeVar("_Item")


def _grouped_by_stamp(reader: Any, ts: Any, path: Path, connections: list[Any],
                      convert: Callable[[dict[str, Any], int, Path], _Item],
                      logtime_topics: frozenset[str] = frozenset()) -> Iterator[_Item]:
    """Read ``connections`` of an open rosbags ``reader`` and yield one item per header stamp.

    Messages sharing a stamp (int nanoseconds from ``header.stamp``; for a topic in
    ``logtime_topics``, which has no header, its bag log time) form a group ``slot``: a dict
    topic -> deserialised message, at most one per topic. Each group is yielded as
    ``convert(slot, stamp, path)``. A group is complete once it holds every topic of
    ``connections`` that the metadata lists messages for; then the still-pending groups with
    an earlier stamp (those lacking an optional message) are yielded first, in stamp order,
    then the complete one. Groups still pending at the end follow in stamp order. A bag logged in
    stamp order thus comes out in stamp order; a stamp that goes back comes out when complete.

    Raises BagError for a second message of one topic in a pending group (a stamp repeated
    after its group was yielded starts a new group), for storage that fails after ``seen`` of
    the ``listed`` messages (``convert`` runs inside that guard too, except for the groups
    yielded at the end), and for fewer messages than the metadata lists.
    """
    errors = _read_errors()
    expected = {c.topic for c in connections if c.msgcount > 0}
    listed = sum(c.msgcount for c in connections)
    pending: dict[int, dict[str, Any]] = {}
    seen = 0
    try:
        for conn, logtime, raw in reader.messages(connections=connections):
            seen += 1
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            if conn.topic in logtime_topics:
                stamp = int(logtime)
            else:
                stamp = int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)
            slot = pending.setdefault(stamp, {})
            if conn.topic in slot:
                raise BagError(f"{path}: two {conn.topic} messages with stamp {stamp}")
            slot[conn.topic] = msg
            if expected <= slot.keys():
                for old in sorted(k for k in pending if k <= stamp):
                    yield convert(pending.pop(old), old, path)
    except errors as err:
        raise BagError(f"{path}: storage unreadable after {seen} of {listed} messages "
                       f"(truncated or corrupted?): {err}") from err
    if seen < listed:
        raise BagError(f"{path} is truncated: metadata lists {listed} messages, storage has {seen}")
    for stamp in sorted(pending):
        yield convert(pending[stamp], stamp, path)


def read_pairs(path: str | Path) -> Iterator[BagPair]:
    """Yield the pairs of a pair bag (sqlite3 or mcap storage), in stamp order.

    Messages are grouped by header stamp. Requires /cegc/source and /cegc/target of type
    PointCloud2; /cegc/ground_truth and /cegc/pair_info are optional (T_target_source None,
    info {} when a pair has none). Raises BagError naming the problem for a missing or
    unreadable bag, a foreign bag (no pair topics, wrong types), a truncated bag (fewer messages
    than its metadata lists, a pair missing a cloud) or a malformed message.
    """
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    errors = _read_errors()
    ts = _typestore()
    try:
        reader = Reader(path)
        reader.open()
    except errors as err:
        raise BagError(f"cannot open bag {path}: {err}") from err
    try:
        yield from _read_open(reader, ts, path)
    finally:
        reader.close()


def _read_open(reader: Any, ts: Any, path: Path) -> Iterator[BagPair]:
    topics = {c.topic: c for c in reader.connections}
    missing = [t for t in (TOPIC_SOURCE, TOPIC_TARGET) if t not in topics]
    if missing:
        raise BagError(f"{path} is not a pair bag: topic(s) {missing} missing; it has "
                       f"{sorted(topics)}")
    for t, c in topics.items():
        if t in _TYPES and c.msgtype != _TYPES[t]:
            raise BagError(f"{path}: topic {t} has type {c.msgtype}, expected {_TYPES[t]}")
    wanted = [c for c in reader.connections if c.topic in _TYPES]
    # pair_info (a String) has no header: its log time is the pair's stamp.
    yield from _grouped_by_stamp(reader, ts, path, wanted, _to_pair, frozenset({TOPIC_INFO}))


def _to_pair(slot: dict[str, Any], stamp: int, path: Path) -> BagPair:
    lacking = [t for t in (TOPIC_SOURCE, TOPIC_TARGET) if t not in slot]
    if lacking:
        raise BagError(f"{path}: pair at stamp {stamp} lacks {lacking} (truncated bag?)")
    T = pose_to_matrix(slot[TOPIC_GT].pose) if TOPIC_GT in slot else None
    info: dict[str, Any] = {}
    if TOPIC_INFO in slot:
        try:
            info = json.loads(slot[TOPIC_INFO].data)
        except json.JSONDecodeError as err:
            raise BagError(f"{path}: pair_info at stamp {stamp} is not JSON: {err}") from err
    return BagPair(pointcloud2_to_xyz(slot[TOPIC_SOURCE]), pointcloud2_to_xyz(slot[TOPIC_TARGET]),
                   T, stamp, info)


# --------------------------------------------------------------------------------------------
# Sequence bags: one cloud stream with ground-truth poses (sequential mode, cegc-eval-seq)
# --------------------------------------------------------------------------------------------
#
# =========================  ==============================  =====================================
# topic                      type                            content
# =========================  ==============================  =====================================
# /cegc/cloud                sensor_msgs/msg/PointCloud2     float32 x y z, the sensor's frame
# /cegc/cloud_ground_truth   geometry_msgs/msg/PoseStamped   T_world_cloud, frame cegc_world
# /cegc/sequence_info        std_msgs/msg/String             JSON, once, logged at the first stamp
# =========================  ==============================  =====================================
#
# A cloud and its ground truth share one header stamp. Replay /cegc/cloud onto the node's
# ``cloud`` topic; the ground truth is for evaluation.

TOPIC_CLOUD = "/cegc/cloud"
TOPIC_CLOUD_GT = "/cegc/cloud_ground_truth"
TOPIC_SEQUENCE_INFO = "/cegc/sequence_info"
FRAME_WORLD = "cegc_world"

_SEQUENCE_TYPES = {TOPIC_CLOUD: "sensor_msgs/msg/PointCloud2",
                   TOPIC_CLOUD_GT: "geometry_msgs/msg/PoseStamped",
                   TOPIC_SEQUENCE_INFO: "std_msgs/msg/String"}


@dataclass
class BagFrame:
    """One cloud of a sequence bag.

    cloud: (N, 3) float32 finite points in the sensor frame ``frame_id``.
    T_world_cloud: (4, 4) float64 ground truth, or None when the bag has none for this stamp.
    """

    cloud: np.ndarray
    T_world_cloud: np.ndarray | None
    stamp_ns: int
    frame_id: str


def write_sequence(path: str | Path, sequence: Any, storage: str = "sqlite3") -> int:
    """Write a sequence into a new rosbag2 directory ``path``; returns the clouds written.

    ``sequence``: an object with ``clouds`` (list of (N, 3)), ``poses`` ((K, 4, 4)
    T_world_cloud, or None: no ground-truth topic), ``stamps_ns`` (K increasing ints),
    ``frame_id`` and ``info`` (dict), e.g. :class:`cegc_ros.data.sequences.Sequence`. Raises
    BagError if ``path`` exists, the storage is unknown, the stamps do not increase, the lengths
    differ, or rosbags refuses to write.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer, WriterError

    if storage not in STORAGES:
        raise BagError(f"unknown storage {storage!r}; expected one of {STORAGES}")
    path = Path(path)
    if path.exists():
        raise BagError(f"{path} exists already; rosbag2 writes new bags only")
    clouds, poses = list(sequence.clouds), sequence.poses
    stamps = [int(s) for s in sequence.stamps_ns]
    if len(stamps) != len(clouds) or (poses is not None and len(poses) != len(clouds)):
        raise BagError(f"sequence has {len(clouds)} clouds, {len(stamps)} stamps and "
                       f"{'no' if poses is None else len(poses)} poses")
    if any(b <= a for a, b in itertools.pairwise(stamps)):
        raise BagError("sequence stamps must increase")
    ts = _typestore()
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    topics = [TOPIC_CLOUD, TOPIC_SEQUENCE_INFO] + ([TOPIC_CLOUD_GT] if poses is not None else [])
    try:
        with Writer(path, version=9, storage_plugin=plugin) as writer:
            conns = {t: writer.add_connection(t, _SEQUENCE_TYPES[t], typestore=ts) for t in topics}
            if clouds:
                info = ts.types["std_msgs/msg/String"](
                    data=json.dumps(dict(sequence.info), default=_jsonable))
                writer.write(conns[TOPIC_SEQUENCE_INFO], stamps[0],
                             ts.serialize_cdr(info, _SEQUENCE_TYPES[TOPIC_SEQUENCE_INFO]))
            for k, (stamp, cloud) in enumerate(zip(stamps, clouds)):
                msgs = [(TOPIC_CLOUD, xyz_to_pointcloud2(
                    ts, cloud, _header(ts, stamp, str(sequence.frame_id))))]
                if poses is not None:
                    msgs.append((TOPIC_CLOUD_GT, matrix_to_pose_stamped(
                        ts, poses[k], _header(ts, stamp, FRAME_WORLD))))
                for topic, msg in msgs:
                    writer.write(conns[topic], stamp, ts.serialize_cdr(msg, _SEQUENCE_TYPES[topic]))
    except WriterError as err:
        raise BagError(f"cannot write bag {path}: {err}") from err
    return len(clouds)


def _open_sequence(path: str | Path) -> tuple[Any, Any, Path]:
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    try:
        reader = Reader(path)
        reader.open()
    except _read_errors() as err:
        raise BagError(f"cannot open bag {path}: {err}") from err
    topics = {c.topic: c for c in reader.connections}
    if TOPIC_CLOUD not in topics:
        reader.close()
        raise BagError(f"{path} is not a sequence bag: topic {TOPIC_CLOUD} missing; it has "
                       f"{sorted(topics)}")
    for t, c in topics.items():
        if t in _SEQUENCE_TYPES and c.msgtype != _SEQUENCE_TYPES[t]:
            reader.close()
            raise BagError(f"{path}: topic {t} has type {c.msgtype}, expected "
                           f"{_SEQUENCE_TYPES[t]}")
    return reader, _typestore(), path


def read_sequence(path: str | Path) -> Iterator[BagFrame]:
    """Yield the clouds of a sequence bag (sqlite3 or mcap) in stamp order, each with its
    ground truth (None where the bag has none), streaming. Raises BagError naming the problem
    for a missing, foreign, truncated or malformed bag, or a ground truth without a cloud."""
    reader, ts, path = _open_sequence(path)
    try:
        wanted = [c for c in reader.connections if c.topic in (TOPIC_CLOUD, TOPIC_CLOUD_GT)]
        yield from _grouped_by_stamp(reader, ts, path, wanted, _to_frame)
    finally:
        reader.close()


def _to_frame(slot: dict[str, Any], stamp: int, path: Path) -> BagFrame:
    if TOPIC_CLOUD not in slot:
        raise BagError(f"{path}: ground truth at stamp {stamp} has no cloud (truncated bag?)")
    msg = slot[TOPIC_CLOUD]
    T = pose_to_matrix(slot[TOPIC_CLOUD_GT].pose) if TOPIC_CLOUD_GT in slot else None
    return BagFrame(pointcloud2_to_xyz(msg), T, stamp, str(msg.header.frame_id))


def read_sequence_info(path: str | Path) -> dict[str, Any]:
    """The /cegc/sequence_info JSON of a sequence bag ({} when it has none)."""
    reader, ts, path = _open_sequence(path)
    try:
        conns = [c for c in reader.connections if c.topic == TOPIC_SEQUENCE_INFO]
        for conn, _, raw in reader.messages(connections=conns):
            text = ts.deserialize_cdr(raw, conn.msgtype).data
            try:
                return dict(json.loads(text))
            except (json.JSONDecodeError, TypeError, ValueError) as err:
                raise BagError(f"{path}: sequence_info is not a JSON object: {err}") from err
    except _read_errors() as err:
        raise BagError(f"{path}: storage unreadable: {err}") from err
    finally:
        reader.close()
    return {}
