"""Richer procedural rooms for different-view training pairs: kitchens, offices, bedrooms, ...

:func:`make_rich_room` builds a room from an integer *room seed* (see :mod:`cegc_ros.data.splits`
for which seeds belong to train / val / test): a kind (living room, kitchen, office, bedroom,
storage room, hall), a non-rectangular footprint (notched and chamfered corners, alcoves,
chimney breasts / columns), walls with door and window holes (an open door shows a corridor
behind it; a window shows nothing, as glass gives a depth camera no return), and furniture of
the kind with clutter on its surfaces and in its open shelves. Everything is a triangle soup in
the world frame (metres, z up, floor at z = 0) reusing the primitives of
:mod:`cegc_ros.data.scenes`; the result is a :class:`RichRoom`, a :class:`scenes.Room` that
also carries the footprint and a floor grid of where a sensor can stand.

Reproducibility: the room is a pure function of the seed (numpy Generator seeded by
``(seed, 0x5200)``), so any room can be rebuilt alone, in any process.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cegc_ros.data.scenes import (
    Room,
    _cabinet,
    _chair,
    _cylinder_item,
    _Local,
    _MeshBuilder,
    _sofa,
)

ROOM_KINDS = ("living", "kitchen", "office", "bedroom", "storage", "hall")
_KIND_PROB = np.array([0.18, 0.2, 0.24, 0.14, 0.12, 0.12])

# Base rectangle (x range, y range) and ceiling height range of each kind, metres.
_KIND_SIZE = {"living": ((4.0, 7.5), (3.5, 6.0), (2.4, 3.0)),
              "kitchen": ((3.0, 6.0), (2.6, 5.0), (2.4, 2.9)),
              "office": ((3.5, 9.0), (3.0, 7.0), (2.5, 3.2)),
              "bedroom": ((3.0, 5.5), (3.0, 4.8), (2.4, 2.9)),
              "storage": ((3.0, 7.0), (2.5, 5.5), (2.5, 3.5)),
              "hall": ((8.0, 16.0), (6.0, 12.0), (3.0, 5.0))}
_WALL_T = 0.12                      # wall thickness
_GRID_RES = 0.05                    # floor grid cell, metres


# --------------------------------------------------------------------------------------------
# Floor grid: where the footprint is, what furniture covers, where a sensor can stand
# --------------------------------------------------------------------------------------------

def inside_polygon(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(N,) bool: which of the (N, 2) points lie inside the simple polygon (V, 2) (even-odd)."""
    x, y = points[:, 0], points[:, 1]
    inside = np.zeros(len(points), bool)
    for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, axis=0)):
        crosses = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xint = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (x < xint)
    return inside


@dataclass
class FloorGrid:
    """A 2-D grid over the room's floor (cell ``(row, col)`` covers y then x).

    inside: cell centre inside the footprint; occupied: covered by furniture (a sensor cannot
    stand there); reserved: kept clear of furniture (door swings) but walkable.
    """

    origin: np.ndarray                  # (2,) xy of the corner of cell (0, 0)
    res: float
    inside: np.ndarray                  # (H, W) bool
    occupied: np.ndarray                # (H, W) bool
    reserved: np.ndarray                # (H, W) bool
    _clearance: np.ndarray | None = field(default=None, repr=False)

    @classmethod
    def over(cls, poly: np.ndarray, res: float = _GRID_RES) -> FloorGrid:
        lo, hi = poly.min(0) - res, poly.max(0) + res
        W, H = (np.ceil((hi - lo) / res)).astype(int)
        xs = lo[0] + (np.arange(W) + 0.5) * res
        ys = lo[1] + (np.arange(H) + 0.5) * res
        xx, yy = np.meshgrid(xs, ys)
        inside = inside_polygon(np.stack([xx.ravel(), yy.ravel()], 1), poly).reshape(H, W)
        return cls(lo, res, inside, np.zeros((H, W), bool), np.zeros((H, W), bool))

    def _rect(self, x: float, y: float, yaw: float, w: float, d: float
              ) -> tuple[np.ndarray, np.ndarray]:
        """Row and column indices of the cells whose centres lie in a rotated rectangle."""
        r = 0.5 * np.hypot(w, d)
        c0, r0 = np.floor((np.array([x, y]) - r - self.origin) / self.res).astype(int)
        c1, r1 = np.ceil((np.array([x, y]) + r - self.origin) / self.res).astype(int)
        H, W = self.inside.shape
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, W), min(r1, H)
        if c0 >= c1 or r0 >= r1:
            return np.zeros(0, int), np.zeros(0, int)
        cols = np.arange(c0, c1)
        rows = np.arange(r0, r1)
        cx = self.origin[0] + (cols + 0.5) * self.res - x
        cy = self.origin[1] + (rows + 0.5) * self.res - y
        c, s = np.cos(yaw), np.sin(yaw)
        lx = c * cx[None, :] + s * cy[:, None]          # world offset -> item-local x, y
        ly = -s * cx[None, :] + c * cy[:, None]
        m = (np.abs(lx) <= w / 2) & (np.abs(ly) <= d / 2)
        rr, cc = np.nonzero(m)
        return rr + r0, cc + c0

    def fits(self, x: float, y: float, yaw: float, w: float, d: float, margin: float = 0.0) -> bool:
        """Whether a (w x d) rectangle (plus margin) lies in the footprint on free floor."""
        rr, cc = self._rect(x, y, yaw, w + 2 * margin, d + 2 * margin)
        if len(rr) == 0:
            return False
        rin, cin = self._rect(x, y, yaw, w, d)
        return bool(self.inside[rin, cin].all() and self.inside[rr, cc].all()
                    and not (self.occupied[rr, cc] | self.reserved[rr, cc]).any())

    def mark(self, x: float, y: float, yaw: float, w: float, d: float, reserve: bool = False) -> None:
        rr, cc = self._rect(x, y, yaw, w, d)
        (self.reserved if reserve else self.occupied)[rr, cc] = True
        self._clearance = None

    @property
    def clearance(self) -> np.ndarray:
        """(H, W) metres from each free cell to the nearest wall or furniture (0 elsewhere)."""
        if self._clearance is None:
            from scipy.ndimage import distance_transform_edt
            self._clearance = distance_transform_edt(self.inside & ~self.occupied) * self.res
        return self._clearance

    def clearance_at(self, xy: np.ndarray) -> np.ndarray:
        """Clearance (metres) at (N, 2) points; 0 outside the grid."""
        xy = np.atleast_2d(xy)
        c = np.floor((xy - self.origin) / self.res).astype(int)
        H, W = self.inside.shape
        ok = (c[:, 0] >= 0) & (c[:, 0] < W) & (c[:, 1] >= 0) & (c[:, 1] < H)
        out = np.zeros(len(xy))
        out[ok] = self.clearance[c[ok, 1], c[ok, 0]]
        return out

    def sample(self, rng: np.random.Generator, min_clearance: float, n: int = 1) -> np.ndarray:
        """(n, 2) random floor points at least min_clearance from walls and furniture.

        Falls back to the most open cells when no cell has that much clearance.
        """
        cl = self.clearance
        rr, cc = np.nonzero(cl >= min_clearance)
        if len(rr) == 0:
            rr, cc = np.nonzero(cl >= 0.8 * cl.max())
        k = rng.integers(len(rr), size=n)
        jitter = rng.uniform(-0.5, 0.5, (n, 2)) * self.res
        return self.origin + (np.stack([cc[k], rr[k]], 1) + 0.5) * self.res + jitter


# --------------------------------------------------------------------------------------------
# Footprint: a rectangle with notched / chamfered corners and alcoves / columns on its edges
# --------------------------------------------------------------------------------------------

