"""bench_runtimes: the network's inputs as the engine fed them, other runtimes timed on them in
processes of their own, and their outputs held against the engine's session."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cegc_ros.onnx_network import OUTPUTS
from cegc_ros.tools import bench_runtimes

pytest.importorskip("onnxruntime")


def test_the_engines_own_inputs_are_captured(tmp_path):
    net, feeds = bench_runtimes.capture_inputs(1500, 2, tmp_path)
    assert len(feeds) == 2
    n = feeds[0]["src"].shape[1]
    assert feeds[0]["src"].shape == (1, n, 3) and feeds[0]["src_desc"].shape == (1, n, 33)
    assert feeds[0]["extra"].dtype == np.int64 and feeds[0]["extra"].shape[:2] == (1, n)
    # a prepared cloud: unit-scale points, unit normals
    np.testing.assert_allclose(np.linalg.norm(feeds[0]["src_normals"][0], axis=1), 1.0, atol=1e-4)
    assert not np.array_equal(feeds[0]["src"], feeds[1]["src"])
    out = dict(zip(OUTPUTS, net.session.run(list(OUTPUTS), feeds[0])))
    assert out["candidates"].shape[:2] == (1, n) and np.isfinite(out["scores"]).all()


def test_runtimes_are_timed_apart_and_checked_against_the_engine(tmp_path, capsys):
    out = tmp_path / "r.json"
    assert bench_runtimes.main(["--size", "1500", "--pairs", "1", "--repeats", "2", "--rounds", "1",
                                "--runtimes", "onnxruntime-parallel", "--hogs", "0",
                                "--cache", str(tmp_path), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    rows = {r["runtime"]: r for r in json.loads(out.read_text())["results"]}
    assert set(rows) == {"onnxruntime", "onnxruntime-parallel"}     # the reference is added
    ref, par = rows["onnxruntime"], rows["onnxruntime-parallel"]
    assert ref["logit_diff"] == 0.0 and ref["candidates_equal"] == 1.0   # the session against itself
    assert 0.0 <= par["logit_diff"] < 1e-3 and par["candidates_equal"] >= 0.99
    assert 0 < ref["min_ms"] <= ref["median_ms"] and 0 < par["min_ms"] <= par["median_ms"]
    assert "| onnxruntime-parallel | 0 |" in text and "command: python -m cegc_ros.tools.bench_runtimes" in text


def test_bad_requests_are_one_line(tmp_path, capsys):
    assert bench_runtimes.main(["--runtimes", "tensorrt", "--cache", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == ("bench_runtimes: --runtimes: unknown runtime 'tensorrt', expected some of "
                   "onnxruntime, onnxruntime-parallel, openvino, openvino-static")
    assert bench_runtimes.main(["--pairs", "0", "--cache", str(tmp_path)]) == 1
    assert "--pairs, --repeats and --rounds >= 1" in capsys.readouterr().err


def test_op_profile_splits_the_warm_runs_kernel_time_by_operator(tmp_path, capsys):
    out = tmp_path / "ops.json"
    assert bench_runtimes.main(["--size", "1500", "--pairs", "1", "--ops", "3", "--cache", str(tmp_path),
                                "--json", str(out)]) == 0
    ops = {r["op"]: r for r in json.loads(out.read_text())["ops"]}
    # the attention and the linear layers are matrix products: the largest share, many nodes
    assert ops["MatMul"]["nodes"] >= 20 and ops["MatMul"]["share"] == max(r["share"] for r in ops.values())
    assert {"LayerNormalization", "TopK", "Softmax"} <= set(ops)
    assert abs(sum(r["share"] for r in ops.values()) - 1.0) < 1e-9
    assert all(r["ms"] > 0 for r in ops.values())
    # no row gather is an Expand + GatherElements pair any more (features.gather)
    assert ops.get("Expand", {"nodes": 0})["nodes"] < ops["Gather"]["nodes"]
    assert "| MatMul |" in capsys.readouterr().out
