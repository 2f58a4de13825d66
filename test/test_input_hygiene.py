"""Input hygiene: no-return zeros, non-finite points, range limits and flying pixels.

Clouds with the defects real sensors produce (an organized cloud with NaN holes and (0, 0, 0)
no-returns, depth-edge flying pixels out to 10 m) must give the pose, the grid and the counts
of the clean cloud.
"""

from __future__ import annotations

import numpy as np
import pytest

from cegc_ros.bounding import (EXTENT_TRIM, ISOLATED_MIN_NEIGHBOURS, ISOLATED_RADIUS, Dropped, bound_pair,
                               clean_points, drop_isolated, extent, robust_extent)
from cegc_ros.config import PreprocessConfig
from cegc_ros.data.corruption import add_flying_pixels
from cegc_ros.metrics import rotation_error_deg


def _room(n: int = 20000, seed: int = 0) -> np.ndarray:
    """A 4 x 3 x 2.5 m room seen from a sensor at the origin (inside the room)."""
    rng = np.random.default_rng(seed)
    k = n // 5
    lo = np.array([-1.0, -1.5, -1.2])
    hi = lo + [4.0, 3.0, 2.5]
    faces = []
    for axis, value in ((2, lo[2]), (0, hi[0]), (1, lo[1]), (1, hi[1]), (0, lo[0])):
        p = rng.uniform(lo, hi, (k, 3))
        p[:, axis] = value
        faces.append(p)
    return np.concatenate(faces)


def test_clean_points_drops_and_counts_each_defect():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (1000, 3)).astype(np.float32)
    pts[:100] = 0.0                                   # no returns
    pts[100:130, 1] = np.nan
    pts[130:140, 2] = np.inf
    r = np.linalg.norm(pts.astype(np.float64), axis=1)
    fin = np.isfinite(r)
    far = fin & (r > 7.0)
    near = fin & (r < 1.0) & (r > 0)
    out, d = clean_points(pts, min_range=1.0, max_range=7.0)
    assert d == Dropped(non_finite=40, no_return=100, out_of_range=int(far.sum() + near.sum()))
    assert len(out) == 1000 - d.total() and out.dtype == np.float32
    assert np.isfinite(out).all() and (np.linalg.norm(out, axis=1) >= 1.0).all()
    same, none = clean_points(pts[150:][fin[150:]])   # limits off: only defects go
    assert none == Dropped() and len(same) == fin[150:].sum()


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_drop_isolated_keeps_exactly_what_a_full_search_keeps(seed):
    """The cube pre-filter only skips searches: the kept set is the brute-force one's."""
    from scipy.spatial import cKDTree
    rng = np.random.default_rng(seed)
    surface = _room()[rng.choice(len(_room()), 6000, replace=False)]
    strays = rng.uniform(-6, 6, (150, 3))                       # lone returns far out
    near = surface[rng.choice(len(surface), 60)] + rng.normal(0, 0.15, (60, 3))   # borderline
    pairs = np.repeat(rng.uniform(-6, 6, (20, 3)), 2, axis=0) + rng.normal(0, 0.01, (40, 3))
    pts = np.concatenate([surface, strays, near, pairs])
    kept, n = drop_isolated(pts, seed=seed)
    # brute force: every point's neighbours within its radius, from the same spacing estimate,
    # the radius grown by the point's range over the sample's median range (at least 1x)
    tree = cKDTree(pts)
    probe = pts[np.random.default_rng(seed).choice(len(pts), 2000, replace=False)]
    spacing = np.median(tree.query(probe, k=2)[0][:, 1])
    scale = np.maximum(1.0, np.linalg.norm(pts, axis=1) / np.median(np.linalg.norm(probe, axis=1)))
    counts = np.array([len(c) - 1 for c in tree.query_ball_point(pts, ISOLATED_RADIUS * spacing * scale)])
    expect = pts[counts >= ISOLATED_MIN_NEIGHBOURS]
    assert n == len(pts) - len(expect) and 100 < n < 250          # the strays, not the surface
    np.testing.assert_array_equal(kept, expect)
    assert (scale[counts < ISOLATED_MIN_NEIGHBOURS] > 1).any()    # the grown radii were used


def _sweep(rng: np.random.Generator) -> np.ndarray:
    """A LiDAR-like sweep from a sensor 1.7 m above flat ground: 16 rings of 900 rays (0.4 deg
    apart) at -15 .. -1 deg elevation, returns out to 60 m, 2 cm range noise."""
    az = np.deg2rad(np.arange(900) * 0.4)
    rays = []
    for el in np.deg2rad(np.linspace(-15.0, -1.0, 16)):
        r = 1.7 / np.sin(-el) + rng.normal(0, 0.02, az.shape)
        keep = r < 60.0
        rays.append(np.c_[r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                          np.full(az.shape, -1.7)][keep])
    return np.concatenate(rays)


