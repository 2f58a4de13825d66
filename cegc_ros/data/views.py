"""Different-view fragment pairs of the rich rooms: the main training diet, and the test bags.

For one room seed and one sensor, :func:`make_room_pairs` renders ``fragments`` fragments from
different viewpoints, each along its own short sensor path with its own noise (so two fragments
never share a point), measures the overlap of every ordered fragment pair against the ground
truth, and keeps up to ``pairs`` of them with overlaps spread over ``overlap_range`` (stratified),
plus ``copy_pairs`` pairs of the copy protocol (a fragment against a moved copy of itself, two
different crops) as a minority.

Viewpoints. A Kinect fragment is a handheld path of 50 frames (1.7 s at 30 fps; every 5th frame
rendered) at 0.5-1.9 m height, starting at a free floor point 0.8-3.5 m from a *focus* (a piece
of furniture or a random point of the room) and looking at it, then drifting (up to 0.3 m/s)
and turning (up to 30 deg/s). The fragments of a room share two or three focuses, so some look
at the same things from different sides (high overlap under a large rotation) and some look
elsewhere (low or no overlap). With ``wall_views`` > 0, that share of the focuses is a point on
a wall (:func:`_wall_focus`), so those fragments overlap on the room's large planes. A LiDAR
fragment is a robot (0.3-1.0 m) or backpack (1.4-2.0 m) path of ``sweeps`` sweeps at a free
floor point, moving up to 1 m/s with any heading.

Ground truth and overlap. ``T_target_source = inv(T_world_target) @ T_world_source`` maps source
points into the target frame. ``overlap`` is the fraction of source points with a target point
within ``overlap_radius`` after the ground truth (3DMatch / Predator convention: 1.5 x the
2.5 cm voxel for Kinect; LiDAR rings are sparser, so 0.1 m), measured on the clouds as stored
(after the point cap and the int16 storage round trip); ``overlap_target`` is the same from the
target side.

Clouds are shuffled, so any prefix of a cloud is a uniform random subsample, and capped at
``max_points``.

Reproducibility: everything is a pure function of (room seed, sensor, config).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from cegc_ros.data import splits
from cegc_ros.data.codec import dequantise, quantise
from cegc_ros.data.protocols import Pair, random_rotation_euler, transform_points
from cegc_ros.data.rooms import RichRoom, get_rich_room
from cegc_ros.data.scenes import camera_rotation
from cegc_ros.data.sensors import SENSORS, KinectSensor, LidarSensor, get_sensor

KINDS = ("views", "copy")
_SENSOR_SALT = {"kinect": 1, "lidar": 2}


@dataclass(frozen=True)
class ViewConfig:
    """How many fragments and pairs a room gives, and how they are kept."""

    fragments: int = 7
    pairs: int = 7
    copy_pairs: int = 1
    overlap_range: tuple[float, float] = (0.1, 0.9)
    overlap_radius: float | None = None         # None: 0.0375 (kinect) / 0.1 (lidar)
    max_points: int = 20000
    #: Share of a Kinect room's focuses put on a wall instead (see :func:`_wall_focus`); 0 keeps
    #: every draw of the generator as it was (the caches made before it stay valid).
    wall_views: float = 0.0

    def radius(self, sensor: str) -> float:
        if self.overlap_radius is not None:
            return self.overlap_radius
        return 0.0375 if sensor == "kinect" else 0.1


@dataclass
class PairRecord:
    """One pair of a room: fragment indices, ground truth, copy-protocol crops, info."""

    kind: str                                   # "views" or "copy"
    source: int                                 # fragment index (source cloud)
    target: int                                 # fragment index (target cloud)
    T_target_source: np.ndarray                 # (4, 4) float64
    crop: np.ndarray                            # (2, 4) copy crops: direction xyz, keep; else 0
    info: dict[str, Any] = field(default_factory=dict)


@dataclass
class RoomPairs:
    """The fragments of one room and the pairs made of them.

    clouds: list of (N_j, 3) float32 (metres, each in its own sensor frame), equal to
    ``dequantise(*codes[j])``: the clouds are at storage precision, so what the pair cache
    returns is bit-identical to them; poses: list of (4, 4) float64 T_world_fragment.
    """

    seed: int
    sensor: str
    room_kind: str
    clouds: list[np.ndarray]
    codes: list[tuple[np.ndarray, np.ndarray, float]]
    poses: list[np.ndarray]
    pairs: list[PairRecord]

    def pair(self, k: int) -> Pair:
        """Pair k as a :class:`cegc_ros.data.protocols.Pair` (clouds copied)."""
        return materialise(self.pairs[k], self.clouds[self.pairs[k].source],
                           self.clouds[self.pairs[k].target])


def crop_half_space(points: np.ndarray, direction: np.ndarray, keep: float) -> np.ndarray:
    """Sorted indices of the ``keep`` fraction of points furthest along ``direction``.

    (The "nearest to a far point" crop of the 7Scenes protocol, with the far point at infinity;
    deterministic: a stable sort.)
    """
    n = max(1, round(keep * len(points)))
    order = np.argsort(-(points.astype(np.float64) @ direction), kind="stable")
    return np.sort(order[:n])


def materialise(rec: PairRecord, source_cloud: np.ndarray, target_cloud: np.ndarray) -> Pair:
    """The Pair a record describes, given its fragments' clouds."""
    if rec.kind == "copy":
        s = source_cloud[crop_half_space(source_cloud, rec.crop[0, :3], rec.crop[0, 3])]
        t = source_cloud[crop_half_space(source_cloud, rec.crop[1, :3], rec.crop[1, 3])]
        return Pair(s.copy(), transform_points(rec.T_target_source, t), rec.T_target_source.copy(),
                    dict(rec.info))
    return Pair(source_cloud.copy(), target_cloud.copy(), rec.T_target_source.copy(),
                dict(rec.info))


