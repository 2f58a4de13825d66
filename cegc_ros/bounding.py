"""Stage 1 of the engine: bound the input, whatever its size, in one linear pass.

After :func:`bound_pair` every later stage works on at most ``preprocess.max_points`` points per
cloud, so time and memory stop growing with the input (5M-point clouds cost one pass here and
the same bounded work afterwards).

1. input hygiene (:func:`clean_points`, shared with the node, which counts what it drops):
   non-finite rows, no-return points at exactly (0, 0, 0) (what organized LiDAR and depth
   drivers write for a pixel without a return), and points nearer than
   ``preprocess.min_range`` or farther than ``preprocess.max_range`` from the cloud frame's
   origin (0 = no limit); ValueError naming the cloud when too few are left;
2. a voxel grid (mean point per voxel, :func:`cegc_ros.geometry.grid_means`: Open3D's voxels
   and means, in the voxels' index order; one pass). Its size is
   ``preprocess.voxel_size`` metres when set, otherwise adaptive: ``preprocess.voxel_ratio`` x
   the larger of the two clouds' robust extents (:func:`robust_extent`: the largest side of the
   box that holds all but :data:`EXTENT_TRIM` of the points on each side of each axis, so that
   a few per cent of flying pixels 10 m out change neither the grid nor the result; each cloud
   measured in its own frame, so it does not depend on the unknown motion; one size for both
   clouds, so both are sampled alike). Why 0.01: KISS-ICP derives its voxel the same way (max
   range / 100) for any sensor; on the 1536-point 7Scenes-protocol crops (unit box) a 0.01 grid
   leaves almost every point alone, so clouds cut from one point set keep their exact shared
   points, and a 4 m Kinect fragment gets 4 cm voxels (3DMatch's fragments use 2.5 cm, its FPFH
   pipelines 5 cm). ``voxel_size = 0`` and ``voxel_ratio = 0`` switch the grid off;
3. a cap: a cloud still above ``max_points`` is re-gridded with a coarser voxel
   (surfaces: points ~ 1 / voxel^2, so the size grows by sqrt(n / max_points)), at most three
   times, then thinned by a seeded random subsample;
4. isolated points dropped (:func:`drop_isolated`) when the extent's sample shows some
   (``STRAY_TRIGGER``): a point with fewer than ``ISOLATED_MIN_NEIGHBOURS`` others within
   ``ISOLATED_RADIUS`` x the cloud's median spacing (more for points beyond the median range
   from the sensor, where a scanner's rays are farther apart) is a flying pixel or a lone stray
   return, not surface. The grid sampling of the next stage gives every occupied
   cell the same chance, so a few per cent of strays spread over a large volume would
   otherwise take a large share of the network's points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .config import PreprocessConfig
from .geometry import cell_ids, checked_cloud, column_max, column_min, grid_means, use_table
from .parallel import both, query_workers


@dataclass
class BoundedPair:
    """Both clouds in metres (float64), at most max_points each, and the grid that bounded them."""

    source: np.ndarray      # (Ns, 3)
    target: np.ndarray      # (Nt, 3)
    voxel: float            # metres; 0 when no grid ran
    input_points: tuple[int, int]   # points kept by clean_points, before the grid
    dropped: tuple[Dropped, Dropped] = field(default_factory=lambda: (Dropped(), Dropped()))  # hygiene


#: Isolated points after the voxel grid: fewer than ISOLATED_MIN_NEIGHBOURS others within
#: ISOLATED_RADIUS x the cloud's median nearest-neighbour spacing (its own spacing, so sparse
#: clouds such as 1.5k-point crops, whose points are farther apart than the voxel, lose
#: nothing). A surface sampled at spacing s has ~50 neighbours within 4 s on a grid and ~11 at
#: random (Poisson: fewer than 2 for 0.02% of its points), an edge or a thin pole 5 or more;
#: a flying pixel out along its ray usually none.
ISOLATED_MIN_NEIGHBOURS = 2
ISOLATED_RADIUS = 4.0
#: Points the median spacing is estimated from (a seeded draw above it).
SPACING_SAMPLE = 2000
#: The whole (gridded) cloud is searched for isolated points only when the extent's sample of
#: EXTENT_SAMPLE points has at least this many (0.15%; a clean surface: ~0.02%), so that clean
#: clouds do not pay for a k-d tree over 20k points.
STRAY_TRIGGER = 3
#: Share of the points cut from each end of each axis before the extent is measured.
#: Chosen on synthetic validation pairs, clean and with 2% flying pixels (docs/pipeline.md).
EXTENT_TRIM = 0.02
#: Points that the extent's quantiles are estimated from (a seeded draw above it: a 2% quantile
#: of 2000 points is within about 0.3% of the cloud's).
EXTENT_SAMPLE = 2000


@dataclass
class Dropped:
    """Points the bound stage removed from one cloud, by reason (:func:`clean_points`, then
    :func:`drop_isolated` after the grid)."""

    non_finite: int = 0
    no_return: int = 0          # exactly (0, 0, 0)
    out_of_range: int = 0       # nearer than min_range or farther than max_range
    isolated: int = 0           # voxels (after the grid) with too few neighbours: flying pixels

    def total(self) -> int:
        return self.non_finite + self.no_return + self.out_of_range + self.isolated


def drop_isolated(points: np.ndarray, seed: int = 0) -> tuple[np.ndarray, int]:
    """(N, 3) points -> those with at least ISOLATED_MIN_NEIGHBOURS others within their radius,
    and how many were dropped. The radius is ISOLATED_RADIUS x the median nearest-neighbour
    spacing (of at most SPACING_SAMPLE seeded points), grown for points farther from the
    cloud frame's origin than the median range of that sample (:func:`_range_scale`)."""
    if ISOLATED_MIN_NEIGHBOURS <= 0 or len(points) <= 2 * ISOLATED_MIN_NEIGHBOURS:
        return points, 0
    from scipy.spatial import cKDTree
    tree = cKDTree(points, balanced_tree=False)          # built in half the time, same answers
    probe = points
    if len(points) > SPACING_SAMPLE:
        probe = points[np.random.default_rng(seed).choice(len(points), SPACING_SAMPLE, replace=False)]
    d, _ = tree.query(probe, k=2, workers=query_workers(len(probe)))
    spacing = float(np.median(d[:, 1]))
    if not spacing > 0:                               # duplicates: nothing is isolated
        return points, 0
    radius = ISOLATED_RADIUS * spacing
    # Any two points in one cube of side radius / sqrt(3) are nearer than the radius, so a point
    # whose cube holds ISOLATED_MIN_NEIGHBOURS others is kept without a search (on a surface
    # almost every point: 14k-point clouds 15 -> 5 ms); only the rest are searched.
    # A second grid shifted by half a cube keeps most of the points the first one cut off at
    # a cube's face (doubtful points 21% -> 4.5% on a gridded 14k-point fragment).
    cube = 0.999 * radius / np.sqrt(3.0)
    keep = _crowded_cells(points, cube, ISOLATED_MIN_NEIGHBOURS + 1)
    doubt = np.flatnonzero(~keep)
    if len(doubt):
        keep |= _crowded_cells(points, cube, ISOLATED_MIN_NEIGHBOURS + 1, shift=0.5)
        doubt = np.flatnonzero(~keep)
    if len(doubt):
        # each doubtful point's own radius (>= radius, so the cubes above never keep too much)
        own = radius * _range_scale(points[doubt], probe)
        # The k-th nearest other point within the radius (k = ISOLATED_MIN_NEIGHBOURS; the first
        # neighbour found is the point itself): cheaper than counting the whole ball.
        far, _ = tree.query(points[doubt], k=ISOLATED_MIN_NEIGHBOURS + 1,
                            workers=query_workers(len(doubt)), distance_upper_bound=float(own.max()))
        keep[doubt] = far[:, -1] < own
    return points[keep], int(len(points) - keep.sum())


