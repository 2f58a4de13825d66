"""The ROS-free engine: checkpoints, input validation, de-normalisation, result contents."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from cegc_ros.config import EngineConfig, PreprocessConfig
from cegc_ros.engine import CheckpointError, default_weights, Registrar, load_checkpoint, save_checkpoint
from cegc_ros.geometry import frame_viewpoints, normalise_pair, prepare_pair, subsample
from cegc_ros.metrics import rotation_error_deg, translation_error
from cegc_ros.model import CEGC, ModelConfig
from cegc_ros.refine import covariance


def euler_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def scene(n: int = 3000, seed: int = 0) -> np.ndarray:
    """A corner of a room with a box: structured enough for normals/FPFH (metres)."""
    rng = np.random.default_rng(seed)
    k = n // 4
    floor = np.c_[rng.uniform(0, 3, k), rng.uniform(0, 3, k), np.zeros(k)]
    wall1 = np.c_[np.zeros(k), rng.uniform(0, 3, k), rng.uniform(0, 2.5, k)]
    wall2 = np.c_[rng.uniform(0, 3, k), np.zeros(k), rng.uniform(0, 2.5, k)]
    box = rng.uniform(0, 1, (n - 3 * k, 3)) * [0.6, 0.4, 0.8] + [1.2, 1.5, 0]
    return np.vstack([floor, wall1, wall2, box]).astype(np.float32)


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory) -> Path:
    torch.manual_seed(0)
    cfg = ModelConfig(agnn_dims=(16, 16, 32), feat_dim=32, attn_heads=2, attn_layers=1, cams_dim=8, hoce_topk=4)
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    save_checkpoint(path, CEGC(cfg), {"note": "random init, for tests"})
    return path


def test_checkpoint_round_trip(tiny_checkpoint):
    model, meta = load_checkpoint(tiny_checkpoint)
    assert meta == {"note": "random init, for tests"}
    ref = torch.load(tiny_checkpoint, weights_only=True)["state_dict"]
    for k, v in model.state_dict().items():
        assert torch.equal(v, ref[k])
    assert model.cfg.feat_dim == 32 and not model.training


def test_missing_checkpoint_names_the_file(tmp_path):
    with pytest.raises(CheckpointError, match="nope.pt: file not found"):
        Registrar.from_checkpoint(tmp_path / "nope.pt", device="cpu")


def test_truncated_checkpoint(tiny_checkpoint, tmp_path):
    bad = tmp_path / "truncated.pt"
    bad.write_bytes(tiny_checkpoint.read_bytes()[:5000])
    with pytest.raises(CheckpointError, match="truncated.pt: unreadable"):
        Registrar.from_checkpoint(bad, device="cpu")


def test_garbage_and_foreign_checkpoints(tmp_path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x00not a checkpoint" * 100)
    with pytest.raises(CheckpointError, match="junk.pt"):
        Registrar.from_checkpoint(junk, device="cpu")
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(CheckpointError, match="foreign.pt: format None"):
        Registrar.from_checkpoint(foreign, device="cpu")


def test_mismatched_checkpoint(tiny_checkpoint, tmp_path):
    payload = torch.load(tiny_checkpoint, weights_only=True)
    payload["model_config"]["feat_dim"] = 64          # the weights are 32-wide
    bad = tmp_path / "mismatch.pt"
    torch.save(payload, bad)
    with pytest.raises(CheckpointError, match="mismatch.pt: does not match"):
        Registrar.from_checkpoint(bad, device="cpu")


def test_too_few_points_and_bad_shapes(tiny_checkpoint):
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu")
    with pytest.raises(ValueError, match="source has 10 usable points"):
        reg.register(scene(10), scene(200))
    with pytest.raises(ValueError, match=r"source has 0 usable points \(0 non-finite, 300 at \(0, 0, 0\)"):
        reg.register(np.zeros((300, 3)), scene(200))
    nan_cloud = scene(200)
    nan_cloud[5:] = np.nan
    with pytest.raises(ValueError, match="target has 5 usable points"):
        reg.register(scene(200), nan_cloud)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        reg.register(np.zeros((100, 2)), scene(200))


def test_result_contents(tiny_checkpoint):
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=PreprocessConfig(num_points=256))
    src = scene(2000, seed=1)
    res = reg.register(src, src @ euler_z(20).T + [0.3, -0.2, 0.1])
    assert res.T_target_source.shape == (4, 4) and res.T_target_source.dtype == np.float64
    assert np.allclose(res.T_target_source[3], [0, 0, 0, 1])
    assert res.source_points.shape == (256, 3) and res.target_points.shape == (256, 3)
    assert res.source_overlap.shape == (256,) and ((res.source_overlap >= 0) & (res.source_overlap <= 1)).all()
    K = len(res.correspondences)
    assert 10 <= K <= 1500 and res.correspondences.shape == (K, 2) and res.weights.shape == (K,)
    assert res.inliers.shape == (K,) and res.inliers.dtype == bool
    assert res.correspondences[:, 0].max() < 256 and res.correspondences[:, 1].max() < 256
    assert res.covariance.shape == (6, 6) and np.allclose(res.covariance, res.covariance.T)
    assert 0.0 <= res.fitness <= 1.0
    assert {"bound", "features", "match", "estimate", "verify", "total"} <= set(res.timings)
    assert res.timings["total"] == pytest.approx(sum(v for k, v in res.timings.items() if k != "total"))


def test_denormalisation_returns_metres_at_any_scale(tiny_checkpoint):
    """The same clouds at 16x scale give the same rotation and a 16x translation.

    A power of two keeps the normalised inputs bit-identical, so any difference would come
    from de-normalisation alone (an untrained network amplifies rounding differences).
    """
    # No ICP: it iterates in metres from the untrained network's far-off pose, where float
    # rounding at two scales can send it to different local minima.
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=PreprocessConfig(num_points=256),
                                    engine=EngineConfig(refine="none"))
    src = scene(1500, seed=2)
    tgt = src @ euler_z(30).T + [0.5, 0.2, -0.1]
    a = reg.register(src, tgt)
    b = reg.register(16.0 * src, 16.0 * tgt)
    assert np.allclose(a.T_target_source[:3, :3], b.T_target_source[:3, :3], atol=1e-6)
    assert np.allclose(16.0 * a.T_target_source[:3, 3], b.T_target_source[:3, 3], atol=1e-5)
    assert np.allclose(16.0 * a.source_points, b.source_points, rtol=1e-5, atol=1e-4)


def test_normalisation_round_trip():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(500, 3)) * 4 + 10
    T = np.eye(4)
    T[:3, :3] = euler_z(40)
    T[:3, 3] = [1.0, -2.0, 3.0]
    tgt = src @ T[:3, :3].T + T[:3, 3]
    src_n, tgt_n, norm = normalise_pair(src, tgt)
    R, t_n = norm.to_normalised(T)
    assert np.allclose(src_n @ R.T + t_n, tgt_n, atol=1e-4)
    assert np.allclose(norm.to_metres(R, t_n), T)


def test_grid_sampling_spreads_points_evenly_where_random_follows_the_density():
    """A Kinect-like density: 90% of the points in the near tenth of a 10 m x 1 m strip. The
    grid draw gives the far 90% of the strip most of its points; a random draw ~10%."""
    rng = np.random.default_rng(0)
    near = rng.uniform([0.0, 0.0, 0.0], [1.0, 1.0, 0.01], (18000, 3))
    far = rng.uniform([1.0, 0.0, 0.0], [10.0, 1.0, 0.01], (2000, 3))
    pts = np.concatenate([near, far])
    far_share = {}
    for sampling in ("grid", "random"):
        idx = subsample(pts, 1000, np.random.default_rng(1), sampling)
        assert len(idx) == 1000 and len(np.unique(idx)) == 1000 and (np.diff(idx) > 0).all()
        assert np.array_equal(idx, subsample(pts, 1000, np.random.default_rng(1), sampling))   # seeded
        far_share[sampling] = float((pts[idx, 0] > 1.0).mean())
    assert far_share["grid"] > 0.75 and far_share["random"] < 0.15
    # fewer points than asked: all of them, padded by repetition; unknown names are refused
    few = subsample(pts[:10], 16, rng, "grid")
    assert len(few) == 16 and set(few.tolist()) == set(range(10))
    dup = subsample(np.zeros((50, 3)), 20, rng, "grid")                  # one cell only: random draw
    assert len(np.unique(dup)) == 20
    with pytest.raises(ValueError, match="sampling must be one of"):
        subsample(pts, 100, rng, "fps")


def _grid_cells_reference(points, n, iterations=20):
    """The bisection of geometry._grid_cells written plainly: int64 keys, np.unique counts."""
    lo = points.min(0)
    hi_size, lo_size, best = float((points.max(0) - lo).max()), 0.0, None
    for _ in range(iterations):
        size = 0.5 * (hi_size + lo_size)
        key = np.floor((points - lo) / size).astype(np.int64)
        dims = key.max(0) + 1
        ids = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
        count = len(np.unique(ids))
        if count >= n:
            best, lo_size = ids, size
            if count < 1.15 * n:
                break
        else:
            hi_size = size
    return best


@pytest.mark.parametrize("case", ["surface", "blob", "far_clusters", "sparse"])
def test_grid_cells_counted_by_table_are_the_plain_bisections(case):
    """Table counts (np.bincount) and float64 ids choose exactly the grid that int64 ids and
    np.unique choose, also where the grid is too fine for a table or for float64 ids."""
    from cegc_ros.geometry import _grid_cells
    rng = np.random.default_rng(4)
    pts = {"surface": scene(14000, seed=5),
           "blob": rng.normal(size=(5000, 3)),
           "far_clusters": np.r_[rng.normal(size=(3000, 3)) * 1e-4, [[1e3, 1e3, 1e3]]],
           "sparse": rng.uniform(-1, 1, (700, 3))}[case]
    for n in (256, 512, 1024):
        ref, got = _grid_cells_reference(pts, n), _grid_cells(pts, n)
        if ref is None:
            assert got is None
            continue
        _, ref_cells = np.unique(ref, return_inverse=True)
        _, got_cells = np.unique(got, return_inverse=True)
        assert got.dtype == np.int64 and np.array_equal(ref_cells, got_cells)


def test_covariance_shrinks_with_more_consistent_correspondences():
    rng = np.random.default_rng(0)
    src = rng.uniform(-1, 1, (200, 3))
    T = np.eye(4)
    cov_small = covariance(src, src + rng.normal(0, 0.001, src.shape), np.ones(200), T)
    cov_large = covariance(src, src + rng.normal(0, 0.05, src.shape), np.ones(200), T)
    assert np.all(np.diag(cov_small) > 0)
    assert np.all(np.diag(cov_small) < np.diag(cov_large))


def test_runtime_update_applies_to_next_call(tiny_checkpoint):
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=PreprocessConfig(num_points=128))
    src = scene(1000, seed=3)
    assert reg.register(src, src).source_points.shape == (128, 3)
    reg.update(preprocess=PreprocessConfig(num_points=192), engine=EngineConfig(refine="icp", estimator="svd"))
    res = reg.register(src, src)
    assert res.source_points.shape == (192, 3) and res.refined == "icp"
    assert reg.engine.checkpoint == str(tiny_checkpoint)


def test_voxel_grid_in_metres(tiny_checkpoint):
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu",
                                    preprocess=PreprocessConfig(voxel_size=2.0, num_points=64))
    with pytest.raises(ValueError, match="after the 2 m voxel grid"):
        reg.register(scene(1000), scene(1000))


def test_shipped_weights_load_with_their_metadata():
    reg = Registrar.from_checkpoint(device="cpu")
    assert reg.checkpoint_path == str(default_weights())
    assert reg.metadata["step"] > 0 and "validation" in reg.metadata


def test_shipped_weights_register_a_held_out_pair_at_10x_scale_in_metres():
    """A synthetic 7Scenes test pair (scenes never trained on), scaled by 10: the transform
    comes back in the scaled units, accurate to the protocol's tolerance."""
    from cegc_ros.data.protocols import make_pair
    pair = make_pair("7scenes", "test", 3)
    reg = Registrar.from_checkpoint(device="cpu")
    res = reg.register(10.0 * pair.source, 10.0 * pair.target)
    T_gt = pair.T_target_source.copy()
    T_gt[:3, 3] *= 10.0
    R_err = np.degrees(np.arccos(np.clip((np.trace(T_gt[:3, :3].T @ res.T_target_source[:3, :3]) - 1) / 2, -1, 1)))
    assert res.valid
    assert R_err < 2.0
    assert np.linalg.norm(res.T_target_source[:3, 3] - T_gt[:3, 3]) < 0.1    # 1 cm at unit scale


