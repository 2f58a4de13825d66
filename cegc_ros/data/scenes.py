"""Procedural indoor rooms seen by a simulated Kinect v1, fused into 3DMatch-like fragments.

Everything here is reproducible from integer seeds: a *scene seed* fixes the room (size,
furniture, clutter) and the handheld camera trajectory through it; fragment ``j`` of a scene
fuses frames ``[j * F, (j + 1) * F)`` of that trajectory (``F = frames_per_fragment``), with
sensor noise drawn from a generator seeded by ``(scene_seed, j)``. So any fragment can be made
alone, in any order, and is bit-identical each time.

Frames and units: metres. The world frame is z-up with the floor at ``z = 0``. Camera frames
follow the OpenCV / ROS optical convention (x right, y down, z forward). A fragment's points are
in the camera frame of its first depth frame, like the 3DMatch / 7-Scenes fragments;
``Fragment.T_world_fragment`` maps them into the world frame.

Rendering uses Open3D's ``RaycastingScene``. Rays are built with camera-frame directions
``((u - cx) / fx, (v - cy) / fy, 1)`` (pixel centres at ``u = col + 0.5``, as
``create_rays_pinhole`` does), so ``t_hit`` is the z-depth directly, not the range.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..geometry import voxel_means

# Kinect v1 disparity: baseline (m) and sub-pixel disparity resolution (1/8 px).
_KINECT_BASELINE = 0.075
_DISPARITY_STEP = 1.0 / 8.0

# Longest trajectory a scene has, in fragments: fragment indices are 0 .. MAX_FRAGMENTS - 1.
MAX_FRAGMENTS = 16


@dataclass(frozen=True)
class KinectCamera:
    """Kinect v1 depth camera intrinsics and working range (metres)."""

    width: int = 640
    height: int = 480
    fx: float = 585.0
    fy: float = 585.0
    cx: float = 320.0
    cy: float = 240.0
    min_depth: float = 0.5
    max_depth: float = 4.0

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class NoiseModel:
    """Kinect-v1-like depth noise (Nguyen et al. 2012; Khoshelham & Elberink 2012).

    axial sigma(z) = axial_a + axial_b * (z - 0.4)^2 (metres); lateral noise as a Gaussian
    jitter of each ray's pixel position (the point is back-projected at the nominal pixel);
    disparity quantised to 1/8 pixel; dropouts at depth discontinuities, at grazing angles and
    at random.
    """

    axial_a: float = 0.0012
    axial_b: float = 0.0019
    lateral_px: float = 0.8
    quantise: bool = True
    edge_jump: float = 0.05            # relative depth jump to a 4-neighbour that marks an edge
    edge_drop_prob: float = 0.7
    grazing_start_deg: float = 65.0    # incidence angle where dropout starts (prob 0) ...
    grazing_end_deg: float = 85.0      # ... and where every pixel is dropped (prob 1)
    random_drop_prob: float = 0.02


NO_NOISE = NoiseModel(axial_a=0.0, axial_b=0.0, lateral_px=0.0, quantise=False,
                      edge_drop_prob=0.0, grazing_start_deg=89.0, grazing_end_deg=90.0,
                      random_drop_prob=0.0)


# --------------------------------------------------------------------------------------------
# Mesh primitives: (V, 3) float64 vertices + (T, 3) int32 triangles, built in numpy.
# --------------------------------------------------------------------------------------------

@dataclass
class _MeshBuilder:
    """Accumulates triangle soups of primitives in world coordinates."""

    vertices: list[np.ndarray] = field(default_factory=list)
    triangles: list[np.ndarray] = field(default_factory=list)
    count: int = 0

    def add(self, v: np.ndarray, t: np.ndarray) -> None:
        self.vertices.append(v)
        self.triangles.append(t + self.count)
        self.count += len(v)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return (np.concatenate(self.vertices).astype(np.float32),
                np.concatenate(self.triangles).astype(np.uint32))

    # ---- primitives; `center` is the primitive's centre, `yaw` a rotation about world z ----
    def box(self, size: Any, center: Any, yaw: float = 0.0) -> None:
        """Axis-aligned (before yaw) box of full extents size = (sx, sy, sz)."""
        h = 0.5 * np.asarray(size, dtype=np.float64)
        c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        t = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                      [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
        self.add(_place(c * h, center, yaw), t)

    def cylinder(self, radius: float, height: float, center: Any, segments: int = 16,
                 top_radius: float | None = None) -> None:
        """Closed vertical cylinder (or cone frustum when top_radius differs)."""
        r1 = radius if top_radius is None else top_radius
        a = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
        zs = np.full(segments, height / 2)
        ring0 = np.stack([radius * np.cos(a), radius * np.sin(a), -zs], 1)
        ring1 = np.stack([r1 * np.cos(a), r1 * np.sin(a), zs], 1)
        v = np.concatenate([ring0, ring1, [[0, 0, -height / 2], [0, 0, height / 2]]])
        i = np.arange(segments)
        j = (i + 1) % segments
        side = np.concatenate([np.stack([i, j, i + segments], 1),
                               np.stack([j, j + segments, i + segments], 1)])
        bottom = np.stack([np.full(segments, 2 * segments), j, i], 1)
        top = np.stack([np.full(segments, 2 * segments + 1), i + segments, j + segments], 1)
        self.add(_place(v, center, 0.0), np.concatenate([side, bottom, top]))

    def sphere(self, radius: float, center: Any, rings: int = 8, segments: int = 12) -> None:
        """UV sphere."""
        th = np.linspace(0, np.pi, rings + 1)[1:-1]
        ph = np.linspace(0, 2 * np.pi, segments, endpoint=False)
        tt, pp = np.meshgrid(th, ph, indexing="ij")
        v = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
        v = v.reshape(-1, 3)
        v = np.concatenate([v, [[0, 0, 1], [0, 0, -1]]]) * radius
        north, south = len(v) - 2, len(v) - 1
        tris = []
        for r in range(rings - 2):
            for s in range(segments):
                a, b = r * segments + s, r * segments + (s + 1) % segments
                c, d = a + segments, b + segments
                tris += [[a, c, b], [b, c, d]]
        last = (rings - 2) * segments
        for s in range(segments):
            tris.append([north, s, (s + 1) % segments])
            tris.append([south, last + (s + 1) % segments, last + s])
        self.add(_place(v, center, 0.0), np.array(tris))


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _place(v: np.ndarray, center: Any, yaw: float) -> np.ndarray:
    return v @ _rot_z(yaw).T + np.asarray(center, dtype=np.float64)


class _Local:
    """Furniture-local frame: xy offsets rotated by the item's yaw about its floor position."""

    def __init__(self, mb: _MeshBuilder, x: float, y: float, yaw: float, z0: float = 0.0):
        self.mb, self.o, self.yaw, self.R = mb, np.array([x, y, z0]), yaw, _rot_z(yaw)

    def p(self, lx: float, ly: float, lz: float) -> np.ndarray:
        return self.o + self.R @ np.array([lx, ly, lz])

    def box(self, size: Any, lx: float, ly: float, lz: float) -> None:
        self.mb.box(size, self.p(lx, ly, lz), self.yaw)

    def cylinder(self, r: float, h: float, lx: float, ly: float, lz: float, **kw: Any) -> None:
        self.mb.cylinder(r, h, self.p(lx, ly, lz), **kw)


