"""Preprocessing shared by the engine and the trainer: the frame the network works in.

The network sees each cloud centred on its own centroid and both divided by one common scale
``s = 2 * max(rms radius of source, rms radius of target)`` (rotation-invariant, unlike a
bounding box), so clouds of any size in metres look alike. With normalised points
``x_n = (x - c_s) / s`` and ``y_n = (y - c_t) / s`` a transform ``y_n = R x_n + t_n`` is, in
metres, ``T_target_source = [R | s t_n + c_t - R c_s]``.

Rotation-invariant inputs (model variant "ri"): normals estimated by PCA over a radius and
oriented towards the cloud's centroid (a rigid motion moves the centroid with the cloud, so the
orientation is invariant), and FPFH descriptors (Open3D) divided by 100 so that each of their
three 11-bin histograms sums to 2 (Open3D's FPFH sums to 200 per histogram). Radii are in normalised units.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

# Feature neighbourhoods (normalised units; the defaults of ModelConfig, which a checkpoint
# stores). Measured on 12 real SUN3D 7Scenes-protocol pairs, share of FPFH mutual nearest
# neighbours that are true matches (within 2x point spacing), clean / noise 0.01 / resampled:
#   normals 0.04 (30 nn), FPFH 0.10 (100 nn): 0.90 / 0.01 / 0.02   (weights before 2026-11-22)
#   normals 0.10 (30 nn), FPFH 0.25 (200 nn): 0.92 / 0.26 / 0.15   (now)
# Wider neighbourhoods average the sensor noise and the sampling out of the histograms.
NORMAL_RADIUS = 0.10
NORMAL_MAX_NN = 30
FPFH_RADIUS = 0.25
FPFH_MAX_NN = 200
LEGACY_FEATURES = {"normal_radius": 0.04, "fpfh_radius": 0.10, "fpfh_max_nn": 100}  # older checkpoints


@dataclass
class Normalisation:
    """Centres (3,) of each cloud and the common scale s (metres per normalised unit)."""

    c_source: np.ndarray
    c_target: np.ndarray
    scale: float

    def to_metres(self, R: np.ndarray, t_n: np.ndarray) -> np.ndarray:
        """(3, 3) rotation and (3,) normalised translation -> 4x4 float64 T_target_source."""
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = self.scale * np.asarray(t_n, np.float64) + self.c_target - R @ self.c_source
        return T

    def to_normalised(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """4x4 T_target_source in metres -> (R, t_n) in the normalised frame."""
        R = T[:3, :3]
        return R, (R @ self.c_source + T[:3, 3] - self.c_target) / self.scale


def checked_cloud(name: str, xyz: object) -> np.ndarray:
    """``xyz`` as an array; ValueError naming ``name`` unless it is (N, 3) and numeric."""
    arr = np.asarray(xyz)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    return arr


def finite_cloud(name: str, xyz: object, min_points: int) -> np.ndarray:
    """(N, 3) numeric points -> a copy of the finite rows (float32 input stays float32, anything
    else becomes float64, so a huge float32 cloud is copied once at its size); ValueError naming ``name``
    when the shape or dtype is wrong or fewer than ``min_points`` rows are finite."""
    arr = checked_cloud(name, xyz)
    arr = arr[np.isfinite(arr).all(axis=1)]                # one copy: float32 stays float32
    arr = arr if arr.dtype in (np.float32, np.float64) else arr.astype(np.float64)
    if len(arr) < min_points:
        raise ValueError(f"{name} has {len(arr)} finite points, at least {min_points} are needed")
    return arr


def normalise_pair(source: np.ndarray, target: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, Normalisation]:
    """(N, 3), (M, 3) metres -> normalised float32 copies and the Normalisation."""
    src = np.asarray(source, np.float64)
    tgt = np.asarray(target, np.float64)
    cs, ct = src.mean(0), tgt.mean(0)
    rs = np.sqrt(((src - cs) ** 2).sum(1).mean())
    rt = np.sqrt(((tgt - ct) ** 2).sum(1).mean())
    s = 2.0 * max(rs, rt)
    if not np.isfinite(s) or s <= 1e-9:
        raise ValueError(f"clouds have no spatial extent (rms radius {max(rs, rt):.3g} m)")
    norm = Normalisation(cs, ct, float(s))
    return ((src - cs) / s).astype(np.float32), ((tgt - ct) / s).astype(np.float32), norm


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Mean point per occupied voxel; (N, 3) -> (K, 3) float32. voxel <= 0 returns the input."""
    if voxel <= 0:
        return np.asarray(points, np.float32)
    import open3d as o3d
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    return np.asarray(pcd.voxel_down_sample(voxel).points, np.float32)