def test_checkpoint_carries_its_feature_radii_and_old_ones_get_the_legacy_radii(tmp_path):
    from cegc_ros.engine import load_checkpoint, save_checkpoint
    from cegc_ros.geometry import LEGACY_FEATURES
    cfg = ModelConfig(agnn_dims=(16, 16, 32), feat_dim=32, attn_heads=2, attn_layers=1, cams_dim=8,
                      normal_radius=0.07, fpfh_radius=0.2, fpfh_max_nn=150)
    save_checkpoint(tmp_path / "new.pt", CEGC(cfg))
    model, _ = load_checkpoint(tmp_path / "new.pt")
    assert model.cfg.features() == {"with_features": True, "normal_radius": 0.07, "fpfh_radius": 0.2,
                                    "fpfh_max_nn": 150}
    # A checkpoint written before the radii were stored was trained on the legacy ones.
    payload = torch.load(tmp_path / "new.pt", weights_only=True)
    for key in LEGACY_FEATURES:
        del payload["model_config"][key]
    torch.save(payload, tmp_path / "old.pt")
    model, _ = load_checkpoint(tmp_path / "old.pt")
    assert {k: getattr(model.cfg, k) for k in LEGACY_FEATURES} == LEGACY_FEATURES


@pytest.mark.skipif(not any(shutil.which(c) for c in ("g++", "c++", "clang++")),
                    reason="torch.compile's CPU backend needs a C++ compiler")
