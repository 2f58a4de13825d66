"""The engine's estimators: confidence-seeded spatial compatibility (SC2-PCR) and the paper's SVD."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cegc_ros.estimator import CompatibilityConfig, estimate, estimate_compatibility, estimate_svd, kabsch
from cegc_ros.metrics import rotation_error_deg


def correspondences(K: int, inlier_ratio: float, seed: int = 0, noise: float = 0.01):
    """K correspondences in a 4 m room-sized box, inlier_ratio of them true under (R, t)."""
    rng = np.random.default_rng(seed)
    src = rng.uniform(-2, 2, (K, 3))
    R = Rotation.random(random_state=seed).as_matrix()
    t = np.array([0.5, -0.3, 1.0])
    tgt = src @ R.T + t + rng.normal(0, noise, (K, 3))
    outliers = rng.choice(K, K - int(round(inlier_ratio * K)), replace=False)
    tgt[outliers] = rng.uniform(-2, 2, (len(outliers), 3)) + t
    truth = np.ones(K, bool)
    truth[outliers] = False
    return src, tgt, R, t, truth


@pytest.mark.parametrize("K,ratio", [(1000, 0.05), (1500, 0.03), (500, 0.5)])
def test_compatibility_finds_the_pose_at_low_inlier_ratios(K, ratio):
    src, tgt, R, t, truth = correspondences(K, ratio)
    est = estimate_compatibility(src, tgt, np.ones(K), 0.05)
    assert est.valid
    assert rotation_error_deg(R, est.R) < 0.5 and np.linalg.norm(est.t - t) < 0.02
    # it keeps the true correspondences and almost nothing else
    assert est.inliers[truth].mean() > 0.9 and est.inliers[~truth].mean() < 0.01


def test_the_paper_svd_fails_where_compatibility_does_not():
    src, tgt, R, _, _ = correspondences(1000, 0.1, seed=1)
    assert rotation_error_deg(R, estimate_svd(src, tgt, np.ones(1000), 0.05).R) > 20.0
    assert rotation_error_deg(R, estimate("compatibility", src, tgt, np.ones(1000), 0.05).R) < 0.5


def test_confidence_seeds_the_consensus():
    """At 0.6% inliers (12 of 2000), with one seed, uniform weights miss the true consensus; the
    same correspondences with a confidence that mildly favours the true ones find it."""
    src, tgt, R, _, truth = correspondences(2000, 0.006, seed=6)
    cfg = CompatibilityConfig(max_seeds=1)
    uniform = estimate_compatibility(src, tgt, np.ones(2000), 0.05, cfg)
    w = np.where(truth, 0.6, 0.3)
    seeded = estimate_compatibility(src, tgt, w, 0.05, cfg)
    assert rotation_error_deg(R, seeded.R) < 0.5
    assert rotation_error_deg(R, uniform.R) > 5.0


def test_a_confident_but_incompatible_correspondence_is_not_an_inlier():
    src, tgt, R, t, _ = correspondences(400, 0.3, seed=3)
    w = np.full(400, 0.1)
    tgt[0] = src[0] @ R.T + t + [1.0, 0.0, 0.0]                    # 1 m off the truth, full confidence
    w[0] = 1.0
    est = estimate_compatibility(src, tgt, w, 0.05)
    assert not est.inliers[0] and rotation_error_deg(R, est.R) < 0.5


def test_degenerate_inputs_give_a_reason_not_an_exception():
    src, tgt, *_ = correspondences(50, 1.0)
    for est in (estimate_compatibility(src[:2], tgt[:2], np.ones(2), 0.05),
                estimate_compatibility(src, tgt, np.zeros(50), 0.05),
                estimate_svd(np.zeros((10, 3)), np.zeros((10, 3)), np.ones(10), 0.05)):
        assert not est.valid and est.reason and np.isfinite(est.R).all()
    line = np.c_[np.linspace(0, 1, 20), np.zeros(20), np.zeros(20)]
    assert kabsch(line, line, np.ones(20)) is None
    with pytest.raises(ValueError, match="estimator must be one of"):
        estimate("ransac", src, tgt, np.ones(50), 0.05)


def test_compatibility_is_deterministic():
    src, tgt, *_ = correspondences(800, 0.1, seed=4)
    a = estimate_compatibility(src, tgt, np.ones(800), 0.05)
    b = estimate_compatibility(src, tgt, np.ones(800), 0.05)
    np.testing.assert_array_equal(a.R, b.R)
    np.testing.assert_array_equal(a.inliers, b.inliers)


def test_geometric_verification_prefers_the_pose_that_lays_the_cloud_on_the_target():
    """Two consistent clusters of 40 correspondences, one under the true pose (confidence 0.8),
    one under a wrong pose (confidence 1), among 300 random ones: the count alone picks the wrong
    pose; with the clouds given, count x fitness picks the truth, because the wrong pose lays
    the source cloud in free space."""
    rng = np.random.default_rng(8)
    cloud = rng.uniform(-2, 2, (1500, 3))
    R = Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix()
    t = np.array([0.3, 0.2, -0.4])
    target = cloud @ R.T + t
    R2 = Rotation.from_euler("xyz", [-40, 60, 5], degrees=True).as_matrix()
    t2 = np.array([1.0, -1.5, 0.5])
    true_idx = rng.choice(1500, 40, replace=False)
    wrong_idx = rng.choice(1500, 40, replace=False)
    noise_idx = rng.choice(1500, 300)
    src = np.concatenate([cloud[true_idx], cloud[wrong_idx], cloud[noise_idx]])
    tgt = np.concatenate([target[true_idx], cloud[wrong_idx] @ R2.T + t2, rng.uniform(-2, 2, (300, 3))])
    w = np.concatenate([np.full(40, 0.8), np.ones(40), np.full(300, 0.5)])
    alone = estimate_compatibility(src, tgt, w, 0.05)
    verified = estimate_compatibility(src, tgt, w, 0.05, CompatibilityConfig(verify=50), clouds=(cloud, target))
    assert rotation_error_deg(R2, alone.R) < 1.0                 # the count alone: the wrong pose
    assert rotation_error_deg(R, verified.R) < 0.5 and np.linalg.norm(verified.t - t) < 0.02
    assert verified.inliers[:40].all() and not verified.inliers[40:80].any()
    off = estimate_compatibility(src, tgt, w, 0.05, clouds=(cloud, target))
    np.testing.assert_array_equal(off.R, alone.R)                 # verify = 0 (the default) switches it off
    # The ranked hypotheses are kept, best-counted first: the wrong pose heads them, the truth is
    # among them; without verification there are none.
    H = verified.hypotheses
    assert H.ndim == 3 and 2 <= len(H) <= 50 and H.shape[1:] == (4, 4)
    np.testing.assert_allclose(H[:, 3], np.tile([0, 0, 0, 1.0], (len(H), 1)))
    assert rotation_error_deg(R2, H[0, :3, :3]) < 1.0
    assert any(rotation_error_deg(R, h[:3, :3]) < 0.5 and np.linalg.norm(h[:3, 3] - t) < 0.02 for h in H)
    assert off.hypotheses.shape == (0, 4, 4) and alone.hypotheses.shape == (0, 4, 4)


def _reference_matrices(src, tgt, d_thr):
    """The compatibility matrices as first written (before the blocked version): SciPy's
    pairwise distances in float64, cast to float32, then the hard and soft tests."""
    from scipy.spatial.distance import cdist
    d = np.abs(cdist(src, src).astype(np.float32) - cdist(tgt, tgt).astype(np.float32))
    hard = d < d_thr
    soft = np.maximum(np.float32(1.0) - np.square(d / np.float32(d_thr)), np.float32(0.0))
    np.fill_diagonal(hard, False)
    np.fill_diagonal(soft, 0.0)
    return hard, soft


@pytest.mark.parametrize("K", [7, 64, 65, 500, 3000])
def test_blocked_compatibility_matrices_equal_the_direct_ones(K):
    from cegc_ros.estimator import compatibility_matrices
    src, tgt, _, _, _ = correspondences(K, 0.3, seed=K)
    tgt = tgt + 100.0                                  # far from the origin: centring keeps precision
    hard, soft = compatibility_matrices(src, tgt, 0.05)
    ref_hard, ref_soft = _reference_matrices(src, tgt, 0.05)
    assert hard.dtype == bool and soft.dtype == np.float32 and hard.shape == (K, K)
    # equal, except where the float32 rounding of the reference puts d_ij on the other side of
    # the threshold (the two round differently: float32 before vs after the difference)
    from scipy.spatial.distance import cdist
    d = np.abs(cdist(src, src) - cdist(tgt, tgt))
    differ = hard != ref_hard
    assert (np.abs(d[differ] - 0.05) < 1e-5).all()
    assert differ.sum() <= 1e-4 * K * K
    assert np.abs(soft - ref_soft).max() < 1e-4
    assert (np.diag(hard) == 0).all() and (np.diag(soft) == 0).all()
    assert hard.sum() > K                               # the inliers are compatible with each other


@pytest.mark.parametrize("K", [5, 63, 64, 65, 700])
def test_bit_packed_second_order_rows_equal_the_matrix_product(K):
    from cegc_ros.estimator import second_order_rows
    rng = np.random.default_rng(K)
    C = rng.random((K, K)) < 0.15
    C[: K // 3, : K // 3] = True                        # a consensus block, as inliers make
    C = C | C.T
    np.fill_diagonal(C, False)
    rows = rng.choice(K, min(K, 150), replace=False)   # 700: three passes of SECOND_ORDER_CHUNK
    F = C.astype(np.float32)
    expected = F[rows] * (F[rows] @ F)
    got = second_order_rows(C, rows)
    assert got.dtype == np.float32 and got.shape == (len(rows), K)
    np.testing.assert_array_equal(got, expected)
    with pytest.MonkeyPatch.context() as m:              # numpy < 2.0 (colcon on Ubuntu 24.04)
        m.delattr(np, "bitwise_count", raising=False)
        np.testing.assert_array_equal(second_order_rows(C, rows), expected)
    assert expected.max() >= K // 3 - 2                 # the block's rows count its members


def test_the_faster_estimator_keeps_the_inlier_sets_of_the_direct_one(monkeypatch):
    """Random problems (40, 200-3000 correspondences, 5-60% inliers, with and without the
    geometric verification): the blocked matrices and the early-stopped power iteration give
    exactly the inlier sets of the direct matrices with 20 full iterations."""
    from cegc_ros import estimator
    fast, slow = [], []
    for seed in range(40):
        K = (200, 800, 1500, 3000)[seed % 4]
        src, tgt, _, _, _ = correspondences(K, (0.05, 0.1, 0.3, 0.6)[seed % 3], seed=seed)
        w = np.random.default_rng(seed).random(K)
        clouds = (src[:400], tgt[:400]) if seed % 2 else None
        cfg = CompatibilityConfig(verify=50 if clouds else 0)
        fast.append(estimate_compatibility(src, tgt, w, 0.05, cfg, clouds).inliers)
        with monkeypatch.context() as m:
            m.setattr(estimator, "compatibility_matrices", _reference_matrices)
            m.setattr(estimator, "SPECTRAL_TOL", 0.0)
            slow.append(estimate_compatibility(src, tgt, w, 0.05, cfg, clouds).inliers)
    assert all((a == b).all() for a, b in zip(fast, slow))
    assert sum(a.sum() for a in fast) > 0.05 * sum(len(a) for a in fast)


def test_residuals_are_the_distances_of_every_moved_correspondence():
    from scipy.spatial.transform import Rotation

    from cegc_ros.estimator import _residuals
    rng = np.random.default_rng(3)
    src, tgt = rng.normal(size=(700, 3)), rng.normal(size=(700, 3))
    R, t = Rotation.random(40, random_state=4).as_matrix(), rng.normal(size=(40, 3))
    expected = np.linalg.norm(np.einsum("hij,kj->hki", R, src) + t[:, None] - tgt[None], axis=-1)
    got = _residuals(R, t, src, tgt)
    assert got.shape == (40, 700)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-13)


def _seeds_built(monkeypatch) -> list[int]:
    """Record how many seeds each call of the estimator's hypothesis builder gets."""
    import cegc_ros.estimator as est_mod
    calls: list[int] = []
    inner = est_mod._hypotheses

    def counting(hard, seeds, *args, **kwargs):
        calls.append(len(seeds))
        return inner(hard, seeds, *args, **kwargs)

    monkeypatch.setattr(est_mod, "_hypotheses", counting)
    return calls


