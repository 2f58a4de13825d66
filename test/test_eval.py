"""cegc-eval end to end: bags written here, baselines, reports, failures, and CEGC offline vs node."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from cegc_ros import baselines
from cegc_ros.data.bag import write_pairs
from cegc_ros.data.protocols import Pair, make_pairs
from cegc_ros.tools import evaluate as E

N_GOOD = 3


def _small_pairs(with_gt: bool = True) -> list[Pair]:
    """Three small 7Scenes-protocol pairs (384 points) and one unusable pair (8 source points)."""
    pairs = make_pairs("7scenes", "test", N_GOOD, seed=0, num_points=512)
    broken = Pair(pairs[0].source[:8].copy(), pairs[0].target.copy(), pairs[0].T_target_source,
                  {"note": "too few points"})
    pairs.append(broken)
    if not with_gt:
        for p in pairs:
            p.T_target_source = None
    return pairs


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("bags") / "small_7scenes"
    assert write_pairs(path, _small_pairs(), protocol="7scenes", seed=0) == N_GOOD + 1
    return path


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory) -> Path:
    """An untrained, small CEGC: enough to compare two ways of running the same weights."""
    import torch

    from cegc_ros.engine import save_checkpoint
    from cegc_ros.model import CEGC, ModelConfig

    torch.manual_seed(0)
    model = CEGC(ModelConfig(agnn_dims=(16, 16, 32), feat_dim=32, attn_layers=1, attn_heads=2,
                             cams_dim=8))
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    save_checkpoint(path, model, {"note": "untrained test model"})
    return path


@pytest.fixture(scope="module")
def small_params(tmp_path_factory) -> Path:
    """The node's parameter file with fewer network points (keeps the test cheap)."""
    import yaml

    doc = yaml.safe_load(E.default_params_file().read_text())
    block = next(iter(doc.values()))["ros__parameters"]
    block.update({"preprocess.num_points": 128, "engine.device": "cpu", "engine.threads": 1,
                  "markers.enabled": False, "output.publish_overlap": False})
    path = tmp_path_factory.mktemp("params") / "register_node.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_baselines_on_bag_write_parseable_reports_and_count_failures(bag, tmp_path):
    out = tmp_path / "eval"
    assert E.main([str(bag), "--methods", "icp,fgr,ransac,sc2pcr", "--out", str(out), "--no-progress"]) == 0

    doc = json.loads((out / "metrics.json").read_text())
    assert doc["n_pairs"] == N_GOOD + 1 and doc["has_ground_truth"] is True
    assert set(doc["methods"]) == {"icp", "fgr", "ransac", "sc2pcr"}
    for m, s in doc["methods"].items():
        # The 8-point pair raised in every baseline: a failure, scored, never skipped.
        assert s["n_exception"] == 1, m
        assert s["n_pairs"] == N_GOOD + 1
        assert s["recall"] <= N_GOOD / (N_GOOD + 1)
        assert s["error_r"] >= 0 and s["median_latency_ms"] > 0
    # FPFH methods solve these same-fragment crops (exact shared points).
    assert doc["methods"]["ransac"]["n_success"] == doc["methods"]["sc2pcr"]["n_success"] == N_GOOD

    with open(out / "pairs.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 4 * (N_GOOD + 1)
    failed = [r for r in rows if r["status"] == "exception"]
    assert len(failed) == 4 and all("points" in r["reason"] for r in failed)
    ok = [r for r in rows if r["method"] in ("ransac", "sc2pcr") and r["status"] == "ok"]
    assert len(ok) == 2 * N_GOOD and all(float(r["rot_error_deg"]) < 5 for r in ok)

    report = (out / "report.md").read_text()
    header = next(ln for ln in report.splitlines() if ln.startswith("| method |"))
    assert [c.strip() for c in header.strip("|").split("|")] == [
        "method", "RMSE(R)", "RMSE(t)", "MAE(R)", "MAE(t)", "Error(R)", "Error(t)", "recall",
        "median ms", "failures"]
    assert "**" in report and "1/4" in report and "ransac: Open3D RANSAC" in report
    assert "sc2pcr: SC2-PCR" in report and "load average" in report
    assert (out / "errors.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bag_without_ground_truth_lists_poses_and_fitness(tmp_path):
    path = tmp_path / "no_gt"
    write_pairs(path, _small_pairs(with_gt=False)[:2])
    out = tmp_path / "eval"
    assert E.main([str(path), "--methods", "fgr", "--out", str(out), "--no-progress"]) == 0
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["has_ground_truth"] is False
    assert "recall" not in doc["methods"]["fgr"] and doc["methods"]["fgr"]["mean_fitness"] > 0
    report = (out / "report.md").read_text()
    assert "No ground truth" in report and "## Poses (T_target_source)" in report
    assert report.count("| fgr | ok |") == 2
    assert not (out / "errors.png").exists()


def _fake_real_dir(root: Path) -> np.ndarray:
    """A real-pairs folder: one fragment (a noisy box corner) seen from two known poses."""
    rng = np.random.default_rng(3)
    pts = []
    for axis in range(3):   # three orthogonal 2 m walls with a few bumps: rich FPFH
        p = rng.uniform(0, 2, (1500, 3))
        p[:, axis] = 0.02 * np.sin(5 * p[:, (axis + 1) % 3])
        pts.append(p)
    pts.append(rng.normal([0.6, 0.6, 0.6], 0.15, (500, 3)))
    world = np.concatenate(pts)
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [20, -10, 35], degrees=True).as_matrix()
    T[:3, 3] = [0.3, -0.2, 0.1]
    source = world
    target = world @ T[:3, :3].T + T[:3, 3]
    (root / "fragments" / "scene").mkdir(parents=True)
    (root / "gt").mkdir()
    np.save(root / "fragments" / "scene" / "a.npy", source)
    np.save(root / "fragments" / "scene" / "b.npy", target)
    np.savetxt(root / "gt" / "p0.txt", T)
    (root / "pairs.tsv").write_text("pair_id\tscene\tsource\ttarget\n" "p0\tscene\ta\tb\n")
    return T


def test_real_dir_pairs_and_7scenes_protocol(tmp_path):
    T = _fake_real_dir(tmp_path)
    pairs = E.real_pairs(tmp_path)
    assert [p.pair_id for p in pairs] == ["p0"]
    np.testing.assert_allclose(pairs[0].T_gt, T)
    ev = E.evaluate(pairs, ["ransac", "ransac+icp"], thresholds=E.metrics.REAL_FRAGMENT_RECALL,
                    progress=False)
    assert ev.summaries["ransac"]["recall"] == ev.summaries["ransac+icp"]["recall"] == 1.0
    assert ev.summaries["ransac"]["error_r"] < 2.0
    # The engine's ICP after RANSAC lands on the exact pose (the two clouds share every point).
    assert ev.summaries["ransac+icp"]["error_r"] < 0.05 < ev.summaries["ransac"]["error_r"]

    proxy = E.real_7scenes_pairs(tmp_path, num_pairs=3, num_points=256, seed=1)
    again = E.real_7scenes_pairs(tmp_path, num_pairs=3, num_points=256, seed=1)
    assert [len(p.source) for p in proxy] == [192] * 3
    for a, b in zip(proxy, again):
        np.testing.assert_array_equal(a.source, b.source)
        np.testing.assert_array_equal(a.T_gt, b.T_gt)
        assert np.ptp(np.concatenate([a.source, a.target]), axis=0).max() < 3.0  # unit-box scale
    thin = E.real_7scenes_pairs(tmp_path, num_pairs=1, num_points=256, seed=1, subsample=100)
    assert len(thin[0].source) == len(thin[0].target) == 100

    # Noise: the same draw, each cloud moved independently by sigma (clipped at 5 sigma).
    noisy = E.real_7scenes_pairs(tmp_path, num_pairs=3, num_points=256, seed=1, noise_sigma=0.01)
    for a, b in zip(proxy, noisy):
        np.testing.assert_array_equal(a.T_gt, b.T_gt)
        d = b.source - a.source
        assert 0.008 < d.std() < 0.012 and np.abs(d).max() <= 0.05 + 1e-6
        assert not np.allclose(b.target - a.target, d[: len(a.target)])   # independent per cloud


def test_real_dir_other_layouts_scans_and_a_single_pair(tmp_path):
    T = _fake_real_dir(tmp_path / "frag")
    a = np.load(tmp_path / "frag" / "fragments" / "scene" / "a.npy")
    b = np.load(tmp_path / "frag" / "fragments" / "scene" / "b.npy")
    scans = tmp_path / "scans_dir"                     # range-scan layout (Stanford bunny)
    (scans / "scans").mkdir(parents=True)
    (scans / "gt").mkdir()
    np.save(scans / "scans" / "s0.npy", a)
    np.save(scans / "scans" / "s1.npy", b)
    np.savetxt(scans / "gt" / "q0.txt", T)
    (scans / "pairs.tsv").write_text("pair_id\tsource\ttarget\nq0\ts0\ts1\n")
    (pair,) = E.real_pairs(scans)
    assert pair.pair_id == "q0" and len(pair.source) == len(a)
    np.testing.assert_allclose(pair.T_gt, T)
    assert [f.name for f in E.real_fragment_files(scans)] == ["s0.npy", "s1.npy"]

    single = tmp_path / "lidar"                        # one pair (LiDAR folder)
    single.mkdir()
    np.save(single / "source.npy", a)
    np.save(single / "target.npy", b)
    np.savetxt(single / "T_target_source.txt", T)
    (pair,) = E.real_pairs(single)
    assert pair.pair_id == "lidar"
    np.testing.assert_allclose(pair.target, b.astype(np.float32))
    np.savetxt(single / "T_target_source.txt", np.eye(3))
    with pytest.raises(E.EvalError, match="expected a 4x4 matrix"):
        E.real_pairs(single)


def test_cli_fails_with_one_line_reasons(bag, tmp_path, capsys):
    assert E.main([str(bag), "--methods", "icp,nope", "--out", str(tmp_path)]) == 2
    assert "unknown method(s) nope" in capsys.readouterr().err
    assert E.main(["--real-dir", str(tmp_path / "missing"), "--methods", "icp",
                   "--out", str(tmp_path)]) == 2
    assert "pairs.tsv not found" in capsys.readouterr().err
    assert E.main([str(tmp_path / "no_such_bag"), "--methods", "icp", "--out", str(tmp_path)]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert E.main([str(bag), "--methods", "cegc", "--checkpoint", str(tmp_path / "none.pt"),
                   "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "none.pt: file not found" in err and len(err.strip().splitlines()) == 1


def test_baseline_rejects_tiny_clouds_with_value_error():
    with pytest.raises(ValueError, match="at least 16"):
        baselines.register("icp", np.zeros((5, 3)), np.random.default_rng(0).random((100, 3)))
    with pytest.raises(baselines.BaselineError):
        baselines.register("nope", np.zeros((50, 3)), np.zeros((50, 3)))


def test_cegc_offline_and_through_node_give_the_same_numbers(bag, tiny_checkpoint, small_params,
                                                             tmp_path):
    common = ["--methods", "cegc", "--checkpoint", str(tiny_checkpoint), "--params",
              str(small_params), "--no-progress"]
    assert E.main([str(bag), *common, "--out", str(tmp_path / "offline")]) == 0
    assert E.main([str(bag), *common, "--through-node", "--out", str(tmp_path / "node")]) == 0

    docs = {k: json.loads((tmp_path / k / "metrics.json").read_text()) for k in ("offline", "node")}
    assert "register_node" in docs["node"]["settings"]["cegc"]
    assert "offline" in docs["offline"]["settings"]["cegc"]
    a, b = docs["offline"]["methods"]["cegc"], docs["node"]["methods"]["cegc"]
    assert a["n_pairs"] == b["n_pairs"] == N_GOOD + 1
    for key in ("rmse_r", "rmse_t", "mae_r", "mae_t", "error_r", "error_t"):
        assert b[key] == pytest.approx(a[key], abs=1e-4), key   # float32 pose message vs float64
    for key in ("recall", "n_success", "n_exception", "n_invalid"):
        assert b[key] == a[key], key
    assert a["n_exception"] == 1   # the 8-point pair: the engine raises, the node rejects it

    rows = {}
    for k in ("offline", "node"):
        with open(tmp_path / k / "pairs.csv") as fh:
            rows[k] = list(csv.DictReader(fh))
    assert [r["status"] for r in rows["node"]] == [r["status"] for r in rows["offline"]] \
        == ["ok"] * N_GOOD + ["exception"]
    for ra, rb in zip(rows["offline"][:N_GOOD], rows["node"][:N_GOOD]):
        assert float(rb["rot_error_deg"]) == pytest.approx(float(ra["rot_error_deg"]), abs=1e-4)
        assert float(rb["trans_error"]) == pytest.approx(float(ra["trans_error"]), abs=1e-5)
        assert float(rb["latency_ms"]) > 0
        # the engine's fitness and ambiguity: offline from its result, through the node from
        # its ~/quality message (4 decimals)
        assert 0.0 <= float(ra["ambiguity"]) <= 1.0 and 0.0 < float(ra["fitness"]) <= 1.0
        for key in ("fitness", "ambiguity"):
            assert float(rb[key]) == pytest.approx(float(ra[key]), abs=2e-4), key
    assert rows["node"][-1]["reason"] == "register_node rejected the pair (too_few_points)"


def test_demo_runs_baselines_on_its_cached_bag_and_fails_in_one_line(tmp_path, capsys):
    from cegc_ros.tools import demo

    args = ["--pairs", "2", "--cache", str(tmp_path), "--methods", "fgr", "--no-progress"]
    assert demo.main(args) == 0
    out = capsys.readouterr().out
    assert "fgr" in out and "Error(R) < 5 deg" in out   # the table's format: test_demo_output.py
    (bag,) = tmp_path.glob("7scenes_test_seed0_2pairs_*")
    assert sorted(p.name for p in bag.iterdir()) == [f"{bag.name}.db3", "metadata.yaml"]   # no .partial
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    stamp = (bag / "metadata.yaml").stat().st_mtime_ns
    assert demo.main(args) == 0                      # the cached bag is reused, not rewritten
    assert (bag / "metadata.yaml").stat().st_mtime_ns == stamp
    assert json.loads((tmp_path / "report" / "metrics.json").read_text())["n_pairs"] == 2

    capsys.readouterr()
    assert demo.main(["--cache", str(tmp_path), "--checkpoint", str(tmp_path / "none.pt"),
                      "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("cegc-demo: error:") and "none.pt" in err and "\n" not in err


def test_suite_runs_every_documented_evaluation_into_one_summary(tmp_path, capsys):
    real = tmp_path / "real" / "sun3d"
    T = _fake_real_dir(real)
    lidar = tmp_path / "real" / "lidar"                # a sibling one-pair folder; no bunny/
    lidar.mkdir()
    np.save(lidar / "source.npy", np.load(real / "fragments" / "scene" / "a.npy"))
    np.save(lidar / "target.npy", np.load(real / "fragments" / "scene" / "b.npy"))
    np.savetxt(lidar / "T_target_source.txt", T)
    out = tmp_path / "suite"
    assert E.main(["--suite", "--suite-pairs", "1", "--suite-fragment-pairs", "1", "--num-pairs",
                   "1", "--suite-hard-pairs", "1", "--num-points", "512", "--real-dir", str(real), "--methods", "icp",
                   "--cache", str(tmp_path / "cache"), "--out", str(out), "--no-progress"]) == 0
    parts = ("7scenes_test", "fragments_test", "real_pairs", "real_7scenes", "real_7scenes_resample",
             "real_7scenes_noise", "lidar")
    doc = json.loads((out / "metrics.json").read_text())
    assert list(doc) == list(parts)
    assert doc["fragments_test"]["recall"] == "Error(R) < 15 deg and Error(t) < 0.3 m"
    assert doc["7scenes_test"]["recall"] == "Error(R) < 5 deg"
    summary = (out / "summary.md").read_text()
    for name in parts:
        assert f"## {name}:" in summary and (out / name / "report.md").is_file()
    assert summary.count("| icp |") == len(parts)
    assert "Skipped: bunny:" in summary and "Skipped: lidar" not in summary
    assert "Gaussian noise sigma 0.01" in doc["real_7scenes_noise"]["source"]

    # --parts picks a subset; an unknown part is a one-line usage error.
    assert E.main(["--suite", "--parts", "lidar,bunny", "--real-dir", str(real), "--methods", "icp",
                   "--out", str(tmp_path / "part"), "--no-progress"]) == 0
    assert list(json.loads((tmp_path / "part" / "metrics.json").read_text())) == ["lidar"]
    assert "Skipped: bunny:" in (tmp_path / "part" / "summary.md").read_text()
    capsys.readouterr()
    assert E.main(["--suite", "--parts", "moon", "--methods", "icp", "--out", str(tmp_path / "x")]) == 2
    assert "unknown suite part(s) moon" in capsys.readouterr().err


def test_ablation_table_covers_the_chosen_sets(tmp_path, tiny_checkpoint, small_params, capsys):
    from cegc_ros.tools import ablation

    _fake_real_dir(tmp_path / "real")
    assert ablation.main(["--checkpoint", f"tiny={tiny_checkpoint}", "--pairs", "1", "--rows",
                          "cegc-uniform,cegc-svd", "--params", str(small_params),
                          "--sets", "real,real_noise", "--real-dir", str(tmp_path / "real")]) == 0
    out = capsys.readouterr().out.splitlines()
    rows = [json.loads(line) for line in out[:2]]
    assert [r["row"] for r in rows] == ["cegc-uniform", "cegc-svd"]
    assert rows[0]["model"] == "tiny" and set(rows[0]) == {"model", "row", "real", "real_noise"}
    assert 0.0 <= rows[0]["real_noise"]["recall5"] <= 1.0 and rows[0]["real_noise"]["mean"] >= 0.0
    assert out[-1].startswith("| tiny | cegc-svd |")
    assert ablation.main(["--checkpoint", f"tiny={tiny_checkpoint}", "--sets", "real,bogus"]) == 2
    assert "unknown set(s) bogus" in capsys.readouterr().err
    assert ablation.main(["--checkpoint", f"tiny={tiny_checkpoint}", "--rows", "ransac"]) == 2
    assert "CEGC rows only" in capsys.readouterr().err


def test_method_groups_and_row_overrides_are_node_parameters():
    assert E.parse_methods("default") == ["cegc+icp", "icp", "fgr", "ransac", "ransac+icp", "sc2pcr",
                                          "sc2pcr+icp"]
    assert E.parse_methods("ablation,sc2pcr,cegc-svd")[-1] == "sc2pcr"
    assert len(E.parse_methods("all")) == len(E.ALL_METHODS) == 13
    with pytest.raises(E.EvalError, match="unknown method.*net\\+icp"):
        E.parse_methods("cegc+icp,net+icp")
    from cegc_ros.evaluation.methods import CEGC_ROWS, node_arguments, row_configs

    pre, eng = E.engine_configs()
    for row, overrides in CEGC_ROWS.items():
        _, row_eng = row_configs(row, pre, eng)
        changed = {f"engine.{k}" for k, v in vars(row_eng).items() if v != getattr(eng, k)}
        assert changed == set(overrides), row       # exactly the row's switches, all effective
    assert node_arguments("cegc-paper") == ["-p", "engine.candidates:=all", "-p", "engine.estimator:=svd"]
    assert node_arguments("cegc+icp") == []


def test_ablation_rows_change_what_the_engine_does(tmp_path, tiny_checkpoint, small_params):
    """Each row is the same registrar under the row's settings, and the settings take effect."""
    _fake_real_dir(tmp_path)
    pair = E.real_pairs(tmp_path)[0]
    src, tgt = pair.source, pair.target
    rows = ["cegc+icp", "cegc", "cegc-uniform", "cegc-learned-cand", "cegc-fpfh-cand", "cegc-svd",
            "cegc-paper"]
    runners = E.make_runners(rows, checkpoint=str(tiny_checkpoint), params_file=small_params)
    assert len({id(r.registrar) for r in runners.values()}) == 1          # one copy of the weights
    results = {}
    for name, run in runners.items():
        T, _, _, _ = run(src, tgt)
        results[name] = run.last
        assert run.registrar.engine == run.engine                      # what ran is the row's config
        assert T.shape == (4, 4) and np.isfinite(T).all()
    assert runners["cegc-uniform"].engine.confidence == "uniform"
    assert runners["cegc-uniform"].engine.candidates == "fpfh"
    assert runners["cegc-uniform"].engine.verify_score == "fitness"         # no learned features either
    assert np.all(results["cegc-uniform"].weights == 1.0)
    assert not np.all(results["cegc+icp"].weights == 1.0)
    assert results["cegc"].refined == "none" and results["cegc+icp"].refined == "icp"
    assert "refine" not in results["cegc"].timings and "refine" in results["cegc+icp"].timings
    # The paper's path keeps one partner per network source point (argmax per row): no source
    # index repeats; the candidate paths give each point several partners.
    paper = results["cegc-paper"].correspondences
    assert len(np.unique(paper[:, 0])) == len(paper)
    both = results["cegc+icp"].correspondences
    assert len(np.unique(both[:, 0])) < len(both)
    # Another estimator on the same matches: another pose.
    assert results["cegc-svd"].T_target_source.tolist() != results["cegc+icp"].T_target_source.tolist()


@pytest.mark.parametrize("protocol, definition", [
    ("views", "Error(R) < 15 deg and Error(t) < 0.3 m"),
    ("fragments", "Error(R) < 15 deg and Error(t) < 0.3 m"),
    ("7scenes", "Error(R) < 5 deg")])
def test_bag_recall_follows_the_protocol(protocol, definition, tmp_path):
    """Different scans in metres (fragments, different views) are scored at 15 deg / 0.3 m."""
    path = tmp_path / "bag"
    write_pairs(path, _small_pairs()[:2], protocol=protocol, seed=0)
    out = tmp_path / "eval"
    assert E.main([str(path), "--methods", "sc2pcr", "--out", str(out), "--no-progress"]) == 0
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["recall_definition"] == definition


def test_the_peer_settings_reach_the_baselines():
    plain = E._baseline_config(E.build_parser().parse_args(["bag", "--out", "o"]))
    turned = E._baseline_config(E.build_parser().parse_args(
        ["bag", "--out", "o", "--sensor-normals", "--mutual-filter", "--voxel-ratio", "0.03"]))
    assert not plain.sensor_normals and not plain.ransac_mutual_filter
    assert turned.sensor_normals and turned.ransac_mutual_filter and turned.voxel_ratio == 0.03
