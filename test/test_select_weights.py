"""tools/select_weights: engine recall of checkpoints on a validation pair cache."""

from __future__ import annotations

import pytest

from cegc_ros.data import pair_cache as PC
from cegc_ros.data import splits, views
from cegc_ros.tools import select_weights


def test_recall_line_per_checkpoint_and_one_line_errors(val_cache, capsys):
    from cegc_ros.engine import default_weights
    n_views = len(PC.PairCache(val_cache, kinds=("views",), sensors=("kinect",)))
    assert n_views == 2
    assert select_weights.main([str(val_cache), str(default_weights()), "--set", "engine.candidates=fpfh"]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"{default_weights()}: recall ") and f"on {n_views} pairs" in line
    recall = float(line.split("recall ")[1].split()[0])
    assert 0.0 <= recall <= 1.0
    assert select_weights.main([str(val_cache), "/nope.pt"]) == 1
    assert "nope.pt" in capsys.readouterr().err
    assert select_weights.main([str(val_cache), str(default_weights()), "--set", "engine.bogus=1"]) == 1
    assert "--set 'engine.bogus=1'" in capsys.readouterr().err
    assert select_weights.main([str(val_cache), str(default_weights()), "--peers", "sc2pcr+icp"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and lines[1].startswith("sc2pcr+icp: recall ") and f"on {n_views} pairs" in lines[1]
    assert lines[2].startswith(f"  against {default_weights()}: won ")          # on the same pairs
    assert select_weights.main([str(val_cache), str(default_weights()), "--peers", "magic"]) == 1
    assert "unknown method 'magic'" in capsys.readouterr().err


def test_a_checkpoint_without_its_onnx_export_is_named_on_stderr(val_cache, tmp_path, capsys):
    """Weights copied without their export run under torch: one stderr line says so and how to
    export; the shipped weights (their export beside them) run as shipped, silently."""
    import shutil
    from cegc_ros.engine import default_weights
    copy = tmp_path / "candidate.pt"
    shutil.copy(default_weights(), copy)
    assert select_weights.main([str(val_cache), str(default_weights()), str(copy)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"select_weights: {copy}: the network runs under torch")
    assert err[0].endswith(f"python -m cegc_ros.tools.export_onnx {copy}") and "no ONNX export" in err[0]


def test_sensor_picks_the_lidar_pairs(tmp_path, capsys):
    """--sensor lidar scores a LiDAR cache's pairs; the Kinect default finds none there (one line)."""
    from cegc_ros.engine import default_weights
    cfg = views.ViewConfig(fragments=3, pairs=2, copy_pairs=0, max_points=2000)
    PC.write_shard(tmp_path / PC.shard_name(0, 1), [views.make_room_pairs(splits.room_seed("val", 3), "lidar", cfg)],
                   {"split": "val"})
    n = len(PC.PairCache(tmp_path, kinds=("views",), sensors=("lidar",)))
    assert n >= 1
    assert select_weights.main([str(tmp_path), str(default_weights()), "--sensor", "lidar"]) == 0
    assert f"on {n} pairs" in capsys.readouterr().out
    assert select_weights.main([str(tmp_path), str(default_weights())]) == 1
    assert "no kinect different-view pairs" in capsys.readouterr().err


def test_seeds_pool_the_recall_and_the_second_checkpoint_is_held_against_the_first(val_cache, capsys):
    import numpy as np
    from cegc_ros.engine import default_weights
    w = str(default_weights())
    assert select_weights.main([val_cache.as_posix(), w, w, "--seeds", "0,1", "--set", "engine.candidates=fpfh"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and "on 2 pairs x 2 seeds" in lines[0] and "of 2," in lines[0]   # 1 low pair x 2
    assert lines[1].split(", median")[0] == lines[0].split(", median")[0]
    assert lines[2] == f"  against {w}: won 0, lost 0 (sign test p = 1.000)"   # the same weights
    ok = np.array([True] * 17 + [False] * 4 + [True] * 5)
    ref = np.array([False] * 17 + [True] * 4 + [True] * 5)
    won, lost, p = select_weights.sign_test(ok, ref)
    assert (won, lost) == (17, 4) and p == pytest.approx(15094 / 2 ** 21)    # 2 x P(X <= 4), X ~ B(21, 1/2)
    assert select_weights.sign_test(ref, ref)[2] == 1.0


def test_evaluate_counts_successes_by_overlap():
    import numpy as np
    from types import SimpleNamespace

    class Exact:
        def register(self, s, t):
            return SimpleNamespace(valid=True, T_target_source=np.eye(4), timings={"total": 0.5})
    T_off = np.eye(4)
    T_off[0, 3] = 1.0
    pairs = [SimpleNamespace(source=None, target=None, T_target_source=np.eye(4), info={"overlap": 0.2}),
             SimpleNamespace(source=None, target=None, T_target_source=T_off, info={"overlap": 0.5}),
             SimpleNamespace(source=None, target=None, T_target_source=np.eye(4), info={"overlap": 0.6})]
    r = select_weights.evaluate(Exact().register, pairs)
    assert r["recall"] == pytest.approx(2 / 3) and r["recall_low"] == 1.0 and r["recall_high"] == 0.5
    assert r["n_low"] == 1 and r["median_s"] == 0.5
    assert r["verification_misses"] == -1                               # no hypotheses reported

    class Ranked:
        """Always the identity, with the verified poses [identity, shifted by 1 m in x]."""
        def register(self, s, t):
            return SimpleNamespace(valid=True, T_target_source=np.eye(4), timings={"total": 0.5},
                                   hypotheses=np.stack([np.eye(4), T_off]))
    rows: list = []
    r = select_weights.evaluate(Ranked().register, pairs, rows)
    # pair 2 (truth T_off) is wrong, but T_off was among the verified: one verification miss
    assert r["verification_misses"] == 1
    assert [row["first_right_hypothesis"] for row in rows] == [0, 1, 0]
    assert [row["hypotheses"] for row in rows] == [2, 2, 2]


def test_ranking_counts_the_true_correspondences_and_how_the_confidences_order_them():
    """Six correspondences, three true under T (a 1 m shift): confidences that put the true ones
    first give AUC 1, the reverse 0; the top-k count sees the order; a peer's result (no
    correspondences) gives nothing."""
    import numpy as np
    from types import SimpleNamespace
    T = np.eye(4)
    T[0, 3] = 1.0
    src = np.arange(18, dtype=np.float32).reshape(6, 3)
    tgt = src.copy()
    tgt[:3, 0] += 1.0                                         # rows 0-2 true under T
    tgt[3:] += 5.0                                            # rows 3-5 false
    corr = np.stack([np.arange(6), np.arange(6)], axis=1)

    def res(w):
        return SimpleNamespace(correspondences=corr, source_points=src, target_points=tgt,
                               weights=np.array(w, np.float32), inlier_distance=0.1)
    good = select_weights.ranking(res([0.9, 0.8, 0.7, 0.3, 0.2, 0.1]), T, top=3)
    assert good == {"true_correspondences": 3, "true_in_top3": 3, "ranking_auc": 1.0}
    bad = select_weights.ranking(res([0.1, 0.2, 0.3, 0.7, 0.8, 0.9]), T, top=3)
    assert bad["true_in_top3"] == 0 and bad["ranking_auc"] == 0.0
    ties = select_weights.ranking(res([0.5] * 6), T, top=3)
    assert ties["ranking_auc"] == 0.5
    assert select_weights.ranking(SimpleNamespace(), T) == {}


def test_overlap_ranking_measures_how_hoce_finds_the_overlap():
    """Ten source points, four of them over the target under T: confidences that put those four
    first give AUC 1 and keep all four in the 40% most confident; reversed, AUC 0 and none kept.
    The target side is measured the same way through T's inverse."""
    import numpy as np
    from types import SimpleNamespace
    T = np.eye(4)
    T[1, 3] = -2.0
    src = np.c_[np.arange(10.0), np.zeros(10), np.zeros(10)].astype(np.float32)
    target = np.c_[np.arange(4.0), np.full(4, -2.0), np.zeros(4)]      # under src[:4] moved by T
    source = src.astype(np.float64)

    def res(w_src):
        return SimpleNamespace(source_points=src, target_points=target.astype(np.float32),
                               source_overlap=np.array(w_src, np.float32),
                               target_overlap=np.full(4, 0.5, np.float32), inlier_distance=0.1)
    good = select_weights.overlap_ranking(res([0.9] * 4 + [0.1] * 6), source, target, T)
    assert good["source_overlap_share"] == 0.4 and good["source_overlap_auc"] == 1.0
    assert good["source_overlap_kept"] == 1.0
    # every target point lies over the source: one kind only, so no AUC; the 40% most confident hold 2 of 4
    assert good["target_overlap_share"] == 1.0 and np.isnan(good["target_overlap_auc"])
    assert good["target_overlap_kept"] == 0.5
    bad = select_weights.overlap_ranking(res([0.1] * 4 + [0.9] * 6), source, target, T)
    assert bad["source_overlap_auc"] == 0.0 and bad["source_overlap_kept"] == 0.0
    assert select_weights.overlap_ranking(SimpleNamespace(), source, target, T) == {}


def test_pose_evidence_prefers_the_pose_that_explains_the_clouds():
    """A room corner seen from the origin (two walls and a floor): the ground truth lays the
    source on the target (nearly every point within the ICP distance, nothing in free space);
    an answer 0.5 m off puts the walls in front of what the target's sensor saw and scores far
    lower; the ground truth itself as the answer scores the same as the truth."""
    import numpy as np

    from cegc_ros.config import EngineConfig
    rng = np.random.default_rng(0)
    n = 3000
    u, v = rng.uniform(-1.5, 1.5, (2, n))
    corner = np.concatenate([np.c_[np.full(n, 3.0), u, v], np.c_[u, np.full(n, 3.0), v],
                             np.c_[u + 1.5, v + 1.5, np.full(n, -1.2)]])
    source, target = corner[::2], corner[1::2]
    T = np.eye(4)
    off = np.eye(4)
    off[:3, 3] = [-0.5, -0.5, 0.0]
    eng = EngineConfig()
    right = select_weights.pose_evidence(T, source, target, T, eng)
    wrong = select_weights.pose_evidence(off, source, target, T, eng)
    assert right["gt_evidence"] > 0.9 and right["result_evidence"] == right["gt_evidence"]
    assert wrong["gt_evidence"] == right["gt_evidence"]
    assert wrong["result_evidence"] < 0.5 * wrong["gt_evidence"]


def test_dump_writes_one_row_per_pair_with_correctness_and_fitness(val_cache, tmp_path, capsys):
    import csv

    from cegc_ros.engine import default_weights
    out = tmp_path / "rows.csv"
    assert select_weights.main([str(val_cache), str(default_weights()), "--dump", str(out)]) == 0
    recall = float(capsys.readouterr().out.split("recall ")[1].split()[0])
    rows = list(csv.DictReader(open(out)))
    assert len(rows) == 2 and {r["run"] for r in rows} == {str(default_weights())}
    assert all(0.0 <= float(r["fitness"]) <= 1.0 and float(r["total_s"]) > 0 for r in rows)
    # the learned ranking of each pair's correspondences against the ground truth
    assert all(int(r["true_in_top100"]) <= min(100, int(r["true_correspondences"])) for r in rows)
    assert all(r["ranking_auc"] == "nan" or 0.0 <= float(r["ranking_auc"]) <= 1.0 for r in rows)
    # and how HOCE's overlap confidences find each cloud's overlap
    assert all(0.0 < float(r["source_overlap_share"]) <= 1.0 and 0.0 <= float(r["target_overlap_kept"]) <= 1.0
               for r in rows)
    # and what the network predicts of it (HOCE's confidences averaged over each cloud), whether
    # the estimator explored and how many draws the pair took (one: the second draw is off)
    from cegc_ros.engine import Registrar
    registrar = Registrar.from_checkpoint(default_weights(), device="cpu")
    pairs, _ = select_weights.validation_pairs(val_cache, 40, "kinect")
    for r, p in zip(rows, pairs):
        res = registrar.register(p.source, p.target)
        for side, conf in (("source", res.source_overlap), ("target", res.target_overlap)):
            assert float(r[f"{side}_predicted_overlap"]) == pytest.approx(float(conf.mean()), abs=1e-6)
        assert r["explored"] == str(res.explored) and r["draws"] == "1"
    # and the geometric evidence of the truth and of the answer: the truth's is pose_evidence's
    # for that pair (it does not depend on the answer); how an answer's compares with it is
    # test_pose_evidence_prefers_the_pose_that_explains_the_clouds' (on these 2000-point pairs
    # a right answer may be 1 deg / 10 cm off, as on the Xeon with AVX-512, and score less)
    from cegc_ros.config import EngineConfig
    assert all(0.0 < float(r["gt_evidence"]) <= 1.0 and 0.0 <= float(r["result_evidence"]) <= 1.0 for r in rows)
    for r, p in zip(rows, pairs):
        own = select_weights.pose_evidence(p.T_target_source, p.source, p.target, p.T_target_source, EngineConfig())
        assert float(r["gt_evidence"]) == pytest.approx(own["gt_evidence"], rel=1e-9)
        assert float(r["overlap"]) == pytest.approx(p.info["overlap"])
    assert recall == sum(r["correct"] == "True" and r["valid"] == "True" for r in rows) / 2
    # correct means within 15 deg and 0.3 m, and the dumped errors say so
    assert all((r["correct"] == "True") == (float(r["rotation_error_deg"]) < 15.0
                                            and float(r["translation_error_m"]) < 0.3) for r in rows)


def test_points_thins_every_cloud_to_a_seeded_subset(val_cache, tmp_path, capsys):
    import numpy as np

    from cegc_ros.data.corruption import thinned
    from cegc_ros.engine import default_weights
    pairs = [PC.PairCache(val_cache, kinds=("views",), sensors=("kinect",))[i] for i in range(2)]
    a, b = thinned(pairs, 700, [0, 1]), thinned(pairs, 700, [0, 1])
    for p, q, r in zip(pairs, a, b):
        assert len(q.source) == len(q.target) == 700 and np.array_equal(q.source, r.source)   # seeded
        assert np.isin(q.source.view([("", q.source.dtype)] * 3), p.source.view([("", p.source.dtype)] * 3)).all()
        assert (q.T_target_source == p.T_target_source).all()
    assert not np.array_equal(a[0].source, thinned(pairs, 700, [5, 6])[0].source)   # keyed by the pair
    assert len(thinned(pairs, 10**6, [0, 1])[0].source) == len(pairs[0].source)     # never grown
    out = tmp_path / "rows.csv"
    assert select_weights.main([str(val_cache), str(default_weights()), "--points", "700", "--dump", str(out)]) == 0
    assert "on 2 pairs" in capsys.readouterr().out
    import csv
    assert len(list(csv.DictReader(open(out)))) == 2
    with pytest.raises(ValueError, match="points must be >= 1"):
        thinned(pairs, 0, [0, 1])


def test_max_overlap_keeps_only_the_pairs_under_it(val_cache, capsys):
    """validation_pairs(max_overlap=X): the pairs under X overlap, spread evenly among them;
    --max-overlap below every pair's overlap is a one-line error naming it."""
    cache = PC.PairCache(val_cache, kinds=("views",), sensors=("kinect",))
    ov = cache.overlaps
    assert len(ov) == 2 and ov.min() < ov.max()
    cut = float(ov.mean())                               # between the two pairs
    pairs, idx = select_weights.validation_pairs(val_cache, 40, "kinect", max_overlap=cut)
    assert list(idx) == [int(ov.argmin())] and pairs[0].info["overlap"] == pytest.approx(ov.min())
    pairs, idx = select_weights.validation_pairs(val_cache, 40, "kinect")
    assert list(idx) == [0, 1]
    assert select_weights.main([str(val_cache), "unused.pt", "--max-overlap", f"{ov.min() / 2:g}"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"no kinect different-view pairs under {ov.min() / 2:g} overlap" in err[0]
