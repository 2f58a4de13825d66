"""Free space: what a pose puts where the other cloud's sensor saw through.

A cloud in its sensor's frame (the origin is the viewpoint, as a sensor's PointCloud2 is) says
more than where its surfaces are: along each ray from the origin, space nearer than the first
return is empty. A wrong pose that lays one cloud's floor on the other's usually puts the rest
of that cloud (walls, furniture) into that seen-through space; the right pose does not. The
verification of the estimator (cegc_ros/estimator.py) ranks its hypotheses by count x fitness
(or feature agreement, ``engine.verify_score``) x exp(-``engine.free_space`` x the share of
violating points, both directions); chosen on the
synthetic validation pairs (docs/pipeline.md).

Range images: the directions from the origin binned by azimuth and elevation in
:data:`BIN_DEG` degree cells, each cell holding the nearest range seen in it. A point violates
free space when its cell was seen and its range is shorter than the cell's by more than
max(:data:`MARGIN_M`, :data:`MARGIN_SHARE` x the cell's range) (noise, the cell's width and a
handheld path's motion within a fused fragment stay inside that margin).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

#: Angular size of a range-image cell (degrees).
BIN_DEG = 2.0
#: A point counts as in free space when nearer than the cell's range by more than the larger
#: of these (metres; share of the cell's range).
MARGIN_M = 0.1
MARGIN_SHARE = 0.1
#: Points of each cloud used (a seeded subsample of the bounded cloud).
POINTS = 3000


def _cells(x: np.ndarray, y: np.ndarray, z: np.ndarray, bin_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates (...) each -> (cell index (...) int64, range (...)) of each point seen from
    the origin."""
    r = np.sqrt(x * x + y * y + z * z)
    az, el = _azimuth_elevation(x, y, np.clip(z / np.maximum(r, 1e-12), -1.0, 1.0))
    rows = int(np.ceil(np.pi / bin_rad)) + 1
    ia = np.floor((az + np.pi) / bin_rad).astype(np.int64)
    ie = np.floor((el + np.pi / 2) / bin_rad).astype(np.int64)
    return ia * rows + ie, r


def _azimuth_elevation(x: np.ndarray, y: np.ndarray, sin_el: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """arctan2(y, x) and arcsin(sin_el), each (...) float64, through torch's vectorised kernels
    (SLEEF, within 1 ulp of numpy's libm calls), which are 3-4x faster than numpy's scalar loops
    on an AVX2 CPU and were two thirds of the free-space check's time. A last-bit difference
    moves a point to the next cell only if its angle lies within 1e-16 rad of a cell's edge:
    the violations of 3990 validation and benchmark poses came out equal to numpy's
    (docs/performance.md). Chunks of the estimator's check (8 poses x 3000 points) stay below
    torch's parallel grain, so no thread is woken for them."""
    import torch

    def tensor(a: np.ndarray) -> torch.Tensor:
        # torch takes neither negative strides nor read-only buffers (a user's reversed view, a
        # PointCloud2's bytes): contiguous, writable float64, copied only where it is not
        a = np.ascontiguousarray(a, np.float64)
        return torch.from_numpy(a if a.flags.writeable else a.copy())

    return torch.atan2(tensor(y), tensor(x)).numpy(), torch.asin(tensor(sin_el)).numpy()


@dataclass
class RangeImage:
    """The nearest range seen in each direction cell of one cloud, from its origin."""

    nearest: np.ndarray         # (cells,) float64, inf where nothing was seen
    bin_rad: float

    @classmethod
    def of(cls, points: np.ndarray, bin_deg: float = BIN_DEG) -> RangeImage:
        """(N, 3) points in their sensor's frame -> their range image."""
        b = np.radians(bin_deg)
        cells = (int(np.ceil(2 * np.pi / b)) + 1) * (int(np.ceil(np.pi / b)) + 1)
        p = np.asarray(points, np.float64)
        key, r = _cells(p[:, 0], p[:, 1], p[:, 2], b)
        nearest = np.full(cells, np.inf)
        np.minimum.at(nearest, key, r)
        return cls(nearest, b)

    def violations(self, points: np.ndarray) -> np.ndarray:
        """(..., N, 3) points in this image's frame -> (...) share of them in seen free space."""
        return self.violations_of(points[..., 0], points[..., 1], points[..., 2])

    def violations_of(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """:meth:`violations` of the points given by coordinate arrays (..., N) each."""
        key, r = _cells(x, y, z, self.bin_rad)
        return (r < self._limit[key]).mean(axis=-1)

    @functools.cached_property
    def _limit(self) -> np.ndarray:
        """(cells,) the range below which a point of the cell is in seen free space: the
        nearest range less the margin; NaN where nothing was seen (inf - inf), which no range
        is below."""
        d = self.nearest
        with np.errstate(invalid="ignore"):
            return d - np.maximum(MARGIN_M, MARGIN_SHARE * d)


def subsample(points: np.ndarray, n: int = POINTS, seed: int = 0) -> np.ndarray:
    """At most n of the (N, 3) points (a seeded draw), float64."""
    pts = np.asarray(points, np.float64)
    if len(pts) <= n:
        return pts
    return pts[np.sort(np.random.default_rng(seed).choice(len(pts), n, replace=False))]


class FreeSpace:
    """Two clouds in their sensors' frames, sampled (:func:`subsample`) and imaged once, for the
    free-space violations of any number of poses T_target_source (:meth:`violations`)."""

    def __init__(self, source: np.ndarray, target: np.ndarray) -> None:
        self.source = subsample(source)                                     # (Ns, 3)
        self.target = subsample(target)                                     # (Nt, 3)
        self.source_image = RangeImage.of(self.source)
        self.target_image = RangeImage.of(self.target)

    def violations(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """R (H, 3, 3), t (H, 3) -> (H,) the share of source points each pose puts in the
        target's free space plus the share of target points the inverse pose puts in the
        source's."""
        # coordinates along the rows, (H, 3, N): each pass runs over N contiguous values
        into_t = R @ np.ascontiguousarray(self.source.T) + t[:, :, None]           # (H, 3, Ns)
        into_s = np.transpose(R, (0, 2, 1)) @ (self.target.T[None] - t[:, :, None])  # R^T (q - t), (H, 3, Nt)
        return (self.target_image.violations_of(*into_t.transpose(1, 0, 2))
                + self.source_image.violations_of(*into_s.transpose(1, 0, 2)))


def free_space_violations(R: np.ndarray, t: np.ndarray, source: np.ndarray, target: np.ndarray
                          ) -> np.ndarray:
    """H poses T_target_source (R (H, 3, 3), t (H, 3)), (Ns, 3) source and (Nt, 3) target
    points, each in its sensor's frame -> (H,) :meth:`FreeSpace.violations`."""
    return FreeSpace(source, target).violations(R, t)