def _range_scale(points: np.ndarray, probe: np.ndarray) -> np.ndarray:
    """(M, 3), the spacing's (P, 3) sample -> (M,) >= 1: each point's range from the cloud
    frame's origin over the sample's median range, at least 1.

    A scanning sensor (LiDAR, depth camera) samples a surface at a spacing that grows with the
    range (a fixed angle between rays), so the far returns of a LiDAR sweep are sparser than the
    median spacing says: on the real LiDAR pair the plain radius dropped 2.5-3% of the points,
    far returns (median range 29 m, the cloud's 8 m) that constrain the rotation (1.0 -> 0.17 deg
    with them kept; docs/performance.md). A cloud not in a sensor's frame (a map, an object)
    has ranges near its median, where nothing changes; the depth-edge flying pixels of a depth
    camera lie at the scene's ranges and stay isolated (test_input_hygiene)."""
    ref = float(np.median(np.sqrt(np.einsum("ij,ij->i", probe, probe))))
    if not ref > 0:
        return np.ones(len(points))
    return np.maximum(1.0, np.sqrt(np.einsum("ij,ij->i", points, points)) / ref)


def _crowded_cells(points: np.ndarray, cell: float, at_least: int, shift: float = 0.0) -> np.ndarray:
    """(N,) bool: the point's cube of the grid of side ``cell`` (its origin ``shift`` cells
    below the points' minimum) holds at least ``at_least`` points (itself included)."""
    lo = column_min(points) - shift * cell
    key = np.floor((points - lo) / cell).astype(np.int64)
    dims = np.floor((column_max(points) - lo) / cell).astype(np.int64) + 1   # = key.max(0) + 1
    grid = cell_ids(key, dims)
    if grid is None:                                        # ids would overflow
        return np.zeros(len(points), bool)
    ids, cells = grid
    if use_table(cells, len(ids)):                          # a table of every cell, no sorting
        return np.bincount(ids, minlength=int(cells))[ids] >= at_least
    _, inverse, counts = np.unique(ids, return_inverse=True, return_counts=True)
    return counts[inverse] >= at_least


