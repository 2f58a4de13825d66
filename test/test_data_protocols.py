"""Pair protocols (cegc_ros.data.protocols): reproducibility, ground truth, overlaps."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from cegc_ros.data import protocols as P


def _aligned_nn(pair: P.Pair) -> np.ndarray:
    """Distance of each GT-aligned source point to its nearest target point."""
    d, _ = cKDTree(pair.target).query(P.transform_points(pair.T_target_source, pair.source))
    return d


def _assert_rigid(T: np.ndarray) -> None:
    assert T.shape == (4, 4) and T.dtype == np.float64
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    assert abs(np.linalg.det(T[:3, :3]) - 1.0) < 1e-9
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


def test_7scenes_same_seed_identical_and_pair_reproducible_alone():
    a = P.make_pairs("7scenes", "test", 3, seed=4)
    b = P.make_pairs("7scenes", "test", 3, seed=4)
    alone = P.make_pair("7scenes", "test", 2, seed=4)
    for x, y in zip(a, b):
        assert np.array_equal(x.source, y.source) and np.array_equal(x.target, y.target)
        assert np.array_equal(x.T_target_source, y.T_target_source) and x.info == y.info
    assert np.array_equal(alone.source, a[2].source) and alone.info == a[2].info


def test_7scenes_protocol_shapes_gt_and_ranges():
    pairs = P.make_pairs("7scenes", "test", 5, seed=4)
    for k, p in enumerate(pairs):
        assert p.source.shape == (1536, 3) and p.target.shape == (1536, 3)
        assert p.source.dtype == np.float32 and p.target.dtype == np.float32
        _assert_rigid(p.T_target_source)
        # Source is the normalised fragment: inside the unit box around the origin.
        assert np.abs(p.source).max() <= 0.5 + 1e-6
        assert np.abs(p.T_target_source[:3, 3]).max() <= 0.5
        angle = np.degrees(np.arccos((np.trace(p.T_target_source[:3, :3]) - 1) / 2))
        assert angle <= 45 * np.sqrt(3) + 1e-6
        # Same points in both crops: the GT puts shared points exactly on each other.
        d = _aligned_nn(p)
        assert np.mean(d < 1e-5) == pytest.approx(p.info["overlap"], abs=1e-9)
        assert 0.5 <= p.info["overlap"] <= 1.0
        assert p.info["index"] == k and p.info["protocol"] == "7scenes"
        assert 0.5 < p.info["scale"] < 6.0                  # metres per unit: a room-sized view


def test_7scenes_sampler_curriculum_knobs():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (100_000, 3)).astype(np.float32)
    p = P.sample_7scenes_pair(pts, rng, num_points=512, keep_ratio=0.5, max_angle_deg=5.0,
                              max_translation=0.1)
    assert p.source.shape == (256, 3)
    angle = np.degrees(np.arccos((np.trace(p.T_target_source[:3, :3]) - 1) / 2))
    assert angle <= 5 * np.sqrt(3) + 1e-6 and np.abs(p.T_target_source[:3, 3]).max() <= 0.1
    q = P.sample_7scenes_pair(pts, rng, resample_target=True)
    d = _aligned_nn(q)
    assert np.mean(d < 1e-6) < 0.05                         # no exact copies any more
    assert np.median(d) < 0.05                              # but the same surface


def test_train_and_test_scenes_are_disjoint_and_seeds_differ():
    train = {P.scene_seed("train", s, k) for s in (0, 1, 999_999) for k in (0, 1, 999_999)}
    test = {P.scene_seed("test", s, k) for s in (0, 1, 999_999) for k in (0, 1, 999_999)}
    assert not train & test
    # (scenes shared with the other tests of this module, to render fewer fragments)
    a = P.make_pair("7scenes", "test", 0, seed=4)
    b = P.make_pair("7scenes", "test", 0, seed=5)
    c = P.make_pair("7scenes", "train", 0, seed=0)
    assert a.info["scene_seed"] != b.info["scene_seed"] != c.info["scene_seed"]
    assert not np.array_equal(a.source, b.source) and not np.array_equal(a.source, c.source)
    with pytest.raises(ValueError, match="split"):
        P.make_pair("7scenes", "val", 0)
    with pytest.raises(ValueError, match="protocol"):
        P.make_pair("kitti", "test", 0)


def test_modelnet_protocol():
    pairs = P.make_pairs("modelnet", "test", 6, seed=2)
    again = P.make_pair("modelnet", "test", 5, seed=2)
    assert np.array_equal(again.source, pairs[5].source)
    other = P.make_pair("modelnet", "test", 5, seed=3)
    assert not np.array_equal(other.source, pairs[5].source)
    for p in pairs:
        assert p.source.shape == (1024, 3) and p.target.shape == (1024, 3)
        _assert_rigid(p.T_target_source)
        assert np.linalg.norm(p.source, axis=1).max() <= 1.0 + 1e-6
        assert np.abs(p.T_target_source[:3, 3]).max() <= 0.5
        d = _aligned_nn(p)
        assert np.mean(d < 1e-5) >= p.info["overlap"] - 1e-9   # shared samples coincide
        assert 0.2 < p.info["overlap"] < 0.8                   # two 70 % crops
    noisy = P.make_pair("modelnet", "test", 0, seed=2, noise_sigma=0.01)
    clean = pairs[0]
    diff = noisy.source - clean.source
    assert 0.007 < diff.std() < 0.013 and np.abs(diff).max() <= 0.05 + 1e-6


def test_fragments_protocol_gt_and_overlaps():
    pairs = P.make_pairs("fragments", "test", P.FRAGMENT_PAIRS_PER_SCENE, seed=5)
    overlaps = np.array([p.info["overlap"] for p in pairs])
    assert np.all((overlaps >= 0.1) & (overlaps <= 0.9))
    assert overlaps.max() - overlaps.min() > 0.3                 # spread over the range
    keys = {(p.info["source_fragment"], p.info["target_fragment"]) for p in pairs}
    assert len(keys) == len(pairs)
    assert all(a != b for a, b in keys)
    for p in pairs:
        _assert_rigid(p.T_target_source)
        d = _aligned_nn(p)
        assert np.mean(d < P.OVERLAP_RADIUS) == pytest.approx(p.info["overlap"])
        # On the overlap, GT-aligned points sit within the 2.5 cm voxel spacing + sensor noise.
        assert np.median(d[d < P.OVERLAP_RADIUS]) < 0.015
    # The same pair index rebuilt alone is identical; another seed is another scene.
    alone = P.make_pair("fragments", "test", 3, seed=5)
    assert np.array_equal(alone.source, pairs[3].source)
    np.testing.assert_array_equal(alone.T_target_source, pairs[3].T_target_source)


def test_fragment_cache_round_trip(tmp_path):
    cache = P.FragmentCache(tmp_path, num_scenes=1, fragments_per_scene=2, seed=0)
    first = cache.load()
    files = sorted(tmp_path.glob("*.npz"))
    assert len(files) == 2 and [(f.scene_seed, f.index) for f in first] == [(0, 0), (0, 1)]
    assert np.array_equal(first[0].points, P._fragment(0, 0).points)    # = the uncached one
    again = P.FragmentCache(tmp_path, num_scenes=1, fragments_per_scene=2, seed=0).load()
    for a, b in zip(first, again):
        assert np.array_equal(a.points, b.points)
        assert np.array_equal(a.T_world_fragment, b.T_world_fragment) and a.info == b.info
    files[0].write_bytes(b"broken")                             # an interrupted write
    healed = P.FragmentCache(tmp_path, num_scenes=1, fragments_per_scene=2, seed=0).load()
    assert np.array_equal(healed[0].points, first[0].points)
