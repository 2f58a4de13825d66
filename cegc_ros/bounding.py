"""Stage 1 of the engine: bound the input, whatever its size, in one linear pass.

After :func:`bound_pair` every later stage works on at most ``preprocess.max_points`` points per
cloud, so time and memory stop growing with the input (5M-point clouds cost one pass here and
the same bounded work afterwards).

1. drop non-finite rows (one pass; ValueError naming the cloud when too few are left);
2. a voxel grid (mean point per voxel, Open3D's hash grid: one pass). Its size is
   ``preprocess.voxel_size`` metres when set, otherwise adaptive: ``preprocess.voxel_ratio`` x
   the larger of the two clouds' largest bounding-box sides (each measured in its own frame,
   so it does not depend on the unknown motion; one size for both clouds, so both are sampled
   alike). Why 0.01: KISS-ICP derives its voxel the same way (max range / 100) for any sensor;
   on the 1536-point 7Scenes-protocol crops (unit box) a 0.01 grid leaves almost every point
   alone, so clouds cut from one point set keep their exact shared points, and a 4 m Kinect
   fragment gets 4 cm voxels (3DMatch's fragments use 2.5 cm, its FPFH pipelines 5 cm).
   ``voxel_size = 0`` and ``voxel_ratio = 0`` switch the grid off;
3. a cap: a cloud still above ``max_points`` is re-gridded with a coarser voxel
   (surfaces: points ~ 1 / voxel^2, so the size grows by sqrt(n / max_points)), at most three
   times, then thinned by a seeded random subsample.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import PreprocessConfig
from .geometry import finite_cloud, voxel_downsample


@dataclass
class BoundedPair:
    """Both clouds in metres (float64), at most max_points each, and the grid that bounded them."""

    source: np.ndarray      # (Ns, 3)
    target: np.ndarray      # (Nt, 3)
    voxel: float            # metres; 0 when no grid ran
    input_points: tuple[int, int]   # finite points before the grid


def extent(points: np.ndarray) -> float:
    """Largest side of the axis-aligned bounding box."""
    return float((points.max(0) - points.min(0)).max())


def cap_points(points: np.ndarray, voxel: float, max_points: int, rng: np.random.Generator) -> np.ndarray:
    """Coarsen the grid (at most three times), then subsample, until at most max_points remain."""
    for _ in range(3):
        if len(points) <= max_points or voxel <= 0:
            break
        voxel *= 1.05 * np.sqrt(len(points) / max_points)
        points = voxel_downsample(points, voxel).astype(np.float64)
    if len(points) > max_points:
        points = points[np.sort(rng.choice(len(points), max_points, replace=False))]
    return points


def bound_pair(source_xyz: object, target_xyz: object, cfg: PreprocessConfig,
               min_points: int) -> BoundedPair:
    """Finite filter, voxel grid and cap for both clouds; ValueError on unusable input."""
    # Memory: one finite copy of a cloud at a time (its input dtype; the extents need only
    # min / max), so a 5M-point pair peaks at the inputs + one copy + Open3D's grid of one cloud.
    ext = max(extent(finite_cloud(name, xyz, min_points))
              for name, xyz in (("source", source_xyz), ("target", target_xyz)))
    voxel = cfg.voxel_size if cfg.voxel_size > 0 else cfg.voxel_ratio * ext
    rng = np.random.default_rng(cfg.seed)
    out, n_in = [], []
    for name, xyz in (("source", source_xyz), ("target", target_xyz)):
        cloud = finite_cloud(name, xyz, min_points)
        n_in.append(len(cloud))
        if voxel > 0:
            cloud = voxel_downsample(cloud, voxel)
        cloud = cap_points(np.asarray(cloud, np.float64), voxel, cfg.max_points, rng)
        if len(cloud) < min_points:
            raise ValueError(f"{name} has {len(cloud)} points after the {voxel:.4g} m voxel grid, "
                             f"at least {min_points} are needed")
        out.append(cloud)
    return BoundedPair(out[0], out[1], float(voxel), (n_in[0], n_in[1]))
