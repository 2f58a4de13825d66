"""Sensor models (cegc_ros.data.sensors): Kinect-style range, noise, fusion; LiDAR rings."""

from __future__ import annotations

import numpy as np

from cegc_ros.data import scenes, sensors


def _room(boxes: list[tuple[tuple[float, float, float], tuple[float, float, float]]]
          ) -> scenes.Room:
    mb = scenes._MeshBuilder()
    for size, centre in boxes:
        mb.box(size, centre)
    v, t = mb.arrays()
    return scenes.Room(0, (1.0, 1.0, 1.0), v, t, [], np.zeros((1, 3)), (np.zeros(3), np.ones(3)))


def _wall_at(x: float) -> scenes.Room:
    return _room([((0.01, 60.0, 60.0), (x + 0.005, 0.0, 0.0))])


def _camera_along_x(n: int = 1) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = scenes.camera_rotation(np.zeros(n), np.zeros(n), np.zeros(n))
    return T


def test_kinect_noise_grows_with_range_squared_and_range_is_limited():
    kin = sensors.KinectSensor()
    cam = kin.fusion.camera
    assert (cam.min_depth, cam.max_depth) == (0.5, 4.5)
    rng = np.random.default_rng(0)
    std = {}
    for d in (1.0, 2.0, 4.0):
        z, _, _ = scenes.render_depth(_wall_at(d), _camera_along_x()[0], rng, cam,
                                      kin.fusion.noise, pixel_stride=4)
        ok = np.isfinite(z)
        assert ok.mean() > 0.9
        std[d] = float(np.std(z[ok] - d))
    # Axial sigma a + b (z - 0.4)^2 plus disparity quantisation ~ z^2: both grow with z^2.
    assert std[2.0] > 2.5 * std[1.0] and std[4.0] > 3.0 * std[2.0], std
    for d in (0.3, 5.0):                                # closer than 0.5 m / beyond 4.5 m
        z, _, _ = scenes.render_depth(_wall_at(d), _camera_along_x()[0], rng, cam,
                                      kin.fusion.noise, pixel_stride=8)
        assert not np.isfinite(z).any()


def test_kinect_drops_depth_edges():
    # A near box in front of a far wall: pixels along the box silhouette go missing.
    room = _room([((0.01, 60.0, 60.0), (3.005, 0.0, 0.0)), ((0.2, 0.6, 0.6), (1.5, 0.0, 0.0))])
    kin = sensors.KinectSensor()
    z, _, _ = scenes.render_depth(room, _camera_along_x()[0], np.random.default_rng(1),
                                  kin.fusion.camera, kin.fusion.noise, pixel_stride=2)
    clean, _, _ = scenes.render_depth(room, _camera_along_x()[0], None, kin.fusion.camera,
                                      kin.fusion.noise, pixel_stride=2)
    near = np.abs(clean - 1.4) < 0.01
    # Two-pixel bands across the left and right silhouettes (the noisy silhouette moves by
    # the lateral jitter), and the box's interior.
    edge = (near ^ np.roll(near, 1, axis=1)) | (near ^ np.roll(near, -1, axis=1))
    edge[:, [0, -1]] = False
    rows = near.any(axis=1)
    edge[~rows] = False
    interior = near & np.roll(near, 3, axis=1) & np.roll(near, -3, axis=1)
    assert edge.sum() > 40
    # 70 % of edge pixels are dropped; inside only the 2 % random dropouts.
    assert np.isfinite(z[edge]).mean() < 0.5
    assert np.isfinite(z[interior]).mean() > 0.9


def test_kinect_fragment_fuses_frames_in_the_first_camera_frame():
    kin = sensors.KinectSensor()
    poses = _camera_along_x(4)
    poses[:, 1, 3] = np.linspace(0.0, 0.3, 4)           # the camera slides 0.3 m to the left
    pts = kin.fragment(_wall_at(2.0), poses, np.random.default_rng(2))
    assert pts.dtype == np.float32 and len(pts) > 1000
    assert abs(np.median(pts[:, 2]) - 2.0) < 0.01       # optical z = depth of the wall
    # Frames 2..4 see further left (optical -x) than frame 1 alone.
    first = kin.fragment(_wall_at(2.0), poses[:1], np.random.default_rng(2))
    assert pts[:, 0].min() < first[:, 0].min() - 0.25
    vox = np.floor(pts / kin.voxel_size).astype(np.int64)
    assert len(np.unique(vox, axis=0)) > 0.95 * len(pts)    # about one point per voxel


def test_lidar_rings_range_limits_and_noise():
    lid = sensors.LidarSensor()
    # A closed 20 m box around the sensor at its centre, 1 m above the floor.
    room = _room([((20.0, 20.0, 0.1), (0.0, 0.0, -1.05)), ((20.0, 20.0, 0.1), (0.0, 0.0, 4.05)),
                  ((0.1, 20.0, 5.0), (10.05, 0.0, 1.5)), ((0.1, 20.0, 5.0), (-10.05, 0.0, 1.5)),
                  ((20.0, 0.1, 5.0), (0.0, 10.05, 1.5)), ((20.0, 0.1, 5.0), (0.0, -10.05, 1.5))])
    clean = lid.sweep(room, np.eye(4), None)
    el = np.degrees(np.arctan2(clean[:, 2], np.hypot(clean[:, 0], clean[:, 1])))
    rings = np.unique(np.round(el, 1))
    assert len(rings) == lid.beams                      # one elevation per beam
    assert el.min() > lid.fov_down_deg - 0.1 and el.max() < lid.fov_up_deg + 0.1
    noisy = lid.sweep(room, np.eye(4), np.random.default_rng(3))
    assert 0.8 * len(clean) < len(noisy) < len(clean)   # dropouts
    # Range noise on the x = 10 wall (horizontal beams): sigma ~ 0.01 + 0.001 r.
    on_wall = (noisy[:, 0] > 9.0) & (np.abs(noisy[:, 1]) < 2.0)
    err = noisy[on_wall, 0] - 10.0
    r = np.linalg.norm(noisy[on_wall], axis=1)
    expected = 0.01 + 0.001 * r.mean()
    assert abs(np.std(err) - expected) < 0.3 * expected
    far = lid.sweep(_wall_at(70.0), np.eye(4), None)    # beyond the 60 m range
    assert len(far) == 0
    # Inside a closed 0.5 m cube every range is < 0.44 m, under the 0.5 m minimum.
    cube = _room([((0.5, 0.5, 0.01), (0.0, 0.0, z)) for z in (-0.255, 0.255)]
                 + [((0.01, 0.5, 0.5), (x, 0.0, 0.0)) for x in (-0.255, 0.255)]
                 + [((0.5, 0.01, 0.5), (0.0, y, 0.0)) for y in (-0.255, 0.255)])
    assert len(lid.sweep(cube, np.eye(4), None)) == 0
    assert len(lid.sweep(cube, np.eye(4), np.random.default_rng(4))) == 0


def test_lidar_fragment_accumulates_sweeps_in_the_first_sweep_frame():
    lid = sensors.LidarSensor()
    room = _wall_at(5.0)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, 1.0, 2.0]                    # driving 2 m towards the wall
    pts = lid.fragment(room, poses, None)
    wall = pts[np.abs(pts[:, 0] - 5.0) < 0.05]
    assert len(wall) > 0.9 * len(pts)                   # everything lands on x = 5 (frame 0)
