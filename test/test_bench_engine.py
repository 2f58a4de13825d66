"""bench_engine: the pairs it generates, one worker's numbers, and its allocator switch."""

from __future__ import annotations

import numpy as np

from cegc_ros.tools import bench_engine as B


def test_resize_subsamples_or_densifies_around_the_original_points():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 1, (1000, 3)).astype(np.float32)
    small = B._resize(pts, 300, np.random.default_rng(1))
    assert small.shape == (300, 3) and len(np.unique(small, axis=0)) == 300
    assert np.isin(small.view("V12"), pts.view("V12")).all()              # a subset
    big = B._resize(pts, 5000, np.random.default_rng(1))
    assert big.shape == (5000, 3)
    np.testing.assert_array_equal(big[:1000], pts)                        # every original kept
    from scipy.spatial import cKDTree
    d, _ = cKDTree(pts).query(big[1000:])
    assert 0.5 * B.JITTER < np.median(d) < 3 * B.JITTER                    # jitter about the points


def test_worker_reports_stage_percentiles_and_memory(tmp_path):
    files = B.make_pairs(1500, 1, tmp_path)
    with np.load(files[0]) as z:
        assert z["source"].shape == (1536, 3) and z["T"].shape == (4, 4)
    assert B.make_pairs(1500, 1, tmp_path) == files                       # cached, not regenerated
    r = B.worker("sc2pcr", [str(f) for f in files], repeats=2)
    assert r["runs"] == 2 and r["points"] == 1536
    for key in ("features", "registration", "total", "wall", "cpu"):
        assert 0 < r["stages"][key]["median_ms"] <= r["stages"][key]["p90_ms"]
    assert r["peak_rss_mb"] >= r["rss_after_loading_mb"] > 10
    assert r["median_rotation_error_deg"] < 5.0                           # same-fragment crops
    assert r["startup_s"] > 0 and r["first_call_ms"] > 0 and r["first_call_ratio"] > 0
    r.update(allocator="system")
    head, _, row = B.table([r]).splitlines()
    assert row.startswith("| 1,536 | system | sc2pcr |") and row.count("|") == head.count("|")
    assert f"{r['first_call_ms']:.0f} ({r['first_call_ratio']:.2f}x)" in row


def test_allocator_environments_and_bad_arguments(capsys, monkeypatch):
    monkeypatch.setenv("LD_PRELOAD", "/some/lib.so")
    env = B._environment("system")
    assert "LD_PRELOAD" not in env and env["CEGC_NO_JEMALLOC"] == "1"
    monkeypatch.setattr("cegc_ros.allocator.jemalloc_path", lambda: None)
    try:
        B._environment("jemalloc")
    except B.BenchError as err:
        assert "jemalloc is not installed" in str(err)
    else:
        raise AssertionError("jemalloc without the library must fail")
    assert B.main(["--methods", "ransac-2threads,nope"]) == 2
    assert "unknown value(s) nope" in capsys.readouterr().err


def test_ratios_compare_the_engine_with_each_peer_of_the_same_size():
    def row(points, method, ms):
        return {"points": points, "allocator": "jemalloc", "method": method,
                "stages": {"total": {"median_ms": ms, "p90_ms": ms}}}
    text = B.ratios([row(1500, "cegc", 120.0), row(1500, "ransac", 60.0), row(1500, "sc2pcr+icp", 240.0),
                     row(20000, "cegc", 250.0), row(20000, "ransac", 1000.0)])
    lines = text.splitlines()
    assert lines[0] == "1,500 points (jemalloc): cegc / ransac 2.00x, sc2pcr+icp 0.50x"
    assert lines[1] == "20,000 points (jemalloc): cegc / ransac 0.25x"


def test_the_machine_line_names_the_cpu_and_its_vector_unit(monkeypatch):
    import builtins
    import io

    from cegc_ros.evaluation import report
    real_open = builtins.open

    def fake(flags):
        text = f"processor\t: 0\nmodel name\t: AMD EPYC 9R45\nflags\t\t: fpu sse2 {flags}\n"
        return lambda path, *a, **k: io.StringIO(text) if path == "/proc/cpuinfo" else real_open(path, *a, **k)

    monkeypatch.setattr(builtins, "open", fake("avx avx2 avx512f avx512bw"))
    assert report.cpu_model() == "AMD EPYC 9R45, AVX-512"
    monkeypatch.setattr(builtins, "open", fake("avx avx2"))
    assert report.cpu_model() == "AMD EPYC 9R45, AVX2"
    assert report.machine_line().startswith("AMD EPYC 9R45, AVX2 (")


def test_real_folders_become_labelled_benchmark_pairs(tmp_path, capsys):
    rng = np.random.default_rng(4)
    one = tmp_path / "lidar"
    one.mkdir()
    src = rng.uniform(0, 10, (500, 3)).astype(np.float32)
    np.save(one / "source.npy", src)
    np.save(one / "target.npy", src + 1.0)
    T = np.eye(4)
    T[:3, 3] = 1.0
    np.savetxt(one / "T_target_source.txt", T)
    files = B.real_pair_files(one, 3, tmp_path / "cache")
    assert [f.name for f in files] == ["real_lidar_lidar.npz"]
    with np.load(files[0]) as z:
        np.testing.assert_array_equal(z["source"], src)
        np.testing.assert_array_equal(z["T"], T)
    row = {"points": 500, "set": "lidar", "allocator": "jemalloc", "method": "cegc",
           "stages": {"total": {"median_ms": 90.0, "p90_ms": 95.0}}}
    peer = dict(row, method="ransac", stages={"total": {"median_ms": 45.0, "p90_ms": 50.0}})
    assert B.ratios([row, peer]) == "500 points, lidar (jemalloc): cegc / ransac 2.00x"
    assert B.main(["--real", str(tmp_path / "nothing"), "--sizes", "1500", "--cache", str(tmp_path / "c")]) == 1
    assert "--real" in capsys.readouterr().err


def test_the_cegc_worker_runs_the_parameter_file_it_is_given(tmp_path):
    from cegc_ros.evaluation.methods import default_params_file
    files = [str(f) for f in B.make_pairs(1500, 1, tmp_path)]
    text = default_params_file().read_text()
    assert 'engine.refine: "icp"' in text
    no_icp = tmp_path / "no_icp.yaml"
    no_icp.write_text(text.replace('engine.refine: "icp"', 'engine.refine: "none"'))
    default, other = B.worker("cegc", files, 1), B.worker("cegc", files, 1, str(no_icp))
    assert "refine" in default["stages"] and "refine" not in other["stages"]
    assert default["median_rotation_error_deg"] < 1.0 and other["median_rotation_error_deg"] < 5.0