def make_footprint(rng: np.random.Generator, sx: float, sy: float) -> np.ndarray:
    """(V, 2) counter-clockwise simple polygon inside-out from a sx x sy rectangle.

    Up to three corners get a rectangular notch (an L / T / U room) or a chamfer (a diagonal
    wall); each edge may get an alcove (outward) or a column / chimney breast (inward).
    """
    corners = np.array([[0.0, 0.0], [sx, 0.0], [sx, sy], [0.0, sy]])
    lengths = np.array([sx, sy, sx, sy])
    dirs = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])   # edge i: corner i -> i+1
    kind = ["none"] * 4
    a = np.zeros(4)                     # cut along the incoming edge (i - 1)
    b = np.zeros(4)                     # cut along the outgoing edge i
    n_mod = int(rng.choice([0, 0, 1, 1, 1, 2, 2, 3]))
    for c in rng.permutation(4)[:n_mod]:
        L_in, L_out = lengths[c - 1], lengths[c]
        if rng.random() < 0.65 and min(L_in, L_out) >= 2.6:
            kind[c] = "notch"
            a[c] = rng.uniform(0.2, 0.42) * L_in
            b[c] = rng.uniform(0.2, 0.42) * L_out
        else:
            kind[c] = "chamfer"
            a[c] = b[c] = min(rng.uniform(0.35, 1.2), 0.3 * min(L_in, L_out))
    poly: list[np.ndarray] = []
    for i in range(4):
        P, d_in, d_out = corners[i], dirs[i - 1], dirs[i]
        if kind[i] == "none":
            poly.append(P)
        elif kind[i] == "chamfer":
            poly += [P - d_in * a[i], P + d_out * b[i]]
        else:
            poly += [P - d_in * a[i], P - d_in * a[i] + d_out * b[i], P + d_out * b[i]]
        # Bumps on edge i, between the corner cuts (0.3 m away from them).
        s_lo, s_hi = b[i] + 0.3, lengths[i] - a[(i + 1) % 4] - 0.3
        if s_hi - s_lo < 1.2 or rng.random() > 0.45:
            continue
        n_out = np.array([d_out[1], -d_out[0]])
        if rng.random() < 0.6:          # alcove / bay
            w, depth = rng.uniform(0.8, min(2.4, s_hi - s_lo)), rng.uniform(0.4, 1.2)
        else:                           # column or chimney breast
            w, depth = rng.uniform(0.3, min(1.0, s_hi - s_lo)), -rng.uniform(0.2, 0.6)
        s = rng.uniform(s_lo + w / 2, s_hi - w / 2)
        q0, q1 = P + d_out * (s - w / 2), P + d_out * (s + w / 2)
        poly += [q0, q0 + n_out * depth, q1 + n_out * depth, q1]
    return np.array(poly)


# --------------------------------------------------------------------------------------------
# Walls with openings
# --------------------------------------------------------------------------------------------

@dataclass
class Opening:
    """A hole in a wall: along-wall interval [s0, s1] and height interval [z0, z1]."""

    kind: str                       # "door" or "window"
    s0: float
    s1: float
    z0: float
    z1: float


@dataclass
class Wall:
    p0: np.ndarray                  # (2,) start (polygon vertex)
    d: np.ndarray                   # (2,) unit direction along the wall
    n: np.ndarray                   # (2,) unit outward normal
    length: float
    convex0: bool                   # the polygon is convex at p0 / p1 (extend the wall there)
    convex1: bool
    openings: list[Opening] = field(default_factory=list)

    @property
    def yaw(self) -> float:
        return float(np.arctan2(self.d[1], self.d[0]))

    def at(self, s: float, inward: float = 0.0) -> np.ndarray:
        """(2,) point at arc length s, ``inward`` metres into the room."""
        return self.p0 + self.d * s - self.n * inward

    def item_yaw(self) -> float:
        """Yaw of an item standing with its local +y (back) towards this wall."""
        return float(np.arctan2(-self.n[0], self.n[1]))

    def free_interval(self, s0: float, s1: float, sill: float | None) -> bool:
        """Whether [s0, s1] avoids doors (always) and windows (when the item's top > sill)."""
        for o in self.openings:
            blocks = o.kind == "door" or (sill is not None and sill > o.z0 - 0.02)
            if blocks and s1 > o.s0 - 0.1 and s0 < o.s1 + 0.1:
                return False
        return True


def _walls(poly: np.ndarray) -> list[Wall]:
    out = []
    V = len(poly)
    for i in range(V):
        p0, p1 = poly[i], poly[(i + 1) % V]
        e = p1 - p0
        L = float(np.linalg.norm(e))
        d = e / L
        n = np.array([d[1], -d[0]])
        e_prev = p0 - poly[i - 1]
        e_next = poly[(i + 2) % V] - p1
        cross0 = e_prev[0] * e[1] - e_prev[1] * e[0]   # > 0: left turn = convex (CCW)
        cross1 = e[0] * e_next[1] - e[1] * e_next[0]
        out.append(Wall(p0, d, n, L, cross0 > 0, cross1 > 0))
    return out


def _build_wall(mb: _MeshBuilder, wall: Wall, height: float) -> None:
    """Wall boxes (inner face on the polygon edge) around its openings."""
    t = _WALL_T
    lo = -t if wall.convex0 else 0.0
    hi = wall.length + (t if wall.convex1 else 0.0)

    def piece(s0: float, s1: float, z0: float, z1: float) -> None:
        if s1 - s0 < 1e-3 or z1 - z0 < 1e-3:
            return
        c = wall.at(0.5 * (s0 + s1), -t / 2)
        mb.box((s1 - s0, t, z1 - z0), (c[0], c[1], 0.5 * (z0 + z1)), wall.yaw)

    cursor = lo
    for o in sorted(wall.openings, key=lambda o: o.s0):
        piece(cursor, o.s0, 0.0, height)
        piece(o.s0, o.s1, 0.0, o.z0)
        piece(o.s0, o.s1, o.z1, height)
        cursor = o.s1
    piece(cursor, hi, 0.0, height)


def _wall_box(mb: _MeshBuilder, wall: Wall, s: float, z: float, w: float, h: float,
              depth: float, inward: float = 0.0) -> None:
    """A box against a wall: centred at arc length s and height z, protruding ``depth``."""
    c = wall.at(s, inward + depth / 2)
    mb.box((w, depth, h), (c[0], c[1], z), wall.yaw)


# --------------------------------------------------------------------------------------------
# Clutter: small objects on flat tops. A top is (cx, cy, w, d, z, hmax) in an item's frame.
# --------------------------------------------------------------------------------------------

_Top = tuple[float, float, float, float, float, float]


def _small_object(mb: _MeshBuilder, rng: np.random.Generator, c: np.ndarray, yaw: float,
                  hmax: float, kitchen: bool) -> float:
    """One small object standing at world point c (its base); returns its footprint radius."""
    u = rng.uniform
    kinds = ["books", "mug", "bottle", "bowl", "box", "laptop", "lamp", "plant", "ball",
             "papers", "pot"]
    p = np.array([2, 2, 2, 1.5, 2, 0.7, 0.6, 0.8, 0.6, 1, 0.2 + 1.5 * kitchen])
    kind = kinds[int(rng.choice(len(kinds), p=p / p.sum()))]
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])

    def at(lx: float, ly: float, z: float) -> np.ndarray:
        return c + np.r_[R @ [lx, ly], z]

    if kind == "books":
        w, d, z = u(0.14, 0.3), u(0.1, 0.22), 0.0
        for _ in range(int(rng.integers(1, 6))):
            h = u(0.015, 0.05)
            if z + h > hmax:
                break
            mb.box((w * u(0.85, 1.0), d * u(0.85, 1.0), h), at(0, 0, z + h / 2), yaw + u(-0.2, 0.2))
            z += h
        return 0.5 * np.hypot(w, d)
    if kind == "mug":
        r, h = u(0.035, 0.05), min(u(0.08, 0.11), hmax)
        mb.cylinder(r, h, at(0, 0, h / 2), segments=10)
        mb.box((0.015, 0.03, h * 0.6), at(r + 0.012, 0, h / 2), yaw)
        return r + 0.03
    if kind == "bottle":
        r, h = u(0.03, 0.05), min(u(0.16, 0.3), hmax)
        mb.cylinder(r, 0.7 * h, at(0, 0, 0.35 * h), segments=10)
        mb.cylinder(r, 0.15 * h, at(0, 0, 0.775 * h), segments=10, top_radius=r * 0.4)
        mb.cylinder(r * 0.4, 0.15 * h, at(0, 0, 0.925 * h), segments=6)
        return r
    if kind == "bowl":
        r = u(0.06, 0.14)
        mb.cylinder(r * 0.5, min(r * 0.6, hmax), at(0, 0, min(r * 0.6, hmax) / 2), segments=14,
                    top_radius=r)
        return r
    if kind == "box":
        s = np.array([u(0.06, 0.35), u(0.06, 0.3), min(u(0.04, 0.3), hmax)])
        mb.box(s, at(0, 0, s[2] / 2), yaw + u(-0.4, 0.4))
        return 0.5 * np.hypot(s[0], s[1])
    if kind == "laptop":
        w, d = u(0.3, 0.38), u(0.21, 0.26)
        mb.box((w, d, 0.018), at(0, 0, 0.009), yaw)
        sh = min(u(0.19, 0.24), hmax)
        mb.box((w, 0.01, sh), at(0, d / 2, sh / 2), yaw)
        return 0.5 * np.hypot(w, d)
    if kind == "lamp":
        h = min(u(0.3, 0.55), hmax)
        mb.cylinder(u(0.06, 0.1), 0.02, at(0, 0, 0.01), segments=12)
        mb.cylinder(0.01, h, at(0, 0, h / 2), segments=6)
        r = u(0.07, 0.14)
        mb.cylinder(r, 0.15, at(0, 0, h), segments=12, top_radius=r * 0.6)
        return r
    if kind == "plant":
        r, h = u(0.05, 0.12), u(0.08, 0.18)
        mb.cylinder(r * 0.75, h, at(0, 0, h / 2), segments=10, top_radius=r)
        for _ in range(int(rng.integers(1, 4))):
            rs = u(0.6, 1.3) * r
            zc = min(h + rs * u(0.5, 1.2), hmax - rs)
            mb.sphere(rs, at(u(-r, r) * 0.5, u(-r, r) * 0.5, max(zc, h)), rings=5, segments=8)
        return 1.3 * r
    if kind == "ball":
        r = min(u(0.03, 0.12), hmax / 2)
        mb.sphere(r, at(0, 0, r), rings=6, segments=10)
        return r
    if kind == "papers":
        w, d = u(0.21, 0.32), u(0.15, 0.3)
        mb.box((w, d, u(0.005, 0.03)), at(0, 0, 0.01), yaw + u(-0.3, 0.3))
        return 0.5 * np.hypot(w, d)
    r, h = u(0.08, 0.14), min(u(0.08, 0.2), hmax)        # cooking pot / kettle
    mb.cylinder(r, h, at(0, 0, h / 2), segments=14)
    mb.box((0.12, 0.02, 0.02), at(r + 0.05, 0, h * 0.8), yaw)
    return r + 0.1