def test_non_finite_network_output_is_an_error_naming_the_runtime(tiny_checkpoint, monkeypatch):
    """A network that returns NaN confidences (a broken checkpoint or runtime: a compiled graph
    built for other CPU kernels did, under ATEN_CPU_CAPABILITY=avx2 on an AVX-512 CPU) stops
    the pair with an error that says so, instead of an invalid result blaming the input; the
    same registrar registers again once the network is sound."""
    from cegc_ros.engine import NetworkOutputError
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", warm=False)
    real = reg.model.score_candidates

    def broken(*args, **kwargs):
        out = real(*args, **kwargs)
        out.scores[..., :3] = float("nan")              # 3 candidates of every source point
        return out
    monkeypatch.setattr(reg.model, "score_candidates", broken)
    src = scene(1000, seed=4)
    tgt = src @ euler_z(15).T + [0.1, 0.2, 0.0]
    with pytest.raises(NetworkOutputError,
                       match=(r"network \(torch\) returned non-finite values: "
                              r"(\d+) of \d+ candidate confidences")) as err:
        reg.register(src, tgt)
    # every source point's first 3 of its learned + FPFH candidates, counted before selection
    n_bad, n_all = map(int, err.value.args[0].split("values: ")[1].split(" candidate")[0].split(" of "))
    assert n_bad * (reg.engine.learned_candidates + reg.engine.fpfh_candidates) == 3 * n_all
    monkeypatch.setattr(reg.model, "score_candidates", real)
    res = reg.register(src, tgt)
    assert np.isfinite(res.weights).all() and len(res.correspondences) > 0