def test_sure_seeds_decide_a_clean_pair_from_the_strongest_seeds_alone(monkeypatch):
    """A cloud seen twice (every correspondence's source point lands on the target cloud, 60%
    of the correspondences true): the 16 strongest seeds already give a pose whose fitness is
    above sure_fitness, so the other seeds are never built, and the pose and inliers are those
    of building all 200 at once."""
    rng = np.random.default_rng(3)
    cloud = rng.uniform(-2, 2, (1500, 3))
    R = Rotation.from_euler("xyz", [15, -5, 40], degrees=True).as_matrix()
    t = np.array([0.4, -0.2, 0.3])
    target = cloud @ R.T + t
    src = cloud.copy()
    tgt = target + rng.normal(0, 0.005, target.shape)
    wrong = rng.choice(1500, 600, replace=False)
    tgt[wrong] = target[rng.permutation(wrong)]
    w = rng.uniform(0.2, 1.0, 1500)
    calls = _seeds_built(monkeypatch)
    cfg = CompatibilityConfig(verify=50, sure_fitness=0.85)
    full = estimate_compatibility(src, tgt, w, 0.05, cfg, clouds=(cloud, target))
    assert calls == [200]
    calls.clear()
    quick = estimate_compatibility(src, tgt, w, 0.05, CompatibilityConfig(verify=50, sure_fitness=0.85, sure_seeds=16),
                                   clouds=(cloud, target))
    assert calls == [16]
    assert rotation_error_deg(R, quick.R) < 0.1 and np.linalg.norm(quick.t - t) < 0.01
    # the same alignment and inliers: the refinement may start from another of the
    # near-identical hypotheses and stop a few thousandths of a degree away on another CPU's
    # rounding (as the half-seen cloud's below did on the Xeon with AVX-512)
    assert rotation_error_deg(full.R, quick.R) < 0.01 and np.linalg.norm(full.t - quick.t) < 1e-3
    np.testing.assert_array_equal(quick.inliers, full.inliers)