# --------------------------------------------------------------------------------------------
# Sensor paths
# --------------------------------------------------------------------------------------------

def _focus_points(room: RichRoom, rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) points the handheld fragments look at: furniture or random points."""
    out = []
    for _ in range(n):
        if len(room.targets) and rng.random() < 0.75:
            p = room.targets[rng.integers(len(room.targets))].copy()
        else:
            p = np.r_[room.grid.sample(rng, 0.2)[0], rng.uniform(0.3, 1.5)]
        out.append(p)
    return np.array(out)


def _wall_focus(room: RichRoom, rng: np.random.Generator) -> np.ndarray:
    """(3,) a point on a wall of the room (walls by length, 20-80% along, 0.8-1.8 m high).

    Why: real handheld fragments overlap mostly on walls and large furniture faces (a third of
    the real low-overlap SUN3D pair's overlap is plane, against 9-14% of the synthetic pairs' at
    every overlap; docs/data.md); a fragment looking at a wall shares its large planes with the
    other fragments that see that wall.
    """
    lengths = np.array([w.length for w in room.walls])
    wall = room.walls[int(rng.choice(len(lengths), p=lengths / lengths.sum()))]
    s = rng.uniform(0.2, 0.8) * wall.length
    z = min(rng.uniform(0.8, 1.8), room.size[2] - 0.3)
    return np.r_[wall.at(s), z]


def kinect_path(room: RichRoom, rng: np.random.Generator, focus: np.ndarray,
                sensor: KinectSensor) -> np.ndarray:
    """(K, 4, 4) T_world_camera of the rendered frames of one handheld fragment."""
    grid = room.grid
    p0 = grid.sample(rng, 0.35)[0]
    for _ in range(40):
        cand = grid.sample(rng, 0.35)[0]
        if 0.8 <= np.hypot(*(focus[:2] - cand)) <= 3.5:
            p0 = cand
            break
    h = rng.uniform(1.0, 1.9) if rng.random() < 0.8 else rng.uniform(0.5, 1.0)
    h = min(h, room.size[2] - 0.3)
    look = focus + rng.normal(0, [0.3, 0.3, 0.2])
    delta = look - np.r_[p0, h]
    yaw0 = np.arctan2(delta[1], delta[0])
    pitch0 = np.clip(np.arctan2(delta[2], np.hypot(delta[0], delta[1])),
                     np.radians(-60), np.radians(10))
    t = (np.arange(sensor.frames) / sensor.fps)[::sensor.fusion.frame_step]
    heading = rng.uniform(0, 2 * np.pi)
    v = rng.uniform(0, 0.3) * np.array([np.cos(heading), np.sin(heading), 0.0])
    v[2] = rng.normal(0, 0.03)
    end = p0 + v[:2] * t[-1]
    if grid.clearance_at(end)[0] < 0.2:
        v[:2] = 0.0
    pos = np.r_[p0, h] + v * t[:, None]
    pos += np.cumsum(rng.normal(0, 0.002, pos.shape), 0)                 # hand shake
    yaw = yaw0 + np.radians(rng.uniform(-30, 30)) * t + rng.normal(0, np.radians(0.2), len(t))
    pitch = pitch0 + np.radians(rng.normal(0, 6)) * t + rng.normal(0, np.radians(0.2), len(t))
    roll = np.radians(rng.normal(0, 3)) + rng.normal(0, np.radians(0.2), len(t))
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, :3, :3] = camera_rotation(yaw, pitch, roll)
    poses[:, :3, 3] = pos
    return poses


def _rot_zyx(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(K, 3, 3) Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    cy, sy, cp, sp, cr, sr = (np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch),
                              np.cos(roll), np.sin(roll))
    R = np.empty((len(yaw), 3, 3))
    R[:, 0] = np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1)
    R[:, 1] = np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1)
    R[:, 2] = np.stack([-sp, cp * sr, cp * cr], -1)
    return R


def lidar_path(room: RichRoom, rng: np.random.Generator, sensor: LidarSensor) -> np.ndarray:
    """(S, 4, 4) T_world_lidar of the sweeps of one robot / backpack fragment."""
    p0 = room.grid.sample(rng, 0.35)[0]
    h = rng.uniform(0.3, 1.0) if rng.random() < 0.7 else rng.uniform(1.4, 2.0)
    h = min(h, room.size[2] - 0.3)
    t = np.arange(sensor.sweeps) / sensor.rate_hz
    yaw0 = rng.uniform(0, 2 * np.pi)
    speed = rng.uniform(0.0, 1.0)
    if room.grid.clearance_at(p0 + speed * t[-1] * np.array([np.cos(yaw0), np.sin(yaw0)]))[0] < 0.2:
        speed = 0.0
    yaw = yaw0 + np.radians(rng.normal(0, 15)) * t
    pos = np.zeros((len(t), 3))
    pos[:, :2] = p0 + speed * t[:, None] * np.stack([np.cos(yaw), np.sin(yaw)], -1)
    pos[:, 2] = h
    pitch = np.radians(rng.normal(0, 2)) + rng.normal(0, np.radians(0.1), len(t))
    roll = np.radians(rng.normal(0, 2)) + rng.normal(0, np.radians(0.1), len(t))
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, :3, :3] = _rot_zyx(yaw, pitch, roll)
    poses[:, :3, 3] = pos
    return poses


# --------------------------------------------------------------------------------------------
# One room -> fragments -> pairs
# --------------------------------------------------------------------------------------------



def overlap_fraction(source: np.ndarray, target_tree: Any, T_target_source: np.ndarray,
                     radius: float) -> float:
    """Fraction of (N, 3) source points with a target point (in a cKDTree) within radius."""
    if len(source) == 0:
        return 0.0
    d, _ = target_tree.query(transform_points(T_target_source, source),
                             distance_upper_bound=radius)
    return float(np.mean(np.isfinite(d)))


def _select(table: np.ndarray, lo: float, hi: float, count: int,
            rng: np.random.Generator) -> list[tuple[int, int]]:
    """Up to ``count`` ordered pairs (a, b), each unordered pair once, with estimated overlaps
    in [lo, hi], stratified: one per equal-width overlap bin first, then random leftovers."""
    F = len(table)
    m = 0.02                                    # the table is estimated: stay clear of bounds
    cand = {}
    for a in range(F):
        for b in range(a + 1, F):
            dirs = [(x, y) for x, y in ((a, b), (b, a)) if lo + m <= table[x, y] <= hi - m]
            if dirs:
                cand[(a, b)] = dirs[int(rng.integers(len(dirs)))]
    chosen: list[tuple[int, int]] = []
    edges = np.linspace(lo, hi, count + 1)
    for k in rng.permutation(count):
        pool = [key for key, ab in cand.items() if edges[k] <= table[ab] < edges[k + 1]]
        if pool:
            key = pool[int(rng.integers(len(pool)))]
            chosen.append(cand.pop(key))
    rest = list(cand.values())
    for i in rng.permutation(len(rest))[:count - len(chosen)]:
        chosen.append(rest[i])
    return chosen


def make_room_pairs(seed: int, sensor: str = "kinect", config: ViewConfig = ViewConfig()
                    ) -> RoomPairs:
    """Render one room's fragments and choose its pairs (see the module docstring)."""
    from scipy.spatial import cKDTree

    if sensor not in SENSORS:
        raise ValueError(f"unknown sensor {sensor!r}; expected one of {SENSORS}")
    model = get_sensor(sensor)
    room = get_rich_room(int(seed))
    salt = _SENSOR_SALT[sensor]
    rng = np.random.default_rng([int(seed), 0x71E5, salt])
    F = config.fragments
    focus = _focus_points(room, rng, int(rng.integers(2, 4)))
    if config.wall_views > 0 and sensor == "kinect" and room.walls:
        # its own stream, so that every other draw stays what it was without wall views
        wall_rng = np.random.default_rng([int(seed), 0xA11, salt])
        for i in range(len(focus)):
            if wall_rng.random() < config.wall_views:
                focus[i] = _wall_focus(room, wall_rng)
    clouds, codes, poses = [], [], []
    for j in range(F):
        if isinstance(model, KinectSensor):
            path = kinect_path(room, rng, focus[(j + int(rng.integers(2))) % len(focus)], model)
        else:
            path = lidar_path(room, rng, model)
        noise = np.random.default_rng([int(seed), 0xF2A, salt, j])
        pts = model.fragment(room, path, noise)
        pts = pts[noise.permutation(len(pts))[:config.max_points]]   # shuffled, capped
        code = quantise(pts)
        codes.append(code)
        clouds.append(dequantise(*code))
        poses.append(path[0].copy())
    radius = config.radius(sensor)
    trees = [cKDTree(c) if len(c) else None for c in clouds]
    T = [[np.linalg.inv(poses[b]) @ poses[a] for b in range(F)] for a in range(F)]
    table = np.zeros((F, F))
    for a in range(F):
        for b in range(F):
            if a != b and trees[b] is not None and len(clouds[a]) >= 100:
                table[a, b] = overlap_fraction(clouds[a][::4], trees[b], T[a][b], radius)
    lo, hi = config.overlap_range
    base = {"protocol": "views", "sensor": sensor, "room_seed": int(seed),
            "room_kind": room.kind, "split": _split_name(seed), "overlap_radius": radius,
            "voxel_size": model.voxel_size}
    pairs = []
    for a, b in _select(table, lo, hi, config.pairs, rng):
        ov = overlap_fraction(clouds[a], trees[b], T[a][b], radius)
        if not lo <= ov <= hi:
            continue
        ov_t = overlap_fraction(clouds[b], trees[a], np.linalg.inv(T[a][b]), radius)
        info = dict(base, kind="views", overlap=ov, overlap_target=ov_t, source_fragment=a,
                    target_fragment=b, **_motion(T[a][b]))
        pairs.append(PairRecord("views", a, b, T[a][b], np.zeros((2, 4)), info))
    for _ in range(config.copy_pairs):
        j = int(rng.integers(F))
        if len(clouds[j]) < 100:
            continue
        Tc = np.eye(4)
        Tc[:3, :3] = random_rotation_euler(rng, 45.0)
        Tc[:3, 3] = rng.uniform(-0.5, 0.5, 3)
        crop = np.zeros((2, 4))
        for k in range(2):
            d = rng.normal(size=3)
            crop[k] = np.r_[d / np.linalg.norm(d), rng.uniform(0.6, 0.9)]
        src = crop_half_space(clouds[j], crop[0, :3], crop[0, 3])
        tgt = crop_half_space(clouds[j], crop[1, :3], crop[1, 3])
        ov = float(np.isin(src, tgt).mean())
        ov_t = float(np.isin(tgt, src).mean())
        info = dict(base, protocol="copy", kind="copy", overlap=ov, overlap_target=ov_t,
                    source_fragment=j, target_fragment=j, overlap_radius=0.0, **_motion(Tc))
        pairs.append(PairRecord("copy", j, j, Tc, crop, info))
    return RoomPairs(int(seed), sensor, room.kind, clouds, codes, poses, pairs)