def clean_points(xyz: np.ndarray, min_range: float = 0.0, max_range: float = 0.0
                 ) -> tuple[np.ndarray, Dropped]:
    """(N, 3) points -> the rows that are finite, not exactly (0, 0, 0) and within
    [min_range, max_range] metres of the origin (0: no limit), and what was dropped. One copy;
    float32 stays float32."""
    arr = np.asarray(xyz)
    x, y, z = arr[:, 0], arr[:, 1], arr[:, 2]            # column views: ~10x faster than axis=1
    keep = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    dropped = Dropped(non_finite=int(len(arr) - keep.sum()))
    zero = (x == 0) & (y == 0) & (z == 0) & keep
    dropped.no_return = int(zero.sum())
    keep &= ~zero
    if min_range > 0 or max_range > 0:
        with np.errstate(invalid="ignore"):
            r2 = np.einsum("ij,ij->i", arr, arr, dtype=np.float64)
            inside = np.ones(len(arr), bool)
            if min_range > 0:
                inside &= r2 >= min_range * min_range
            if max_range > 0:
                inside &= r2 <= max_range * max_range
        dropped.out_of_range = int((keep & ~inside).sum())
        keep &= inside
    return (arr if keep.all() else arr[keep]), dropped


def extent(points: np.ndarray) -> float:
    """Largest side of the axis-aligned bounding box."""
    return float((column_max(points) - column_min(points)).max())


def robust_extent(points: np.ndarray, trim: float | None = None, seed: int = 0) -> float:
    """Largest side of the box between the ``trim`` (default :data:`EXTENT_TRIM`) and
    ``1 - trim`` quantiles of each axis (``trim`` 0: the bounding box), from at most
    EXTENT_SAMPLE seeded points less their isolated ones (:func:`drop_isolated`: flying pixels
    far out would otherwise still move the far quantile)."""
    return _survey(points, trim, seed)[0]


def _survey(points: np.ndarray, trim: float | None, seed: int) -> tuple[float, int]:
    """(robust extent, isolated points in the sample) of one cloud."""
    trim = EXTENT_TRIM if trim is None else trim
    if trim <= 0:
        return extent(points), STRAY_TRIGGER       # no sample taken: check the whole cloud
    pts = np.asarray(points, np.float64)
    if len(pts) > EXTENT_SAMPLE:
        pts = pts[np.random.default_rng(seed).choice(len(pts), EXTENT_SAMPLE, replace=False)]
    pts, strays = drop_isolated(pts, seed)
    lo, hi = np.quantile(pts, [trim, 1.0 - trim], axis=0)
    return float((hi - lo).max()), strays


def cap_points(points: np.ndarray, voxel: float, max_points: int, rng: np.random.Generator) -> np.ndarray:
    """Coarsen the grid (at most three times), then subsample, until at most max_points remain."""
    for _ in range(3):
        if len(points) <= max_points or voxel <= 0:
            break
        voxel *= 1.05 * np.sqrt(len(points) / max_points)
        points = grid_means(points, voxel).astype(np.float64)
    if len(points) > max_points:
        points = points[np.sort(rng.choice(len(points), max_points, replace=False))]
    return points