def test_compiled_networks_give_the_eager_answer_and_other_sizes_run_eagerly(tiny_checkpoint):
    pre = PreprocessConfig(num_points=128)
    eager = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=pre,
                                      engine=EngineConfig(refine="none"))
    comp = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=pre,
                                     engine=EngineConfig(refine="none", compile=True))
    assert eager.warm_up() == 0.0 and eager.compiled_runs == 0
    assert comp.warm_up() > 0.0 and comp.compiled_runs == 1
    src = scene(1000, seed=4)
    tgt = src @ euler_z(15).T + [0.1, 0.2, 0.0]
    a, b = eager.register(src, tgt), comp.register(src, tgt)
    assert comp.compiled_runs == 2
    # The network's outputs agree; the pose is not compared: the estimator's ranking of
    # near-tied hypotheses turns 1e-5 differences in the weights (a compiled graph fuses
    # differently, by CPU) into different but equally good poses.
    np.testing.assert_allclose(np.sort(b.weights), np.sort(a.weights), atol=1e-4)
    np.testing.assert_allclose(b.source_overlap, a.source_overlap, atol=1e-4)
    np.testing.assert_allclose(b.target_overlap, a.target_overlap, atol=1e-4)
    # a runtime change of num_points would need a new graph: that size runs eagerly
    comp.update(preprocess=PreprocessConfig(num_points=96), engine=EngineConfig())
    assert comp.engine.compile and comp.register(src, tgt).source_points.shape == (96, 3)
    assert comp.compiled_runs == 2