def _clutter(mb: _MeshBuilder, rng: np.random.Generator, f: _Local, tops: list[_Top],
             density: float, kitchen: bool = False) -> None:
    """Scatter small objects (Poisson, ``density`` per m^2 of top) on an item's tops."""
    for cx, cy, w, d, z, hmax in tops:
        if hmax < 0.04 or w < 0.1 or d < 0.08:
            continue
        placed: list[tuple[float, float, float]] = []
        for _ in range(int(rng.poisson(density * w * d + 0.3))):
            lx, ly = cx + rng.uniform(-0.42, 0.42) * w, cy + rng.uniform(-0.4, 0.4) * d
            if any(np.hypot(lx - a, ly - b) < r + 0.08 for a, b, r in placed):
                continue
            yaw = f.yaw + (rng.normal(0, 0.1) if rng.random() < 0.6 else rng.uniform(0, 2 * np.pi))
            r = _small_object(mb, rng, f.p(lx, ly, z), yaw, hmax, kitchen)
            placed.append((lx, ly, r))


def _as_tops(tops: list[tuple[float, float, float]], hmax: float = 0.4) -> list[_Top]:
    """The (w, d, z) tops of the scenes-module builders as centred _Top tuples."""
    return [(0.0, 0.0, w, d, z, hmax) for w, d, z in tops]


# --------------------------------------------------------------------------------------------
# Furniture. Local frame: x along the item's width, +y towards its back (the wall for wall
# items), z up from the floor; items are centred on the local origin. Each returns its tops.
# --------------------------------------------------------------------------------------------

def _fronts(f: _Local, rng: np.random.Generator, w: float, y_front: float, z0: float,
            z1: float) -> None:
    """Door / drawer fronts with handles across [-w/2, w/2] on a carcass face at y_front."""
    n = max(1, round(w / rng.uniform(0.4, 0.6)))
    fw = w / n
    for k in range(n):
        cx = -w / 2 + (k + 0.5) * fw
        drawers = int(rng.integers(2, 5)) if rng.random() < 0.35 else 1
        fh = (z1 - z0) / drawers
        for j in range(drawers):
            zc = z0 + (j + 0.5) * fh
            f.box((fw - 0.008, 0.018, fh - 0.008), cx, y_front - 0.009, zc)
            if drawers > 1:
                f.box((min(0.3, fw * 0.5), 0.025, 0.015), cx, y_front - 0.03, zc + fh * 0.25)
            else:
                hx = cx + (fw / 2 - 0.06) * (1 if k % 2 else -1)
                f.box((0.015, 0.025, min(0.25, fh * 0.4)), hx, y_front - 0.03, z0 + fh * 0.7)


def _counter(f: _Local, rng: np.random.Generator, w: float, d: float) -> list[_Top]:
    """Kitchen base cabinets with countertop (sink, hob), upper cabinets / open shelves."""
    u = rng.uniform
    h, tt, pl = u(0.86, 0.92), u(0.03, 0.045), u(0.08, 0.12)
    body = h - tt - pl
    y_front = -d / 2 + 0.04
    sink = w > 1.1 and rng.random() < 0.7
    sw, sd = u(0.4, 0.7), u(0.34, 0.44)
    sxc = u(-w / 2 + sw / 2 + 0.1, w / 2 - sw / 2 - 0.1) if sink else 0.0
    y0, y1 = -d / 2 - 0.02, d / 2
    if sink:
        bd = u(0.15, 0.22)                                      # basin depth
        xl, xr = sxc - sw / 2, sxc + sw / 2
        for a, b in ((-w / 2, xl), (xr, w / 2)):                # carcass beside the sink
            if b - a > 1e-3:
                f.box((b - a, d - 0.04, body), (a + b) / 2, 0.02, pl + body / 2)
        f.box((sw, d - 0.04, body - bd), sxc, 0.02, pl + (body - bd) / 2)
        for a, b in ((-w / 2, xl), (xr, w / 2)):
            if b - a > 1e-3:
                f.box((b - a, y1 - y0, tt), (a + b) / 2, (y0 + y1) / 2, h - tt / 2)
        yf, yb = -0.02 - sd / 2, -0.02 + sd / 2
        f.box((sw, yf - y0, tt), sxc, (y0 + yf) / 2, h - tt / 2)
        f.box((sw, y1 - yb, tt), sxc, (yb + y1) / 2, h - tt / 2)
        for yw in (yf, yb):                                     # basin front / back walls
            f.box((sw, 0.01, bd), sxc, yw, h - tt - bd / 2)
        f.cylinder(0.015, 0.25, sxc, yb + 0.06, h + 0.125, segments=6)      # tap
        f.box((0.02, 0.15, 0.02), sxc, yb + 0.0, h + 0.24)
    else:
        f.box((w, d - 0.04, body), 0, 0.02, pl + body / 2)
        f.box((w, y1 - y0, tt), 0, (y0 + y1) / 2, h - tt / 2)
    f.box((w, d - 0.1, pl), 0, 0.05, pl / 2)                    # recessed plinth
    _fronts(f, rng, w, y_front, pl, h - tt - 0.005)
    tops: list[_Top] = []
    free_lo, free_hi = (-w / 2, sxc - sw / 2) if sink else (-w / 2, w / 2)
    if sink and w / 2 - (sxc + sw / 2) > free_hi - free_lo:
        free_lo, free_hi = sxc + sw / 2, w / 2
    if free_hi - free_lo > 0.7 and rng.random() < 0.6:          # hob on the free part
        hx = u(free_lo + 0.35, free_hi - 0.35)
        for ox in (-0.14, 0.14):
            for oy in (-0.12, 0.12):
                f.cylinder(u(0.06, 0.1), 0.012, hx + ox, oy, h + 0.006, segments=12)
    tops.append(((free_lo + free_hi) / 2, -0.05, free_hi - free_lo, d * 0.8, h, 0.45))
    if rng.random() < 0.75:                                     # upper cabinets on the wall
        z0, uh, ud = u(1.4, 1.55), u(0.55, 0.8), u(0.3, 0.37)
        n = max(1, round(w / u(0.5, 0.9)))
        sw_ = w / n
        for k in range(n):
            cx = -w / 2 + (k + 0.5) * sw_
            yc = d / 2 - ud / 2
            if rng.random() < 0.25:                             # an open shelf section
                f.box((0.02, ud, uh), cx - sw_ / 2 + 0.01, yc, z0 + uh / 2)
                f.box((0.02, ud, uh), cx + sw_ / 2 - 0.01, yc, z0 + uh / 2)
                levels = int(rng.integers(2, 4))
                for j in range(levels):
                    zb = z0 + j * uh / (levels - 1) if levels > 1 else z0
                    f.box((sw_ - 0.04, ud, 0.02), cx, yc, zb)
                    if j < levels - 1:
                        tops.append((cx, yc, sw_ - 0.1, ud - 0.05, zb + 0.01,
                                     uh / (levels - 1) - 0.04))
            else:
                f.box((sw_ - 0.006, ud, uh), cx, yc, z0 + uh / 2)
                f.box((0.015, 0.025, 0.12), cx + sw_ / 2 - 0.06, yc - ud / 2 - 0.0125,
                      z0 + 0.1)
    return tops


