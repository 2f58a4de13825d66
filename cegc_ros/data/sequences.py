"""Sequences of consecutive clouds with ground-truth poses, for odometry (sequential mode).

Three sources:

* :func:`make_room_sequence`: a handheld Kinect moving through a procedural room of
  :mod:`cegc_ros.data.scenes` (the same trajectory generator as the fragments). Each cloud is one
  noisy depth frame back-projected into its camera frame, or with ``frames_per_cloud > 1`` a
  short fragment fusing that many consecutive frames in the first one's camera frame.
* :func:`make_lidar_sequence`: a spinning multi-beam LiDAR (:class:`cegc_ros.data.sensors.
  LidarSensor`) on a ground robot driving the same kind of loop, one sweep per cloud; ``scale``
  enlarges the whole world (room, path, range noise) into a hall or a yard.
* :func:`load_bunny_sequence`: the Stanford bunny range scans (``../shared/data/real/bunny``) as
  an object sequence (a turntable ring by default), poses chained from the pairwise ground truth.

Poses are ``T_world_cloud`` (maps cloud points into one world frame). Odometry starts at the
first cloud, so compare against ``Sequence.relative_poses()`` = ``inv(T_world_0) @ T_world_k``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import scenes

FRAME_ID = "cegc_cloud"
BUNNY_RING = ("bun000", "bun045", "bun090", "bun180", "bun270", "bun315")


@dataclass
class Sequence:
    """Consecutive clouds of one sensor with their ground truth.

    clouds: list of (N_k, 3) float32, metres, each in its own sensor frame.
    poses: (K, 4, 4) float64 T_world_cloud, or None without ground truth.
    stamps_ns: (K,) int64 header stamps, increasing.
    """

    clouds: list[np.ndarray]
    poses: np.ndarray | None
    stamps_ns: np.ndarray
    frame_id: str = FRAME_ID
    info: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.clouds)

    def relative_poses(self) -> np.ndarray:
        """(K, 4, 4) ground-truth poses in the first cloud's frame (the odometry frame)."""
        if self.poses is None:
            raise ValueError("sequence has no ground-truth poses")
        return np.linalg.inv(self.poses[0]) @ self.poses

    def subset(self, keep: np.ndarray | list[int]) -> Sequence:
        """The frames at indices ``keep`` (e.g. to drop a stretch), stamps and poses kept."""
        idx = [int(i) for i in keep]
        return Sequence([self.clouds[i] for i in idx],
                        None if self.poses is None else self.poses[idx],
                        self.stamps_ns[idx], self.frame_id, dict(self.info))


def backproject(depth: np.ndarray, u: np.ndarray, v: np.ndarray,
                camera: scenes.KinectCamera) -> np.ndarray:
    """Depth frame (H', W') with pixel centres u (W',), v (H',) -> (N, 3) float32 camera-frame
    points (optical frame: x right, y down, z forward) of the finite pixels, row-major order."""
    vv, uu = np.nonzero(np.isfinite(depth))
    z = depth[vv, uu]
    x = ((u[uu] - camera.cx) / camera.fx).astype(np.float32) * z
    y = ((v[vv] - camera.cy) / camera.fy).astype(np.float32) * z
    return np.stack([x, y, z], axis=1).astype(np.float32)


def robot_trajectory(room: scenes.Room, num_frames: int, fps: float = 30.0, speed: float = 0.4,
                     height: float = 1.2, pitch_deg: float = -20.0, clearance: float = 0.3,
                     ) -> np.ndarray:
    """Poses T_world_camera (num_frames, 4, 4) of a forward-looking camera on a ground robot.

    The robot drives at ``speed`` m/s round an ellipse about the room's centre that keeps
    ``clearance`` metres from every surface (the first of 200 seeded candidates that does),
    the camera ``height`` m above the floor, pitched ``pitch_deg``, looking along the path
    with a slow +-20 deg sway (so rotation and translation are not locked together).
    Deterministic from the room's seed. ValueError when no clear ellipse is found.
    """
    import open3d as o3d

    rng = np.random.default_rng([room.seed, 0x20B])
    sx, sy, _ = room.size
    u = np.linspace(0.0, 2 * np.pi, 721)[:-1]
    for _ in range(200):
        cx, cy = sx / 2 + rng.uniform(-0.1, 0.1) * sx, sy / 2 + rng.uniform(-0.1, 0.1) * sy
        ax, ay = rng.uniform(0.15, 0.35) * sx, rng.uniform(0.15, 0.35) * sy
        loop = np.stack([cx + ax * np.cos(u), cy + ay * np.sin(u), np.full_like(u, height)], 1)
        dist = room.scene.compute_distance(o3d.core.Tensor(loop.astype(np.float32))).numpy()
        if dist.min() >= clearance:
            break
    else:
        raise ValueError(f"room {room.seed}: no ellipse keeps {clearance} m from every surface")
    closed = np.vstack([loop, loop[:1]])
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))]   # (721,)
    s = (np.arange(num_frames) * speed / fps) % arc[-1]
    pos = np.stack([np.interp(s, arc, closed[:, k]) for k in range(3)], 1)
    uu = np.interp(s, arc, np.r_[u, 2 * np.pi])
    heading = np.arctan2(ay * np.cos(uu), -ax * np.sin(uu))          # d/du of the ellipse
    t = np.arange(num_frames) / fps
    yaw = heading + np.radians(20.0) * np.sin(2 * np.pi * t / 6.0)
    pitch = np.full(num_frames, np.radians(pitch_deg)) + np.radians(3.0) * np.sin(t)
    roll = np.radians(1.0) * np.sin(0.7 * t)
    poses = np.tile(np.eye(4), (num_frames, 1, 1))
    poses[:, :3, :3] = scenes.camera_rotation(yaw, pitch, roll)
    poses[:, :3, 3] = pos
    return poses