# --------------------------------------------------------------------------------------------
# Furniture. Each builder puts an item whose footprint is (w along local x, d along local y)
# centred at the local origin, and returns the heights of flat tops where clutter can stand.
# --------------------------------------------------------------------------------------------

_Tops = list[tuple[float, float, float]]     # (width, depth, height) of flat tops for clutter


def _legs(f: _Local, rng: np.random.Generator, w: float, d: float, h: float, t: float) -> None:
    round_legs = rng.random() < 0.5
    for sx in (-1, 1):
        for sy in (-1, 1):
            lx, ly = sx * (w / 2 - t), sy * (d / 2 - t)
            if round_legs:
                f.cylinder(t * 0.7, h, lx, ly, h / 2, segments=8)
            else:
                f.box((t, t, h), lx, ly, h / 2)


def _table(f: _Local, rng: np.random.Generator, w: float, d: float) -> _Tops:
    h = rng.uniform(0.68, 0.78)
    top = rng.uniform(0.025, 0.05)
    _legs(f, rng, w, d, h - top, rng.uniform(0.03, 0.06))
    f.box((w, d, top), 0, 0, h - top / 2)
    return [(w, d, h)]


def _chair(f: _Local, rng: np.random.Generator, w: float, d: float) -> _Tops:
    h = rng.uniform(0.42, 0.48)
    _legs(f, rng, w, d, h - 0.04, 0.03)
    f.box((w, d, 0.04), 0, 0, h - 0.02)
    back = rng.uniform(0.35, 0.5)
    f.box((w, 0.04, back), 0, d / 2 - 0.02, h + back / 2)
    return []