def _fridge(f: _Local, rng: np.random.Generator, w: float, d: float) -> list[_Top]:
    h = rng.uniform(1.6, 2.0)
    f.box((w, d, h), 0, 0, h / 2)
    split = h * rng.uniform(0.3, 0.45)
    f.box((w - 0.01, 0.01, 0.01), 0, -d / 2 - 0.005, split)     # door gap line
    f.box((0.025, 0.04, 0.4), w / 2 - 0.06, -d / 2 - 0.02, split + 0.35)
    f.box((0.025, 0.04, 0.25), w / 2 - 0.06, -d / 2 - 0.02, split - 0.2)
    return [(0.0, 0.0, w, d, h, 0.3)]


def _island(f: _Local, rng: np.random.Generator, w: float, d: float) -> list[_Top]:
    h, oh = rng.uniform(0.88, 0.95), rng.uniform(0.1, 0.3)
    f.box((w, d - oh, h - 0.04), 0, -oh / 2, (h - 0.04) / 2)     # overhang on the +y side
    f.box((w + 0.04, d, 0.04), 0, 0, h - 0.02)
    _fronts(f, rng, w, -d / 2, 0.1, h - 0.05)
    return [(0.0, 0.0, w, d, h, 0.45)]


def _stool(f: _Local, rng: np.random.Generator, h: float) -> None:
    r = rng.uniform(0.15, 0.2)
    f.cylinder(r, 0.04, 0, 0, h - 0.02, segments=14)
    f.cylinder(0.025, h - 0.04, 0, 0, (h - 0.04) / 2, segments=6)
    f.cylinder(r * 1.1, 0.02, 0, 0, 0.01, segments=14)


def _table(f: _Local, rng: np.random.Generator, w: float, d: float,
           h: float | None = None) -> list[_Top]:
    h = rng.uniform(0.7, 0.78) if h is None else h
    top = rng.uniform(0.025, 0.05)
    t = rng.uniform(0.035, 0.06)
    if rng.random() < 0.25:                                     # pedestal / trestle table
        f.box((t * 2, d * 0.6, h - top), -w / 2 + 0.25, 0, (h - top) / 2)
        f.box((t * 2, d * 0.6, h - top), w / 2 - 0.25, 0, (h - top) / 2)
        f.box((w - 0.5, t, t), 0, 0, 0.3)
    else:
        for sx in (-1, 1):
            for sy in (-1, 1):
                f.box((t, t, h - top), sx * (w / 2 - t), sy * (d / 2 - t), (h - top) / 2)
        if rng.random() < 0.5:                                  # apron
            f.box((w - 2 * t, 0.02, 0.08), 0, d / 2 - t, h - top - 0.04)
            f.box((w - 2 * t, 0.02, 0.08), 0, -d / 2 + t, h - top - 0.04)
    f.box((w, d, top), 0, 0, h - top / 2)
    return [(0.0, 0.0, w, d, h, 0.45)]


def _desk(f: _Local, rng: np.random.Generator, w: float, d: float) -> list[_Top]:
    """Office desk: top, panel or leg frame, drawer unit, monitor(s) and keyboard."""
    u = rng.uniform
    h, top = u(0.72, 0.76), 0.03
    if rng.random() < 0.5:
        f.box((0.03, d - 0.04, h - top), -w / 2 + 0.02, 0, (h - top) / 2)
        f.box((0.03, d - 0.04, h - top), w / 2 - 0.02, 0, (h - top) / 2)
        f.box((w - 0.06, 0.02, 0.35), 0, d / 2 - 0.08, h - top - 0.2)   # modesty panel
    else:
        for sx in (-1, 1):
            f.box((0.05, d - 0.1, 0.03), sx * (w / 2 - 0.06), 0, 0.015)
            f.box((0.05, 0.05, h - top), sx * (w / 2 - 0.06), 0, (h - top) / 2)
    f.box((w, d, top), 0, 0, h - top / 2)
    if rng.random() < 0.5:                                      # drawer unit under one side
        dx = (w / 2 - 0.25) * rng.choice([-1, 1])
        f.box((0.4, 0.55, 0.6), dx, 0, 0.3)
        for j in range(3):
            f.box((0.36, 0.01, 0.17), dx, -0.28, 0.1 + j * 0.2)
    tops: list[_Top] = []
    if rng.random() < 0.8:
        n = 2 if w > 1.3 and rng.random() < 0.4 else 1
        for k in range(n):
            mx = (k - (n - 1) / 2) * u(0.5, 0.6) + u(-0.1, 0.1)
            mw, mh = u(0.45, 0.62), u(0.28, 0.38)
            f.box((0.22, 0.18, 0.015), mx, d / 2 - 0.2, h + 0.0075)       # foot
            f.box((0.04, 0.03, 0.12), mx, d / 2 - 0.16, h + 0.07)
            f.box((mw, 0.025, mh), mx, d / 2 - 0.17, h + 0.1 + mh / 2)   # screen
        f.box((u(0.35, 0.45), 0.14, 0.02), u(-0.1, 0.1), -d / 2 + 0.2, h + 0.01)   # keyboard
        tops.append((0.0, -d / 4, w * 0.9, d * 0.45, h, 0.45))
    else:
        tops.append((0.0, 0.0, w, d, h, 0.45))
    return tops


def _office_chair(f: _Local, rng: np.random.Generator) -> None:
    sh = rng.uniform(0.44, 0.52)
    for k in range(5):                                          # star base
        a = f.yaw + k * 2 * np.pi / 5
        c = f.p(0, 0, 0.05) + 0.16 * np.array([np.cos(a), np.sin(a), 0.0])
        f.mb.box((0.32, 0.04, 0.03), c, a)
        f.mb.sphere(0.025, c + 0.15 * np.array([np.cos(a), np.sin(a), 0.0]) - [0, 0, 0.025],
                    rings=4, segments=6)
    f.cylinder(0.025, sh - 0.12, 0, 0, 0.06 + (sh - 0.12) / 2, segments=8)
    f.box((0.48, 0.46, 0.07), 0, 0, sh)
    bh = rng.uniform(0.4, 0.6)
    f.box((0.44, 0.06, bh), 0, 0.24, sh + 0.08 + bh / 2)
    if rng.random() < 0.6:                                      # arm rests
        for sx in (-1, 1):
            f.box((0.05, 0.25, 0.03), sx * 0.26, 0.02, sh + 0.22)
            f.box((0.03, 0.03, 0.2), sx * 0.26, 0.05, sh + 0.11)


def _bookcase(f: _Local, rng: np.random.Generator, w: float, d: float) -> list[_Top]:
    """Open shelves with rows of upright books, gaps, lying stacks and objects."""
    u = rng.uniform
    h = u(0.9, 2.2)
    t = 0.02
    n = max(2, int(h / u(0.3, 0.42)))
    f.box((t, d, h), -w / 2 + t / 2, 0, h / 2)
    f.box((t, d, h), w / 2 - t / 2, 0, h / 2)
    if rng.random() < 0.7:
        f.box((w, t, h), 0, d / 2 - t / 2, h / 2)               # back panel
    tops: list[_Top] = []
    gap = (h - t) / n
    for k in range(n + 1):
        z = t / 2 + k * gap
        f.box((w - 2 * t, d - t, t), 0, -t / 2, z)
        if k == n:
            tops.append((0.0, 0.0, w, d, z + t / 2, 0.4))
            break
        x = -w / 2 + t + u(0.0, 0.1)
        x_end = w / 2 - t
        while x < x_end - 0.03:
            if rng.random() < 0.15:                             # a gap
                x += u(0.05, 0.25)
                continue
            if rng.random() < 0.75:                             # a run of upright books
                for _ in range(int(rng.integers(3, 14))):
                    bw = u(0.015, 0.05)
                    if x + bw > x_end:
                        break
                    bh = min(u(0.16, 0.32), gap - 0.03)
                    bd = min(u(0.13, 0.25), d - 0.04)
                    f.box((bw, bd, bh), x + bw / 2, -d / 2 + bd / 2 + u(0.0, 0.04),
                          z + t / 2 + bh / 2)
                    x += bw + 0.001
            else:                                               # a lying stack or an object
                ow = min(u(0.12, 0.3), x_end - x)
                if ow > 0.06:
                    tops.append((x + ow / 2, -0.02, ow, d - 0.06, z + t / 2, gap - 0.03))
                x += ow
    return tops


