"""Different-view pairs of the rich rooms (cegc_ros.data.views)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from cegc_ros.data import splits, views
from cegc_ros.data.protocols import overlap_ratio, transform_points

SMALL = views.ViewConfig(fragments=4, pairs=4, copy_pairs=1, max_points=4000)


@pytest.fixture(scope="module")
def kinect_room() -> views.RoomPairs:
    return views.make_room_pairs(splits.room_seed("train", 3), "kinect", SMALL)


@pytest.fixture(scope="module")
def lidar_room() -> views.RoomPairs:
    return views.make_room_pairs(splits.room_seed("train", 4), "lidar", SMALL)


def test_room_pairs_are_deterministic_by_seed(kinect_room):
    again = views.make_room_pairs(splits.room_seed("train", 3), "kinect", SMALL)
    assert len(again.pairs) == len(kinect_room.pairs) >= 3
    for a, b in zip(again.clouds, kinect_room.clouds):
        assert np.array_equal(a, b)
    for a, b in zip(again.pairs, kinect_room.pairs):
        assert np.array_equal(a.T_target_source, b.T_target_source) and a.info == b.info
    other = views.make_room_pairs(splits.room_seed("train", 5), "kinect", SMALL)
    assert not np.array_equal(other.clouds[0][:100], kinect_room.clouds[0][:100])


@pytest.mark.parametrize("room", ["kinect_room", "lidar_room"])
def test_overlap_is_in_range_and_measured_against_ground_truth(room, request):
    rp = request.getfixturevalue(room)
    got = [rec for rec in rp.pairs if rec.kind == "views"]
    assert len(got) >= 2
    for k, rec in enumerate(rp.pairs):
        if rec.kind != "views":
            continue
        pair = rp.pair(k)
        assert 0.1 <= pair.info["overlap"] <= 0.9
        radius = pair.info["overlap_radius"]
        assert radius == (0.0375 if rp.sensor == "kinect" else 0.1)
        # Recomputed from the clouds and the ground truth alone.
        assert pair.info["overlap"] == pytest.approx(
            overlap_ratio(pair.source, pair.target, pair.T_target_source, radius), abs=1e-12)
        assert pair.info["overlap_target"] == pytest.approx(
            overlap_ratio(pair.target, pair.source, np.linalg.inv(pair.T_target_source), radius),
            abs=1e-12)
        # The ground truth is right: moving the source off it by 2 radii in any axis direction
        # loses overlap.
        off = []
        for axis in range(3):
            for sign in (-1.0, 1.0):
                T = pair.T_target_source.copy()
                T[axis, 3] += sign * 2 * radius
                off.append(overlap_ratio(pair.source, pair.target, T, radius))
        assert np.mean(off) < 0.8 * pair.info["overlap"], (off, pair.info["overlap"])
        assert pair.info["rotation_deg"] > 1.0 or pair.info["translation_m"] > 0.1


def test_views_pairs_share_no_points_and_copy_pairs_do(kinect_room):
    kinds = set()
    for k, rec in enumerate(kinect_room.pairs):
        pair = kinect_room.pair(k)
        kinds.add(rec.kind)
        d, _ = cKDTree(pair.target).query(transform_points(pair.T_target_source, pair.source))
        within_1mm = float(np.mean(d < 0.001))
        if rec.kind == "views":
            assert rec.source != rec.target
            assert within_1mm < 0.02                # independent samplings: no copies
        else:
            assert rec.source == rec.target
            # Copy protocol: the overlapping points are exact copies (up to float32).
            assert within_1mm == pytest.approx(pair.info["overlap"], abs=1e-9)
    assert kinds == {"views", "copy"}


def test_clouds_are_capped_shuffled_float32_metres(kinect_room):
    for c in kinect_room.clouds:
        assert c.dtype == np.float32 and c.shape[1] == 3 and 100 < len(c) <= SMALL.max_points
        assert np.abs(c).max() < 10.0                   # metres, indoor
    # Shuffled: the first half is spread like the whole (voxel order would sort along x).
    c = kinect_room.clouds[0]
    assert abs(np.median(c[: len(c) // 2, 0]) - np.median(c[:, 0])) < 0.2


def test_iter_view_pairs_uses_the_split_rooms_only():
    pairs = list(views.iter_view_pairs("test", 3, "kinect", config=SMALL))
    assert [p.info["index"] for p in pairs] == [0, 1, 2]
    for p in pairs:
        assert p.info["kind"] == "views" and p.info["split"] == "test"
        assert splits.split_of(p.info["room_seed"]) == "test"


def test_sensor_for_room_mixes_by_fraction():
    seeds = range(2000)
    lidar = sum(views.sensor_for_room(s, 0.1) == "lidar" for s in seeds)
    assert 150 < lidar < 250
    assert all(views.sensor_for_room(s, 0.0) == "kinect" for s in range(50))


def test_make_bag_writes_view_pairs_that_read_back_exactly(tmp_path, monkeypatch, capsys):
    from cegc_ros.data.bag import read_pairs
    from cegc_ros.tools import make_bag

    made: list[views.RoomPairs] = []
    real = views.make_room_pairs

    def small(seed: int, sensor: str, config: views.ViewConfig) -> views.RoomPairs:
        made.append(real(seed, sensor, replace(SMALL, copy_pairs=config.copy_pairs)))
        return made[-1]

    monkeypatch.setattr(views, "make_room_pairs", small)
    out = tmp_path / "views_val"
    assert make_bag.main(["--protocol", "views", "--split", "val", "--pairs", "3", "--out",
                          str(out), "--no-progress"]) == 0
    got = list(read_pairs(out))
    want = [rp.pair(k) for rp in made for k, rec in enumerate(rp.pairs) if rec.kind == "views"]
    assert len(got) == 3
    for g, w in zip(got, want):
        assert np.array_equal(g.source, w.source) and np.array_equal(g.target, w.target)
        np.testing.assert_allclose(g.T_target_source, w.T_target_source, atol=1e-9)
        assert g.info["split"] == "val" and g.info["kind"] == "views"
        assert g.info["overlap"] == w.info["overlap"]
    for bad in (["--protocol", "7scenes", "--split", "val"],
                ["--protocol", "views", "--split", "test", "--seed", "10"]):
        with pytest.raises(SystemExit) as exc:
            make_bag.main(bad + ["--pairs", "1", "--out", str(tmp_path / "x")])
        assert exc.value.code == 2


def test_wall_views_look_at_walls_and_zero_keeps_every_draw(kinect_room):
    seed = splits.room_seed("train", 3)
    room = views.get_rich_room(seed)
    rng = np.random.default_rng(0)
    foci = np.array([views._wall_focus(room, rng) for _ in range(200)])
    # on the footprint's boundary (a wall's plane), at the documented heights
    poly = room.footprint
    a, b = poly, np.roll(poly, -1, 0)
    ab = b - a
    s = np.clip(np.einsum("pkd,kd->pk", foci[:, None, :2] - a[None], ab) / (ab ** 2).sum(1), 0, 1)
    d = np.linalg.norm(foci[:, None, :2] - (a[None] + s[..., None] * ab[None]), axis=-1).min(1)
    assert d.max() < 1e-9
    assert foci[:, 2].min() >= 0.8 - 1e-9 and foci[:, 2].max() <= min(1.8, room.size[2] - 0.3)
    # 0 is the generator as before: the same clouds and poses as the default config
    zero = views.make_room_pairs(seed, "kinect", replace(SMALL, wall_views=0.0))
    assert all(np.array_equal(x, y) for x, y in zip(zero.clouds, kinect_room.clouds))
    # all focuses on walls: other views; the LiDAR rooms are untouched
    walls = views.make_room_pairs(seed, "kinect", replace(SMALL, wall_views=1.0))
    assert not np.array_equal(walls.clouds[0][:100], kinect_room.clouds[0][:100])
    lidar = views.make_room_pairs(splits.room_seed("train", 4), "lidar", replace(SMALL, wall_views=1.0))
    assert np.array_equal(lidar.clouds[0], views.make_room_pairs(
        splits.room_seed("train", 4), "lidar", SMALL).clouds[0])