def _shelf(f: _Local, rng: np.random.Generator, w: float, d: float) -> _Tops:
    h = rng.uniform(1.2, 2.0)
    t = 0.02
    n = int(rng.integers(3, 6))
    f.box((t, d, h), -w / 2 + t / 2, 0, h / 2)
    f.box((t, d, h), w / 2 - t / 2, 0, h / 2)
    f.box((w, t, h), 0, d / 2 - t / 2, h / 2)                   # back panel (towards the wall)
    tops = []
    for k in range(n + 1):
        z = 0.05 + k * (h - 0.07) / n
        f.box((w - 2 * t, d - t, t), 0, -t / 2, z)
        tops.append((w - 0.1, d - 0.05, z + t / 2))
    return tops


def _cabinet(f: _Local, rng: np.random.Generator, w: float, d: float) -> _Tops:
    h = rng.uniform(0.5, 1.2)
    f.box((w, d, h - 0.05), 0, 0, (h - 0.05) / 2 + 0.05)
    f.box((w - 0.04, d - 0.04, 0.05), 0, 0, 0.025)              # recessed plinth
    doors = int(rng.integers(1, 4))
    for k in range(doors):                                      # handles on the front (-y)
        lx = -w / 2 + (k + 0.5) * w / doors
        f.box((0.1, 0.03, 0.02), lx, -d / 2 - 0.015, h * rng.uniform(0.6, 0.85))
    return [(w, d, h)]


def _sofa(f: _Local, rng: np.random.Generator, w: float, d: float) -> _Tops:
    seat = rng.uniform(0.38, 0.48)
    arm = rng.uniform(0.1, 0.22)
    f.box((w, d, seat), 0, 0, seat / 2)
    back_h = rng.uniform(0.35, 0.5)
    f.box((w, 0.2, back_h), 0, d / 2 - 0.1, seat + back_h / 2)
    arm_h = rng.uniform(0.15, 0.3)
    f.box((arm, d, arm_h), -w / 2 + arm / 2, 0, seat + arm_h / 2)
    f.box((arm, d, arm_h), w / 2 - arm / 2, 0, seat + arm_h / 2)
    cushions = int(rng.integers(0, 3))
    for k in range(cushions):
        f.box((0.4, 0.12, 0.35), rng.uniform(-w / 4, w / 4), d / 2 - 0.26, seat + 0.18)
    return []


def _floor_box(f: _Local, rng: np.random.Generator, w: float, d: float) -> _Tops:
    h = rng.uniform(0.2, 0.8)
    f.box((w, d, h), 0, 0, h / 2)
    if rng.random() < 0.4:                                      # a second box stacked on it
        w2, d2, h2 = w * rng.uniform(0.4, 0.9), d * rng.uniform(0.4, 0.9), rng.uniform(0.1, 0.4)
        f.box((w2, d2, h2), rng.uniform(-0.1, 0.1) * w, 0, h + h2 / 2)
    return [(w, d, h)]


def _cylinder_item(f: _Local, rng: np.random.Generator, w: float, d: float) -> _Tops:
    r = min(w, d) / 2
    kind = rng.integers(0, 3)
    if kind == 0:                                               # bin / barrel
        h = rng.uniform(0.3, 0.9)
        f.cylinder(r, h, 0, 0, h / 2, segments=20)
        return [(r, r, h)]
    if kind == 1:                                               # floor lamp: base, pole, shade
        h = rng.uniform(1.0, 1.2)
        f.cylinder(r * 0.8, 0.03, 0, 0, 0.015, segments=16)
        f.cylinder(0.015, h, 0, 0, h / 2, segments=8)
        f.cylinder(r, 0.25, 0, 0, h, segments=16, top_radius=r * 0.5)
        return []
    h = rng.uniform(0.4, 0.75)                                  # round side table
    f.cylinder(0.03, h, 0, 0, h / 2, segments=8)
    f.cylinder(r, 0.03, 0, 0, h, segments=24)
    return [(r, r, h + 0.015)]


_WALL_ITEMS = {"shelf": (_shelf, (0.6, 1.4), (0.25, 0.45)),
               "cabinet": (_cabinet, (0.5, 1.6), (0.35, 0.6)),
               "sofa": (_sofa, (1.4, 2.2), (0.75, 0.95))}