TRAJECTORIES = ("robot", "handheld")


def make_room_sequence(scene_seed: int, num_clouds: int, frame_step: int = 3,
                       frames_per_cloud: int = 1, first_frame: int = 0, pixel_stride: int = 4,
                       voxel_size: float = 0.0, noise: bool = True, fps: float = 30.0,
                       trajectory: str = "robot",
                       start_ns: int = 1_700_000_000 * 10**9) -> Sequence:
    """A camera sequence through the room of ``scene_seed``.

    ``trajectory``: "robot" (:func:`robot_trajectory`: a forward-looking camera on a ground
    robot, walls and furniture in view) or "handheld" (:func:`cegc_ros.data.scenes.
    camera_trajectory`, the fragments' scanning motion: often mostly floor and one wall in view,
    which leaves a direction that geometry does not constrain).

    Cloud k starts at trajectory frame ``first_frame + k * frame_step`` (30 fps trajectory, so
    ``frame_step=3`` is a 10 Hz sensor) and fuses ``frames_per_cloud`` consecutive frames (1 = a
    single depth frame) in that frame's camera coordinates. Depth is rendered at every
    ``pixel_stride``-th pixel with the Kinect noise model (``noise=False``: exact depth), then
    averaged per voxel of ``voxel_size`` metres (0: kept as rendered). Stamps follow the
    trajectory's clock. Deterministic from the arguments.
    """
    if num_clouds < 1 or frame_step < 1 or frames_per_cloud < 1 or first_frame < 0:
        raise ValueError(f"num_clouds, frame_step, frames_per_cloud must be >= 1 and first_frame "
                         f">= 0; got {num_clouds}, {frame_step}, {frames_per_cloud}, {first_frame}")
    if trajectory not in TRAJECTORIES:
        raise ValueError(f"trajectory must be one of {TRAJECTORIES}, got {trajectory!r}")
    room = scenes.get_room(int(scene_seed))
    last = first_frame + (num_clouds - 1) * frame_step + frames_per_cloud
    poses_all = (robot_trajectory(room, last, fps=fps) if trajectory == "robot"
                 else scenes.camera_trajectory(room, last, fps=fps))
    camera = scenes.KinectCamera()
    noise_model = scenes.NoiseModel() if noise else scenes.NO_NOISE
    clouds, poses, stamps = [], [], []
    for k in range(num_clouds):
        f0 = first_frame + k * frame_step
        T_cloud_world = np.linalg.inv(poses_all[f0])
        chunks = []
        for f in range(f0, f0 + frames_per_cloud):
            rng = np.random.default_rng([int(scene_seed), f, 0x5E0]) if noise else None
            depth, u, v = scenes.render_depth(room, poses_all[f], rng, camera, noise_model,
                                              pixel_stride)
            p = backproject(depth, u, v, camera).astype(np.float64)
            T = T_cloud_world @ poses_all[f]
            chunks.append(p @ T[:3, :3].T + T[:3, 3])
        pts = np.concatenate(chunks).astype(np.float32)
        if voxel_size > 0:
            pts = scenes.voxel_downsample(pts, voxel_size)
        clouds.append(pts)
        poses.append(poses_all[f0])
        stamps.append(int(start_ns + round(f0 / fps * 1e9)))
    info = {"source": "room", "trajectory": trajectory, "scene_seed": int(scene_seed),
            "frame_step": frame_step,
            "frames_per_cloud": frames_per_cloud, "first_frame": first_frame,
            "pixel_stride": pixel_stride, "voxel_size": voxel_size, "noise": noise, "fps": fps,
            "room_size": list(room.size)}
    return Sequence(clouds, np.stack(poses), np.asarray(stamps, np.int64), FRAME_ID, info)


