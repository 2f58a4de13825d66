"""Sensor defects added to clean clouds, so that robustness is measured, not assumed.

``add_flying_pixels``: depth sensors (Kinect v2, ToF, stereo) return "flying pixels" at depth
edges, where a pixel mixes a near and a far surface: the point lies on the pixel's ray, but
anywhere between the two surfaces and beyond. The corruption moves a share of the points along
their rays from the sensor (the cloud frame's origin) out to a uniformly drawn range in
``[max(its range, near), far]``: a Kinect v2 room cloud looked like this with 2% of its points
out to 12 m (issue: real sensors). Used by ``cegc-eval --flying-pixels`` and
``select_weights --flying-pixels``.

``thinned``: the same pairs as a sparser sensor would see them (``select_weights --points``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

#: Range (metres from the sensor) the flying pixels are pushed out to.
FLYING_NEAR, FLYING_FAR = 3.0, 12.0


def add_flying_pixels(points: np.ndarray, share: float, rng: np.random.Generator,
                      near: float = FLYING_NEAR, far: float = FLYING_FAR) -> np.ndarray:
    """(N, 3) metres, sensor at the origin -> a copy with round(share x N) points moved along
    their rays to ranges in [max(range, near), far]. The ground truth of a pair is unchanged
    (the moved points are outliers, not surface)."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"flying-pixel share must be in [0, 1], got {share}")
    out = np.array(points, dtype=np.float64, copy=True)
    k = int(round(share * len(out)))
    if k == 0:
        return out.astype(np.asarray(points).dtype, copy=False)
    idx = rng.choice(len(out), k, replace=False)
    p = out[idx]
    r = np.linalg.norm(p, axis=1)
    ok = r > 1e-9
    lo = np.maximum(r[ok], near)
    new_r = rng.uniform(lo, np.maximum(lo, far))
    p[ok] *= (new_r / r[ok])[:, None]
    out[idx] = p
    return out.astype(np.asarray(points).dtype, copy=False)


def with_flying_pixels(pairs: Sequence[Any], share: float, keys: Iterable[int]) -> list[Any]:
    """Copies of ``pairs`` (dataclasses with ``source`` and ``target`` clouds) with ``share``
    flying pixels in both clouds, each seeded by its pair's key (source [key, 0], target
    [key, 1]), so that a pair gets the same defects whichever set it is drawn into."""
    return [dataclasses.replace(p, source=add_flying_pixels(p.source, share, np.random.default_rng([int(k), 0])),
                                target=add_flying_pixels(p.target, share, np.random.default_rng([int(k), 1])))
            for k, p in zip(keys, pairs)]


def thinned(pairs: Sequence[Any], points: int, keys: Iterable[int]) -> list[Any]:
    """Copies of ``pairs`` with each cloud thinned to at most ``points`` points (a uniform draw
    seeded by its pair's key: source [key, 2], target [key, 3]), as a sparser sensor would see
    the same surfaces. The ground truth is unchanged."""
    if points < 1:
        raise ValueError(f"points must be >= 1, got {points}")

    def thin(cloud: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        cloud = np.asarray(cloud)
        if len(cloud) <= points:
            return cloud
        return cloud[np.sort(rng.choice(len(cloud), points, replace=False))]
    return [dataclasses.replace(p, source=thin(p.source, np.random.default_rng([int(k), 2])),
                                target=thin(p.target, np.random.default_rng([int(k), 3])))
            for k, p in zip(keys, pairs)]
