"""Rich procedural rooms (cegc_ros.data.rooms) and the room-seed splits (cegc_ros.data.splits)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from cegc_ros.data import rooms, splits


def _area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _cast(room: rooms.RichRoom, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    import open3d as o3d
    rays = np.concatenate([origins, dirs], 1).astype(np.float32)
    return room.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()


def test_room_is_a_pure_function_of_its_seed():
    a, b, c = rooms.make_rich_room(7), rooms.make_rich_room(7), rooms.make_rich_room(8)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.triangles, b.triangles)
    assert a.items == b.items and a.kind == b.kind
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)


def test_rooms_vary_in_kind_footprint_and_openings():
    built = [rooms.make_rich_room(s) for s in range(40)]
    kinds = {r.kind for r in built}
    assert len(kinds) >= 5, kinds
    non_rect = [r for r in built if len(r.footprint) > 4]
    assert len(non_rect) >= 20                      # notches, chamfers, alcoves, columns
    diagonal = [r for r in built if any(abs(w.d[0]) > 0.1 and abs(w.d[1]) > 0.1 for w in r.walls)]
    assert diagonal                                 # some chamfered (non axis-aligned) walls
    for r in built:
        assert _area(r.footprint) > 4.0             # counter-clockwise, a usable floor
        kinds_of_holes = {o.kind for w in r.walls for o in w.openings}
        assert "door" in kinds_of_holes             # every room has a door
        assert len(r.items) >= 2
    assert sum(any(o.kind == "window" for w in r.walls for o in w.openings) for r in built) >= 20


def test_windows_and_open_doors_are_holes_in_the_wall():
    checked = 0
    for seed in range(30):
        room = rooms.make_rich_room(seed)
        for wall in room.walls:
            for o in wall.openings:
                if o.kind != "window":
                    continue
                s = 0.5 * (o.s0 + o.s1)
                # Horizontal rays from 0.3 m inside the room, through the hole and through the
                # solid wall beside it (towards the outward normal).
                z_hole = 0.5 * (o.z0 + o.z1)
                p_hole = np.r_[wall.at(s, 0.3), z_hole]
                d = np.r_[wall.n, 0.0]
                t = _cast(room, p_hole[None], d[None])[0]
                # Mullions or curtains may sit in the hole; the wall itself (at 0.3 m) must not.
                if np.isfinite(t) and abs(t - 0.3) < 0.01:
                    pytest.fail(f"room {seed}: window at s={s:.2f} is not a hole")
                p_wall = np.r_[wall.at(s, 0.3), o.z1 + 0.05]           # just above the window
                if o.z1 + 0.05 < room.size[2] - 0.05:
                    t2 = _cast(room, p_wall[None], d[None])[0]
                    assert np.isfinite(t2) and t2 <= 0.3 + 1e-3
                checked += 1
    assert checked >= 10


def test_sensor_positions_are_on_free_floor():
    for seed in (1, 4, 9, 15):
        room = rooms.make_rich_room(seed)
        xy = room.grid.sample(np.random.default_rng(seed), 0.35, n=50)
        assert rooms.inside_polygon(xy, room.footprint).all()
        # Straight down from 1 m: the floor (or a thin rug), never furniture.
        o = np.c_[xy, np.ones(len(xy))]
        t = _cast(room, o, np.tile([0.0, 0.0, -1.0], (len(xy), 1)))
        assert np.all(np.abs(t - 1.0) < 0.02), t


def test_splits_are_disjoint_and_round_trip():
    ranges = sorted(splits.ROOM_SPLITS.values())
    assert all(hi <= lo2 for (_, hi), (lo2, _) in itertools.pairwise(ranges))
    for name in splits.SPLITS:
        for k in (0, 5, splits.num_rooms(name) - 1):
            assert splits.split_of(splits.room_seed(name, k)) == name
    with pytest.raises(ValueError, match="room index"):
        splits.room_seed("val", splits.num_rooms("val"))
    with pytest.raises(ValueError, match="unknown split"):
        splits.room_seed("dev", 0)