def _shelf_rack(f: _Local, rng: np.random.Generator, w: float, d: float) -> list[_Top]:
    """Metal storage rack: four posts, 3-6 boards, cartons on the boards."""
    u = rng.uniform
    h = u(1.5, 2.6)
    n = int(rng.integers(3, 7))
    for sx in (-1, 1):
        for sy in (-1, 1):
            f.box((0.04, 0.04, h), sx * (w / 2 - 0.02), sy * (d / 2 - 0.02), h / 2)
    tops: list[_Top] = []
    for k in range(n):
        z = 0.1 + k * (h - 0.15) / (n - 1)
        f.box((w, d, 0.025), 0, 0, z)
        x = -w / 2 + 0.03
        while x < w / 2 - 0.15 and k < n - 1:
            bw = u(0.2, 0.6)
            if x + bw > w / 2 - 0.03:
                break
            if rng.random() < 0.75:
                bh = min(u(0.15, 0.45), (h - 0.15) / (n - 1) - 0.05)
                bd = u(0.5, 0.95) * d
                f.box((bw, bd, bh), x + bw / 2, u(-0.05, 0.05) * d, z + 0.0125 + bh / 2)
            x += bw + u(0.01, 0.15)
        if k == n - 1:
            tops.append((0.0, 0.0, w, d, z + 0.0125, 0.5))
    return tops


def _wardrobe(f: _Local, rng: np.random.Generator, w: float, d: float) -> list[_Top]:
    h = rng.uniform(1.8, 2.3)
    f.box((w, d, h - 0.06), 0, 0, 0.06 + (h - 0.06) / 2)
    f.box((w - 0.04, d - 0.04, 0.06), 0, 0.02, 0.03)
    f.box((w + 0.04, d + 0.03, 0.04), 0, -0.015, h + 0.02)      # crown
    n = max(2, round(w / 0.5))
    for k in range(n):
        x = -w / 2 + (k + 0.5) * w / n
        f.box((w / n - 0.006, 0.018, h - 0.1), x, -d / 2 - 0.009, 0.06 + (h - 0.06) / 2)
        hx = x + (w / n / 2 - 0.05) * (1 if k % 2 else -1)
        f.box((0.015, 0.03, 0.3), hx, -d / 2 - 0.03, h * 0.5)
    return [(0.0, 0.0, w, d, h + 0.04, 0.4)]


def _bed(f: _Local, rng: np.random.Generator, w: float, d: float) -> list[_Top]:
    """Bed with its head (+y) at the wall: frame, mattress, duvet, pillows, headboard."""
    u = rng.uniform
    fh = u(0.2, 0.35)
    f.box((w, d, fh), 0, 0, fh / 2)
    mh = u(0.18, 0.25)
    f.box((w - 0.06, d - 0.06, mh), 0, 0, fh + mh / 2)
    f.box((w + 0.04, u(0.6, 0.8) * d, 0.06), 0, -d * u(0.05, 0.15), fh + mh + 0.02)   # duvet
    hb = u(0.4, 0.8)
    f.box((w + 0.04, 0.06, fh + mh + hb), 0, d / 2 + 0.03, (fh + mh + hb) / 2)
    n = 2 if w > 1.2 else 1
    for k in range(n):
        px = (k - (n - 1) / 2) * w / 2
        f.box((min(0.65, w / n - 0.1), u(0.3, 0.4), u(0.1, 0.16)), px + u(-0.05, 0.05),
              d / 2 - 0.25, fh + mh + 0.06)
    return []


def _plant(f: _Local, rng: np.random.Generator, w: float, d: float) -> list[_Top]:
    r = min(w, d) / 2
    h = rng.uniform(0.25, 0.5)
    f.cylinder(r * 0.7, h, 0, 0, h / 2, segments=14, top_radius=r)
    top = h
    for _ in range(int(rng.integers(2, 6))):
        rs = rng.uniform(0.5, 1.0) * r * 1.4
        c = f.p(rng.uniform(-r, r) * 0.6, rng.uniform(-r, r) * 0.6, top + rng.uniform(0.1, 0.9))
        f.mb.sphere(rs, c, rings=6, segments=9)
    return []


def _tv_stand(f: _Local, rng: np.random.Generator, w: float, d: float) -> list[_Top]:
    h = rng.uniform(0.4, 0.6)
    f.box((w, d, h - 0.05), 0, 0, 0.05 + (h - 0.05) / 2)
    f.box((w - 0.04, d - 0.04, 0.05), 0, 0, 0.025)
    _fronts(f, rng, w, -d / 2, 0.07, h - 0.02)
    tw = min(w - 0.1, rng.uniform(0.8, 1.5))
    th = tw * 0.58
    f.box((0.3, 0.2, 0.02), 0, 0.05, h + 0.01)
    f.box((0.06, 0.04, 0.1), 0, 0.08, h + 0.07)
    f.box((tw, 0.05, th), 0, 0.08, h + 0.1 + th / 2)
    return [(-w / 2 + (w - tw) / 4, 0.0, (w - tw) / 2, d, h, 0.4),
            (w / 2 - (w - tw) / 4, 0.0, (w - tw) / 2, d, h, 0.4)]


def _carton_stack(f: _Local, rng: np.random.Generator, w: float, d: float) -> list[_Top]:
    z = 0.0
    if rng.random() < 0.4:                                      # a pallet under the stack
        for k in range(5):
            f.box((w, 0.09, 0.02), 0, -d / 2 + 0.045 + k * (d - 0.09) / 4, 0.13)
        for k in range(3):
            f.box((0.1, d, 0.1), -w / 2 + 0.05 + k * (w - 0.1) / 2, 0, 0.06)
        z = 0.14
    for _ in range(int(rng.integers(1, 4))):
        bw, bd, bh = w * rng.uniform(0.5, 1.0), d * rng.uniform(0.5, 1.0), rng.uniform(0.2, 0.5)
        f.box((bw, bd, bh), rng.uniform(-0.1, 0.1) * w, rng.uniform(-0.1, 0.1) * d, z + bh / 2)
        z += bh
        w, d = bw, bd
    return [(0.0, 0.0, w, d, z, 0.3)]


def _pillar(f: _Local, rng: np.random.Generator, w: float, d: float, height: float) -> None:
    if rng.random() < 0.5:
        f.cylinder(min(w, d) / 2, height, 0, 0, height / 2, segments=18)
    else:
        f.box((w, d, height), 0, 0, height / 2)


def _radiator(mb: _MeshBuilder, wall: Wall, s: float, w: float) -> None:
    h = 0.5
    n = max(3, int(w / 0.06))
    for k in range(n):
        _wall_box(mb, wall, s - w / 2 + (k + 0.5) * w / n, 0.15 + h / 2, 0.03, h, 0.08,
                  inward=0.04)
    _wall_box(mb, wall, s, 0.15 + 0.05, w, 0.03, 0.02, inward=0.05)


# --------------------------------------------------------------------------------------------
# The room
# --------------------------------------------------------------------------------------------

@dataclass
class RichRoom(Room):
    """A :class:`scenes.Room` (vertices, triangles, raycasting scene) plus its layout.

    kind: one of ROOM_KINDS; footprint: (V, 2) CCW polygon of the floor; grid: floor grid of
    free space (where a camera holder or a robot can stand); walls: the footprint edges with
    their openings.
    """

    kind: str = "living"
    footprint: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    grid: FloorGrid | None = None
    walls: list[Wall] = field(default_factory=list)