def test_sure_seeds_build_every_seed_when_the_first_choice_is_not_sure(monkeypatch):
    """Half of the source cloud has no counterpart (fitness of the true pose ~0.5 < 0.85): the
    16 strongest seeds do not decide, the other 184 are built after them, and the pose is the one
    of building all 200 at once."""
    src, tgt, R, t, truth = correspondences(1500, 0.1, seed=4)
    cloud_s = src
    cloud_t = np.concatenate([(src @ R.T + t)[:750], np.random.default_rng(4).uniform(-2, 2, (750, 3))])
    calls = _seeds_built(monkeypatch)
    full = estimate_compatibility(src, tgt, np.ones(1500), 0.05, CompatibilityConfig(verify=50),
                                  clouds=(cloud_s, cloud_t))
    assert calls == [200]
    calls.clear()
    split = estimate_compatibility(src, tgt, np.ones(1500), 0.05, CompatibilityConfig(verify=50, sure_seeds=16,
                                                                                        sure_fitness=0.85),
                                   clouds=(cloud_s, cloud_t))
    assert calls == [16, 184]
    assert rotation_error_deg(R, split.R) < 0.5
    assert rotation_error_deg(full.R, split.R) < 1e-3 and np.linalg.norm(full.t - split.t) < 1e-5
    np.testing.assert_array_equal(split.inliers, full.inliers)


