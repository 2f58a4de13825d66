"""Procedural rooms, Kinect rendering and fragments (cegc_ros.data.scenes)."""

from __future__ import annotations

import numpy as np
import pytest

from cegc_ros.data import scenes


def _wall_room(distance: float = 2.0) -> scenes.Room:
    """A single large wall at x = distance (a plane facing the origin)."""
    mb = scenes._MeshBuilder()
    mb.box((0.01, 40.0, 40.0), (distance + 0.005, 0.0, 0.0))
    v, t = mb.arrays()
    return scenes.Room(0, (1.0, 1.0, 1.0), v, t, [], np.zeros((1, 3)),
                       (np.zeros(3), np.ones(3)))


def _looking_along_x() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = scenes.camera_rotation(np.zeros(1), np.zeros(1), np.zeros(1))[0]
    return T


def test_render_returns_z_depth_not_range():
    z, u, v = scenes.render_depth(_wall_room(2.0), _looking_along_x(), rng=None, pixel_stride=4)
    assert z.shape == (120, 160)
    assert u[0] == 0.5 and v[-1] == 476.5          # pixel centres
    # Every pixel of a fronto-parallel wall has z = 2, even at the image corners where the
    # range along the ray is 2 * sqrt(1 + ((320 - 0.5) / 585)^2 + ...) ~ 2.34.
    np.testing.assert_allclose(z, 2.0, atol=1e-5)


def test_kinect_noise_level_and_range():
    rng = np.random.default_rng(0)
    z, _, _ = scenes.render_depth(_wall_room(2.0), _looking_along_x(), rng=rng, pixel_stride=2)
    ok = np.isfinite(z)
    assert 0.9 < ok.mean() < 0.99                  # 2 % random dropouts, no edges
    sigma = 0.0012 + 0.0019 * (2.0 - 0.4) ** 2     # 6.1 mm axial
    q = 2.0**2 / (585 * 0.075) / 8                 # 11.4 mm disparity step at 2 m
    expected = np.hypot(sigma, q / np.sqrt(12))    # ~6.9 mm
    assert abs(np.std(z[ok]) - expected) < 0.0015
    assert abs(np.mean(z[ok]) - 2.0) < 0.002
    far, _, _ = scenes.render_depth(_wall_room(5.0), _looking_along_x(), rng=rng, pixel_stride=8)
    assert not np.isfinite(far).any()              # beyond the 4 m Kinect range


def test_grazing_surfaces_drop_out():
    T = np.eye(4)
    T[:3, :3] = scenes.camera_rotation(np.zeros(1), np.radians([-5.0]), np.zeros(1))[0]
    floor = scenes._MeshBuilder()
    floor.box((40.0, 40.0, 0.01), (0.0, 0.0, -0.305))  # floor 0.3 m below the camera
    v, t = floor.arrays()
    room = scenes.Room(0, (1.0, 1.0, 1.0), v, t, [], np.zeros((1, 3)), (np.zeros(3), np.ones(3)))
    clean, _, _ = scenes.render_depth(room, T, rng=None, pixel_stride=4)
    noisy, _, _ = scenes.render_depth(room, T, rng=np.random.default_rng(1), pixel_stride=4)
    seen = np.isfinite(clean)
    # Rows just below the horizon see the floor at > 85 deg incidence: (almost) all dropped.
    grazing_rows = seen[:, 80] & (np.arange(120) < 75)
    assert grazing_rows.sum() > 3
    assert np.isfinite(noisy[grazing_rows, 80]).mean() < 0.2
    assert np.isfinite(noisy[seen]).mean() > 0.3


def test_fragment_is_reproducible_and_seed_dependent():
    a = scenes.make_fragment(11, 2)
    b = scenes.make_fragment(11, 2)
    c = scenes.make_fragment(12, 2)
    assert np.array_equal(a.points, b.points)
    assert np.array_equal(a.T_world_fragment, b.T_world_fragment)
    assert a.points.dtype == np.float32 and a.points.shape[1] == 3
    assert len(a.points) > 5000
    assert a.points.shape != c.points.shape or not np.array_equal(a.points, c.points)
    assert scenes.get_room(11).size != scenes.get_room(12).size
    # Inside 3DMatch's TSDF volume of the first camera and voxel-downsampled to 2.5 cm.
    assert a.points[:, 2].min() >= 0.5 and a.points[:, 2].max() <= 3.5
    assert np.abs(a.points[:, :2]).max() <= 1.5
    keys = np.floor(a.points / 0.025).astype(np.int64)
    assert len(np.unique(keys, axis=0)) >= 0.9 * len(keys)


def test_fragment_points_lie_on_the_room_surfaces():
    frag = scenes.make_fragment(11, 2)
    room = scenes.get_room(11)
    import open3d as o3d
    world = frag.points @ frag.T_world_fragment[:3, :3].T.astype(np.float32) \
        + frag.T_world_fragment[:3, 3].astype(np.float32)
    d = room.scene.compute_distance(o3d.core.Tensor(world.astype(np.float32))).numpy()
    # Noise (~1 cm at 3 m before averaging) and voxel averaging across corners.
    assert np.median(d) < 0.01
    assert np.percentile(d, 95) < 0.03


def test_trajectory_is_smooth_and_handheld():
    poses = scenes.camera_trajectory(scenes.get_room(11), 300)
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-9)
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) * 30   # m/s at 30 fps
    assert np.median(step) < 1.0 and step.max() < 2.0
    lo, hi = scenes.get_room(11).camera_box
    assert np.all(poses[:, :3, 3] >= lo - 0.21) and np.all(poses[:, :3, 3] <= hi + 0.21)


def test_voxel_downsample_averages_per_voxel():
    p = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.3, 0.3, 0.3]], np.float32)
    out = scenes.voxel_downsample(p, 0.025)
    np.testing.assert_allclose(out, [[0.015, 0.015, 0.015], [0.3, 0.3, 0.3]], atol=1e-7)


def test_voxel_downsample_keeps_voxels_apart_when_their_ids_would_overflow():
    """A cloud spanning 9e5 m at 0.1 m voxels: more cells than int64 ids can number, so the
    voxels are told apart by their index rows; still one mean per voxel, in index order."""
    rng = np.random.default_rng(5)
    p = np.r_[rng.uniform(0, 1, (2000, 3)), [[9e5, 9e5, 9e5]]]
    out = scenes.voxel_downsample(p, 0.1)
    key = np.floor(p / 0.1).astype(np.int64)
    voxels, inverse = np.unique(key, axis=0, return_inverse=True)      # sorted: x, then y, then z
    want = np.stack([np.bincount(inverse.ravel(), weights=p[:, k]) for k in range(3)], 1)
    want /= np.bincount(inverse.ravel())[:, None]
    assert len(voxels) < 0.8 * len(p)
    np.testing.assert_array_equal(out, want)


def test_fragment_index_is_checked():
    with pytest.raises(ValueError, match="fragment index"):
        scenes.make_fragment(11, scenes.MAX_FRAGMENTS)
