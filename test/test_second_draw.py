"""The second draw of the network points (cegc_ros/second_draw.py, engine.redraw_ambiguity): when
it is wanted, how the two answers are scored, and the engine's use of it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cegc_ros import second_draw as S
from cegc_ros.estimator import hypothesis_counts
from cegc_ros.refine import landing_evidence
from cegc_ros.verification import FEATURES, VerificationModel, features
from cegc_ros.visibility import FreeSpace


def _model(free_space: float = 20.0) -> VerificationModel:
    return VerificationModel({"log_count": 0.8, "log_agreement": 9.0, "log_fitness": -1.0,
                              "log_overlap_landed": 0.1, "overlap_precision": 15.0}, free_space, {})


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _draw(rng: np.random.Generator, T: np.ndarray, n: int = 300) -> S.Draw:
    """Network points of a box-shaped room seen by both clouds (the target is the source moved
    by T, other points), half of the correspondences true, a similarity high on true partners."""
    room = rng.uniform(-2, 2, (4 * n, 3))
    room[np.arange(4 * n), rng.integers(0, 3, 4 * n)] = rng.choice([-2.0, 2.0], 4 * n)
    src = room[rng.choice(len(room), n, replace=False)]
    tgt = src @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.01, (n, 3))
    tgt = tgt[rng.permutation(n)]
    moved = src @ T[:3, :3].T + T[:3, 3]
    partner = np.linalg.norm(moved[:, None] - tgt[None], axis=2).argmin(1)
    k = n // 2
    i = rng.choice(n, k, replace=False)
    j = np.where(np.arange(k) < k // 2, partner[i], rng.integers(0, n, k))
    sim = rng.uniform(-0.2, 0.4, (n, n))
    sim[np.arange(n), partner] = 0.9
    return S.Draw(src, tgt, src[i], tgt[j], rng.uniform(0.2, 1.0, k), sim, rng.uniform(0.3, 1.0, n), 0.1)


def test_a_second_draw_is_wanted_only_for_an_explored_answer_above_the_threshold():
    assert S.wanted(True, 0.6, 0.5)
    assert not S.wanted(True, 0.5, 0.5)            # above, not at
    assert not S.wanted(False, 0.9, 0.5)           # the first seeds settled it
    assert not S.wanted(True, 1.0, 1.0)            # 1: never (ambiguity is at most 1)
    assert S.wanted(True, 0.01, 0.0)


def test_scores_sum_the_learned_evidence_over_the_draws_and_the_free_space_per_draw():
    """scores() is the model's linear evidence (the estimator's own count and landing evidence)
    summed over the draws, less free_space x violations once per draw."""
    rng = np.random.default_rng(3)
    T_true = _pose(Rotation.from_rotvec([0.1, -0.3, 0.2]).as_matrix(), np.array([0.4, 0.1, -0.2]))
    draws = [_draw(rng, T_true), _draw(rng, T_true)]
    poses = np.stack([T_true, np.eye(4), _pose(Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix(), np.zeros(3))])
    model = _model()
    w = np.array([model.weights[f] for f in FEATURES])
    expect = np.zeros(3)
    for d in draws:
        R, t = poses[:, :3, :3], poses[:, :3, 3]
        count = hypothesis_counts(R, t, d.source_matched, d.target_matched, d.weights, d.inlier_distance)
        fit, agree, landed, prec = landing_evidence(R, t, d.source_points, d.target_points, d.similarity,
                                                    d.source_overlap, d.inlier_distance)
        expect += features(count, agree, fit, landed, prec) @ w
    np.testing.assert_allclose(S.scores(model, poses, draws, None), expect, rtol=1e-12)
    space = FreeSpace(draws[0].source_points * 2.0, draws[0].target_points * 2.0)
    v = space.violations(poses[:, :3, :3], poses[:, :3, 3])
    np.testing.assert_allclose(S.scores(model, poses, draws, space), expect - 2 * model.free_space * v, rtol=1e-12)
    # the right pose is the best scored, by a margin
    s = S.scores(model, poses, draws, None)
    assert s.argmax() == 0 and s[0] > s[1:].max() + 5.0


def test_choose_keeps_the_best_valid_answer_and_the_first_on_a_tie_or_when_none_is_valid():
    rng = np.random.default_rng(4)
    T_true = _pose(Rotation.from_rotvec([0.0, 0.2, -0.1]).as_matrix(), np.array([0.2, 0.0, 0.3]))
    draws = [_draw(rng, T_true), _draw(rng, T_true)]
    model = _model()
    right_second = np.stack([np.eye(4), T_true])
    assert S.choose(model, right_second, np.array([True, True]), draws, None) == 1
    assert S.choose(model, right_second, np.array([True, False]), draws, None) == 0   # invalid loses
    assert S.choose(model, right_second, np.array([False, False]), draws, None) == 0  # none: the first
    assert S.choose(model, np.stack([T_true, T_true]), np.array([True, True]), draws, None) == 0  # tie


def test_the_engine_draws_again_when_in_doubt_and_keeps_the_answer_the_verification_prefers(val_cache):
    """A synthetic different-view validation pair with the exploring pass forced and redraw_ambiguity 0:
    the engine registers it twice (the second draw at seed + SEED_OFFSET), keeps the answer
    second_draw.choose picks, times it as the stage 'redraw' inside 'total'; redraw_ambiguity 1
    (never) and verify_score 'features' give the first draw's answer alone."""
    from cegc_ros import engine
    from cegc_ros.config import EngineConfig
    from cegc_ros.data.pair_cache import PairCache
    forced = dict(sure_fitness=1.01, sure_ambiguity=-1.0)
    reg = engine.Registrar.from_checkpoint(None, device="cpu", engine=EngineConfig(redraw_ambiguity=0.0, **forced))
    seed = reg.preprocess.seed
    one = engine.Registrar.from_checkpoint(None, device="cpu", engine=EngineConfig(redraw_ambiguity=1.0, **forced),
                                           warm=False)
    cache = PairCache(val_cache)
    # a pair whose first answer has a distinct rival, so that threshold 0 calls for the second draw
    pair, first = next((p, r) for p, r in ((cache[i], one.register(cache[i].source, cache[i].target))
                                           for i in range(len(cache))) if r.ambiguity > 0.0)
    assert first.explored and first.draws == 1 and first.seed == seed and "redraw" not in first.timings
    one.update(preprocess=dataclasses.replace(one.preprocess, seed=seed + S.SEED_OFFSET))
    second = one.register(pair.source, pair.target)
    assert second.seed == seed + S.SEED_OFFSET
    assert not np.allclose(first.source_points, second.source_points)   # another draw of the points

    res = reg.register(pair.source, pair.target)
    assert res.draws == 2 and res.valid
    assert res.timings["redraw"] > 0
    stages = sum(v for k, v in res.timings.items() if k not in ("total", "redraw"))
    assert res.timings["total"] == pytest.approx(stages + res.timings["redraw"], rel=1e-9)
    m1 = reg.match_pair(pair.source, pair.target)
    reg.update(preprocess=dataclasses.replace(reg.preprocess, seed=seed + S.SEED_OFFSET))
    m2 = reg.match_pair(pair.source, pair.target)
    draws = [engine.Registrar.draw_evidence(m, r.inlier_distance) for m, r in ((m1, first), (m2, second))]
    pick = S.choose(reg.verifier, np.stack([first.T_target_source, second.T_target_source]),
                    np.array([first.valid, second.valid]), draws, FreeSpace(m1.bounded.source, m1.bounded.target))
    chosen, other = (first, second)[pick], (first, second)[1 - pick]
    # (two registrars' runs of the same draw agree to rounding; the draws' answers differ more)
    np.testing.assert_allclose(res.T_target_source, chosen.T_target_source, atol=1e-9)
    assert np.abs(res.T_target_source - other.T_target_source).max() > 1e-6
    assert res.seed == chosen.seed
    reg.update(preprocess=dataclasses.replace(reg.preprocess, seed=seed),
               engine=EngineConfig(redraw_ambiguity=1.0, **forced))
    alone = reg.register(pair.source, pair.target)
    assert alone.draws == 1 and "redraw" not in alone.timings
    np.testing.assert_allclose(alone.T_target_source, first.T_target_source, atol=1e-9)
    reg.update(engine=EngineConfig(redraw_ambiguity=0.0, verify_score="features", **forced))
    assert reg.register(pair.source, pair.target).draws == 1


def test_the_loop_closure_overlay_turns_the_second_draw_on_and_nothing_else():
    """params/loop_closure.yaml (shipped) sets engine.redraw_ambiguity to 0.5 over the defaults,
    as the evaluation (and the node, a second --params-file) read it."""
    from pathlib import Path

    from cegc_ros.config import EngineConfig, PreprocessConfig
    from cegc_ros.evaluation.methods import engine_configs
    from cegc_ros.params_file import read_params_file
    overlay = Path(__file__).resolve().parents[1] / "params" / "loop_closure.yaml"
    assert read_params_file(overlay) == {"engine.redraw_ambiguity": 0.5}
    pre, eng = engine_configs(overlay)
    assert eng.redraw_ambiguity == 0.5 != EngineConfig().redraw_ambiguity
    assert dataclasses.replace(eng, redraw_ambiguity=EngineConfig().redraw_ambiguity) == EngineConfig()
    assert pre == PreprocessConfig()