def test_an_unambiguous_first_choice_is_sure_below_sure_fitness(monkeypatch):
    """The half-seen cloud above (fitness ~0.5 < 0.85): with sure_ambiguity, the 16 strongest
    seeds decide when no distinct alignment among their hypotheses comes within it, with the
    pose and inliers of building every seed; an ambiguous first choice (the half-turn
    symmetric scene below) still gets every seed."""
    from dataclasses import replace
    src, tgt, R, t, truth = correspondences(1500, 0.1, seed=4)
    cloud_t = np.concatenate([(src @ R.T + t)[:750], np.random.default_rng(4).uniform(-2, 2, (750, 3))])
    calls = _seeds_built(monkeypatch)
    cfg = CompatibilityConfig(verify=50, sure_seeds=16, sure_fitness=0.85, sure_ambiguity=0.5)
    full = estimate_compatibility(src, tgt, np.ones(1500), 0.05, CompatibilityConfig(verify=50),
                                  clouds=(src, cloud_t))
    calls.clear()
    quick = estimate_compatibility(src, tgt, np.ones(1500), 0.05, cfg, clouds=(src, cloud_t))
    assert calls == [16] and quick.ambiguity <= 0.5
    # the same alignment: the refinement may start from another of the near-identical
    # hypotheses that more seeds give and stop a few thousandths of a degree away (0.003 deg,
    # 0.2 mm on the Xeon with AVX-512), against 0.014 deg from the truth at this noise
    assert rotation_error_deg(full.R, quick.R) < 0.01 and np.linalg.norm(full.t - quick.t) < 1e-3
    assert rotation_error_deg(R, quick.R) < 0.05 and np.linalg.norm(quick.t - t) < 5e-3
    np.testing.assert_array_equal(quick.inliers, full.inliers)
    # the fitness floor: above every fitness here, so the first choice is never sure
    calls.clear()
    estimate_compatibility(src, tgt, np.ones(1500), 0.05,
                           CompatibilityConfig(verify=50, sure_seeds=16, sure_fitness=0.85, sure_ambiguity=0.5,
                                               sure_min_fitness=0.8), clouds=(src, cloud_t))
    assert calls == [16, 184]
    # a scene symmetric under a half turn: two alignments explain it alike (and fully, so the
    # fitness rule is switched off here), never sure by ambiguity
    rng = np.random.default_rng(3)
    half = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    base = rng.uniform(-2, 2, (750, 3)) + [2.5, 0, 0]
    sym = np.concatenate([base, base @ half.T])
    source = sym.copy()
    i, j = rng.choice(1500, 200, replace=False), rng.choice(1500, 200, replace=False)
    noise = rng.choice(1500, 600)
    s2 = np.concatenate([source[i], source[j], source[noise]])
    t2 = np.concatenate([sym[i], sym[j] @ half.T, rng.uniform(-4, 4, (600, 3))])
    calls.clear()
    amb = estimate_compatibility(s2, t2, np.ones(len(s2)), 0.05, replace(cfg, sure_fitness=1.01), clouds=(source, sym))
    assert calls[0] == 16 and len(calls) > 1 and amb.ambiguity > 0.9