def test_far_returns_of_a_scanner_are_not_isolated_points():
    """A scanner's rays spread with the range, so the far rings of a LiDAR sweep are much
    sparser than its median spacing: each point's radius grows with its range, so they are
    kept, while lone returns in the air are still dropped."""
    rng = np.random.default_rng(0)
    ground = _sweep(rng)
    r = np.linalg.norm(ground, axis=1)
    strays = rng.uniform(-30, 30, (60, 3)) * [1, 1, 0.2] + [0, 0, 4.0]   # returns in the air
    pts = np.concatenate([ground, strays])
    kept, n = drop_isolated(pts)
    kept_ground = np.isin(ground.view([("", float)] * 3).ravel(), kept.view([("", float)] * 3).ravel())
    assert (r > 30).sum() > 1000 and kept_ground[r > 30].all()   # the far rings, every point
    assert kept_ground.mean() > 0.999
    assert 0.9 * len(strays) <= n <= len(strays) + 0.001 * len(ground)


def test_robust_extent_ignores_a_few_per_cent_of_flying_pixels():
    room = _room()
    flying = add_flying_pixels(room, 0.02, np.random.default_rng(1), near=3.0, far=10.0)
    assert extent(flying) > 1.8 * extent(room)        # the bounding box follows them out
    assert robust_extent(flying) == pytest.approx(robust_extent(room), rel=0.1)
    assert robust_extent(room, trim=0) == extent(room)
    assert 0 < EXTENT_TRIM < 0.1


def test_flying_pixels_move_points_along_their_rays_only():
    room = _room(2000)
    out = add_flying_pixels(room, 0.05, np.random.default_rng(2))
    moved = np.flatnonzero(np.abs(out - room).max(1) > 0)
    assert len(moved) == 100
    u_in = room[moved] / np.linalg.norm(room[moved], axis=1, keepdims=True)
    u_out = out[moved] / np.linalg.norm(out[moved], axis=1, keepdims=True)
    assert np.abs(u_in - u_out).max() < 1e-9                              # same ray
    r = np.linalg.norm(out[moved], axis=1)
    assert (r >= 3.0).all() and (r <= 12.0).all()
    with pytest.raises(ValueError, match="share"):
        add_flying_pixels(room, 1.5, np.random.default_rng(0))


def _organized_with_defects(cloud: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, int, int]:
    """An organized-cloud-like array: cloud rows, then NaN holes and (0, 0, 0) no-returns in
    between (as a depth image's invalid pixels), 2% of the valid points flying out to 5-10 m."""
    flying = add_flying_pixels(cloud, 0.02, rng, near=5.0, far=10.0)
    n_nan, n_zero = len(cloud) // 3, len(cloud) // 2
    rows = np.concatenate([flying, np.full((n_nan, 3), np.nan), np.zeros((n_zero, 3))])
    return rows[rng.permutation(len(rows))], n_nan, n_zero


def test_the_grid_and_the_counts_of_a_defective_pair_are_the_clean_pairs():
    rng = np.random.default_rng(3)
    src, tgt = _room(20000, 4), _room(20000, 5)
    clean = bound_pair(src, tgt, PreprocessConfig(), 16)
    (s_bad, nan_s, zero_s), (t_bad, nan_t, zero_t) = (_organized_with_defects(c, rng) for c in (src, tgt))
    bad = bound_pair(s_bad, t_bad, PreprocessConfig(), 16)
    assert bad.voxel == pytest.approx(clean.voxel, rel=0.1)
    flyers = round(0.02 * len(src))
    for d, n_nan, n_zero in zip(bad.dropped, (nan_s, nan_t), (zero_s, zero_t)):
        assert (d.non_finite, d.no_return, d.out_of_range) == (n_nan, n_zero, 0)
        assert 0.9 * flyers <= d.isolated <= flyers + 0.002 * len(src)   # the flying pixels
    assert clean.dropped[0].isolated <= 0.002 * len(src)                  # a clean room loses ~none
    assert bad.input_points == (len(src), len(tgt))
    # max_range takes the flying pixels out as well (the room is within 3.7 m of the sensor).
    ranged = bound_pair(s_bad, t_bad, PreprocessConfig(max_range=4.5), 16)
    assert ranged.dropped[0].out_of_range == round(0.02 * len(src))
    assert ranged.input_points[0] == len(src) - round(0.02 * len(src))


def test_a_pair_with_sensor_defects_registers_as_the_clean_pair():
    from cegc_ros.data.protocols import make_pair
    from cegc_ros.engine import Registrar

    p = make_pair("fragments", "test", 3)            # two Kinect-like fragments, 39% overlap
    reg = Registrar.from_checkpoint(device="cpu")
    clean = reg.register(p.source, p.target)
    rng = np.random.default_rng(6)
    (s_bad, nan_s, zero_s), (t_bad, _, _) = (_organized_with_defects(c, rng) for c in (p.source, p.target))
    bad = reg.register(s_bad, t_bad)
    d = bad.dropped[0]
    assert (d.non_finite, d.no_return, d.out_of_range) == (nan_s, zero_s, 0)
    assert 0.9 * round(0.02 * len(p.source)) <= d.isolated                # the flying pixels
    assert bad.voxel_size == pytest.approx(clean.voxel_size, rel=0.1)
    G = p.T_target_source
    for r in (clean, bad):
        assert r.valid
        assert rotation_error_deg(G[:3, :3], r.T_target_source[:3, :3]) < 2.0
        assert np.linalg.norm(G[:3, 3] - r.T_target_source[:3, 3]) < 0.1