def test_a_failed_compile_leaves_the_engine_running_eagerly(tiny_checkpoint, monkeypatch):
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=PreprocessConfig(num_points=128),
                                    engine=EngineConfig(compile=True))

    def broken(model, **kwargs):
        def run(*args, **kwargs):
            raise RuntimeError("no working C++ compiler")
        return run
    monkeypatch.setattr(torch, "compile", broken)
    with pytest.raises(RuntimeError, match="engine.compile failed.*no working C"):
        reg.warm_up()
    assert not reg.engine.compile
    eager = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=PreprocessConfig(num_points=128),
                                      engine=EngineConfig())
    src = scene(1000, seed=4)
    tgt = src @ euler_z(15).T
    np.testing.assert_allclose(reg.register(src, tgt).T_target_source, eager.register(src, tgt).T_target_source)


def _moved_resamples(seed: int = 3):
    """Two independent draws of one room corner (no shared points), the source moved: (src, tgt, T)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = euler_z(35.0), [0.4, -0.3, 0.1]
    src_world = scene(4000, seed=seed)
    src = (src_world - T[:3, 3]) @ T[:3, :3]                    # source frame: p_t = R p_s + t
    return src.astype(np.float32), scene(4000, seed=seed + 1), T


def _errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error) of a 4x4 estimate."""
    return (float(rotation_error_deg(T_true[:3, :3], T_est[:3, :3])),
            float(translation_error(T_true[:3, 3], T_est[:3, 3])))


def test_without_the_learned_part_the_pipeline_is_sc2pcr_on_fpfh(tiny_checkpoint):
    """Uniform confidence and FPFH candidates: an untrained network cannot help or hurt, and the
    compatibility estimator + ICP register two independent scans of a room corner."""
    src, tgt, T = _moved_resamples()
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=PreprocessConfig(num_points=512),
                                    engine=EngineConfig(confidence="uniform", candidates="fpfh"))
    res = reg.register(src, tgt)
    rot, trans = _errors(res.T_target_source, T)
    assert res.valid and rot < 2.0 and trans < 0.05
    assert (res.weights == 1.0).all() and res.inliers.sum() >= 10
    assert res.fitness > 0.5 and np.diag(res.covariance).max() < 1e-2
    assert set(res.timings) == {"bound", "features", "match", "estimate", "refine", "verify", "total"}