class _Ctx:
    """Building state shared by the furnishing helpers."""

    def __init__(self, rng: np.random.Generator, kind: str, poly: np.ndarray, height: float):
        self.rng, self.kind, self.poly, self.height = rng, kind, poly, height
        self.mb = _MeshBuilder()
        self.walls = _walls(poly)
        self.grid = FloorGrid.over(poly)
        self.items: list[str] = []
        self.targets: list[np.ndarray] = []
        self.density = {"kitchen": 9.0, "office": 7.0, "storage": 5.0}.get(kind, 5.0)

    # ---- placement ----
    def wall_item(self, name: str, build: Any, w: float, d: float, top: float,
                  tries: int = 12, gap: float = 0.01) -> _Local | None:
        """Put an item with its back to a random wall; None when it does not fit."""
        rng = self.rng
        walls = [wl for wl in self.walls if wl.length >= w + 0.1]
        if not walls:
            return None
        L = np.array([wl.length for wl in walls])
        for _ in range(tries):
            wall = walls[int(rng.choice(len(walls), p=L / L.sum()))]
            s = rng.uniform(w / 2 + 0.02, wall.length - w / 2 - 0.02)
            if not wall.free_interval(s - w / 2, s + w / 2, top):
                continue
            x, y = wall.at(s, d / 2 + gap)
            yaw = wall.item_yaw()
            if not self.grid.fits(x, y, yaw, w, d, margin=0.01):
                continue
            return self._put(name, build, x, y, yaw, w, d)
        return None

    def free_item(self, name: str, build: Any, w: float, d: float, margin: float = 0.4,
                  tries: int = 15, xy: np.ndarray | None = None,
                  yaw: float | None = None) -> _Local | None:
        """Put an item on free floor (keeping ``margin`` of walkway); None when it fails."""
        rng = self.rng
        for _ in range(tries):
            p = self.grid.sample(rng, 0.5 * np.hypot(w, d) + margin)[0] if xy is None else xy
            a = yaw
            if a is None:
                a = rng.integers(4) * np.pi / 2 + (rng.normal(0, 0.08) if rng.random() < 0.75
                                                   else rng.uniform(0, 2 * np.pi))
            if self.grid.fits(p[0], p[1], a, w, d, margin=margin):
                return self._put(name, build, p[0], p[1], a, w, d)
            if xy is not None:
                break
        return None

    def _put(self, name: str, build: Any, x: float, y: float, yaw: float, w: float,
             d: float) -> _Local:
        f = _Local(self.mb, x, y, yaw)
        tops = build(f, self.rng, w, d) if build is not None else []
        self.grid.mark(x, y, yaw, w, d)
        _clutter(self.mb, self.rng, f, tops, self.density, kitchen=self.kind == "kitchen")
        self.items.append(name)
        z = max([t[4] for t in tops], default=0.6)
        self.targets.append(np.array([x, y, min(z, 1.5)]))
        return f

    def chairs_around(self, f: _Local, w: float, d: float, n: int, office: bool = False) -> None:
        """Up to n chairs facing the item at f, on its four sides."""
        rng = self.rng
        sides = rng.permutation([(0, -1), (0, 1), (-1, 0), (1, 0)] * 2)[:n]
        for sx, sy in sides:
            dist = (abs(sx) * w + abs(sy) * d) / 2 + rng.uniform(0.05, 0.3)
            off = rng.uniform(-0.3, 0.3) * (w if sy else d)
            lx, ly = (sx * dist, off) if sx else (off, sy * dist)
            p = f.p(lx, ly, 0.0)
            # The chair's back (+y) points away from the table.
            yaw = np.arctan2(p[1] - f.o[1], p[0] - f.o[0]) - np.pi / 2 + rng.normal(0, 0.25)
            if not self.grid.fits(p[0], p[1], yaw, 0.5, 0.5, margin=0.0):
                continue
            fc = _Local(self.mb, p[0], p[1], yaw)
            if office:
                _office_chair(fc, rng)
            else:
                _chair(fc, rng, rng.uniform(0.42, 0.5), rng.uniform(0.42, 0.5))
            self.grid.mark(p[0], p[1], yaw, 0.5, 0.5)
            self.items.append("chair")


def _openings(ctx: _Ctx) -> None:
    """Doors (with a corridor behind an open one) and windows in the walls."""
    rng, H = ctx.rng, ctx.height
    walls = ctx.walls
    n_doors = 1 + int(rng.random() < (0.5 if ctx.kind == "hall" else 0.25))
    n_windows = int(rng.choice([0, 1, 1, 2, 2, 3, 4])) if ctx.kind != "storage" else \
        int(rng.integers(0, 2))
    for kind, count in (("door", n_doors), ("window", n_windows)):
        for _ in range(count):
            for _try in range(20):
                if kind == "door":
                    double = rng.random() < 0.15 and min(ctx.poly.max(0) - ctx.poly.min(0)) > 4
                    w = rng.uniform(1.4, 1.9) if double else rng.uniform(0.8, 1.0)
                    z0, z1 = 0.0, min(H - 0.2, rng.uniform(2.0, 2.2))
                else:
                    w = rng.uniform(0.6, 2.2)
                    z0 = rng.uniform(0.7, 1.1)
                    z1 = min(H - 0.15, z0 + rng.uniform(0.9, 1.6))
                fit = [wl for wl in walls if wl.length >= w + 0.5]
                if not fit:
                    continue
                L = np.array([wl.length for wl in fit])
                wall = fit[int(rng.choice(len(fit), p=L / L.sum()))]
                s = rng.uniform(w / 2 + 0.2, wall.length - w / 2 - 0.2)
                if any(s + w / 2 > o.s0 - 0.25 and s - w / 2 < o.s1 + 0.25 for o in wall.openings):
                    continue
                o = Opening(kind, s - w / 2, s + w / 2, z0, z1)
                if kind == "door" and not _door(ctx, wall, o, closed_ok=_try >= 15):
                    continue
                wall.openings.append(o)
                if kind == "window":
                    _window_details(ctx, wall, o)
                break


def _door(ctx: _Ctx, wall: Wall, o: Opening, closed_ok: bool) -> bool:
    """Door frame, leaf and (for an open door) a corridor behind it. Where a corridor would cut
    into the room the door is closed (``closed_ok``) or not placed (returns False)."""
    rng, mb = ctx.rng, ctx.mb
    w = o.s1 - o.s0
    depth, extra = rng.uniform(1.2, 2.5), rng.uniform(0.3, 1.5)
    # Corridor rectangle outside the wall must not contain any footprint point.
    probe = []
    for a in np.linspace(-extra, w + extra, 12):
        for b in np.linspace(_WALL_T + 0.05, depth, 6):
            probe.append(wall.at(o.s0 + a, -b))
    room_behind = bool(inside_polygon(np.array(probe), ctx.poly).any())
    if room_behind and not closed_ok:
        return False
    # Reserve the swing area in front of the door.
    c = wall.at(0.5 * (o.s0 + o.s1), 0.55)
    ctx.grid.mark(c[0], c[1], wall.item_yaw(), w + 0.2, 1.1, reserve=True)
    for side in (o.s0 - 0.04, o.s1 + 0.04):                     # casing
        _wall_box(mb, wall, side, o.z1 / 2, 0.08, o.z1, 0.02)
    _wall_box(mb, wall, 0.5 * (o.s0 + o.s1), o.z1 + 0.04, w + 0.16, 0.08, 0.02)
    state = rng.random()
    if state < 0.25 or room_behind:                             # closed: a leaf in the hole
        _wall_box(mb, wall, 0.5 * (o.s0 + o.s1), o.z1 / 2, w, o.z1, 0.04, inward=-0.08)
        return True
    if state < 0.8:                                             # open leaf swung into the room
        ang = rng.uniform(0.3, 1.8)
        hinge_s, sign = (o.s0, 1.0) if rng.random() < 0.5 else (o.s1, -1.0)
        hinge = wall.at(hinge_s, 0.0)
        dirv = sign * np.cos(ang) * wall.d - np.sin(ang) * wall.n   # into the room
        lw = w if w < 1.2 else w / 2
        c2 = hinge + dirv * lw / 2
        mb.box((lw, 0.04, o.z1 - 0.01), (c2[0], c2[1], o.z1 / 2), float(np.arctan2(dirv[1], dirv[0])))
        ctx.grid.mark(c2[0], c2[1], float(np.arctan2(dirv[1], dirv[0])), lw, 0.1)
    # Corridor behind the opening: floor, ceiling, side walls, end wall (and a cabinet).
    H = ctx.height
    s_lo, s_hi = o.s0 - extra, o.s1 + extra
    mid = 0.5 * (s_lo + s_hi)
    span = s_hi - s_lo
    for z, h in ((-0.05, 0.1), (H + 0.05, 0.1)):
        c = wall.at(mid, -(_WALL_T + depth / 2))
        mb.box((span, depth, h), (c[0], c[1], z), wall.yaw)
    c = wall.at(mid, -(_WALL_T + depth + 0.05))
    mb.box((span, 0.1, H), (c[0], c[1], H / 2), wall.yaw)
    for s_side in (s_lo - 0.05, s_hi + 0.05):
        c = wall.at(s_side, -(_WALL_T + depth / 2))
        mb.box((0.1, depth, H), (c[0], c[1], H / 2), wall.yaw)
    if rng.random() < 0.5:
        c = wall.at(mid + rng.uniform(-0.3, 0.3) * span, -(_WALL_T + depth - 0.2))
        mb.box((rng.uniform(0.4, 1.0), 0.4, rng.uniform(0.5, 1.8)), (c[0], c[1], 0.6), wall.yaw)
    return True


def _window_details(ctx: _Ctx, wall: Wall, o: Opening) -> None:
    rng, mb = ctx.rng, ctx.mb
    s, w = 0.5 * (o.s0 + o.s1), o.s1 - o.s0
    _wall_box(mb, wall, s, o.z0 - 0.015, w + 0.1, 0.03, rng.uniform(0.05, 0.2))   # sill
    if rng.random() < 0.6:                                      # mullions / frame bars
        for k in range(1, int(rng.integers(1, 4)) + 1):
            _wall_box(mb, wall, o.s0 + k * w / (k + 1), 0.5 * (o.z0 + o.z1), 0.05,
                      o.z1 - o.z0, 0.05, inward=-_WALL_T / 2 - 0.025)
    if rng.random() < 0.4 and o.z0 > 0.75:
        _radiator(mb, wall, s, min(w, rng.uniform(0.5, 1.4)))
    if rng.random() < 0.3:                                      # curtains beside the window
        for side in (o.s0 - 0.15, o.s1 + 0.15):
            _wall_box(mb, wall, side, ctx.height / 2 - 0.1, 0.25, ctx.height - 0.4, 0.08,
                      inward=0.03)