def test_ambiguity_is_the_best_distinct_rivals_score_over_the_answers():
    """Poses that put the source points within the distance of the best one's are its own
    variants, not rivals; the best of the others sets the ratio; none: 0."""
    from cegc_ros.estimator import ambiguity
    src = np.random.default_rng(0).uniform(-1, 1, (200, 3))
    R = np.tile(np.eye(3), (4, 1, 1))
    R[3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    t = np.array([[0, 0, 0], [0.02, 0, 0], [1.0, 0, 0], [0, 0, 0]], float)
    rank = np.array([10.0, 9.9, 6.0, 7.0])
    assert ambiguity(R, t, rank, src, 0.1) == pytest.approx(0.7)        # the rotated pose, not the shifted one
    assert ambiguity(R[:3], t[:3], rank[:3], src, 0.1) == pytest.approx(0.6)
    assert ambiguity(R[:2], t[:2], rank[:2], src, 0.1) == 0.0           # a near variant only
    assert ambiguity(R[:1], t[:1], rank[:1], src, 0.1) == 0.0
    assert ambiguity(R, t, np.zeros(4), src, 0.1) == 0.0


def test_distinct_poses_from_the_moments_match_the_gaps_point_by_point():
    """_distinct's mean square gap from the source's mean and covariance equals the gap measured
    point by point (1e-12 relative), and so does every verdict, near the distance too."""
    from cegc_ros.estimator import _distinct
    rng = np.random.default_rng(7)
    source = rng.normal([2.0, -1.0, 0.5], [2.0, 1.5, 0.7], (512, 3))
    R = Rotation.from_rotvec(rng.normal(0, 0.02, (300, 3))).as_matrix()
    t = rng.normal(0, 0.05, (300, 3))
    R[:100] = Rotation.random(100, random_state=8).as_matrix()             # far rivals too
    for b in (0, 150, 299):
        gap = source[None] @ np.transpose(R - R[b], (0, 2, 1)) + (t - t[b])[:, None]
        rms = np.sqrt(np.square(gap).sum(-1).mean(1))
        distance = float(np.median(rms[100:]))                              # near ones on each side
        got = _distinct(R, t, b, source, distance)
        assert got.tolist() == (rms > distance).tolist()
        assert not got[b] and 0 < got.sum() < 299
        if b >= 100:
            assert got[:100].all()                                          # the random rotations
        # the moments' value itself, through the verdict at distances just either side of it
        for h in rng.choice(300, 20, replace=False):
            if h != b:
                assert _distinct(R[[b, h]], t[[b, h]], 0, source, rms[h] * (1 - 1e-12))[1]
                assert not _distinct(R[[b, h]], t[[b, h]], 0, source, rms[h] * (1 + 1e-12))[1]


def test_a_symmetric_scene_makes_the_answer_ambiguous_and_an_asymmetric_one_does_not():
    """A target laid out symmetrically under a half turn about z: 40 correspondences under the
    true pose and 40 under the true pose followed by the half turn lay the source on the target
    equally well, so the estimate's ambiguity is about 1. Without the mirrored half, and
    without the rival cluster, the same true cluster among 300 random correspondences leaves no
    alignment near it."""
    rng = np.random.default_rng(3)
    half = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    R = Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix()
    t = np.array([0.3, 0.2, -0.4])
    base = rng.uniform(-2, 2, (750, 3)) + [2.5, 0, 0]

    def problem(target, rival):
        source = (target - t) @ R                                          # R source + t = target
        i = rng.choice(len(target), 40, replace=False)
        j = rng.choice(len(target), 40, replace=False)
        noise = rng.choice(len(target), 300)
        src = [source[i], source[noise]] + ([source[j]] if rival else [])
        tgt = [target[i], rng.uniform(-4, 4, (300, 3))] + ([target[j] @ half.T] if rival else [])
        return np.concatenate(src), np.concatenate(tgt), source

    sym = np.concatenate([base, base @ half.T])
    src, tgt, source = problem(sym, rival=True)
    est = estimate_compatibility(src, tgt, np.ones(len(src)), 0.05, CompatibilityConfig(verify=50),
                                 clouds=(source, sym))
    assert est.ambiguity > 0.9
    asym = np.concatenate([base, rng.uniform(-2, 2, (750, 3)) - [2.5, 0, 0]])
    src, tgt, source = problem(asym, rival=False)
    est = estimate_compatibility(src, tgt, np.ones(len(src)), 0.05, CompatibilityConfig(verify=50),
                                 clouds=(source, asym))
    assert rotation_error_deg(R, est.R) < 0.5 and est.ambiguity < 0.5
    # without verification there is nothing to compare: 0
    assert estimate_compatibility(src, tgt, np.ones(len(src)), 0.05).ambiguity == 0.0


def test_free_space_scores_are_checked_lazily_with_the_same_choice_and_ambiguity():
    """_free_space_scores checks only the poses that can still be the best or its best distinct
    rival: on random problems (poses around a few alignments, spread and tied scores, free-space
    factors from 1 to 0.02) the choice, its score and the ambiguity equal those of checking
    every pose, every checked score is the full one, and fewer poses are checked than there
    are. Then the same with real range images (visibility.FreeSpace)."""
    from cegc_ros.estimator import _free_space_scores, ambiguity
    from cegc_ros.visibility import FreeSpace

    class Table:
        """Violations looked up by pose (its translation), counting the poses checked."""

        def __init__(self, t: np.ndarray, v: np.ndarray) -> None:
            self.t, self.v, self.checked = t, v, 0

        def violations(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
            self.checked += len(t)
            return np.array([self.v[int(np.argmin(np.abs(self.t - row).sum(1)))] for row in t])

    rng = np.random.default_rng(7)
    src = rng.uniform(-2, 2, (300, 3))
    checked = total = 0
    for trial in range(200):
        H = int(rng.integers(2, 60))
        centres = Rotation.random(4, random_state=trial).as_matrix()
        pick = rng.integers(0, 4, H)
        R = np.einsum("hij,hjk->hik", centres[pick],
                      Rotation.from_rotvec(rng.normal(0, 0.01, (H, 3))).as_matrix())
        t = rng.normal(0, 0.5, (4, 3))[pick] + rng.normal(0, 0.005, (H, 3))
        upper = rng.exponential(1.0, H)
        v = rng.uniform(0.0, 0.4, H)
        if trial % 3 == 0:                                   # ties at the top, some exact
            tied = rng.integers(0, H, max(1, H // 2))
            upper[tied], v[tied[::2]] = upper.max(), 0.0
        space = Table(t, v)
        full = upper * np.exp(-10.0 * v)
        lazy = _free_space_scores(upper, R, t, 10.0, space, src, 0.2)
        seen = np.isfinite(lazy)
        assert space.checked == seen.sum()
        assert np.array_equal(lazy[seen], full[seen])
        assert int(lazy.argmax()) == int(full.argmax())
        assert ambiguity(R, t, lazy, src, 0.2) == ambiguity(R, t, full, src, 0.2)
        checked, total = checked + space.checked, total + H
    assert checked < 0.8 * total

    # real range images: a box of walls seen from inside, poses around the identity
    wall = rng.uniform(-3, 3, (2500, 3))
    wall[np.arange(2500), rng.integers(0, 3, 2500)] = rng.choice([-3.0, 3.0], 2500)
    space = FreeSpace(wall, wall[rng.permutation(2500)[:2000]])
    R = Rotation.from_rotvec(rng.normal(0, 0.3, (50, 3))).as_matrix()
    t = rng.normal(0, 0.5, (50, 3))
    upper = rng.exponential(1.0, 50)
    full = upper * np.exp(-10.0 * space.violations(R, t))
    lazy = _free_space_scores(upper, R, t, 10.0, space, wall[:500], 0.2)
    seen = np.isfinite(lazy)
    assert np.array_equal(lazy[seen], full[seen]) and int(lazy.argmax()) == int(full.argmax())
    assert ambiguity(R, t, lazy, wall[:500], 0.2) == ambiguity(R, t, full, wall[:500], 0.2)


def test_feature_agreement_picks_the_truth_where_a_slide_fits_as_well():
    """A lattice laid on itself one step off fits almost as well as the truth (7/8 of the points
    land on a point), and more correspondences agree with the slide: count x fitness takes the
    slide. Given the points' descriptors (the same place has the same descriptor in both
    clouds), count x feature agreement takes the truth: the slide brings together points the
    descriptors tell apart."""
    rng = np.random.default_rng(3)
    g = np.arange(8) * 0.1
    cloud = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)            # (512, 3)
    R = Rotation.from_euler("xyz", [5, -10, 20], degrees=True).as_matrix()
    t = np.array([0.2, -0.1, 0.3])
    target = cloud @ R.T + t
    slide = np.array([0.1, 0.0, 0.0])                                    # one lattice step in x
    true_idx = rng.choice(512, 40, replace=False)
    wrong_idx = rng.choice(np.flatnonzero(cloud[:, 0] < 0.65), 50, replace=False)
    noise_idx = rng.choice(512, 300)
    src = np.concatenate([cloud[true_idx], cloud[wrong_idx], cloud[noise_idx]])
    tgt = np.concatenate([target[true_idx], (cloud[wrong_idx] + slide) @ R.T + t,
                          target[rng.choice(512, 300)]])
    w = np.concatenate([np.full(40, 0.8), np.ones(50), np.full(300, 0.3)])
    desc = rng.normal(size=(512, 32))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    cfg = CompatibilityConfig(verify=50)
    by_fitness = estimate_compatibility(src, tgt, w, 0.05, cfg, clouds=(cloud, target))
    by_features = estimate_compatibility(src, tgt, w, 0.05, cfg, clouds=(cloud, target), similarity=desc @ desc.T)
    np.testing.assert_allclose(by_fitness.t, t + R @ slide, atol=0.01)                  # the slide
    assert rotation_error_deg(R, by_features.R) < 0.5 and np.linalg.norm(by_features.t - t) < 0.01
    assert by_features.inliers[:40].all() and not by_features.inliers[40:90].any()
