"""On-disk pair cache (cegc_ros.data.pair_cache) and its generator CLI (cegc-make-pairs)."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from cegc_ros.data import pair_cache as PC
from cegc_ros.data import splits, views
from cegc_ros.tools import make_pairs

SMALL = views.ViewConfig(fragments=3, pairs=2, copy_pairs=1, max_points=2000)


@pytest.fixture(scope="module")
def rooms() -> list[views.RoomPairs]:
    return [views.make_room_pairs(splits.room_seed("val", k), s, SMALL)
            for k, s in ((0, "kinect"), (1, "lidar"))]


def test_quantise_round_trip_error_is_below_half_a_step():
    rng = np.random.default_rng(0)
    for scale in (3.0, 60.0):
        p = (rng.uniform(-1, 1, (5000, 3)) * scale + [1.0, -2.0, 3.0]).astype(np.float32)
        q, origin, step = PC.quantise(p)
        assert q.dtype == np.int16
        assert step <= scale / 32767 * 1.0001
        back = PC.dequantise(q, origin, step)
        assert back.dtype == np.float32
        assert np.abs(back.astype(np.float64) - p).max() <= step / 2 + 1e-6 * scale
    q, origin, step = PC.quantise(np.zeros((0, 3), np.float32))
    assert PC.dequantise(q, origin, step).shape == (0, 3)


def test_shard_round_trip_is_bit_identical(tmp_path, rooms):
    n = PC.write_shard(tmp_path / PC.shard_name(0, 2), rooms, {"split": "val"})
    assert n == sum(len(r.pairs) for r in rooms)
    assert not list(tmp_path.glob("*.partial"))
    cache = PC.PairCache(tmp_path, split="val")
    assert len(cache) == n
    k = 0
    for rp in rooms:
        for j in range(len(rp.pairs)):
            want, got = rp.pair(j), cache[k]
            assert np.array_equal(want.source, got.source)
            assert np.array_equal(want.target, got.target)
            assert got.source.dtype == np.float32 and got.T_target_source.dtype == np.float64
            assert np.array_equal(want.T_target_source, got.T_target_source)
            assert got.info == want.info and cache.infos[k] == want.info
            k += 1
    assert np.array_equal(cache[-1].source, cache[n - 1].source)
    with pytest.raises(IndexError):
        cache[n]
    assert cache.room_seeds == {rp.seed for rp in rooms}
    assert np.all((cache.overlaps >= 0) & (cache.overlaps <= 1))


def test_filters_refresh_and_pickle(tmp_path, rooms):
    PC.write_shard(tmp_path / PC.shard_name(0, 1), rooms[:1], {"split": "val"})
    views_only = PC.PairCache(tmp_path, kinds=("views",))
    assert len(views_only) == sum(r.kind == "views" for r in rooms[0].pairs)
    lidar = PC.PairCache(tmp_path, sensors=("lidar",))
    assert len(lidar) == 0
    PC.write_shard(tmp_path / PC.shard_name(1, 2), rooms[1:], {"split": "val"})
    assert lidar.refresh() == len(rooms[1].pairs) and len(lidar) == len(rooms[1].pairs)
    assert {i["sensor"] for i in lidar.infos} == {"lidar"}
    clone = pickle.loads(pickle.dumps(lidar))          # as a DataLoader worker gets it
    assert np.array_equal(clone[0].source, lidar[0].source)


def test_cache_errors_name_the_problem(tmp_path, rooms):
    with pytest.raises(PC.PairCacheError, match="not a directory"):
        PC.PairCache(tmp_path / "missing")
    PC.write_shard(tmp_path / PC.shard_name(0, 1), rooms[:1], {"split": "val"})
    with pytest.raises(PC.PairCacheError, match="split 'val'"):
        PC.PairCache(tmp_path, split="train")
    (tmp_path / PC.shard_name(1, 2)).write_bytes(b"not a zip file")
    with pytest.raises(PC.PairCacheError, match="shard_0000001_0000002.npz: unreadable"):
        PC.PairCache(tmp_path)


def test_cli_generates_resumes_and_refuses_other_settings(tmp_path, capsys):
    out = tmp_path / "pairs"
    args = ["--split", "val", "--rooms", "2", "--rooms-per-shard", "1", "--out", str(out),
            "--fragments", "3", "--pairs", "2", "--max-points", "1500", "--quiet"]
    assert make_pairs.main(args) == 0
    shards = PC.list_shards(out)
    assert [p.name for p in shards] == [PC.shard_name(0, 1), PC.shard_name(1, 2)]
    mtimes = [p.stat().st_mtime_ns for p in shards]
    assert make_pairs.main(args) == 0                  # resume: nothing left to do
    assert [p.stat().st_mtime_ns for p in PC.list_shards(out)] == mtimes
    cache = PC.PairCache(out, split="val")
    assert len(cache) >= 3
    assert all(splits.split_of(s) == "val" for s in cache.room_seeds)
    with np.load(shards[0]) as z:
        meta = json.loads(str(z["meta"]))
    assert meta["split"] == "val" and meta["seconds"] > 0 and meta["generator"]
    assert make_pairs.main(args[:-1] + ["--pairs", "3", "--quiet"]) == 1
    assert "other settings" in capsys.readouterr().err
    # a cache made before --wall-views existed had none: resumable without it, refused with it
    manifest = json.loads((out / PC.MANIFEST).read_text())
    del manifest["wall_views"]
    (out / PC.MANIFEST).write_text(json.dumps(manifest))
    assert make_pairs.main(args) == 0
    assert make_pairs.main(args + ["--wall-views", "0.5"]) == 1
    assert "wall_views" in capsys.readouterr().err
    capsys.readouterr()
    assert make_pairs.main(["--stats", "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["pairs"] == len(cache) and report["split"] == "val"
    with pytest.raises(SystemExit) as exc:
        make_pairs.main(["--out", str(out), "--split", "val"])
    assert exc.value.code == 2


def test_cli_first_room_grows_a_cache_in_pieces(tmp_path, capsys):
    """--first-room renders the later rooms alone; the earlier ones come after, into the same
    folder, and the cache is then the one a single run makes."""
    base = ["--split", "val", "--rooms", "3", "--rooms-per-shard", "1", "--fragments", "3",
            "--pairs", "2", "--max-points", "1500", "--quiet"]
    grown = tmp_path / "grown"
    assert make_pairs.main(base + ["--out", str(grown), "--first-room", "2"]) == 0
    assert [p.name for p in PC.list_shards(grown)] == [PC.shard_name(2, 3)]
    late = PC.PairCache(grown, split="val")
    assert len(late) >= 1 and all(splits.room_seed("val", 2) == s for s in late.room_seeds)
    assert make_pairs.main(base + ["--out", str(grown)]) == 0
    assert make_pairs.main(base + ["--out", str(tmp_path / "whole")]) == 0
    a, b = PC.PairCache(grown), PC.PairCache(tmp_path / "whole")
    assert len(a) == len(b) and len(PC.list_shards(grown)) == 3
    for i in range(len(a)):
        np.testing.assert_array_equal(a[i].source, b[i].source)
        np.testing.assert_array_equal(a[i].T_target_source, b[i].T_target_source)
    for bad, why in ((["--first-room", "3"], "in [0, --rooms)"),
                     (["--first-room", "1", "--rooms-per-shard", "2"], "multiple of --rooms-per-shard")):
        with pytest.raises(SystemExit) as exc:
            make_pairs.main(base + ["--out", str(tmp_path / "bad")] + bad)
        assert exc.value.code == 2 and why in capsys.readouterr().err


def test_cli_workers_write_the_same_pairs(tmp_path):
    """--workers 2 renders shards in two spawned processes: the same shards, pair for pair, as
    one process (only the timing fields of their meta differ)."""
    base = ["--split", "val", "--rooms", "3", "--rooms-per-shard", "1", "--fragments", "3",
            "--pairs", "2", "--max-points", "1500", "--quiet"]
    assert make_pairs.main(base + ["--out", str(tmp_path / "one")]) == 0
    assert make_pairs.main(base + ["--out", str(tmp_path / "two"), "--workers", "2"]) == 0
    one, two = PC.list_shards(tmp_path / "one"), PC.list_shards(tmp_path / "two")
    assert [p.name for p in one] == [p.name for p in two] == [PC.shard_name(k, k + 1) for k in range(3)]
    timing = ("seconds", "cpu_seconds", "load_avg")
    for a, b in zip(one, two):
        with np.load(a) as za, np.load(b) as zb:
            assert sorted(za.files) == sorted(zb.files)
            for key in za.files:
                if key == "meta":
                    ma, mb = (json.loads(str(z["meta"])) for z in (za, zb))
                    assert {k: v for k, v in ma.items() if k not in timing} == \
                        {k: v for k, v in mb.items() if k not in timing}
                else:
                    np.testing.assert_array_equal(za[key], zb[key])
    assert len(PC.PairCache(tmp_path / "two")) == len(PC.PairCache(tmp_path / "one")) >= 3
    with pytest.raises(SystemExit):
        make_pairs.main(base + ["--out", str(tmp_path / "bad"), "--workers", "0"])