def make_lidar_sequence(scene_seed: int, num_clouds: int, scale: float = 1.0,
                        rate_hz: float = 10.0, height: float = 1.2,
                        start_ns: int = 1_700_000_000 * 10**9) -> Sequence:
    """Sweeps of a LiDAR on a ground robot in the room of ``scene_seed``, ``rate_hz`` apart.

    The robot drives :func:`robot_trajectory`'s loop (0.4 m/s, +-20 deg sway) with the sensor
    ``height`` m above the floor, level (z up, x along the view); one noisy 32-beam sweep per
    cloud (:class:`cegc_ros.data.sensors.LidarSensor`, no motion distortion), in the sensor
    frame. ``scale`` multiplies every length (room, path, points, noise): 10 turns a 3-5 m room
    into a 30-50 m hall driven at 4 m/s. Deterministic from the arguments.
    """
    from .sensors import LidarSensor

    if num_clouds < 1 or not scale > 0 or not rate_hz > 0:
        raise ValueError(f"num_clouds must be >= 1, scale and rate_hz > 0; got {num_clouds}, "
                         f"{scale}, {rate_hz}")
    room = scenes.get_room(int(scene_seed))
    fps = 30.0
    step = max(1, round(fps / rate_hz))
    cams = robot_trajectory(room, (num_clouds - 1) * step + 1, fps=fps, height=height,
                            pitch_deg=0.0)[::step]
    sensor = LidarSensor()
    clouds, poses, stamps = [], [], []
    for k, T_cam in enumerate(cams):
        fwd = T_cam[:3, 2]                                   # optical z: the view direction
        yaw = float(np.arctan2(fwd[1], fwd[0]))
        T = np.eye(4)
        T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0],
                     [0.0, 0.0, 1.0]]
        T[:3, 3] = T_cam[:3, 3]
        rng = np.random.default_rng([int(scene_seed), k, 0x11DA])
        clouds.append((sensor.sweep(room, T, rng) * np.float32(scale)).astype(np.float32))
        T_scaled = T.copy()
        T_scaled[:3, 3] *= scale
        poses.append(T_scaled)
        stamps.append(int(start_ns + round(k * step / fps * 1e9)))
    info = {"source": "lidar", "scene_seed": int(scene_seed), "scale": float(scale),
            "rate_hz": fps / step, "height": height, "beams": sensor.beams,
            "room_size": [float(x) * scale for x in room.size]}
    return Sequence(clouds, np.stack(poses), np.asarray(stamps, np.int64), "cegc_lidar", info)


def _bunny_pair_graph(root: Path) -> dict[str, list[tuple[str, np.ndarray]]]:
    """scan -> [(neighbour, T_neighbour_scan)] from pairs.tsv and gt/<pair_id>.txt."""
    table = root / "pairs.tsv"
    if not table.is_file():
        raise FileNotFoundError(f"{table} not found (expected the bunny folder of the real data)")
    graph: dict[str, list[tuple[str, np.ndarray]]] = {}
    lines = table.read_text().splitlines()
    for line in lines[1:]:
        cols = line.split("\t")
        if len(cols) < 3:
            continue
        pair_id, source, target = cols[:3]
        T = np.loadtxt(root / "gt" / f"{pair_id}.txt").reshape(4, 4)     # T_target_source
        graph.setdefault(source, []).append((target, T))
        graph.setdefault(target, []).append((source, np.linalg.inv(T)))
    return graph


def load_bunny_sequence(root: str | Path, order: tuple[str, ...] = BUNNY_RING,
                        spacing_ns: int = 1_000_000_000,
                        start_ns: int = 1_700_000_000 * 10**9) -> Sequence:
    """The bunny scans named in ``order`` as a sequence (``spacing_ns`` apart).

    Ground truth: Stanford's registration, chained breadth-first over the pairs of
    ``pairs.tsv`` into the frame of ``order[0]``. FileNotFoundError for a missing folder or scan;
    ValueError when a scan is not connected to the first by ground-truth pairs.
    """
    root = Path(root)
    graph = _bunny_pair_graph(root)
    world: dict[str, np.ndarray] = {order[0]: np.eye(4)}          # T_first_scan
    queue = deque([order[0]])
    while queue:
        a = queue.popleft()
        for b, T_a_b in ((n, np.linalg.inv(T_n_a)) for n, T_n_a in graph.get(a, [])):
            if b not in world:
                world[b] = world[a] @ T_a_b
                queue.append(b)
    missing = [name for name in order if name not in world]
    if missing:
        raise ValueError(f"bunny scans {missing} share no ground-truth pair chain with {order[0]}")
    clouds = []
    for name in order:
        path = root / "scans" / f"{name}.npy"
        if not path.is_file():
            raise FileNotFoundError(f"bunny scan {path} not found")
        clouds.append(np.load(path).astype(np.float32).reshape(-1, 3))
    poses = np.stack([world[name] for name in order])
    stamps = start_ns + spacing_ns * np.arange(len(order), dtype=np.int64)
    return Sequence(clouds, poses, stamps, "bunny_scanner",
                    {"source": "bunny", "scans": list(order)})