def test_a_pair_gets_the_same_flying_pixels_whichever_set_it_is_drawn_into():
    from dataclasses import dataclass

    from cegc_ros.data.corruption import with_flying_pixels

    @dataclass
    class P:
        source: np.ndarray
        target: np.ndarray

    pairs = [P(_room(1000, k), _room(1000, k + 10)) for k in range(3)]
    a = with_flying_pixels(pairs, 0.05, [7, 8, 9])
    b = with_flying_pixels(pairs[1:], 0.05, [8, 9])               # another selection, same keys
    np.testing.assert_array_equal(a[1].source, b[0].source)
    np.testing.assert_array_equal(a[2].target, b[1].target)
    moved = np.abs(a[0].source - pairs[0].source).max(1) > 0
    assert moved.sum() == 50 and not np.array_equal(a[0].source, a[0].target)
    assert np.array_equal(pairs[0].source, _room(1000, 0))         # the originals are untouched


@pytest.mark.parametrize("case", ["dense", "sparse_box"])
def test_crowded_cells_count_the_same_by_table_or_by_sort(case):
    """A dense cloud counts its cubes with a table, a sparse one in a big box (a LiDAR sweep:
    hundreds of cells a point) by np.unique; both are the plain count per cube."""
    from cegc_ros.bounding import _crowded_cells
    from cegc_ros.geometry import TABLE_CELLS_PER_POINT, use_table
    rng = np.random.default_rng(7)
    pts = {"dense": rng.uniform(0, 1, (2000, 3)) * [2.0, 2.0, 0.05],
           "sparse_box": np.r_[np.repeat(rng.uniform(0, 80, (300, 3)) * [1, 1, 0.04], 5, axis=0)
                               + rng.normal(0, 0.02, (1500, 3)),        # returns in clumps
                               rng.uniform(0, 80, (1500, 3)) * [1, 1, 0.04]]}[case]
    cell = {"dense": 0.05, "sparse_box": 0.5}[case]
    lo = pts.min(0)
    key = np.floor((pts - lo) / cell).astype(np.int64)
    dims = key.max(0) + 1
    cells = float(np.prod(dims.astype(float)))
    assert use_table(cells, len(pts)) == (case == "dense")
    assert (cells <= TABLE_CELLS_PER_POINT * len(pts)) == (case == "dense")
    ids = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
    _, inverse, counts = np.unique(ids, return_inverse=True, return_counts=True)
    for at_least in (2, 3):
        want = counts[inverse] >= at_least
        got = _crowded_cells(pts, cell, at_least)
        assert np.array_equal(got, want) and 0 < want.sum() < len(pts)


@pytest.mark.parametrize("case", ["dense", "sparse_box", "huge_extent"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_bound_grid_has_open3ds_voxels_and_means_in_index_order(case, dtype):
    """geometry.grid_means (the bound stage's grid) gives exactly the points of Open3D's
    voxel_down_sample (geometry.voxel_downsample), by each of its three ways of counting (a
    table, np.unique of cell ids, np.unique of index rows when ids would overflow), ordered by
    voxel index: x, then y, then z."""
    from cegc_ros.geometry import grid_means, voxel_downsample
    rng = np.random.default_rng(11)
    pts, voxel = {"dense": (_room(20000, 3), 0.05),
                  "sparse_box": (np.repeat(rng.uniform(0, 80, (1000, 3)) * [1, 1, 0.04], 3, axis=0)
                                 + rng.normal(0, 0.02, (3000, 3)), 0.3),          # returns in clumps
                  "huge_extent": (np.r_[rng.uniform(0, 1, (2000, 3)), [[9e5, 9e5, 9e5]]], 0.1)}[case]
    pts = pts.astype(dtype)
    got, want = grid_means(pts, voxel), voxel_downsample(pts, voxel)
    assert got.dtype == np.float32 and got.shape == want.shape and len(got) < 0.8 * len(pts)
    sort = lambda a: a[np.lexsort(a.T[::-1])]  # noqa: E731
    np.testing.assert_array_equal(sort(got), sort(want))
    origin = pts.astype(np.float64).min(0) - 0.5 * voxel
    index = np.floor((got.astype(np.float64) - origin) / voxel).astype(np.int64)   # each mean's voxel
    assert len(np.unique(index, axis=0)) == len(got)
    assert np.array_equal(np.lexsort(index.T[::-1]), np.arange(len(got)))        # in index order
    np.testing.assert_array_equal(grid_means(pts, 0.0), pts.astype(np.float32))