def _wall_decor(ctx: _Ctx) -> None:
    """Pictures, wall shelves with clutter, whiteboards, skirting."""
    rng, mb = ctx.rng, ctx.mb
    for wall in ctx.walls:
        if wall.length > 0.4:
            _wall_box(mb, wall, wall.length / 2, 0.04, wall.length, 0.08, 0.015)    # skirting
        for _ in range(int(rng.poisson(0.35 * wall.length))):
            w = rng.uniform(0.3, 1.4)
            if wall.length < w + 0.3:
                continue
            s = rng.uniform(w / 2 + 0.1, wall.length - w / 2 - 0.1)
            if not wall.free_interval(s - w / 2, s + w / 2, 10.0):
                continue
            r = rng.random()
            if r < 0.45:                                        # picture / poster / clock
                h = rng.uniform(0.3, 1.0)
                _wall_box(mb, wall, s, rng.uniform(1.3, 1.9), w * 0.8, h, rng.uniform(0.01, 0.05))
            elif r < 0.8:                                       # wall shelf with clutter
                z = rng.uniform(1.1, 1.9)
                dd = rng.uniform(0.18, 0.3)
                _wall_box(mb, wall, s, z, w, 0.025, dd)
                for bs in (s - w / 2 + 0.08, s + w / 2 - 0.08):
                    _wall_box(mb, wall, bs, z - 0.08, 0.02, 0.14, dd * 0.8)
                x, y = wall.at(s, dd / 2)
                f = _Local(mb, x, y, wall.item_yaw())
                _clutter(mb, rng, f, [(0.0, 0.0, w, dd, z + 0.0125, 0.35)], ctx.density)
            else:                                               # whiteboard / TV / panel
                h = rng.uniform(0.6, 1.2)
                _wall_box(mb, wall, s, rng.uniform(1.2, 1.6), w, h, rng.uniform(0.02, 0.07))


def _ceiling(ctx: _Ctx) -> None:
    rng, mb, H = ctx.rng, ctx.mb, ctx.height
    lo, hi = ctx.poly.min(0), ctx.poly.max(0)
    if rng.random() < 0.3:                                      # beams across the short side
        along_x = (hi - lo)[0] < (hi - lo)[1]
        n = int(rng.integers(1, 4))
        for k in range(n):
            t = (k + 1) / (n + 1)
            bh = rng.uniform(0.15, 0.35)
            if along_x:
                mb.box((hi[0] - lo[0], 0.2, bh), ((lo[0] + hi[0]) / 2, lo[1] + t * (hi[1] - lo[1]),
                                                  H - bh / 2))
            else:
                mb.box((0.2, hi[1] - lo[1], bh), (lo[0] + t * (hi[0] - lo[0]), (lo[1] + hi[1]) / 2,
                                                  H - bh / 2))
    for _ in range(int(rng.integers(1, 4))):                    # lamps / ceiling panels
        p = ctx.grid.sample(rng, 0.3)[0]
        if rng.random() < 0.5:
            drop = rng.uniform(0.2, max(0.25, min(0.9, H - 2.3)))   # keep the lamp above 2 m
            mb.cylinder(0.006, drop, (p[0], p[1], H - drop / 2), segments=4)
            r = rng.uniform(0.12, 0.3)
            mb.cylinder(r, 0.2, (p[0], p[1], H - drop - 0.1), segments=14, top_radius=r * 0.4)
        else:
            mb.box((rng.uniform(0.5, 1.2), rng.uniform(0.3, 0.6), 0.05), (p[0], p[1], H - 0.025),
                   rng.integers(2) * np.pi / 2)
    if ctx.kind in ("storage", "hall") and rng.random() < 0.6:  # a duct along the ceiling
        r = rng.uniform(0.1, 0.25)
        y = rng.uniform(lo[1] + 0.5, hi[1] - 0.5)
        n_seg = max(1, int((hi[0] - lo[0]) / 1.0))
        for k in range(n_seg):                                  # horizontal: boxes in series
            x0 = lo[0] + k * (hi[0] - lo[0]) / n_seg
            mb.box(((hi[0] - lo[0]) / n_seg - 0.02, 2 * r, 2 * r),
                   (x0 + (hi[0] - lo[0]) / n_seg / 2, y, H - r - 0.1))