_FREE_ITEMS = {"table": (_table, (0.7, 1.8), (0.6, 1.0)),
               "chair": (_chair, (0.4, 0.5), (0.4, 0.5)),
               "box": (_floor_box, (0.25, 0.8), (0.25, 0.8)),
               "cylinder": (_cylinder_item, (0.25, 0.6), (0.25, 0.6))}


def _clutter(mb: _MeshBuilder, rng: np.random.Generator, f: _Local,
             tops: list[tuple[float, float, float]]) -> None:
    """Small objects (boxes, cylinders, spheres) standing on the flat tops of an item."""
    for w, d, z in tops:
        for _ in range(int(rng.poisson(1.5))):
            lx, ly = rng.uniform(-0.4, 0.4) * w, rng.uniform(-0.35, 0.35) * d
            c = f.p(lx, ly, z)
            kind = rng.integers(0, 3)
            if kind == 0:
                s = rng.uniform(0.05, 0.3, 3) * np.array([1, 1, 0.8])
                mb.box(s, c + [0, 0, s[2] / 2], rng.uniform(0, np.pi))
            elif kind == 1:
                r, h = rng.uniform(0.03, 0.1), rng.uniform(0.06, 0.3)
                mb.cylinder(r, h, c + [0, 0, h / 2], segments=12)
            else:
                r = rng.uniform(0.04, 0.12)
                mb.sphere(r, c + [0, 0, r])


# --------------------------------------------------------------------------------------------
# Rooms
# --------------------------------------------------------------------------------------------

@dataclass
class Room:
    """A procedural room: its triangle soup (world frame, metres) and a raycasting scene."""

    seed: int
    size: tuple[float, float, float]        # (x extent, y extent, height), floor at z = 0
    vertices: np.ndarray                    # (V, 3) float32
    triangles: np.ndarray                   # (T, 3) uint32
    items: list[str]                        # names of the furniture placed
    targets: np.ndarray                     # (K, 3) points of interest the camera looks at
    camera_box: tuple[np.ndarray, np.ndarray]   # (lo, hi) xyz bounds of camera positions
    _scene: Any = field(default=None, repr=False)

    @property
    def scene(self) -> Any:
        """The ``open3d.t.geometry.RaycastingScene`` holding the room (built on first use)."""
        if self._scene is None:
            import open3d as o3d
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))
            self._scene = scene
        return self._scene