def _usable(name: str, xyz: object, cfg: PreprocessConfig, min_points: int
            ) -> tuple[np.ndarray, Dropped]:
    """Shape and dtype checked (geometry.checked_cloud), then :func:`clean_points`; ValueError
    naming the cloud when fewer than min_points are left."""
    cloud, dropped = clean_points(checked_cloud(name, xyz), cfg.min_range, cfg.max_range)
    cloud = cloud if cloud.dtype in (np.float32, np.float64) else cloud.astype(np.float64)
    if len(cloud) < min_points:
        why = (f" ({dropped.non_finite} non-finite, {dropped.no_return} at (0, 0, 0), "
               f"{dropped.out_of_range} out of range dropped)" if dropped.total() else "")
        raise ValueError(f"{name} has {len(cloud)} usable points{why}, at least {min_points} "
                         f"are needed")
    return cloud, dropped


#: Pairs whose clouds both have between these many input points are bounded side by side on
#: two threads: the stage's numpy grid and k-d trees release the GIL, so a 300k-point pair takes
#: 49 instead of 63 ms idle, 79-87 instead of 123 beside two busy processes, the 70k-point LiDAR
#: pair 29 instead of 43 (51 / 85); at 20k points it gains nothing idle, and at 1.5k points the
#: threads' hand-offs cost 5 ms beside busy processes. Above the upper bound both clouds'
#: grid arrays at once would cost more memory than the time is worth (a 5M-point pair: 0.6-0.75
#: instead of 0.76-0.84 s, but a 975 instead of 637 MB peak; docs/performance.md).
SIDE_BY_SIDE_POINTS = (50_000, 1_000_000)


def _rows(xyz: object) -> int:
    """Rows of an input cloud, 0 when it has no length (it fails the checks that follow)."""
    try:
        return len(xyz)                                     # type: ignore[arg-type]
    except TypeError:
        return 0


def bound_pair(source_xyz: object, target_xyz: object, cfg: PreprocessConfig,
               min_points: int) -> BoundedPair:
    """Input hygiene, voxel grid and cap for both clouds; ValueError on unusable input. When both
    clouds' sizes are within :data:`SIDE_BY_SIDE_POINTS`, their hygiene, grids and stray
    checks run side by side (:func:`cegc_ros.parallel.both`: the same answers and errors as one
    after the other); the cap's seeded thinning takes them in turn, source first."""
    # Memory: one clean copy of each cloud (its input dtype); a 5M-point pair peaks at the
    # inputs + their copies + the grid's index arrays of one cloud (about 50 bytes a point;
    # pairs above SIDE_BY_SIDE_POINTS[1] are bounded in turn for this).
    def usable(named: tuple[str, object]) -> tuple[np.ndarray, Dropped, tuple[float, int]]:
        cloud, dropped = _usable(named[0], named[1], cfg, min_points)
        return cloud, dropped, _survey(cloud, None, cfg.seed)

    rows = (_rows(source_xyz), _rows(target_xyz))
    side = SIDE_BY_SIDE_POINTS[0] <= min(rows) and max(rows) <= SIDE_BY_SIDE_POINTS[1]
    clean = both(usable, ("source", source_xyz), ("target", target_xyz), side)
    ext = max(survey[0] for _, _, survey in clean)
    voxel = cfg.voxel_size if cfg.voxel_size > 0 else cfg.voxel_ratio * ext

    def gridded(cloud: np.ndarray) -> np.ndarray:
        return np.asarray(grid_means(cloud, voxel) if voxel > 0 else cloud, np.float64)

    grids = both(gridded, clean[0][0], clean[1][0], side)
    rng = np.random.default_rng(cfg.seed)
    capped = [cap_points(cloud, voxel, cfg.max_points, rng) for cloud in grids]

    def strays_dropped(which: int) -> tuple[np.ndarray, int]:
        if clean[which][2][1] >= STRAY_TRIGGER:
            return drop_isolated(capped[which], cfg.seed)
        return capped[which], 0

    out = both(strays_dropped, 0, 1, side)
    for name, (cloud, isolated), (_, dropped, _) in zip(("source", "target"), out, clean):
        dropped.isolated = isolated
        if len(cloud) < min_points:
            raise ValueError(f"{name} has {len(cloud)} points after the {voxel:.4g} m voxel grid, "
                             f"at least {min_points} are needed")
    return BoundedPair(out[0][0], out[1][0], float(voxel), (len(clean[0][0]), len(clean[1][0])),
                       (clean[0][1], clean[1][1]))
