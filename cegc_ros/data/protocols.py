"""Registration pairs made with the paper's protocols from synthetic scenes and objects.

Three protocols (see ``/work/notes/readme_data.md`` for the full description):

``7scenes``   RIENet / FMR protocol on one fragment: centre + scale (largest bbox side = 1),
              resample, two independent "nearest to a random far point" crops, the target moved
              by a random Euler rotation and translation. Units: normalised (``info["scale"]``
              metres per unit).
``fragments`` two different fragments of the same scene, metres, ground truth from their poses,
              overlap ratios spread over [0.1, 0.9].
``modelnet``  RPM-Net protocol on CAD-like objects built from primitives: unit sphere, crop
              keeping 70% by a random plane through the centroid, Euler +-45 deg, +-0.5 shift,
              1024 points, optional clipped Gaussian noise.

Every pair carries ``T_target_source`` (4, 4) float64 with ``p_target = R @ p_source + t``.

Reproducibility: pair ``i`` of ``make_pairs(protocol, split, n, seed)`` depends only on
``(protocol, split, seed, i)`` (see :func:`make_pair`), so one pair can be rebuilt alone. Scene
and object seeds of the train and test splits come from disjoint integer ranges.
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cegc_ros.data import scenes

PROTOCOLS = ("7scenes", "fragments", "modelnet")
SPLITS = ("train", "test")

# Disjoint seed ranges: scene / object seed = split base + seed * SEEDS_PER_SEED + k.
_SPLIT_BASE = {"train": 0, "test": 10**12}
SEEDS_PER_SEED = 10**6
MAX_SEED = 10**6 - 1

# How pairs share the expensive parts (documented in readme_data.md).
SEVENSCENES_PAIRS_PER_FRAGMENT = 5
SEVENSCENES_FRAGMENTS_PER_SCENE = 4
FRAGMENT_PAIRS_PER_SCENE = 10
FRAGMENTS_PER_SCENE = 8
OVERLAP_RANGE = (0.1, 0.9)
OVERLAP_RADIUS = 0.0375          # metres: 1.5 x the 2.5 cm voxel, as in 3DMatch / Predator


@dataclass
class Pair:
    """One registration problem with its ground truth.

    source: (N, 3) float32 ; target: (M, 3) float32, each in its own frame.
    T_target_source: (4, 4) float64, maps source points into the target frame.
    info: JSON-able dict: protocol, split, seed, index, overlap (ratio in [0, 1]) and
          protocol-specific provenance (scene seed, fragment ids, scale, ...).
    """

    source: np.ndarray
    target: np.ndarray
    T_target_source: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------------

def random_rotation_euler(rng: np.random.Generator, max_angle_deg: float) -> np.ndarray:
    """(3, 3) rotation Rz @ Ry @ Rx with each angle uniform in [-max, max] degrees."""
    ax, ay, az = np.radians(rng.uniform(-max_angle_deg, max_angle_deg, 3))
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def random_transform(rng: np.random.Generator, max_angle_deg: float,
                     max_translation: float) -> np.ndarray:
    """(4, 4) float64: Euler rotation up to max_angle_deg per axis, translation in +-max."""
    T = np.eye(4)
    T[:3, :3] = random_rotation_euler(rng, max_angle_deg)
    T[:3, 3] = rng.uniform(-max_translation, max_translation, 3)
    return T


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (N, 3) points; keeps the dtype of p."""
    return (p.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(p.dtype)


def overlap_ratio(source: np.ndarray, target: np.ndarray, T_target_source: np.ndarray,
                  radius: float) -> float:
    """Fraction of source points with a target point within radius after T_target_source."""
    from scipy.spatial import cKDTree

    if len(source) == 0 or len(target) == 0:
        return 0.0
    d, _ = cKDTree(target).query(transform_points(T_target_source, source),
                                 distance_upper_bound=radius)
    return float(np.mean(np.isfinite(d)))


def normalise_unit_box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre on the bounding-box centre and scale so the largest side is 1.

    Returns (normalised (N, 3) float32, centre (3,) metres, scale: metres per unit).
    """
    lo, hi = points.min(0).astype(np.float64), points.max(0).astype(np.float64)
    centre, scale = (lo + hi) / 2, float(np.max(hi - lo))
    return ((points - centre) / scale).astype(np.float32), centre, scale


def crop_nearest_far_point(points: np.ndarray, rng: np.random.Generator,
                           keep: int) -> np.ndarray:
    """Indices of the ``keep`` points nearest a random point 500 units away (PRNet crop)."""
    direction = rng.normal(size=3)
    far = 500.0 * direction / np.linalg.norm(direction)
    d2 = np.sum((points.astype(np.float64) - far) ** 2, axis=1)
    return np.sort(np.argpartition(d2, keep - 1)[:keep])


def crop_plane(points: np.ndarray, rng: np.random.Generator, keep_ratio: float) -> np.ndarray:
    """RPM-Net crop: indices of the points on the kept side of a random plane through the
    centroid, keeping ``keep_ratio`` of them."""
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    dist = (points - points.mean(0)) @ normal
    return np.flatnonzero(dist > np.percentile(dist, (1.0 - keep_ratio) * 100))


def _rng(*key: int | str) -> np.random.Generator:
    """Generator seeded by a tuple of ints/strings (strings hashed stably)."""
    ints = [int(k) if not isinstance(k, str) else
            int.from_bytes(hashlib.sha256(k.encode()).digest()[:4], "little") for k in key]
    return np.random.default_rng(ints)


def scene_seed(split: str, seed: int, k: int) -> int:
    """Seed of the k-th scene (or object) of a split; train and test ranges are disjoint."""
    _check_split(split)
    if not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed {seed} outside 0..{MAX_SEED}")
    if not 0 <= k < SEEDS_PER_SEED:
        raise ValueError(f"scene index {k} outside 0..{SEEDS_PER_SEED - 1}")
    return _SPLIT_BASE[split] + seed * SEEDS_PER_SEED + k


def _check_split(split: str) -> None:
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")


# --------------------------------------------------------------------------------------------
# 7scenes (RIENet / FMR)
# --------------------------------------------------------------------------------------------

def sample_7scenes_pair(points: np.ndarray, rng: np.random.Generator, num_points: int = 2048,
                        keep_ratio: float = 0.75, max_angle_deg: float = 45.0,
                        max_translation: float = 0.5, noise_sigma: float = 0.0,
                        resample_target: bool = False) -> Pair:
    """One RIENet/FMR 7Scenes pair from a fragment (N, 3) in metres.

    The fragment is centred on its bounding box and scaled so its largest side is 1, then
    ``num_points`` points are drawn without replacement (with replacement when it has fewer).
    Source and target each keep the ``keep_ratio`` of those points nearest an independent random
    far point; the target is then moved by a random rotation (each Euler angle uniform in
    +-max_angle_deg) and translation (uniform in +-max_translation per axis). With
    ``resample_target`` the target crops its own independent draw of the fragment (no exact
    point-to-point correspondences); ``noise_sigma`` (normalised units) adds Gaussian noise,
    clipped at 5 sigma, to each cloud independently. Point order is shuffled. Returns source
    (K, 3), target (K, 3) float32, K = round(keep_ratio * num_points), in normalised units;
    info has ``scale`` (metres per unit) and ``centre`` so metric errors can be recovered, and
    ``overlap``.
    """
    pts, centre, scale = normalise_unit_box(np.asarray(points, dtype=np.float32))
    keep = int(round(keep_ratio * num_points))
    if keep < 1:
        raise ValueError(f"keep_ratio * num_points = {keep} < 1")

    def draw() -> np.ndarray:
        replace = len(pts) < num_points
        return rng.choice(len(pts), num_points, replace=replace)

    idx_s = draw()
    idx_t = draw() if resample_target else idx_s
    src_i = idx_s[crop_nearest_far_point(pts[idx_s], rng, keep)]
    tgt_i = idx_t[crop_nearest_far_point(pts[idx_t], rng, keep)]
    src_i, tgt_i = rng.permutation(src_i), rng.permutation(tgt_i)
    T = random_transform(rng, max_angle_deg, max_translation)
    source = pts[src_i]
    target = transform_points(T, pts[tgt_i])
    if noise_sigma > 0:   # clipped at 5 sigma, as the paper's (RPM-Net's) 0.01 / 0.05 noise
        clip = 5.0 * noise_sigma
        source = source + np.clip(rng.normal(0, noise_sigma, source.shape), -clip, clip).astype(np.float32)
        target = target + np.clip(rng.normal(0, noise_sigma, target.shape), -clip, clip).astype(np.float32)
    if resample_target:
        overlap = overlap_ratio(source, target, T, OVERLAP_RADIUS / scale)
    else:                                   # exact: fraction of source points also in target
        overlap = float(np.isin(src_i, tgt_i).mean())
    info = {"protocol": "7scenes", "overlap": overlap, "scale": scale,
            "centre": [float(c) for c in centre], "num_points": num_points,
            "keep_ratio": keep_ratio, "max_angle_deg": max_angle_deg,
            "max_translation": max_translation}
    return Pair(source.astype(np.float32), target.astype(np.float32), T, info)


# --------------------------------------------------------------------------------------------
# fragments (what a SLAM user feeds the node)
# --------------------------------------------------------------------------------------------

def sample_fragments_pair(source: scenes.Fragment, target: scenes.Fragment,
                          overlap_radius: float = OVERLAP_RADIUS) -> Pair:
    """A pair of two fragments of the same scene, metres, GT from their poses.

    ``info["overlap"]`` is the fraction of source points with a target point within
    ``overlap_radius`` after the ground truth (3DMatch / Predator convention).
    """
    if source.scene_seed != target.scene_seed:
        raise ValueError("fragments of different scenes have no common world frame")
    T = np.linalg.inv(target.T_world_fragment) @ source.T_world_fragment
    overlap = overlap_ratio(source.points, target.points, T, overlap_radius)
    info = {"protocol": "fragments", "overlap": overlap, "scene_seed": source.scene_seed,
            "source_fragment": source.index, "target_fragment": target.index, "scale": 1.0}
    return Pair(source.points.copy(), target.points.copy(), T, info)


@functools.lru_cache(maxsize=64)
def _fragment(scene: int, index: int) -> scenes.Fragment:
    return scenes.make_fragment(scene, index)


@functools.lru_cache(maxsize=4)
def _overlap_table(scene: int) -> np.ndarray:
    """(F, F) overlap ratio of fragment a (source) onto fragment b (target) of a scene.

    Estimated on every 4th source point (for speed); the pair records the exact value.
    """
    from scipy.spatial import cKDTree

    frags = [_fragment(scene, j) for j in range(FRAGMENTS_PER_SCENE)]
    trees = [cKDTree(f.points) for f in frags]
    table = np.zeros((FRAGMENTS_PER_SCENE, FRAGMENTS_PER_SCENE))
    for a in range(FRAGMENTS_PER_SCENE):
        for b in range(FRAGMENTS_PER_SCENE):
            if a != b:
                T = np.linalg.inv(frags[b].T_world_fragment) @ frags[a].T_world_fragment
                d, _ = trees[b].query(transform_points(T, frags[a].points[::4]),
                                      distance_upper_bound=OVERLAP_RADIUS)
                table[a, b] = float(np.mean(np.isfinite(d)))
    return table


def _select_fragment_pairs(scene: int, count: int, lo: float, hi: float,
                           rng: np.random.Generator) -> list[tuple[int, int]]:
    """``count`` ordered fragment pairs with overlaps spread over [lo, hi] (stratified).

    For stratum k a target overlap is drawn in [lo + k w, lo + (k + 1) w] and the unused
    candidate pair closest to it is taken; when the scene has fewer in-range pairs than
    ``count``, pairs are reused.
    """
    table = _overlap_table(scene)
    m = 0.01                                # the table is estimated: stay clear of the bounds
    cand = [(a, b) for a in range(len(table)) for b in range(len(table))
            if a != b and lo + m <= table[a, b] <= hi - m]
    if not cand:
        raise RuntimeError(f"scene {scene} has no fragment pair with overlap in [{lo}, {hi}]")
    used: set[tuple[int, int]] = set()
    out = []
    w = (hi - lo) / count
    for k in range(count):
        goal = lo + (k + rng.random()) * w
        pool = [c for c in cand if c not in used] or cand
        best = min(pool, key=lambda c: abs(table[c] - goal))
        used.add(best)
        out.append(best)
    return out


# --------------------------------------------------------------------------------------------
# modelnet (RPM-Net protocol on primitive-built objects)
# --------------------------------------------------------------------------------------------

def make_object(seed: int, num_points: int = 2048) -> np.ndarray:
    """A CAD-like object from primitives, sampled uniformly on its surface.

    Categories: table, chair, lamp, mug, bottle, airplane-like, car-like, shelf, monitor, bed.
    Returns (num_points, 3) float32 centred on the centroid and scaled into the unit sphere
    (as ModelNet40 hdf5 clouds are). Internal faces where primitives overlap are sampled too.
    """
    rng = np.random.default_rng([int(seed), 0x0B1])
    mb = scenes._MeshBuilder()
    kind = int(rng.integers(0, 10))
    u = rng.uniform
    if kind == 0:                                   # table
        w, d, h = u(0.8, 2), u(0.5, 1.2), u(0.5, 1)
        mb.box((w, d, 0.05), (0, 0, h))
        for sx in (-1, 1):
            for sy in (-1, 1):
                mb.box((0.06, 0.06, h), (sx * (w / 2 - 0.05), sy * (d / 2 - 0.05), h / 2))
    elif kind == 1:                                 # chair
        w, h = u(0.4, 0.6), u(0.4, 0.55)
        mb.box((w, w, 0.05), (0, 0, h))
        b = u(0.4, 0.8)
        mb.box((w, 0.05, b), (0, w / 2, h + b / 2))
        for sx in (-1, 1):
            for sy in (-1, 1):
                mb.box((0.04, 0.04, h), (sx * (w / 2 - 0.03), sy * (w / 2 - 0.03), h / 2))
    elif kind == 2:                                 # lamp
        h = u(0.8, 1.6)
        mb.cylinder(u(0.1, 0.2), 0.04, (0, 0, 0.02))
        mb.cylinder(0.02, h, (0, 0, h / 2), segments=8)
        r = u(0.12, 0.3)
        mb.cylinder(r, u(0.15, 0.35), (0, 0, h), top_radius=r * u(0.3, 0.8))
    elif kind == 3:                                 # mug
        r, h = u(0.3, 0.5), u(0.6, 1.2)
        mb.cylinder(r, h, (0, 0, h / 2), segments=24)
        mb.box((0.08, 0.3, h * 0.6), (0, r + 0.12, h / 2))
        mb.box((0.08, 0.16, 0.06), (0, r + 0.05, h * 0.78))
        mb.box((0.08, 0.16, 0.06), (0, r + 0.05, h * 0.22))
    elif kind == 4:                                 # bottle
        r, h = u(0.15, 0.3), u(0.6, 1.2)
        mb.cylinder(r, h, (0, 0, h / 2), segments=20)
        mb.cylinder(r, 0.2, (0, 0, h + 0.1), segments=20, top_radius=r * 0.35)
        mb.cylinder(r * 0.35, 0.2, (0, 0, h + 0.3), segments=12)
    elif kind == 5:                                 # airplane-like
        L, r = u(1.5, 2.5), u(0.1, 0.2)
        mb.box((L, 2 * r, 2 * r), (0, 0, 0))
        mb.box((u(0.3, 0.6), u(1.5, 2.5), 0.04), (u(-0.2, 0.2), 0, 0))
        mb.box((0.25, u(0.5, 0.9), 0.03), (-L / 2 + 0.15, 0, 0))
        mb.box((0.25, 0.03, u(0.3, 0.5)), (-L / 2 + 0.15, 0, 0.2))
        mb.sphere(r, (L / 2, 0, 0))
    elif kind == 6:                                 # car-like
        L, W, H = u(1.5, 2.2), u(0.7, 1.0), u(0.3, 0.45)
        mb.box((L, W, H), (0, 0, H / 2 + 0.15))
        mb.box((L * u(0.4, 0.6), W * 0.9, H * 0.8), (u(-0.2, 0.1), 0, H + 0.15 + H * 0.4))
        for sx in (-1, 1):
            for sy in (-1, 1):
                mb.sphere(0.16, (sx * L * 0.33, sy * W / 2, 0.16), rings=6, segments=10)
    elif kind == 7:                                 # shelf
        w, d, h, n = u(0.6, 1.2), u(0.25, 0.4), u(1, 2), int(rng.integers(3, 6))
        mb.box((0.03, d, h), (-w / 2, 0, h / 2))
        mb.box((0.03, d, h), (w / 2, 0, h / 2))
        for k in range(n + 1):
            mb.box((w, d, 0.03), (0, 0, k * h / n))
    elif kind == 8:                                 # monitor
        w, h = u(0.8, 1.4), u(0.5, 0.8)
        mb.box((w, 0.05, h), (0, 0, h / 2 + 0.4))
        mb.box((0.08, 0.05, 0.4), (0, 0.05, 0.2))
        mb.box((0.4, 0.25, 0.03), (0, 0.05, 0.015))
    else:                                           # bed
        L, W = u(1.8, 2.2), u(0.9, 1.8)
        mb.box((L, W, 0.4), (0, 0, 0.2))
        mb.box((0.08, W, u(0.6, 1.0)), (-L / 2, 0, 0.4))
        mb.box((0.4, W * 0.8, 0.12), (-L / 2 + 0.3, 0, 0.46))
    v, tri = mb.arrays()
    v = v.astype(np.float64)
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    face = rng.choice(len(tri), num_points, p=area / area.sum())
    r1, r2 = rng.random(num_points), rng.random(num_points)
    s = np.sqrt(r1)
    p = ((1 - s)[:, None] * a[face] + (s * (1 - r2))[:, None] * b[face]
         + (s * r2)[:, None] * c[face])
    p -= p.mean(0)
    p /= np.linalg.norm(p, axis=1).max()
    return p.astype(np.float32)


def sample_modelnet_pair(points: np.ndarray, rng: np.random.Generator, num_points: int = 1024,
                         keep_ratio: float = 0.7, max_angle_deg: float = 45.0,
                         max_translation: float = 0.5, noise_sigma: float = 0.0,
                         noise_clip: float = 0.05) -> Pair:
    """One RPM-Net "crop" pair from an object's points (N, 3) in the unit sphere.

    Source and target are independent crops of the object (random plane through the centroid,
    keeping ``keep_ratio``), each resampled to ``num_points``; the target is moved by a random
    Euler rotation (+-max_angle_deg per axis) and translation (+-max_translation per axis); then
    optional Gaussian noise (sigma ``noise_sigma``, clipped to +-``noise_clip``) is added to
    each independently. Returns (num_points, 3) float32 clouds.
    """
    pts = np.asarray(points, dtype=np.float32)
    src_i = crop_plane(pts, rng, keep_ratio)
    tgt_i = crop_plane(pts, rng, keep_ratio)
    src_i = rng.choice(src_i, num_points, replace=len(src_i) < num_points)
    tgt_i = rng.choice(tgt_i, num_points, replace=len(tgt_i) < num_points)
    T = random_transform(rng, max_angle_deg, max_translation)
    source, target = pts[src_i], transform_points(T, pts[tgt_i])
    if noise_sigma > 0:
        for cloud in (source, target):
            cloud += np.clip(rng.normal(0, noise_sigma, cloud.shape), -noise_clip, noise_clip
                             ).astype(np.float32)
    overlap = float(np.isin(src_i, tgt_i).mean())
    info = {"protocol": "modelnet", "overlap": overlap, "scale": 1.0, "num_points": num_points,
            "keep_ratio": keep_ratio, "noise_sigma": noise_sigma}
    return Pair(source.astype(np.float32), target.astype(np.float32), T, info)


# --------------------------------------------------------------------------------------------
# Datasets
# --------------------------------------------------------------------------------------------

def make_pair(protocol: str, split: str, index: int, seed: int = 0, **kwargs: Any) -> Pair:
    """Pair ``index`` of a dataset, reproducible alone from (protocol, split, seed, index).

    Sharing (so that 100 pairs cost ~20 fragments, not 100):
    - 7scenes: pair i uses fragment (i // 5) % 4 of scene i // 20; its crops and transform
      come from a generator seeded by (protocol, split, seed, i).
    - fragments: scene i // 10 renders 8 fragments; the 10 pairs of a scene are ordered
      fragment pairs chosen with overlaps stratified over [0.1, 0.9].
    - modelnet: one object per pair (cheap).
    ``kwargs`` go to the protocol's sampler (e.g. ``noise_sigma=0.01`` for modelnet).
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r}; expected one of {PROTOCOLS}")
    _check_split(split)
    if index < 0:
        raise ValueError(f"pair index {index} < 0")
    rng = _rng(protocol, split, seed, index)
    if protocol == "7scenes":
        per_scene = SEVENSCENES_PAIRS_PER_FRAGMENT * SEVENSCENES_FRAGMENTS_PER_SCENE
        scene = scene_seed(split, seed, index // per_scene)
        frag = (index % per_scene) // SEVENSCENES_PAIRS_PER_FRAGMENT
        pair = sample_7scenes_pair(_fragment(scene, frag).points, rng, **kwargs)
        pair.info.update(scene_seed=scene, fragment=frag)
    elif protocol == "fragments":
        scene = scene_seed(split, seed, index // FRAGMENT_PAIRS_PER_SCENE)
        chosen = _select_fragment_pairs(scene, FRAGMENT_PAIRS_PER_SCENE, *OVERLAP_RANGE,
                                        _rng("select", scene))
        a, b = chosen[index % FRAGMENT_PAIRS_PER_SCENE]
        pair = sample_fragments_pair(_fragment(scene, a), _fragment(scene, b), **kwargs)
    else:
        obj = scene_seed(split, seed, index)
        pair = sample_modelnet_pair(make_object(obj), rng, **kwargs)
        pair.info.update(object_seed=obj)
    pair.info.update(protocol=protocol, split=split, seed=int(seed), index=int(index))
    return pair


def iter_pairs(protocol: str, split: str, n: int, seed: int = 0, start: int = 0,
               **kwargs: Any) -> Iterator[Pair]:
    """Pairs start .. start + n - 1 of a dataset (see :func:`make_pair`), lazily."""
    for i in range(start, start + n):
        yield make_pair(protocol, split, i, seed, **kwargs)


def make_pairs(protocol: str, split: str, n: int, seed: int = 0, **kwargs: Any) -> list[Pair]:
    """The first n pairs of a dataset as a list (see :func:`make_pair`)."""
    return list(iter_pairs(protocol, split, n, seed, **kwargs))


# --------------------------------------------------------------------------------------------
# Training cache
# --------------------------------------------------------------------------------------------

class FragmentCache:
    """Train-split fragments rendered once and kept as .npz files for training.

    ``FragmentCache(root, num_scenes=50, fragments_per_scene=4, seed=0).load()`` returns a list
    of :class:`~cegc_ros.data.scenes.Fragment` (metres, own frames), rendering the missing ones
    (scene k of the train split, fragments 0 .. fragments_per_scene - 1). File names carry the
    scene seed, fragment index and a hash of the fragment settings, so a changed generator never
    silently reuses stale files. Only train-split scenes are cached: test scenes stay disjoint.
    """

    VERSION = 1

    def __init__(self, root: str | Path = ".cache/fragments", num_scenes: int = 50,
                 fragments_per_scene: int = 4, seed: int = 0,
                 config: scenes.FragmentConfig = scenes.FragmentConfig()) -> None:
        if not 1 <= fragments_per_scene <= scenes.MAX_FRAGMENTS:
            raise ValueError(f"fragments_per_scene must be in 1..{scenes.MAX_FRAGMENTS}")
        self.root = Path(root)
        self.num_scenes, self.fragments_per_scene, self.seed = num_scenes, fragments_per_scene, seed
        self.config = config
        tag = json.dumps([self.VERSION, repr(config)], sort_keys=True).encode()
        self.tag = hashlib.sha256(tag).hexdigest()[:10]

    def keys(self) -> list[tuple[int, int]]:
        """(scene seed, fragment index) of every cached fragment, in load order."""
        return [(scene_seed("train", self.seed, k), j) for k in range(self.num_scenes)
                for j in range(self.fragments_per_scene)]

    def path(self, scene: int, index: int) -> Path:
        return self.root / f"frag_{self.tag}_s{scene}_f{index}.npz"

    def load(self, progress: bool = False) -> list[scenes.Fragment]:
        """All fragments, rendering and saving those not yet on disk."""
        keys = self.keys()
        it: Any = keys
        if progress:
            from tqdm import tqdm
            it = tqdm(keys, desc="fragments", unit="frag")
        self.root.mkdir(parents=True, exist_ok=True)
        return [self._get(scene, j) for scene, j in it]

    def _get(self, scene: int, index: int) -> scenes.Fragment:
        path = self.path(scene, index)
        if path.exists():
            try:
                with np.load(path) as z:
                    return scenes.Fragment(z["points"], z["T_world_fragment"], scene, index,
                                           json.loads(str(z["info"])))
            except (OSError, ValueError, KeyError):
                pass                                # unreadable (e.g. interrupted): re-render
        frag = scenes.make_fragment(scene, index, self.config)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, points=frag.points, T_world_fragment=frag.T_world_fragment,
                 info=json.dumps(frag.info))
        tmp.replace(path)
        return frag