def make_room(seed: int) -> Room:
    """Build the room of a scene seed: walls, floor, ceiling, 5-12 furniture items, clutter."""
    rng = np.random.default_rng([int(seed), 0x700])
    sx, sy, sz = rng.uniform(3.5, 7.0), rng.uniform(3.0, 6.0), rng.uniform(2.4, 3.0)
    mb = _MeshBuilder()
    t = 0.1
    mb.box((sx + 2 * t, sy + 2 * t, t), (sx / 2, sy / 2, -t / 2))          # floor
    mb.box((sx + 2 * t, sy + 2 * t, t), (sx / 2, sy / 2, sz + t / 2))      # ceiling
    mb.box((t, sy, sz), (-t / 2, sy / 2, sz / 2))                          # walls
    mb.box((t, sy, sz), (sx + t / 2, sy / 2, sz / 2))
    mb.box((sx, t, sz), (sx / 2, -t / 2, sz / 2))
    mb.box((sx, t, sz), (sx / 2, sy + t / 2, sz / 2))
    # Wall relief so that no wall is a featureless plane: skirting, a door frame, windows, frames.
    for wall in range(4):
        length = (sx, sy)[wall % 2]
        for _ in range(int(rng.integers(0, 3))):
            w, h = rng.uniform(0.3, 1.2), rng.uniform(0.3, 1.0)
            pos = rng.uniform(w / 2 + 0.1, length - w / 2 - 0.1)
            z = rng.uniform(0.9, sz - h / 2 - 0.2)
            depth = rng.uniform(0.02, 0.12) * rng.choice([-1.0, 1.0])     # picture or window niche
            _wall_box(mb, wall, (sx, sy), pos, z, w, h, depth)
        _wall_box(mb, wall, (sx, sy), length / 2, 0.05, length, 0.1, 0.015)  # skirting board

    items: list[str] = []
    footprints: list[tuple[float, float, float]] = []      # (x, y, radius) of placed items
    cam_margin = 0.9

    def free(x: float, y: float, r: float) -> bool:
        return all(np.hypot(x - a, y - b) > r + c for a, b, c in footprints)

    # Wall-standing items, backs to the wall (local +y points to the wall).
    for _ in range(int(rng.integers(2, 6))):
        name = str(rng.choice(list(_WALL_ITEMS)))
        build, wr, dr = _WALL_ITEMS[name]
        w, d = rng.uniform(*wr), rng.uniform(*dr)
        wall = int(rng.integers(0, 4))
        length = (sx, sy)[wall % 2]
        if length < w + 0.2:
            continue
        s = rng.uniform(w / 2 + 0.05, length - w / 2 - 0.05)
        x, y, yaw = _wall_pose(wall, (sx, sy), s, d / 2 + 0.01)
        r = 0.5 * np.hypot(w, d)
        if not free(x, y, r):
            continue
        footprints.append((x, y, r))
        f = _Local(mb, x, y, yaw)
        _clutter(mb, rng, f, build(f, rng, w, d))
        items.append(name)
    # Free-standing items anywhere on the floor (kept below camera height).
    for _ in range(int(rng.integers(5, 12))):
        name = str(rng.choice(list(_FREE_ITEMS)))
        build, wr, dr = _FREE_ITEMS[name]
        w, d = rng.uniform(*wr), rng.uniform(*dr)
        r = 0.5 * np.hypot(w, d)
        x, y = rng.uniform(r + 0.05, sx - r - 0.05), rng.uniform(r + 0.05, sy - r - 0.05)
        if sx < 2 * r + 0.1 or sy < 2 * r + 0.1 or not free(x, y, r):
            continue
        footprints.append((x, y, r))
        f = _Local(mb, x, y, rng.uniform(0, 2 * np.pi))
        _clutter(mb, rng, f, build(f, rng, w, d))
        items.append(name)
        if name == "table":                                    # chairs around tables
            for k in range(int(rng.integers(0, 4))):
                ang = f.yaw + k * np.pi / 2 + rng.normal(0, 0.15)
                dist = (w if k % 2 == 0 else d) / 2 + 0.15
                cx_, cy_ = x + dist * np.cos(ang), y + dist * np.sin(ang)
                if 0.3 < cx_ < sx - 0.3 and 0.3 < cy_ < sy - 0.3:
                    fc = _Local(mb, cx_, cy_, ang - np.pi / 2)
                    _chair(fc, rng, 0.45, 0.45)
                    items.append("chair")
    v, tri = mb.arrays()
    lo = np.array([cam_margin, cam_margin, 1.2])
    hi = np.array([sx - cam_margin, sy - cam_margin, 1.8])
    targets = [(x, y, 0.6) for x, y, _ in footprints] + [(sx / 2, sy / 2, 0.5)]
    return Room(int(seed), (float(sx), float(sy), float(sz)), v, tri, items,
                np.array(targets), (lo, hi))


def _wall_pose(wall: int, size: tuple[float, float], s: float,
               off: float) -> tuple[float, float, float]:
    """Floor position and yaw of an item at arc-length s along a wall, local +y towards it."""
    sx, sy = size
    if wall == 0:
        return s, off, np.pi            # wall y = 0
    if wall == 1:
        return sx - off, s, -np.pi / 2  # wall x = sx
    if wall == 2:
        return s, sy - off, 0.0         # wall y = sy
    return off, s, np.pi / 2            # wall x = 0


def _wall_box(mb: _MeshBuilder, wall: int, size: tuple[float, float], s: float, z: float,
              w: float, h: float, depth: float) -> None:
    """A thin box flush with a wall (depth > 0 protrudes into the room, < 0 a recess frame)."""
    x, y, yaw = _wall_pose(wall, size, s, abs(depth) / 2 if depth > 0 else 0.0)
    if depth > 0:
        mb.box((w, abs(depth), h), (x, y, z), yaw)
    else:                                   # a window-like frame: four bars around the opening
        bar = 0.05
        R = _rot_z(yaw)
        for lx, lz, bw, bh in ((0, h / 2, w, bar), (0, -h / 2, w, bar),
                               (-w / 2, 0, bar, h), (w / 2, 0, bar, h)):
            c = np.array([x, y, z]) + R @ np.array([lx, 0.0, lz])
            mb.box((bw, abs(depth), bh), c, yaw)


@functools.lru_cache(maxsize=8)
def get_room(seed: int) -> Room:
    """Cached :func:`make_room` (the raycasting scene is reused across fragments)."""
    return make_room(seed)


# --------------------------------------------------------------------------------------------
# Handheld trajectory
# --------------------------------------------------------------------------------------------

