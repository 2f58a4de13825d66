"""cegc-register: two files in, T_target_source out; and the parameter-file reader it uses."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cegc_ros.metrics import rotation_error_deg, translation_error
from cegc_ros.params_file import ParamsFileError, read_params_file
from cegc_ros.tools import register_files as cli

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A held-out 7Scenes-protocol pair: source as .npy, target as .ply, and its ground truth."""
    import open3d as o3d

    from cegc_ros.data.protocols import make_pair

    p = make_pair("7scenes", "test", 0)
    d = tmp_path_factory.mktemp("pair")
    np.save(d / "source.npy", p.source)
    o3d.io.write_point_cloud(str(d / "target.ply"), o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(p.target.astype(np.float64))))
    return d / "source.npy", d / "target.ply", p.T_target_source, p.source


def test_json_result_matches_the_ground_truth_and_out_moves_the_source(pair, tmp_path, capsys):
    source, target, T_gt, source_xyz = pair
    out = tmp_path / "moved.npy"
    assert cli.main([str(source), str(target), "--json", "--out", str(out)]) == 0
    doc = json.loads(capsys.readouterr().out)          # exactly one JSON object
    assert set(doc) >= {"T_target_source", "fitness", "ambiguity", "draws", "valid", "timings"}
    assert doc["draws"] == 1 and "redraw" not in doc["timings"]   # the default: one draw
    T = np.array(doc["T_target_source"])
    assert T.shape == (4, 4) and doc["valid"] is True
    # The first network + ICP on this kind of pair: hundredths of a degree (docs/accuracy.md).
    assert rotation_error_deg(T_gt[:3, :3], T[:3, :3]) < 0.5
    assert translation_error(T_gt[:3, 3], T[:3, 3]) < 0.005   # unit-box scene
    assert 0.5 < doc["fitness"] <= 1.0
    assert 0.0 <= doc["ambiguity"] < 0.5        # a clean copy pair: no rival alignment near it
    assert doc["timings"]["total"] > 0 and all(v >= 0 for v in doc["timings"].values())
    moved = np.load(out)
    expected = source_xyz @ T_gt[:3, :3].T + T_gt[:3, 3]
    assert moved.shape == source_xyz.shape
    assert np.abs(moved - expected).max() < 0.01


def test_readable_output_with_the_nodes_params_file(pair, tmp_path, capsys):
    _, target, _, _ = pair
    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    preprocess:\n      num_points: 512\n"
                      "register_node:\n  ros__parameters:\n    engine.refine: icp\n"
                      "    output.min_fitness: 0.3\n")
    assert cli.main([str(target), str(target), "--params", str(params)]) == 0
    text = capsys.readouterr().out.splitlines()
    assert text[0].startswith("T_target_source")
    matrix = np.array([[float(v) for v in line.split()] for line in text[1:5]])
    assert np.allclose(matrix, np.eye(4), atol=1e-3)      # a cloud onto itself
    assert text[5].startswith("rotation ") and " deg" in text[5]
    assert text[6].startswith("fitness  ") and text[7].startswith("ambiguity ")
    assert text[8] == "valid    yes"
    assert text[9].startswith("timings  ms: ") and "total" in text[9]
    # a pair the engine drew twice says so, before the timings (which include the redraw stage)
    import dataclasses
    from cegc_ros.engine import RegistrationResult
    one = RegistrationResult(np.eye(4), *(np.zeros((0, 3), np.float32),) * 2, *(np.zeros(0, np.float32),) * 2,
                             np.zeros((0, 2), np.int64), np.zeros(0, np.float32), np.zeros(0, bool), np.eye(6),
                             0.5, 0.1, True, timings={"estimate": 0.05, "redraw": 0.1, "total": 0.15})
    assert "draws" not in cli.format_result(one)
    lines = cli.format_result(dataclasses.replace(one, draws=2)).splitlines()
    assert lines[-2].startswith("draws    2 ") and "redraw 100.0" in lines[-1]


def _error(capsys, argv: list[str]) -> str:
    assert cli.main(argv) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("cegc-register: error: ")
    return lines[0]


def test_bad_files_are_one_line_and_exit_1(pair, tmp_path, capsys):
    source, target, _, _ = pair
    missing = tmp_path / "nope.pcd"
    assert f"{missing}: no such file" in _error(capsys, [str(missing), str(target)])
    empty = tmp_path / "empty.npy"
    np.save(empty, np.zeros((0, 3)))
    assert f"{empty}: no points" in _error(capsys, [str(empty), str(target)])
    flat = tmp_path / "flat.npy"
    np.save(flat, np.zeros(12))
    assert "expected an (N, 3) numeric array" in _error(capsys, [str(source), str(flat)])
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"not a ply\x00\x01\x02")
    assert f"{garbage}: no points" in _error(capsys, [str(garbage), str(target)])
    text = tmp_path / "cloud.txt"
    text.write_text("1 2 3\n")
    assert "unknown format .txt" in _error(capsys, [str(source), str(text)])
    corrupt = tmp_path / "corrupt.npy"
    corrupt.write_bytes(b"\x93NUMPY garbage")
    assert "not a readable .npy array" in _error(capsys, [str(corrupt), str(target)])
    named = tmp_path / "text_named.npy"          # numpy would suggest allow_pickle=True here
    named.write_text("1 2 3\n4 5 6\n")
    line = _error(capsys, [str(named), str(target)])
    assert f"{named}: not a readable .npy array (not a .npy file)" in line and "pickle" not in line
    nans = tmp_path / "nans.npy"
    np.save(nans, np.full((50, 3), np.nan))
    assert f"{nans}: no finite points (all 50 have a NaN or inf coordinate)" in \
        _error(capsys, [str(source), str(nans)])