def test_ablation_switches_select_the_path(tiny_checkpoint):
    src, tgt, _ = _moved_resamples()
    pre = PreprocessConfig(num_points=256)
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=pre,
                                    engine=EngineConfig(candidates="learned", max_correspondences=10000))
    learned = reg.register(src, tgt)
    assert len(learned.correspondences) == 256 * 3                      # 3 learned candidates per point
    assert ((learned.weights > 0) & (learned.weights < 1)).all()           # sigmoid(overlap) x sigmoid(score)
    reg.update(engine=EngineConfig(candidates="both", max_correspondences=10000))
    both = reg.register(src, tgt)
    assert 256 * 3 < len(both.correspondences) <= 256 * 5                 # + 2 FPFH ones, duplicates merged
    reg.update(engine=EngineConfig(candidates="all", estimator="svd"))   # the paper: top-N rows, argmax
    paper = reg.register(src, tgt)
    assert len(paper.correspondences) == 128 and len(np.unique(paper.correspondences[:, 0])) == 128
    reg.update(engine=EngineConfig(max_correspondences=50))
    assert len(reg.register(src, tgt).correspondences) == 50


def test_small_clouds_get_fewer_network_points_and_large_ones_as_many_as_asked(tiny_checkpoint):
    """Below points_per_network_point x num_points points in the smaller cloud, one network
    point per points_per_network_point points (at least 64), the support scaled alike; 0 off."""
    from cegc_ros.geometry import point_budget
    assert point_budget(1536, 512, 1024, 4) == (384, 768)
    assert point_budget(2048, 512, 1024, 4) == point_budget(20000, 512, 1024, 4) == (512, 1024)
    assert point_budget(100, 512, 1024, 4) == (64, 128)
    assert point_budget(1536, 512, 1024, 0) == point_budget(1536, 512, 1024, 3) == (512, 1024)
    assert PreprocessConfig().points_per_network_point == 0          # off by default
    pre = PreprocessConfig(voxel_ratio=0.0, points_per_network_point=4)   # no grid: the clouds stay
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=pre, warm=False)
    small, large = scene(1536, seed=2), scene(3000, seed=3)
    from cegc_ros.bounding import bound_pair
    bounded = bound_pair(small, large, pre, 16)            # less a few isolated points
    n = point_budget(min(len(bounded.source), len(bounded.target)), 512, 1024, 4)[0]
    assert 370 <= n <= 384
    res = reg.register(small, large)                        # the smaller cloud sets the budget
    assert res.source_points.shape == (n, 3) and res.target_points.shape == (n, 3)
    assert res.correspondences[:, 0].max() < n and res.source_overlap.shape == (n,)
    assert reg.register(large, scene(2400, seed=4)).source_points.shape == (512, 3)
    reg.update(preprocess=PreprocessConfig(voxel_ratio=0.0))
    assert reg.register(small, large).source_points.shape == (512, 3)


def test_work_is_bounded_whatever_the_input_size(tiny_checkpoint):
    """A 400k-point cloud is gridded and capped: later stages see at most max_points, and the
    adaptive voxel (voxel_ratio x extent) is reported."""
    from cegc_ros.bounding import bound_pair, robust_extent
    rng = np.random.default_rng(0)
    big = scene(400_000, seed=6) + rng.normal(0, 0.002, (400_000, 3)).astype(np.float32)
    pre = PreprocessConfig(num_points=256, max_points=5000)
    bounded = bound_pair(big, big[::2], pre, 16)
    assert len(bounded.source) <= 5000 and len(bounded.target) <= 5000
    # voxel_ratio x the robust extent (the trimmed box; the room corner is 3 m wide)
    assert bounded.voxel == pytest.approx(0.01 * max(robust_extent(big), robust_extent(big[::2])))
    assert 0.8 * 0.03 < bounded.voxel <= 0.03
    assert bounded.input_points == (400_000, 200_000)
    off = bound_pair(big, big, PreprocessConfig(voxel_ratio=0.0, max_points=5000), 16)
    assert off.voxel == 0.0                                                # no grid: subsampled to the cap,
    assert len(off.source) == 5000 - off.dropped[0].isolated               # less the few isolated ones
    assert off.dropped[0].isolated < 0.002 * 5000
    res = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=pre).register(big, big[::2])
    assert res.voxel_size == pytest.approx(bounded.voxel)