def camera_trajectory(room: Room, num_frames: int, fps: float = 30.0) -> np.ndarray:
    """Smooth handheld-like camera poses T_world_camera, (num_frames, 4, 4) float64.

    Control points one second apart (random walk of the position inside the room's camera box;
    the view aimed at points of interest, pitch -45..-5 deg, roll +-6 deg) interpolated with
    cubic splines, plus a little hand shake. Deterministic from the room's seed.
    """
    from scipy.interpolate import CubicSpline

    rng = np.random.default_rng([room.seed, 0x7A1])
    lo, hi = room.camera_box
    n_ctrl = int(np.ceil(num_frames / fps)) + 4
    pos = np.empty((n_ctrl, 3))
    pos[0] = rng.uniform(lo, hi)
    for k in range(1, n_ctrl):
        step = rng.normal(0, [0.35, 0.35, 0.08])
        pos[k] = np.clip(pos[k - 1] + step, lo, hi)
    # Handheld scanning looks at things: each control point looks at a point of interest
    # (furniture or the room centre), held for a few seconds, plus a random offset.
    look = np.empty((n_ctrl, 3))
    k = 0
    while k < n_ctrl:
        hold = int(rng.integers(2, 5))
        look[k:k + hold] = room.targets[rng.integers(len(room.targets))]
        k += hold
    look += rng.normal(0, [0.6, 0.6, 0.3], look.shape)
    delta = look - pos
    dist = np.linalg.norm(delta[:, :2], axis=1)
    near = dist < 1.0                       # too close to look at: look past it instead
    delta[near, :2] += 1.0 * delta[near, :2] / np.maximum(dist[near, None], 1e-6)
    yaw = np.unwrap(np.arctan2(delta[:, 1], delta[:, 0]))
    yaw = yaw[0] + np.r_[0.0, np.cumsum(np.clip(np.diff(yaw), -1.0, 1.0))]   # <= 57 deg/s
    pitch = np.clip(np.arctan2(delta[:, 2], np.linalg.norm(delta[:, :2], axis=1)),
                    np.radians(-45), np.radians(-5))
    roll = rng.normal(0, np.radians(3), n_ctrl).clip(np.radians(-6), np.radians(6))
    tc = np.arange(n_ctrl) * fps
    t = np.arange(num_frames, dtype=np.float64) + fps        # skip the spline's first second
    p = CubicSpline(tc, pos)(t)
    ang = CubicSpline(tc, np.stack([yaw, pitch, roll], 1))(t)
    p += np.cumsum(rng.normal(0, 0.0008, p.shape), 0).clip(-0.01, 0.01)   # hand shake
    ang += rng.normal(0, np.radians(0.15), ang.shape)
    p = np.clip(p, lo - 0.2, hi + 0.2)
    poses = np.tile(np.eye(4), (num_frames, 1, 1))
    poses[:, :3, :3] = camera_rotation(ang[:, 0], ang[:, 1], ang[:, 2])
    poses[:, :3, 3] = p
    return poses


def camera_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """R_world_camera (F, 3, 3) of an optical camera (x right, y down, z forward) in the z-up
    world, looking along ``yaw`` (about z), tilted up by ``pitch``, rolled by ``roll`` (each (F,),
    radians). Shared by the fragment, different-view and sequence generators."""
    fwd = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], -1)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    down = np.cross(fwd, right)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    right, down = c * right + s * down, -s * right + c * down
    return np.stack([right, down, fwd], -1)


# --------------------------------------------------------------------------------------------
# Depth rendering and fragments
# --------------------------------------------------------------------------------------------