@pytest.mark.parametrize("content, message", [
    ("/**:\n  ros__parameters:\n    preprocess.num_points: 10\n",
     "preprocess.num_points = 10 is out of range"),
    ("/**:\n  ros__parameters:\n    engine.refine: magic\n", "engine.refine = 'magic'"),
    ("/**:\n  ros__parameters:\n    engine.refin: icp\n", "unknown parameter engine.refin"),
    ("/**:\n  ros__parameters: [1, 2]\n", "ros__parameters must be a mapping"),
    ("preprocess.num_points: 512\n", "no ros__parameters block"),
    ("/**: {ros__parameters: {a: 1}\n", "not valid YAML"),
])
def test_bad_params_files_are_one_line_and_exit_1(pair, tmp_path, capsys, content, message):
    source, target, _, _ = pair
    params = tmp_path / "p.yaml"
    params.write_text(content)
    line = _error(capsys, [str(source), str(target), "--params", str(params)])
    assert message in line and str(params) in line


def test_usage_errors_exit_2():
    for argv in (["only_one.npy"], ["a.npy", "b.npy", "--pairs", "list.txt"], []):
        with pytest.raises(SystemExit) as err:
            cli.main(argv)
        assert err.value.code == 2


def test_a_list_of_pairs_in_one_process_one_json_line_each_and_bad_lines_named(pair, tmp_path, capsys):
    source, target, T_gt, source_xyz = pair
    lst = tmp_path / "pairs.txt"
    lst.write_text(f"# source target [out]\n{source} {target} moved.npy\n\n"
                   f"{source} missing.ply   # a bad pair does not stop the others\n"
                   f"{target} {target}\n")
    assert cli.main(["--pairs", str(lst), "--json"]) == 1       # one pair failed
    captured = capsys.readouterr()
    docs = [json.loads(line) for line in captured.out.strip().splitlines()]
    assert [d["line"] for d in docs] == [2, 5]
    T = np.array(docs[0]["T_target_source"])
    assert docs[0]["valid"] and rotation_error_deg(T_gt[:3, :3], T[:3, :3]) < 0.5
    assert docs[0]["wall_s"] >= docs[0]["timings"]["total"] > 0
    assert np.abs(np.array(docs[1]["T_target_source"]) - np.eye(4)).max() < 1e-3   # a cloud onto itself
    moved = np.load(tmp_path / "moved.npy")                     # OUT relative to the list's folder
    assert np.abs(moved - (source_xyz @ T_gt[:3, :3].T + T_gt[:3, 3])).max() < 0.01
    err = captured.err.strip().splitlines()
    assert err == [f"cegc-register: error: --pairs {lst}:4: {tmp_path / 'missing.ply'}: no such file"]
    bad = tmp_path / "bad.txt"
    bad.write_text(f"{source}\n")
    assert f"--pairs {bad}:1: expected 'SOURCE TARGET [OUT]', got 1 fields" in \
        _error(capsys, ["--pairs", str(bad)])


def test_a_bad_file_from_the_command_line_prints_no_traceback(tmp_path):
    empty = tmp_path / "empty.xyz"
    empty.write_text("")
    proc = subprocess.run([sys.executable, "-m", "cegc_ros.tools.register_files", str(empty),
                           str(empty)], capture_output=True, text=True, timeout=120, cwd=REPO,
                          stdin=subprocess.DEVNULL)
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.strip() == f"cegc-register: error: {empty}: no points (empty, or not a " \
                                  f"readable .xyz file)"


# --- the parameter-file reader -------------------------------------------------------------


def test_params_file_reader_merges_blocks_and_nested_names(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("/**:\n  ros__parameters:\n    preprocess.num_points: 512\n"
                    "    engine: {refine: none}\n"
                    "robot1:\n  register_node:\n    ros__parameters:\n"
                    "      preprocess: {num_points: 717, voxel_size: 0.05}\n")
    assert read_params_file(path) == {"preprocess.num_points": 717, "engine.refine": "none",
                                      "preprocess.voxel_size": 0.05}


def test_the_shipped_params_file_reads_as_the_config_defaults():
    from cegc_ros.node.params import build_sections, check_values

    values = read_params_file(REPO / "params" / "register_node.yaml")
    sections = build_sections(check_values(values))
    from cegc_ros.config import EngineConfig, PreprocessConfig
    assert sections["preprocess"] == PreprocessConfig()
    assert sections["engine"] == EngineConfig()


def test_params_file_reader_errors_name_the_file(tmp_path):
    with pytest.raises(ParamsFileError, match="cannot read it"):
        read_params_file(tmp_path / "missing.yaml")