def test_exact_copies_register_to_the_identity_with_the_adaptive_grid(tiny_checkpoint):
    """The 0.01 grid must not break clouds cut from one point set: a cloud against itself comes
    back at the identity (uniform FPFH path, so the untrained network does not matter)."""
    src = scene(1536, seed=8)
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=PreprocessConfig(num_points=512),
                                    engine=EngineConfig(confidence="uniform", candidates="fpfh"))
    res = reg.register(src, src)
    assert _errors(res.T_target_source, np.eye(4))[0] < 0.05
    assert np.linalg.norm(res.T_target_source[:3, 3]) < 1e-3


def test_a_pose_that_explains_almost_none_of_the_source_is_invalid_with_its_reason():
    """Noise in a 6 m cube against a 60 cm corner (as a 5M-point noise cloud against a crop):
    whatever pose the estimator finds lays almost none of the source on the target; the
    verdict says so. With the floor off, the same result is valid."""
    reg = Registrar.from_checkpoint(device="cpu", engine=EngineConfig(refine="none"))
    noise = np.random.default_rng(7).uniform(-3.0, 3.0, (20000, 3))
    tgt = 0.2 * scene(4000, seed=8)
    res = reg.register(noise, tgt)
    assert res.fitness < reg.engine.min_valid_fitness == 0.05
    assert not res.valid
    assert res.reason.startswith(f"fitness {res.fitness:.3f} < engine.min_valid_fitness 0.05")
    reg.update(engine=EngineConfig(refine="none", min_valid_fitness=0.0))
    off = reg.register(noise, tgt)
    assert off.valid and off.fitness == res.fitness
    np.testing.assert_array_equal(off.T_target_source, res.T_target_source)
    # A true pair stays valid, far above the floor.
    good = reg.register(tgt, tgt @ euler_z(20).T)
    assert good.valid and good.fitness > 0.5


def test_box_corner_is_three_seeded_faces_of_the_unit_cube():
    """The warm-up cloud of Registrar.warm_start and KeyframeOdometry.warm_start: k points on
    each of the faces z = 0, x = 0, y = 0, inside the unit cube, the same for the same seed."""
    from cegc_ros.geometry import box_corner
    c = box_corner(50)
    assert c.shape == (150, 3)
    assert (c[:50, 2] == 0).all() and (c[50:100, 0] == 0).all() and (c[100:, 1] == 0).all()
    assert c.min() >= 0.0 and c.max() <= 1.0 and (c > 0).sum(1).min() == 2
    np.testing.assert_array_equal(c, box_corner(50))
    assert not np.array_equal(c, box_corner(50, seed=1))


def test_verify_score_features_hands_the_network_features_to_the_verification(tiny_checkpoint, monkeypatch):
    """engine.verify_score features: the estimator gets the cosine similarities of the network
    points' attention features (the learned candidates' feature space); 'fitness', and the
    paper's path (which has no candidate features), give it none."""
    from cegc_ros import estimator
    seen = []
    real = estimator.estimate

    def spy(*args, **kwargs):
        seen.append(args[8] if len(args) > 8 else kwargs.get("similarity"))
        return real(*args, **kwargs)
    monkeypatch.setattr(estimator, "estimate", spy)
    src, tgt, _ = _moved_resamples()
    pre = PreprocessConfig(num_points=256)
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu", preprocess=pre,
                                    engine=EngineConfig(verify_score="features"))
    res = reg.register(src, tgt)
    sim = seen[-1]
    assert sim.shape == (len(res.source_points), len(res.target_points))
    assert np.abs(sim).max() <= 1.0 + 1e-5 and sim.std() > 0.01
    # the learned candidates are each source point's most similar target points
    m = reg.match_pair(src, tgt).matches
    np.testing.assert_array_equal(m.similarity, sim)
    learned = m.correspondences[m.rank == 0]
    assert len(learned) > 50
    np.testing.assert_array_equal(sim[learned[:, 0]].argmax(1), learned[:, 1])
    reg.update(engine=EngineConfig(verify_score="fitness"))
    reg.register(src, tgt)
    assert seen[-1] is None
    reg.update(engine=EngineConfig(verify_score="features", candidates="all"))
    reg.register(src, tgt)
    assert seen[-1] is None