def grid_means(points: np.ndarray, voxel: float) -> np.ndarray:
    """Mean point per occupied voxel, as :func:`voxel_downsample` (Open3D's grid: the same
    voxels, origin half a voxel below the minimum, and the same means, summed in float64 in
    the points' order), but in the voxels' index order, x-major, instead of the order of
    Open3D's hash map; (N, 3) -> (K, 3) float32, voxel <= 0 returns the input.

    The bound stage's grid (cegc_ros/bounding.py): :func:`voxel_means` instead of a hash map,
    faster on large clouds (300k points about 14 against 23-30 ms, 5M points 0.9 against 4.0 s
    on the AVX2 EPYC, docs/performance.md), and an order that no library's hashing decides. The
    classical peers keep :func:`voxel_downsample`; the data generator its own grid
    (cegc_ros/data/scenes.py), so the caches and bags stay as they were."""
    if voxel <= 0:
        return np.asarray(points, np.float32)
    p = np.asarray(points)
    if len(p) == 0:
        return np.zeros((0, 3), np.float32)
    origin = column_min(p).astype(np.float64) - 0.5 * voxel
    key = np.empty((len(p), 3), np.int64)
    for k in range(3):                        # column by column: 2x faster than on (N, 3)
        c = p[:, k].astype(np.float64)
        c -= origin[k]
        c /= voxel
        key[:, k] = np.floor(c, out=c)
    return voxel_means(p, key).astype(np.float32)


def cell_ids(key: np.ndarray, dims: Any) -> tuple[np.ndarray, float] | None:
    """(N, 3) int64 cell indices, each column in [0, dims[k]) -> ((N,) int64 ids, x-major, and
    the grid's number of cells), or None when the ids would overflow int64."""
    cells = float(dims[0]) * float(dims[1]) * float(dims[2])
    if cells >= 2.0 ** 62:
        return None
    return (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2], cells


def voxel_means(points: np.ndarray, key: np.ndarray) -> np.ndarray:
    """(N, 3) points and their (N, 3) int64 voxel indices (>= 0) -> (K, 3) float64: the mean
    point of each occupied voxel, in the voxels' index order (x, then y, then z), summed in
    float64 in the points' order. Occupied voxels are counted by a table when it is small
    (:func:`use_table`), else by np.unique of the cell ids, or of the index rows when the ids
    would overflow."""
    dims = key[:, 0].max() + 1, key[:, 1].max() + 1, key[:, 2].max() + 1
    grid = cell_ids(key, dims)
    if grid is None:                          # a huge extent for the voxel: rows as keys
        _, slot, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    elif use_table(grid[1], len(key)):        # a table of every cell, no sorting
        count = np.bincount(grid[0], minlength=int(grid[1]))
        occupied = count > 0
        slot = (np.cumsum(occupied) - 1)[grid[0]]                 # (N,) voxel of each point
        count = count[occupied]
    else:
        _, slot, count = np.unique(grid[0], return_inverse=True, return_counts=True)
    slot = slot.reshape(-1)
    out = np.empty((len(count), 3), np.float64)
    for k in range(3):
        out[:, k] = np.bincount(slot, weights=points[:, k], minlength=len(count))
    out /= count[:, None]
    return out