def render_depth(room: Room, T_world_camera: np.ndarray, rng: np.random.Generator | None = None,
                 camera: KinectCamera = KinectCamera(), noise: NoiseModel = NoiseModel(),
                 pixel_stride: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one (noisy) Kinect depth frame of the room.

    Returns (depth, u, v): depth (H', W') float32 z-depth in metres, NaN where the sensor gives
    no reading; u, v (W',) and (H',) the nominal pixel-centre coordinates of the columns/rows
    (``col + 0.5`` for every ``pixel_stride``-th pixel). Without rng the noise is not applied.
    """
    import open3d as o3d

    u = np.arange(0, camera.width, pixel_stride) + 0.5
    v = np.arange(0, camera.height, pixel_stride) + 0.5
    shape = (len(v), len(u))
    xn = np.broadcast_to(((u - camera.cx) / camera.fx).astype(np.float32), shape)
    yn = np.broadcast_to(((v - camera.cy) / camera.fy).astype(np.float32)[:, None], shape)
    if rng is not None and noise.lateral_px > 0:      # jitter where the ray samples the scene
        xn = xn + rng.standard_normal(shape, np.float32) * np.float32(noise.lateral_px / camera.fx)
        yn = yn + rng.standard_normal(shape, np.float32) * np.float32(noise.lateral_px / camera.fy)
    R = T_world_camera[:3, :3].astype(np.float32)
    rays = np.empty(shape + (6,), np.float32)
    rays[..., :3] = T_world_camera[:3, 3]
    # World direction of camera-frame (xn, yn, 1): dir_cam.z = 1 makes t_hit the z-depth.
    rays[..., 3:] = xn[..., None] * R[:, 0] + yn[..., None] * R[:, 1] + R[:, 2]
    hit = room.scene.cast_rays(o3d.core.Tensor(rays))
    z = hit["t_hit"].numpy()                                            # (H', W') float32
    z[~np.isfinite(z)] = np.nan
    if rng is None:
        z[(z < camera.min_depth) | (z > camera.max_depth)] = np.nan
        return z, u, v

    # Grazing incidence: dropout probability linear in the angle between ray and normal.
    n = hit["primitive_normals"].numpy()                                # (H', W', 3) world
    cos_inc = np.abs(np.einsum("hwc,hwc->hw", n, rays[..., 3:]))
    cos_inc /= np.sqrt(xn * xn + yn * yn + 1.0)
    p_drop = np.zeros(shape, np.float32)
    steep = cos_inc < np.cos(np.radians(noise.grazing_start_deg))
    inc = np.degrees(np.arccos(np.clip(cos_inc[steep], 0.0, 1.0)))
    p_drop[steep] = np.clip((inc - noise.grazing_start_deg)
                            / (noise.grazing_end_deg - noise.grazing_start_deg), 0.0, 1.0)
    # Depth discontinuities: relative jump to any 4-neighbour (missing neighbours count as edges).
    zz = np.where(np.isfinite(z), z, np.float32(1e6))    # a missing neighbour is a huge jump
    jump = np.zeros(shape, np.float32)
    for axis in (0, 1):
        dz = np.abs(np.diff(zz, axis=axis))
        lo_, hi_ = [slice(None)] * 2, [slice(None)] * 2
        lo_[axis], hi_[axis] = slice(0, -1), slice(1, None)
        np.maximum(jump[tuple(lo_)], dz, out=jump[tuple(lo_)])
        np.maximum(jump[tuple(hi_)], dz, out=jump[tuple(hi_)])
    edge = jump > noise.edge_jump * zz
    p_drop[edge] = np.maximum(p_drop[edge], noise.edge_drop_prob)
    p_drop = 1.0 - (1.0 - p_drop) * (1.0 - noise.random_drop_prob)
    z[rng.random(shape, np.float32) < p_drop] = np.nan
    sigma = noise.axial_a + noise.axial_b * (z - np.float32(0.4)) ** 2
    z += rng.standard_normal(shape, np.float32) * sigma
    if noise.quantise:
        fb = np.float32(camera.fx * _KINECT_BASELINE)
        step = np.float32(_DISPARITY_STEP)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = fb / (np.round(fb / z / step) * step)
    with np.errstate(invalid="ignore"):
        z[~((z >= camera.min_depth) & (z <= camera.max_depth))] = np.nan
    return z.astype(np.float32, copy=False), u, v


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Mean of the points in each occupied voxel, (N, 3) -> (M, 3) in the points' dtype, in
    sorted voxel order (a grid aligned at the origin; cegc_ros.geometry.voxel_means).

    Deterministic, unlike hash-map based implementations.
    """
    if voxel_size <= 0 or len(points) == 0:
        return points
    key = np.floor(points / voxel_size).astype(np.int64)
    key -= key.min(0)
    return voxel_means(points, key).astype(points.dtype, copy=False)


@dataclass
class Fragment:
    """A fused RGB-D fragment, like a 3DMatch ``cloud_bin_*``.

    points: (N, 3) float32, metres, in the camera frame of the fragment's first depth frame.
    T_world_fragment: (4, 4) float64, maps fragment points into the room's world frame.
    """

    points: np.ndarray
    T_world_fragment: np.ndarray
    scene_seed: int
    index: int
    info: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class FragmentConfig:
    """How fragments are rendered and fused.

    3DMatch fuses 50 consecutive 640x480 frames with a TSDF; here every ``frame_step``-th frame
    of the 50 is rendered at every ``pixel_stride``-th pixel and the back-projected points are
    averaged per voxel of ``voxel_size`` (the averaging also smooths the sensor noise, as TSDF
    fusion does). Points are kept inside 3DMatch's TSDF volume: a cube of side ``volume_size``
    with its corner at ``volume_origin`` in the first camera's frame (x, y in [-1.5, 1.5] m,
    z in [0.5, 3.5] m, as the real SUN3D fragments show); ``volume_size=None`` keeps all.
    The defaults keep a fragment under ~1 s on 2 CPU cores.
    """

    frames_per_fragment: int = 50
    frame_step: int = 5
    pixel_stride: int = 2
    voxel_size: float = 0.025
    volume_origin: tuple[float, float, float] = (-1.5, -1.5, 0.5)
    volume_size: float | None = 3.0
    camera: KinectCamera = KinectCamera()
    noise: NoiseModel = NoiseModel()


def fuse_depth_frames(room: Room, poses: np.ndarray, rng: np.random.Generator | None,
                      config: FragmentConfig) -> np.ndarray:
    """Render a depth frame at each pose and fuse them into one voxelized cloud.

    poses: (K, 4, 4) float64 T_world_camera of the frames to render (already subsampled: every
    pose is rendered). Returns (N, 3) float32 points in the camera frame of ``poses[0]``, kept
    inside the config's TSDF-like volume, averaged per ``config.voxel_size`` voxel. Noise is
    drawn from ``rng`` frame after frame (None: noiseless).
    """
    cam = config.camera
    T_frag_world = np.linalg.inv(poses[0])
    chunks = []
    lo = np.asarray(config.volume_origin, np.float32)
    for T_world_cam in poses:
        z, u, v = render_depth(room, T_world_cam, rng, cam, config.noise, config.pixel_stride)
        vv, uu = np.nonzero(np.isfinite(z))
        zz = z[vv, uu]
        xn = ((u - cam.cx) / cam.fx).astype(np.float32)
        yn = ((v - cam.cy) / cam.fy).astype(np.float32)
        T = (T_frag_world @ T_world_cam).astype(np.float32)
        # p_frag = R_frag_cam @ (xn z, yn z, z) + t, written per column of R (float32).
        p = (xn[uu] * zz)[:, None] * T[:3, 0] + (yn[vv] * zz)[:, None] * T[:3, 1] \
            + zz[:, None] * T[:3, 2] + T[:3, 3]
        if config.volume_size is not None:
            rel = p - lo
            p = p[np.all((rel >= 0) & (rel <= config.volume_size), axis=1)]
        chunks.append(p)
    return voxel_downsample(np.concatenate(chunks), config.voxel_size)


def make_fragment(scene_seed: int, index: int,
                  config: FragmentConfig = FragmentConfig()) -> Fragment:
    """Render and fuse fragment ``index`` (0 .. MAX_FRAGMENTS - 1) of a scene."""
    if not 0 <= index < MAX_FRAGMENTS:
        raise ValueError(f"fragment index {index} outside 0..{MAX_FRAGMENTS - 1}")
    room = get_room(int(scene_seed))
    F = config.frames_per_fragment
    poses = _scene_trajectory(int(scene_seed), F)[index * F:(index + 1) * F]
    rng = np.random.default_rng([int(scene_seed), int(index), 0xF4A])
    pts = fuse_depth_frames(room, poses[::config.frame_step], rng, config)
    info = {"scene_seed": int(scene_seed), "fragment": int(index),
            "frames": [index * F, (index + 1) * F], "room_size": list(room.size),
            "voxel_size": config.voxel_size}
    return Fragment(pts, poses[0].copy(), int(scene_seed), int(index), info)


@functools.lru_cache(maxsize=16)
def _scene_trajectory(scene_seed: int, frames_per_fragment: int) -> np.ndarray:
    poses = camera_trajectory(get_room(scene_seed), MAX_FRAGMENTS * frames_per_fragment)
    poses.setflags(write=False)
    return poses


def room_to_legacy_mesh(room: Room) -> Any:
    """The room as an ``open3d.geometry.TriangleMesh`` (for viewing / debugging)."""
    import open3d as o3d
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(room.vertices.astype(np.float64)),
                                  o3d.utility.Vector3iVector(room.triangles.astype(np.int32)))
    m.compute_vertex_normals()
    return m