def _table_views() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two views from one sensor 1 m above a 1 m table top (z = 0): the first also sees the
    floor 1 m below, around the table; the second, a wall rising 3 m behind the table. Each
    cloud in its sensor's frame (the sensor at the origin), and the table's mask."""
    rng = np.random.default_rng(0)
    top = np.c_[rng.uniform(0, 1, 3000), rng.uniform(0, 1, 3000), np.zeros(3000)]
    floor = np.c_[rng.uniform(-1, 2, 6000), rng.uniform(-1, 2, 6000), np.full(6000, -1.0)]
    floor = floor[~((floor[:, 0] > 0) & (floor[:, 0] < 1) & (floor[:, 1] > 0) & (floor[:, 1] < 1))]
    wall = np.c_[rng.uniform(-0.5, 1.5, 6000), np.full(6000, 1.5), rng.uniform(0, 2, 6000)]
    sensor = np.array([0.5, 0.5, 1.0])
    a, b = np.vstack([top, floor]) - sensor, np.vstack([top, wall]) - sensor
    return a, b, sensor


def test_normals_turned_to_the_sensors_agree_across_views_where_centroids_disagree():
    """The table top seen in both views: turned to each view's centroid its normals point down
    in the first view (the floor below pulls the centroid) and up in the second (the wall above);
    turned to the sensors (preprocess.normals 'sensor', the frames' origins) up in both."""
    a, b, sensor = _table_views()
    side = {}
    for normals in ("centroid", "sensor"):
        ps, pt, norm = prepare_pair(a, b, 512, 1024, np.random.default_rng(0), ModelConfig().features(), "grid",
                                    frame_viewpoints(normals))
        ups = []
        for cloud, c in ((ps, norm.c_source), (pt, norm.c_target)):
            world = cloud.points * norm.scale + c + sensor
            on_top = (np.abs(world[:, 2]) < 0.01) & (world[:, :2] > 0.1).all(1) & (world[:, :2] < 0.9).all(1)
            assert on_top.sum() > 20
            ups.append(float(np.median(cloud.normals[on_top, 2])))
        side[normals] = ups
    assert side["centroid"][0] < -0.9 and side["centroid"][1] > 0.9
    assert side["sensor"][0] > 0.9 and side["sensor"][1] > 0.9
    with pytest.raises(ValueError, match="normals must be 'sensor' or 'centroid'"):
        frame_viewpoints("up")


def test_the_engine_turns_normals_as_preprocess_normals_says(tiny_checkpoint, monkeypatch):
    import cegc_ros.engine as engine_mod
    seen = []
    real = engine_mod.prepare_pair

    def spy(*args, **kwargs):
        seen.append(args[7] if len(args) > 7 else kwargs["viewpoints"])
        return real(*args, **kwargs)
    monkeypatch.setattr(engine_mod, "prepare_pair", spy)
    reg = Registrar.from_checkpoint(tiny_checkpoint, device="cpu")
    a, b, _ = _table_views()
    reg.register(a, b)                                    # the default: 'sensor'
    sensor = seen[-1]
    reg.update(preprocess=PreprocessConfig(normals="centroid"))
    reg.register(a, b)
    assert all(v is not None and np.array_equal(v, np.zeros(3)) for v in sensor)
    assert seen[-1] == (None, None)