def box_corner(points_per_face: int, seed: int = 0) -> np.ndarray:
    """(3 * points_per_face, 3) float64: three faces of the unit cube that meet at the origin,
    uniformly drawn (seeded). The warm-up cloud of ``Registrar.warm_start`` and
    ``KeyframeOdometry.warm_start``: small, with normals in three directions."""
    rng = np.random.default_rng(seed)
    k = points_per_face
    return np.concatenate([np.c_[rng.uniform(0, 1, (k, 2)), np.zeros(k)],
                           np.c_[np.zeros(k), rng.uniform(0, 1, (k, 2))],
                           np.c_[rng.uniform(0, 1, k), np.zeros(k), rng.uniform(0, 1, k)]])


def column_min(points: np.ndarray) -> np.ndarray:
    """(N, D) -> (D,) per-column minimum; ``points.min(0)`` reduces a narrow C-order array
    element by element (300k x 3: 8 ms), one column at a time is 0.1 ms."""
    return np.array([points[:, k].min() for k in range(points.shape[1])])


def column_max(points: np.ndarray) -> np.ndarray:
    """(N, D) -> (D,) per-column maximum (see :func:`column_min`)."""
    return np.array([points[:, k].max() for k in range(points.shape[1])])


SAMPLINGS = ("grid", "random")


def subsample(points: np.ndarray, n: int, rng: np.random.Generator, sampling: str = "grid") -> np.ndarray:
    """Indices of n of the (N, 3) points, sorted for a stable order; fewer than n points are
    padded by repetition so that the network always sees n.

    ``random``: n distinct points drawn uniformly. ``grid`` (the default): spatially even, one
    seeded random point per cell of the coarsest cubic grid with at least n occupied cells, then
    n of those cells' points at random. A random draw follows the sensor's density (a Kinect
    fragment is dense near the camera), so the far side of an overlap gets few points and a
    source point's true partner is often missing from the target's draw; the grid keeps the
    spacing even, as the classical pipelines' voxel grids do. Chosen on synthetic validation
    pairs (docs/pipeline.md).
    """
    N = len(points)
    if N <= n:
        idx = np.arange(N)
        if N < n:
            idx = np.concatenate([idx, rng.choice(N, n - N, replace=True)])
        return idx
    if sampling == "random":
        return np.sort(rng.choice(N, n, replace=False))
    if sampling != "grid":
        raise ValueError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
    cells = _grid_cells(np.asarray(points, np.float64), n)
    if cells is None:                              # (near-)duplicate points: fewer than n cells
        return np.sort(rng.choice(N, n, replace=False))
    perm = rng.permutation(N)
    _, first = np.unique(cells[perm], return_index=True)   # one random point per occupied cell
    pick = perm[first]
    if len(pick) > n:
        pick = rng.choice(pick, n, replace=False)
    return np.sort(pick)


#: Grids of at most this many cells count their occupied cells with a table (np.bincount)
#: instead of np.unique's sort: the same count in about a third of the time ...
BINCOUNT_CELLS = 1 << 22
#: ... when the table is not much larger than the points: zeroing and scanning it costs ~1 ns a
#: cell, so a sparse cloud in a big box (a LiDAR sweep: up to 660 cells a point) counts faster
#: by np.unique (20k points: table 0.2 ms at 16 cells a point, 6 ms at 4M cells; unique 0.6 ms;
#: docs/performance.md).
TABLE_CELLS_PER_POINT = 16


def use_table(cells: float, n_points: int) -> bool:
    """Whether a grid of ``cells`` cells over ``n_points`` points counts them by a table."""
    return cells <= BINCOUNT_CELLS and cells <= TABLE_CELLS_PER_POINT * max(n_points, 1)


