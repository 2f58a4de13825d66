"""The confidence-guided robust solver."""

from __future__ import annotations

import numpy as np

from cegc_ros.solver import kabsch_weighted, robust_pose


def rot(axis: np.ndarray, deg: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def problem(n=400, outlier_frac=0.7, seed=0):
    rng = np.random.default_rng(seed)
    R = rot(rng.normal(size=3), 40)
    t = rng.uniform(-0.5, 0.5, 3)
    src = rng.uniform(-0.5, 0.5, (n, 3))
    tgt = src @ R.T + t + rng.normal(0, 0.002, (n, 3))
    bad = rng.random(n) < outlier_frac
    tgt[bad] = rng.uniform(-0.5, 0.5, (bad.sum(), 3))
    return src, tgt, R, t, bad


def test_recovers_pose_with_70_percent_outliers_and_flat_weights():
    src, tgt, R, t, bad = problem()
    R_est, t_est, inl, valid = robust_pose(src, tgt, np.ones(len(src)), inlier_distance=0.01)
    assert valid
    ang = np.degrees(np.arccos(np.clip((np.trace(R.T @ R_est) - 1) / 2, -1, 1)))
    assert ang < 0.5 and np.linalg.norm(t_est - t) < 0.005
    assert (inl & bad).sum() <= 3 and (inl & ~bad).sum() >= 0.9 * (~bad).sum()


def test_confidences_guide_the_search_at_95_percent_outliers():
    src, tgt, R, t, bad = problem(outlier_frac=0.95, seed=1)
    w = np.where(bad, 0.05, 0.9)                    # an informative confidence head
    R_est, _, _, valid = robust_pose(src, tgt, w, inlier_distance=0.01, hypotheses=300)
    assert valid and np.abs(R_est - R).max() < 0.02


def test_zero_weights_or_too_few_points_are_invalid():
    src, tgt, *_ = problem(n=50)
    assert not robust_pose(src, tgt, np.zeros(50), 0.01)[3]
    assert not robust_pose(src[:2], tgt[:2], np.ones(2), 0.01)[3]


def test_deterministic_for_a_seed():
    src, tgt, *_ = problem(seed=3)
    a = robust_pose(src, tgt, np.ones(len(src)), 0.01, seed=5)
    b = robust_pose(src, tgt, np.ones(len(src)), 0.01, seed=5)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[2], b[2])


def test_weighted_kabsch_exact_and_degenerate():
    src, _, R, t, _ = problem(outlier_frac=0.0)
    sol = kabsch_weighted(src, src @ R.T + t, np.random.default_rng(0).uniform(0.1, 1, len(src)))
    assert sol is not None and np.allclose(sol[0], R, atol=1e-9) and np.allclose(sol[1], t, atol=1e-9)
    line = np.linspace(0, 1, 20)[:, None] * [1.0, 2.0, 3.0]
    assert kabsch_weighted(line, line, np.ones(20)) is None


def test_budget_keeps_drawing_until_a_low_inlier_pose_is_found():
    # 4% inliers and flat weights: an all-inlier triplet turns up once in ~16k draws.
    src, tgt, R, t, bad = problem(outlier_frac=0.96, seed=2)
    w = np.ones(len(src))
    R_one, _, _, _ = robust_pose(src, tgt, w, inlier_distance=0.01, hypotheses=1000)
    stats: dict = {}
    R_all, t_all, inl, valid = robust_pose(src, tgt, w, inlier_distance=0.01, hypotheses=1000,
                                           max_hypotheses=150000, stats=stats)
    err = lambda Re: np.degrees(np.arccos(np.clip((np.trace(R.T @ Re) - 1) / 2, -1, 1)))  # noqa: E731
    assert err(R_one) > 10.0                       # one round of 1000 misses it
    assert valid and err(R_all) < 0.5 and np.linalg.norm(t_all - t) < 0.005
    assert 1000 < stats["drawn"] <= 150000
    assert (inl & ~bad).sum() >= 0.9 * (~bad).sum() and (inl & bad).sum() <= 3


def test_easy_pairs_stop_after_the_first_round():
    # 30% inliers: the stopping rule holds after round one, so a large budget changes nothing.
    src, tgt, *_ = problem(seed=4)
    a = robust_pose(src, tgt, np.ones(len(src)), 0.01, hypotheses=2000, seed=7)
    stats: dict = {}
    b = robust_pose(src, tgt, np.ones(len(src)), 0.01, hypotheses=2000, seed=7, max_hypotheses=10**6,
                    stats=stats)
    assert stats["drawn"] == 2000
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[2], b[2])