def _furnish(ctx: _Ctx) -> None:
    rng, u, kind = ctx.rng, ctx.rng.uniform, ctx.kind
    area = float(ctx.grid.inside.sum()) * ctx.grid.res ** 2

    def some(n_lo: int, n_hi: int) -> int:
        return int(rng.integers(n_lo, n_hi + 1))

    if kind == "kitchen":
        runs = some(1, 3)
        for _ in range(runs):
            w = u(1.2, 3.6)
            ctx.wall_item("counter", _counter, w, 0.62, 0.92, tries=30) or \
                ctx.wall_item("counter", _counter, w / 2, 0.62, 0.92, tries=30)
        if rng.random() < 0.8:
            ctx.wall_item("fridge", _fridge, u(0.6, 0.9), u(0.62, 0.72), 2.0)
        if area > 14 and rng.random() < 0.5:
            w, d = u(1.2, 2.2), u(0.8, 1.1)
            f = ctx.free_item("island", _island, w, d, margin=0.8)
            if f is not None:
                for k in range(some(0, 3)):
                    p = f.p(-w / 2 + (k + 0.5) * w / 3, d / 2 + 0.3, 0.0)
                    if ctx.grid.fits(p[0], p[1], 0.0, 0.4, 0.4):
                        _stool(_Local(ctx.mb, p[0], p[1], 0.0), rng, u(0.6, 0.75))
                        ctx.grid.mark(p[0], p[1], 0.0, 0.4, 0.4)
        if rng.random() < 0.7:
            w, d = u(0.8, 1.6), u(0.7, 1.0)
            f = ctx.free_item("table", _table, w, d, margin=0.6)
            if f is not None:
                ctx.chairs_around(f, w, d, some(1, 4))
        for _ in range(some(0, 2)):
            ctx.wall_item("cabinet", lambda f, r, w, d: _as_tops(_cabinet(f, r, w, d)),
                          u(0.5, 1.2), u(0.35, 0.5), 1.2)
    elif kind == "office":
        n_desks = max(1, int(area / u(4.0, 8.0)))
        for _ in range(n_desks):
            w, d = u(1.0, 1.8), u(0.6, 0.8)
            if rng.random() < 0.6:
                f = ctx.wall_item("desk", _desk, w, d, 0.8)
            else:
                f = ctx.free_item("desk", _desk, w, d, margin=0.7)
            if f is not None:
                p = f.p(u(-0.2, 0.2) * w, -d / 2 - u(0.2, 0.5), 0.0)
                yaw = f.yaw + np.pi + rng.normal(0, 0.4)
                if ctx.grid.fits(p[0], p[1], yaw, 0.55, 0.55):
                    _office_chair(_Local(ctx.mb, p[0], p[1], yaw), rng)
                    ctx.grid.mark(p[0], p[1], yaw, 0.55, 0.55)
                    ctx.items.append("office_chair")
        for _ in range(some(1, 4)):
            ctx.wall_item("bookcase", _bookcase, u(0.6, 1.6), u(0.28, 0.4), 2.2)
        for _ in range(some(0, 3)):
            ctx.wall_item("filing", lambda f, r, w, d: _as_tops(_cabinet(f, r, w, d)),
                          u(0.4, 0.9), u(0.45, 0.6), 1.3)
        if area > 16 and rng.random() < 0.6:
            w, d = u(1.6, 3.0), u(0.9, 1.3)
            f = ctx.free_item("meeting_table", _table, w, d, margin=0.7)
            if f is not None:
                ctx.chairs_around(f, w, d, some(2, 6), office=True)
        for _ in range(some(0, 3)):
            ctx.free_item("plant", _plant, u(0.3, 0.5), u(0.3, 0.5), margin=0.2)
    elif kind == "living":
        ctx.wall_item("sofa", lambda f, r, w, d: (_sofa(f, r, w, d), [])[1],
                      u(1.5, 2.4), u(0.8, 0.95), 0.9)
        for _ in range(some(0, 2)):
            ctx.free_item("armchair", lambda f, r, w, d: (_sofa(f, r, w, d), [])[1],
                          u(0.75, 0.95), u(0.75, 0.9), margin=0.4)
        ctx.free_item("coffee_table", lambda f, r, w, d: _table(f, r, w, d, r.uniform(0.35, 0.48)),
                      u(0.8, 1.3), u(0.5, 0.8), margin=0.45)
        ctx.wall_item("tv_stand", _tv_stand, u(1.0, 2.0), u(0.4, 0.5), 1.4)
        for _ in range(some(1, 3)):
            ctx.wall_item("bookcase", _bookcase, u(0.6, 1.4), u(0.28, 0.4), 2.2)
        for _ in range(some(0, 3)):
            ctx.free_item("cylinder", lambda f, r, w, d: _as_tops(_cylinder_item(f, r, w, d)),
                          u(0.3, 0.55), u(0.3, 0.55), margin=0.3)
        for _ in range(some(0, 3)):
            ctx.free_item("plant", _plant, u(0.3, 0.55), u(0.3, 0.55), margin=0.2)
        if rng.random() < 0.5:
            w, d = u(1.0, 1.6), u(0.8, 1.0)
            f = ctx.free_item("table", _table, w, d, margin=0.6)
            if f is not None:
                ctx.chairs_around(f, w, d, some(1, 4))
    elif kind == "bedroom":
        w = u(0.9, 1.8)
        f = ctx.wall_item("bed", _bed, w, u(1.95, 2.15), 0.6, tries=30)
        if f is not None:
            for sx in (-1, 1):
                if rng.random() < 0.75:
                    p = f.p(sx * (w / 2 + 0.3), 2.05 / 2 - 0.22, 0.0)
                    if ctx.grid.fits(p[0], p[1], f.yaw, 0.45, 0.4):
                        fn = _Local(ctx.mb, p[0], p[1], f.yaw)
                        tops = _as_tops(_cabinet(fn, rng, 0.45, 0.4))
                        ctx.grid.mark(p[0], p[1], f.yaw, 0.45, 0.4)
                        _clutter(ctx.mb, rng, fn, tops, ctx.density)
        ctx.wall_item("wardrobe", _wardrobe, u(1.0, 2.2), u(0.55, 0.65), 2.3)
        if rng.random() < 0.6:
            f = ctx.wall_item("desk", _desk, u(0.9, 1.4), u(0.5, 0.7), 0.8)
            if f is not None:
                p = f.p(0.0, -0.6, 0.0)
                if ctx.grid.fits(p[0], p[1], f.yaw + np.pi, 0.5, 0.5):
                    _chair(_Local(ctx.mb, p[0], p[1], f.yaw + np.pi + rng.normal(0, 0.3)),
                           rng, 0.45, 0.45)
                    ctx.grid.mark(p[0], p[1], f.yaw, 0.5, 0.5)
        for _ in range(some(0, 2)):
            ctx.wall_item("dresser", lambda f, r, w, d: _as_tops(_cabinet(f, r, w, d)),
                          u(0.8, 1.4), u(0.4, 0.55), 1.2)
        for _ in range(some(0, 1)):
            ctx.wall_item("bookcase", _bookcase, u(0.5, 1.0), u(0.25, 0.35), 2.2)
    elif kind == "storage":
        for _ in range(some(2, 6)):
            ctx.wall_item("rack", _shelf_rack, u(0.9, 2.0), u(0.4, 0.6), 2.6)
        for _ in range(some(0, 3)):
            ctx.free_item("rack", _shelf_rack, u(0.9, 2.0), u(0.4, 0.6), margin=0.6)
        for _ in range(some(1, 6)):
            ctx.free_item("cartons", _carton_stack, u(0.4, 1.2), u(0.4, 1.0), margin=0.3)
        for _ in range(some(0, 3)):
            ctx.free_item("cylinder", lambda f, r, w, d: _as_tops(_cylinder_item(f, r, w, d)),
                          u(0.3, 0.6), u(0.3, 0.6), margin=0.3)
    else:                                                       # hall
        lo, hi = ctx.poly.min(0), ctx.poly.max(0)
        if rng.random() < 0.7:                                  # a grid of pillars
            step = u(3.5, 6.0)
            pw = u(0.3, 0.6)
            for x in np.arange(lo[0] + step, hi[0] - 1.0, step):
                for y in np.arange(lo[1] + step, hi[1] - 1.0, step):
                    if ctx.grid.fits(x, y, 0.0, pw, pw, margin=0.1):
                        _pillar(_Local(ctx.mb, x, y, 0.0), rng, pw, pw, ctx.height)
                        ctx.grid.mark(x, y, 0.0, pw, pw)
                        ctx.items.append("pillar")
        for _ in range(some(2, 6)):
            ctx.wall_item("rack", _shelf_rack, u(1.2, 3.0), u(0.5, 0.9), 2.6)
        for _ in range(some(1, 4)):
            w, d = u(1.2, 2.5), u(0.7, 1.2)
            f = ctx.free_item("table", _table, w, d, margin=1.0)
            if f is not None:
                ctx.chairs_around(f, w, d, some(0, 6))
        for _ in range(some(2, 8)):
            ctx.free_item("cartons", _carton_stack, u(0.5, 1.3), u(0.5, 1.2), margin=0.6)
        for _ in range(some(0, 4)):
            ctx.free_item("plant", _plant, u(0.3, 0.6), u(0.3, 0.6), margin=0.4)
        if rng.random() < 0.5:
            ctx.wall_item("counter", lambda f, r, w, d: _as_tops(_cabinet(f, r, w, d)),
                          u(1.5, 3.0), u(0.6, 0.8), 1.2)
    # A few extra generic items everywhere, for variety (more where little else fitted).
    extra = some(0, 3)
    for k in range(30):
        if k >= extra and len(ctx.items) >= 4:
            break
        r = rng.random()
        if r < 0.4:
            ctx.free_item("box", _carton_stack, u(0.25, 0.6), u(0.25, 0.6), margin=0.3)
        elif r < 0.7:
            ctx.free_item("cylinder", lambda f, r_, w, d: _as_tops(_cylinder_item(f, r_, w, d)),
                          u(0.25, 0.5), u(0.25, 0.5), margin=0.3)
        elif r < 0.85:
            ctx.wall_item("cabinet", lambda f, r_, w, d: _as_tops(_cabinet(f, r_, w, d)),
                          u(0.4, 1.0), u(0.3, 0.5), 1.2)
        else:
            ctx.free_item("table", _table, u(0.6, 1.0), u(0.5, 0.8), margin=0.4)
    if rng.random() < 0.3:                                      # a rug (a thin slab)
        ctx.mb.box((u(1.2, 2.5), u(0.9, 1.8), 0.012),
                   np.r_[ctx.grid.sample(rng, 1.0)[0], 0.006], u(0, np.pi))


def make_rich_room(seed: int) -> RichRoom:
    """Build the rich room of a room seed (see the module docstring)."""
    rng = np.random.default_rng([int(seed), 0x5200])
    kind = str(ROOM_KINDS[int(rng.choice(len(ROOM_KINDS), p=_KIND_PROB))])
    (x0, x1), (y0, y1), (h0, h1) = _KIND_SIZE[kind]
    sx, sy, H = rng.uniform(x0, x1), rng.uniform(y0, y1), rng.uniform(h0, h1)
    if rng.random() < 0.5:
        sx, sy = sy, sx
    poly = make_footprint(rng, sx, sy)
    ctx = _Ctx(rng, kind, poly, H)
    _openings(ctx)
    for wall in ctx.walls:
        _build_wall(ctx.mb, wall, H)
    lo, hi = poly.min(0) - 0.3, poly.max(0) + 0.3
    c, s = (lo + hi) / 2, hi - lo
    ctx.mb.box((s[0], s[1], 0.1), (c[0], c[1], -0.05))          # floor
    ctx.mb.box((s[0], s[1], 0.1), (c[0], c[1], H + 0.05))       # ceiling
    _wall_decor(ctx)
    _furnish(ctx)
    _ceiling(ctx)
    v, tri = ctx.mb.arrays()
    targets = ctx.targets + [np.r_[ctx.grid.sample(rng, 0.5)[0], 1.0]]
    cam_lo = np.r_[poly.min(0), 0.3]
    cam_hi = np.r_[poly.max(0), min(2.0, H - 0.3)]
    return RichRoom(int(seed), (float(sx), float(sy), float(H)), v, tri, ctx.items,
                    np.array(targets), (cam_lo, cam_hi), kind=kind, footprint=poly,
                    grid=ctx.grid, walls=ctx.walls)


@functools.lru_cache(maxsize=4)
def get_rich_room(seed: int) -> RichRoom:
    """Cached :func:`make_rich_room` (the raycasting scene is reused across renders)."""
    return make_rich_room(seed)