def _grid_cells(points: np.ndarray, n: int, iterations: int = 20) -> np.ndarray | None:
    """(N, 3) -> (N,) int64 cell ids of the coarsest cubic grid found (bisection on the cell
    size) with at least n and, when reachable, under 1.15 n occupied cells; None when even the
    finest tried grid has fewer than n. At most 2^20 cells a side, so the ids fit in int64."""
    lo = column_min(points)
    span = column_max(points) - lo
    hi_size, lo_size = float(span.max()), 0.0
    if not hi_size > 0:
        return None
    rel = points - lo
    best = None
    for _ in range(iterations):
        size = 0.5 * (hi_size + lo_size)
        key = np.floor(rel / size)                     # float64 cell indices, exact integers
        # the largest index is that of the farthest point: no pass over the keys for it
        dims = np.floor(span / size) + 1.0
        cells = float(dims.prod())
        if cells < 2.0 ** 53:                          # float64 ids are exact integers
            ids = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
        else:                                          # a grid this fine (far-apart clusters): int64
            k, d = key.astype(np.int64), dims.astype(np.int64)
            ids = (k[:, 0] * d[1] + k[:, 1]) * d[2] + k[:, 2]
        if use_table(cells, len(ids)):                 # a table of every cell: no sorting
            count = int(np.count_nonzero(np.bincount(ids.astype(np.intp), minlength=int(cells))))
        else:
            count = len(np.unique(ids))
        if count >= n:
            best, lo_size = ids.astype(np.int64), size
            if count < 1.15 * n:
                break
        else:
            hi_size = size
    return best


