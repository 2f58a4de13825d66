"""Sensor models that turn a room and a short sensor path into one fragment (a point cloud).

Two kinds, both rendered with Open3D ray casting on a :class:`cegc_ros.data.scenes.Room`:

:class:`KinectSensor`
    A Kinect-v1-style depth camera (:func:`cegc_ros.data.scenes.render_depth`): axial noise
    growing with the square of the depth, 1/8-pixel disparity quantisation, lateral jitter,
    missing data at grazing incidence, at depth edges and at random, readings only in
    [0.5, 4.5] m. A fragment fuses several depth frames along a short handheld path into the
    first frame's camera frame (optical: x right, y down, z forward), kept inside a 3 m TSDF-like
    cube and averaged per 2.5 cm voxel, as 3DMatch fragments are.
:class:`LidarSensor`
    A rotating multi-beam LiDAR (32 rings over -25..+15 deg, 1024 azimuth steps, 10 Hz):
    per-beam elevation and azimuth jitter, Gaussian range noise growing with range, dropouts at
    grazing incidence and at random, readings only in [0.5, 60] m. A fragment accumulates a few
    sweeps along a short robot path into the first sweep's sensor frame (x forward, y left,
    z up; no motion skew within a sweep), averaged per voxel.

A sensor's ``fragment(room, poses, rng)`` takes the path as (K, 4, 4) T_world_sensor poses (the
frames actually rendered) and returns (N, 3) float32 points in the frame of ``poses[0]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cegc_ros.data.scenes import (
    FragmentConfig,
    KinectCamera,
    NoiseModel,
    Room,
    fuse_depth_frames,
    voxel_downsample,
)

SENSORS = ("kinect", "lidar")


@dataclass(frozen=True)
class KinectSensor:
    """Kinect-v1-style depth camera; fragments fuse ``frames`` depth frames of a 30 fps path.

    ``frames`` handheld frames span the fragment's path (3DMatch fuses 50); every
    ``fusion.frame_step``-th of them is rendered, at every ``fusion.pixel_stride``-th pixel.
    """

    fusion: FragmentConfig = field(default_factory=lambda: FragmentConfig(
        camera=KinectCamera(max_depth=4.5), noise=NoiseModel()))
    frames: int = 50
    fps: float = 30.0
    name: str = "kinect"

    @property
    def voxel_size(self) -> float:
        return self.fusion.voxel_size

    def fragment(self, room: Room, poses: np.ndarray, rng: np.random.Generator | None
                 ) -> np.ndarray:
        """Fuse depth frames rendered at ``poses`` (K, 4, 4) into (N, 3) float32 points."""
        return fuse_depth_frames(room, poses, rng, self.fusion)


@dataclass(frozen=True)
class LidarSensor:
    """Rotating multi-beam LiDAR; fragments accumulate ``sweeps`` sweeps at ``rate_hz``.

    Range noise sigma(r) = range_sigma_a + range_sigma_b * r (metres).
    """

    beams: int = 32
    fov_down_deg: float = -25.0
    fov_up_deg: float = 15.0
    azimuth_steps: int = 1024
    min_range: float = 0.5
    max_range: float = 60.0
    range_sigma_a: float = 0.01
    range_sigma_b: float = 0.001
    angle_jitter_deg: float = 0.03
    grazing_start_deg: float = 75.0
    grazing_end_deg: float = 88.0
    random_drop_prob: float = 0.03
    sweeps: int = 4
    rate_hz: float = 10.0
    voxel_size: float = 0.025
    name: str = "lidar"

    def elevations(self) -> np.ndarray:
        """(beams,) beam elevation angles, radians."""
        return np.radians(np.linspace(self.fov_down_deg, self.fov_up_deg, self.beams))

    def sweep(self, room: Room, T_world_lidar: np.ndarray, rng: np.random.Generator | None
              ) -> np.ndarray:
        """One 360-degree sweep: (N, 3) float32 points in the LiDAR frame (NaN-free)."""
        import open3d as o3d

        el = self.elevations()[:, None]
        phase = rng.uniform(0, 2 * np.pi / self.azimuth_steps) if rng is not None else 0.0
        az = (np.arange(self.azimuth_steps) * 2 * np.pi / self.azimuth_steps + phase)[None, :]
        shape = (self.beams, self.azimuth_steps)
        if rng is not None and self.angle_jitter_deg > 0:
            j = np.radians(self.angle_jitter_deg)
            el = el + rng.normal(0, j, shape)
            az = az + rng.normal(0, j, shape)
        el, az = np.broadcast_to(el, shape), np.broadcast_to(az, shape)
        d_local = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
        R = T_world_lidar[:3, :3]
        rays = np.empty(shape + (6,), np.float32)
        rays[..., :3] = T_world_lidar[:3, 3]
        rays[..., 3:] = d_local @ R.T                          # unit directions: t_hit = range
        hit = room.scene.cast_rays(o3d.core.Tensor(rays))
        r = hit["t_hit"].numpy().astype(np.float64)
        ok = np.isfinite(r)
        if rng is not None:
            n = hit["primitive_normals"].numpy()
            cos_inc = np.abs(np.einsum("bac,bac->ba", n, rays[..., 3:]))
            inc = np.degrees(np.arccos(np.clip(cos_inc, 0.0, 1.0)))
            p_drop = np.clip((inc - self.grazing_start_deg)
                             / (self.grazing_end_deg - self.grazing_start_deg), 0.0, 1.0)
            p_drop = 1.0 - (1.0 - p_drop) * (1.0 - self.random_drop_prob)
            ok &= rng.random(shape) >= p_drop
            r = r + rng.standard_normal(shape) * (self.range_sigma_a + self.range_sigma_b
                                                  * np.where(ok, r, 0.0))
        ok &= (r >= self.min_range) & (r <= self.max_range)
        return (d_local[ok] * r[ok, None]).astype(np.float32)

    def fragment(self, room: Room, poses: np.ndarray, rng: np.random.Generator | None
                 ) -> np.ndarray:
        """Accumulate sweeps taken at ``poses`` (K, 4, 4) into (N, 3) float32 points in the
        frame of the first sweep, averaged per ``voxel_size`` voxel."""
        T_frag_world = np.linalg.inv(poses[0])
        chunks = []
        for T_world_lidar in poses:
            p = self.sweep(room, T_world_lidar, rng).astype(np.float64)
            T = T_frag_world @ T_world_lidar
            chunks.append(p @ T[:3, :3].T + T[:3, 3])
        pts = np.concatenate(chunks)
        return voxel_downsample(pts, self.voxel_size).astype(np.float32)


def get_sensor(name: str) -> KinectSensor | LidarSensor:
    """The default sensor model of a name in SENSORS."""
    if name == "kinect":
        return KinectSensor()
    if name == "lidar":
        return LidarSensor()
    raise ValueError(f"unknown sensor {name!r}; expected one of {SENSORS}")
