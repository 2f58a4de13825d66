"""The learned verification (cegc_ros/verification.py), its evidence (refine.landing_evidence),
its place in the estimator and the tool that fits it (tools/fit_verification)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cegc_ros import verification as V
from cegc_ros.estimator import CompatibilityConfig, _verify, hypothesis_counts
from cegc_ros.refine import landing_evidence


def _model(**weights: float) -> V.VerificationModel:
    free = weights.pop("free_space", 0.0)
    return V.VerificationModel({f: weights.get(f, 0.0) for f in V.FEATURES}, free)


def test_fit_recovers_the_weights_that_chose_the_right_hypotheses():
    """3000 evaluations of 20 hypotheses each; the right one drawn by the softmax of known
    weights (and a free-space penalty): the fit recovers each weight within 15%."""
    rng = np.random.default_rng(3)
    true = {"log_count": 1.0, "log_agreement": 2.0, "log_fitness": -0.5, "log_overlap_landed": 0.8,
            "overlap_precision": 1.5}
    free = 4.0
    n, h = 3000, 20
    x = rng.normal(0, 1, (n * h, len(V.FEATURES)))
    v = rng.uniform(0, 0.5, n * h)
    s = (x @ np.array([true[f] for f in V.FEATURES]) - free * v).reshape(n, h)
    p = np.exp(s - s.max(1, keepdims=True))
    p /= p.sum(1, keepdims=True)
    pick = (p.cumsum(1) > rng.uniform(0, 1, (n, 1))).argmax(1)
    right = np.zeros((n, h), bool)
    right[np.arange(n), pick] = True
    weights, got_free = V.fit(x, v, np.repeat(np.arange(n), h), right.ravel(), l2=0.0)
    for f in V.FEATURES:
        assert weights[f] == pytest.approx(true[f], rel=0.15), f
    assert got_free == pytest.approx(free, rel=0.15)
    with pytest.raises(ValueError, match="nothing to fit"):
        V.fit(x[:40], v[:40], np.repeat([0, 1], 20), np.zeros(40, bool))


def test_a_model_of_count_and_agreement_alone_ranks_as_count_times_agreement():
    """Weights 1 on log count and log agreement: p = 1 and each score is count x agreement over
    the best's (up to the EPS inside the logarithms), so ratios such as the ambiguity keep
    their meaning; the free-space strength is the weight itself."""
    rng = np.random.default_rng(0)
    count, agree = rng.uniform(1, 30, 50), rng.uniform(1, 60, 50)
    x = V.features(count, agree, rng.uniform(0, 1, 50), rng.uniform(0, 1, 50), rng.uniform(0, 1, 50))
    assert x.shape == (50, len(V.FEATURES))
    model = _model(log_count=1.0, log_agreement=1.0, free_space=10.0)
    assert model.scale == 1.0 and model.free_space_strength == 10.0
    plain = count * agree
    np.testing.assert_allclose(model.ranks(x), plain / plain.max(), rtol=1e-3)
    assert int(model.ranks(x).argmax()) == int(plain.argmax())
    # twice the weights: the same scores (p halves)
    np.testing.assert_allclose(_model(log_count=2.0, log_agreement=2.0).ranks(x), model.ranks(x), rtol=1e-12)


def test_model_files_round_trip_and_bad_ones_fail_in_one_line(tmp_path):
    model = _model(log_count=0.7, log_agreement=4.0, overlap_precision=9.0, free_space=30.0)
    path = tmp_path / "v.json"
    V.VerificationModel(model.weights, model.free_space, {"cache": "train"}).save(path)
    back = V.VerificationModel.load(path)
    assert back.weights == model.weights and back.free_space == 30.0 and back.meta == {"cache": "train"}
    doc = json.loads(path.read_text())
    for change, message in [({"format": 2}, "format 2, expected 1"),
                            ({"free_space": -1.0}, "free_space weight must be >= 0"),
                            ({"weights": {"log_count": 1.0}}, "weights must name log_count"),
                            ({"weights": {**doc["weights"], "log_count": -5.0}}, "must be > 0")]:
        path.write_text(json.dumps({**doc, **change}))
        with pytest.raises(V.VerificationModelError, match=message) as err:
            V.VerificationModel.load(path)
        assert "\n" not in str(err.value)
    path.write_text("{not json")
    with pytest.raises(V.VerificationModelError, match="unreadable"):
        V.VerificationModel.load(path)
    with pytest.raises(V.VerificationModelError, match="unreadable"):
        V.VerificationModel.load(tmp_path / "missing.json")


def test_the_shipped_model_was_fitted_on_training_pairs_and_weighs_what_was_measured():
    """The shipped weights/verification.json loads; it was fitted on a training cache (never
    validation or real pairs) and chose more right hypotheses there than the score it replaces;
    agreement and free space weigh in as measured (docs/accuracy.md, "Learned verification")."""
    from cegc_ros.paths import VERIFICATION_WEIGHTS, shipped_weights
    model = V.VerificationModel.load(shipped_weights(VERIFICATION_WEIGHTS))
    assert "train" in model.meta["cache"] and model.meta["evaluations"] >= 500
    assert model.meta["chosen_right_fitted"] > model.meta["chosen_right_before"]
    # the agreement weighs several times the count (count x agreement weighed them alike)
    assert model.weights["log_agreement"] > 3 * model.weights["log_count"] > 0
    assert model.free_space > 0


def test_landing_evidence_is_what_a_brute_force_search_finds():
    rng = np.random.default_rng(5)
    source, target = rng.uniform(-1, 1, (200, 3)), rng.uniform(-1, 1, (300, 3))
    sim = rng.uniform(-1, 1, (200, 300))
    overlap = rng.uniform(0, 1, 200)
    R = Rotation.random(6, random_state=1).as_matrix()
    R[0] = np.eye(3)
    t = rng.normal(0, 0.1, (6, 3))
    fit, agree, landed, precision = landing_evidence(R, t, source, target, sim, overlap, 0.12)
    for h in range(6):
        d = np.linalg.norm((source @ R[h].T + t[h])[:, None] - target[None], axis=2)
        near = d.min(1) <= 0.12
        assert fit[h] == pytest.approx(near.mean())
        cos = sim[np.arange(200), d.argmin(1)]
        assert agree[h] == pytest.approx(max(cos[near].sum(), 0.0))
        assert landed[h] == pytest.approx(overlap[near].sum() / overlap.sum())
        assert precision[h] == pytest.approx(overlap[near].mean() if near.any() else 0.0)
    fit_only = landing_evidence(R, t, source, target, None, overlap, 0.12)
    np.testing.assert_array_equal(fit_only[1], fit)                  # no similarity: agreement = fitness
    far = landing_evidence(R[:1], t[:1] + 10.0, source, target, sim, overlap, 0.12)
    assert far[0][0] == far[2][0] == far[3][0] == 0.0


def _hypotheses(rng, n):
    R = Rotation.from_rotvec(rng.normal(0, 0.15, (n, 3))).as_matrix()
    return R, rng.normal(0, 0.1, (n, 3))


def test_the_estimator_chooses_by_the_model_in_the_pass_with_the_free_space_check():
    """_verify with a model, the similarity, the overlap and the visibility chooses the verified
    hypothesis of the best model score x free-space factor (checked against every hypothesis
    scored in full); a count-and-agreement model with free space F chooses as the 'features'
    score with engine.free_space F; without the visibility (the first pass) the model is not used."""
    from cegc_ros.visibility import FreeSpace
    rng = np.random.default_rng(11)
    wall = rng.uniform(-3, 3, (2000, 3))
    wall[np.arange(2000), rng.integers(0, 3, 2000)] = rng.choice([-3.0, 3.0], 2000)
    source, target = wall[:400] * 0.5, wall[400:800] * 0.5
    vis = (wall[:1500], wall[500:])
    sim = rng.uniform(-0.2, 1, (400, 400))
    overlap = rng.uniform(0, 1, 400)
    model = _model(log_count=0.7, log_agreement=4.0, log_fitness=-0.5, log_overlap_landed=1.0,
                   overlap_precision=8.0, free_space=30.0)
    cfg = CompatibilityConfig(verify=40, free_space=10.0)
    for trial in range(5):
        R, t = _hypotheses(rng, 60)
        total = rng.uniform(1, 20, 60)
        best, top, fit, rank = _verify(R, t, total, 0.1, cfg, (source, target), vis, {}, sim, overlap, model)
        ev = landing_evidence(R[top], t[top], source, target, sim, overlap, 0.1)
        full = model.ranks(V.features(total[top], ev[1], ev[0], ev[2], ev[3])) * np.exp(
            -model.free_space_strength * FreeSpace(*vis).violations(R[top], t[top]))
        assert best == top[int(full.argmax())] and fit == pytest.approx(ev[0][int(full.argmax())])
        plain = _verify(R, t, total, 0.1, cfg, (source, target), vis, {}, sim, overlap, None)
        same = _verify(R, t, total, 0.1, cfg, (source, target), vis, {}, sim, overlap,
                       _model(log_count=1.0, log_agreement=1.0, free_space=10.0))
        assert same[0] == plain[0]
        first = _verify(R, t, total, 0.1, cfg, (source, target), None, {}, sim, overlap, model)
        no_vis = _verify(R, t, total, 0.1, cfg, (source, target), None, {}, sim, overlap, None)
        assert first[0] == no_vis[0] and np.array_equal(first[3], no_vis[3])


def test_hypothesis_counts_are_the_estimators():
    """The count the fitting tool records is the one step 5 ranks by: a pose that explains a
    correspondence exactly counts its confidence, one at the inlier distance nothing."""
    src = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    w = np.array([0.5, 1.0, 0.25])
    tgt = src.copy()
    tgt[2, 0] += 0.05                                        # half the inlier distance off
    counts = hypothesis_counts(np.stack([np.eye(3)] * 2), np.array([[0, 0, 0], [0, 0, 5.0]]), src, tgt, w, 0.1)
    np.testing.assert_allclose(counts, [0.5 + 1.0 + 0.25 * 0.5, 0.0])


def test_the_engine_registers_with_the_learned_verification_and_names_a_bad_model(monkeypatch, tmp_path):
    """A held-out synthetic 7Scenes pair (as test_engine registers it), the exploring pass forced
    (engine.sure_fitness above 1, engine.sure_ambiguity -1): the shipped model ranks the
    hypotheses and the pose is right; engine.verification loads another model; a bad model file
    fails at start-up in one line naming the setting."""
    from cegc_ros import engine, paths
    from cegc_ros.config import EngineConfig
    from cegc_ros.data.protocols import make_pair
    from cegc_ros.metrics import rotation_error_deg
    pair = make_pair("7scenes", "test", 3)
    reg = engine.Registrar.from_checkpoint(None, device="cpu",
                                           engine=EngineConfig(verify_score="learned", sure_fitness=1.01,
                                                                sure_ambiguity=-1.0))
    calls = []

    class Counting(V.VerificationModel):
        def ranks(self, x: np.ndarray) -> np.ndarray:
            calls.append(len(x))
            return super().ranks(x)

    shipped = reg.verifier
    assert shipped is not None and "train" in shipped.meta["cache"]
    reg.verifier = Counting(shipped.weights, shipped.free_space, shipped.meta)
    res = reg.register(pair.source, pair.target)
    assert calls and all(n >= 1 for n in calls)
    assert res.valid and rotation_error_deg(pair.T_target_source[:3, :3], res.T_target_source[:3, :3]) < 2.0
    assert np.linalg.norm(res.T_target_source[:3, 3] - pair.T_target_source[:3, 3]) < 0.01
    # engine.verification: a model of one's own (here the shipped one with another free-space
    # weight) is the one used; update() keeps it (read-only, like the checkpoint)
    own = tmp_path / "own.json"
    V.VerificationModel(shipped.weights, 3.0, {"cache": "mine"}).save(own)
    mine = engine.Registrar.from_checkpoint(None, device="cpu", engine=EngineConfig(verification=str(own)),
                                            warm=False)
    assert mine.verifier is not None and mine.verifier.free_space == 3.0 and mine.verifier.meta == {"cache": "mine"}
    mine.update(engine=EngineConfig())
    assert mine.engine.verification == str(own)
    bad = tmp_path / "verification.json"
    bad.write_text('{"format": 1, "weights": {}, "free_space": 1}')
    with pytest.raises(engine.CheckpointError, match="verification model .*verification.json: weights must name"):
        engine.Registrar.from_checkpoint(None, device="cpu", engine=EngineConfig(verification=str(bad)), warm=False)
    weights = engine.default_weights()
    monkeypatch.setattr(paths, "shipped_weights", lambda name: bad)
    with pytest.raises(engine.CheckpointError,
                       match="engine.verify_score learned: verification model .*: weights must name") as err:
        engine.Registrar.from_checkpoint(weights, device="cpu", engine=EngineConfig(verify_score="learned"),
                                         warm=False)
    assert "\n" not in str(err.value)


def test_fit_verification_tool_records_evidence_and_fails_in_one_line(val_cache, tmp_path, capsys):
    """The tool's evidence of a registered pair: one row per verified hypothesis, its right
    flags those of the metric; bad arguments and an empty cache give one line and exit 1."""
    from cegc_ros.engine import Registrar
    from cegc_ros.metrics import within
    from cegc_ros.tools import fit_verification as FV
    pairs = list(FV.training_pairs(val_cache, 2, 0.5))
    assert 1 <= len(pairs) <= 2
    reg = Registrar.from_checkpoint(None, device="cpu")
    ev = FV.evidence(reg, pairs[0])
    res = reg.register(pairs[0].source, pairs[0].target)
    assert ev["x"].shape == (len(res.hypotheses), len(V.FEATURES)) == (len(ev["violations"]), len(V.FEATURES))
    assert np.isfinite(ev["x"]).all() and ((ev["violations"] >= 0) & (ev["violations"] <= 1)).all()
    assert list(ev["right"]) == [within(pairs[0].T_target_source, H) for H in res.hypotheses]
    assert FV.chosen_right(np.array([1.0, 2.0, 3.0, 0.5]), np.array([0, 0, 1, 1]),
                           np.array([False, True, False, True])) == 1
    assert FV.main([str(val_cache), "--low-share", "2", "--out", str(tmp_path / "m.json")]) == 1
    assert capsys.readouterr().err.strip() == "fit_verification: --pairs must be >= 1 and --low-share in [0, 1]"
    assert FV.main([str(tmp_path), "--out", str(tmp_path / "m.json")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("fit_verification: ") and len(err.splitlines()) == 1
    assert FV.main([str(val_cache), "--checkpoint", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "m.json")]) == 1
    err = capsys.readouterr().err.strip()
    assert "nope.pt" in err and len(err.splitlines()) == 1 and not (tmp_path / "m.json").exists()