def normals_and_fpfh(points: np.ndarray, normal_radius: float = NORMAL_RADIUS,
                     fpfh_radius: float = FPFH_RADIUS, fpfh_max_nn: int = FPFH_MAX_NN,
                     viewpoint: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) normalised points -> normals (N, 3) float32, FPFH / 100 (N, 33) float32.

    Each normal is turned towards ``viewpoint`` (3,) in the points' frame, or towards the
    points' centroid when it is None (``preprocess.normals``). FPFH's angles change with a
    normal's sign, so the two views of a surface give alike descriptors only when their normals
    agree: turned to their sensors they do (both sensors saw the surface's front), turned to
    each view's own centroid they disagree wherever the two centroids lie on different sides
    of a surface, which at low overlap is common.

    Open3D's tensor pipeline (``o3d.t``): 2.4-3x faster than the legacy
    ``compute_fpfh_feature`` on one thread at 1024 points (12 vs 28 ms on 20k-point fragments'
    support, 15 vs 48 on the denser 1.5k crops; docs/performance.md). Same definition: normals
    equal to 1e-7; 82-84% of FPFH rows equal to 1e-4, the rest differ by 0.003 of a row's mass
    on average (the neighbour order at the max_nn cut and the legacy code's acos ties). Recall
    with weights trained on the legacy features: 196 validation pairs 0.505 (legacy 0.520, 1 won
    / 4 lost), both synthetic test bags up 0.6 / 1.3 points (docs/accuracy.md)."""
    import open3d as o3d
    pts = np.asarray(points, np.float64)
    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts))
    pcd.estimate_normals(max_nn=NORMAL_MAX_NN, radius=normal_radius)
    n = pcd.point.normals.numpy()
    toward = pts.mean(0) if viewpoint is None else np.asarray(viewpoint, np.float64)
    flip = ((toward - pts) * n).sum(1) < 0
    n[flip] *= -1.0
    pcd.point.normals = o3d.core.Tensor(n)
    fpfh = o3d.t.pipelines.registration.compute_fpfh_feature(pcd, max_nn=fpfh_max_nn, radius=fpfh_radius)
    return n.astype(np.float32), (fpfh.numpy() / 100.0).astype(np.float32)


@dataclass
class PreparedCloud:
    """One cloud as the network takes it (normalised frame)."""

    points: np.ndarray      # (n, 3) float32 normalised
    normals: np.ndarray     # (n, 3) float32
    desc: np.ndarray        # (n, 33) float32
    index: np.ndarray       # (n,) indices into the cloud given to prepare_cloud


def prepare_cloud(points_n: np.ndarray, num_points: int, rng: np.random.Generator,
                  support_points: int, with_features: bool = True,
                  normal_radius: float = NORMAL_RADIUS, fpfh_radius: float = FPFH_RADIUS,
                  fpfh_max_nn: int = FPFH_MAX_NN, sampling: str = "grid",
                  viewpoint: np.ndarray | None = None) -> PreparedCloud:
    """Support subsample -> normals + FPFH on the support (normals turned to ``viewpoint``, see
    :func:`normals_and_fpfh`) -> network subsample of num_points (both subsamples by
    ``sampling``, see :func:`subsample`).

    The feature radii must be those the network was trained with (``ModelConfig.features()``).
    """
    sup = (subsample(points_n, support_points, rng, sampling) if len(points_n) > support_points
           else np.arange(len(points_n)))
    pts = points_n[sup]
    if with_features:
        normals, desc = normals_and_fpfh(pts, normal_radius, fpfh_radius, fpfh_max_nn, viewpoint)
    else:
        normals = np.zeros_like(pts)
        desc = np.zeros((len(pts), 33), np.float32)
    sel = subsample(pts, num_points, rng, sampling)
    return PreparedCloud(pts[sel], normals[sel], desc[sel], sup[sel])


#: The fewest network points a small cloud is given (the ONNX export's point axes need >= 64).
MIN_NETWORK_POINTS = 64


def point_budget(n_points: int, num_points: int, support_points: int, points_per_network_point: int
                 ) -> tuple[int, int]:
    """(network points, support points) for a pair whose smaller bounded cloud has ``n_points``:
    ``num_points`` and ``support_points`` (``preprocess``), or, for a cloud of fewer than
    ``points_per_network_point`` x ``num_points`` points, one network point per
    ``points_per_network_point`` points (at least MIN_NETWORK_POINTS, never more than asked) and
    the support scaled by the same factor. ``points_per_network_point`` 0: always as asked."""
    if points_per_network_point <= 0 or n_points >= points_per_network_point * num_points:
        return num_points, support_points
    net = min(num_points, max(MIN_NETWORK_POINTS, n_points // points_per_network_point))
    return net, max(net, round(support_points * net / num_points))


def frame_viewpoints(normals: str) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``preprocess.normals`` -> :func:`prepare_pair`'s ``viewpoints``: 'sensor' each cloud's
    frame origin (a cloud in its sensor's frame, as a sensor's PointCloud2 is), 'centroid' none
    (each cloud's centroid)."""
    if normals == "sensor":
        return np.zeros(3), np.zeros(3)
    if normals == "centroid":
        return None, None
    raise ValueError(f"normals must be 'sensor' or 'centroid', got {normals!r}")


def prepare_pair(source: np.ndarray, target: np.ndarray, num_points: int, support_points: int,
                 rng: np.random.Generator, features: dict[str, Any], sampling: str = "grid",
                 viewpoints: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
                 ) -> tuple[PreparedCloud, PreparedCloud, Normalisation]:
    """The engine's features stage, shared with training: (N, 3), (M, 3) metres (bounded) ->
    both clouds normalised, normals + FPFH on ``support_points``, ``num_points`` network points.
    ``features``: :meth:`ModelConfig.features` of the network; ``sampling``: :func:`subsample`;
    ``viewpoints``: each cloud's sensor position (3,) in its own frame, metres, its normals are
    turned to, or None to turn them to its centroid (:func:`normals_and_fpfh`)."""
    src_n, tgt_n, norm = normalise_pair(source, target)
    view_s, view_t = ((None if v is None else (np.asarray(v, np.float64) - c) / norm.scale)
                      for v, c in zip(viewpoints, (norm.c_source, norm.c_target)))
    ps = prepare_cloud(src_n, num_points, rng, support_points=support_points, sampling=sampling,
                       viewpoint=view_s, **features)
    pt = prepare_cloud(tgt_n, num_points, rng, support_points=support_points, sampling=sampling,
                       viewpoint=view_t, **features)
    return ps, pt, norm
