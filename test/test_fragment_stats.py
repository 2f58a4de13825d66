"""fragment_stats: the statistics that compare synthetic with real fragments measure what they say."""

from __future__ import annotations

import numpy as np
import pytest

from cegc_ros.tools import fragment_stats as F


def plane(n: int, sigma: float, seed: int) -> np.ndarray:
    """(n, 3) points on a 2 m x 2 m floor with Gaussian height noise sigma (m)."""
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(0, 2, (n, 2)), rng.normal(0, sigma, n)]


def test_noise_spacing_and_planarity_of_a_noisy_floor():
    flat = F.cloud_stats(F._grid(plane(40000, 0.0005, 0), F.GRID))
    rough = F.cloud_stats(F._grid(plane(40000, 0.01, 0), F.GRID))
    assert flat["noise_mm"] < 1.0 < rough["noise_mm"]
    assert flat["planar"] > 0.95 and rough["planar"] < flat["planar"]
    assert 15.0 < flat["spacing_mm"] < 30.0                  # about one 2.5 cm voxel apart
    assert flat["extent_m"] == pytest.approx(2.0, abs=0.05)


def test_overlap_and_fpfh_inliers_of_a_room_corner_and_its_moved_half():
    from scipy.spatial.transform import Rotation
    from test_refine import room_corner

    corner = room_corner(60000, 1)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 0.4]).as_matrix()
    T[:3, 3] = [0.3, -0.2, 0.1]
    half = corner[corner[:, 0] < 1.5]                        # the source: half the corner
    target = corner @ T[:3, :3].T + T[:3, 3]                 # the whole corner, moved
    s = F.pair_stats(half, target, T)
    assert s["overlap"] > 0.9                                # all of the source lies on the target
    wrong = np.eye(4)
    wrong[:3, 3] = [5.0, 0.0, 0.0]
    assert F.pair_stats(half, target, wrong)["overlap"] == 0.0
    assert np.isnan(F.pair_stats(half, target, wrong)["fpfh_inlier"])
    # the same points on both sides: every descriptor finds itself; 1 cm of noise on the target
    # makes the corner's planes ambiguous, as real sensor noise does
    same = F.pair_stats(corner, corner, np.eye(4))["fpfh_inlier"]
    noisy = corner + np.random.default_rng(2).normal(0, 0.01, corner.shape)
    assert same > 0.95 and F.pair_stats(corner, noisy, np.eye(4))["fpfh_inlier"] < 0.5 * same


def test_overlap_planar_tells_a_bare_floor_from_clutter_in_the_overlap():
    """The source overlaps the target on a bare floor, or on a heap of boxes standing on it."""
    rng = np.random.default_rng(4)
    floor = plane(30000, 0.0005, 5)
    boxes = np.concatenate([rng.uniform(0, 0.3, (3000, 3)) * [1, 1, 1] + c for c in
                            ([1.2, 1.2, 0.0], [1.5, 1.3, 0.1], [1.3, 1.6, 0.05])])   # filled cubes
    target = np.concatenate([floor, boxes])
    bare = F._grid(floor[floor[:, 0] < 1.0], F.GRID)                 # overlaps on the floor only
    cluttered = F._grid(np.concatenate([floor[floor[:, 0] > 1.1], boxes]), F.GRID)
    target = F._grid(target, F.GRID)
    assert F.overlap_planar(bare, target, np.eye(4)) > 0.9
    assert F.overlap_planar(cluttered, target, np.eye(4)) < F.overlap_planar(bare, target, np.eye(4)) - 0.2
    far = np.eye(4)
    far[:3, 3] = [10.0, 0.0, 0.0]
    assert np.isnan(F.overlap_planar(bare, target, far))
    assert "overlap_planar" in F.COLUMNS


def test_bands_summarise_by_the_measured_overlap():
    stats = [dict.fromkeys(F.COLUMNS, 1.0) | {"overlap": o} for o in (0.1, 0.2, 0.4, 0.9)]
    rows = F.summarise(stats)
    assert [(name.split("overlap ")[1], n) for name, n, _ in rows] == [("0%-30%", 2), ("30%-50%", 1), ("50%-100%", 1)]
    assert rows[0][2]["overlap"] == pytest.approx(0.15)


def test_smoothing_projects_a_rough_floor_onto_its_plane():
    rough = plane(20000, 0.01, 3)
    smooth = F.smooth_surface(rough, 16)
    before = F.cloud_stats(F._grid(rough, F.GRID))["noise_mm"]
    after = F.cloud_stats(F._grid(smooth, F.GRID))["noise_mm"]
    assert after < 0.5 * before
    lateral = np.linalg.norm(smooth[:, :2] - rough[:, :2], axis=1)       # moved along local normals
    assert np.median(lateral) < 0.002 and lateral.max() < 0.02
    assert np.abs(smooth[:, 2]).mean() < 0.5 * np.abs(rough[:, 2]).mean()
    np.testing.assert_array_equal(F.smooth_surface(rough, 0), rough)       # 0: unchanged