def _motion(T: np.ndarray) -> dict[str, float]:
    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1.0, 1.0)))
    return {"rotation_deg": float(angle), "translation_m": float(np.linalg.norm(T[:3, 3]))}


def _split_name(seed: int) -> str | None:
    try:
        return splits.split_of(int(seed))
    except ValueError:
        return None


def sensor_for_room(seed: int, lidar_fraction: float) -> str:
    """The sensor a room is scanned with in a mixed cache (deterministic from the seed)."""
    u = np.random.default_rng([int(seed), 0x5E5]).random()
    return "lidar" if u < lidar_fraction else "kinect"


# --------------------------------------------------------------------------------------------
# A stream of different-view pairs (for bags): room after room of a split
# --------------------------------------------------------------------------------------------

def iter_view_pairs(split: str, n: int, sensor: str = "kinect", first_room: int = 0,
                    config: ViewConfig = ViewConfig(), kinds: tuple[str, ...] = ("views",)
                    ) -> Iterator[Pair]:
    """The first ``n`` pairs of the given kinds of rooms first_room, first_room + 1, ... of a
    split, in order (a room's pairs in its record order). info gains ``index`` (0-based)."""
    splits.check_split(split)
    if sensor not in SENSORS:
        raise ValueError(f"unknown sensor {sensor!r}; expected one of {SENSORS}")
    cfg = replace(config, copy_pairs=0) if "copy" not in kinds else config
    count, k = 0, first_room
    while count < n:
        rp = make_room_pairs(splits.room_seed(split, k), sensor, cfg)
        for i, rec in enumerate(rp.pairs):
            if rec.kind not in kinds:
                continue
            pair = rp.pair(i)
            pair.info.update(index=count, room_index=k)
            yield pair
            count += 1
            if count == n:
                return
        k += 1
