"""Trajectory metrics (cegc_ros.sequential.metrics) and the cegc-eval-seq command."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cegc_ros.data import bag as B
from cegc_ros.data.sequences import make_room_sequence
from cegc_ros.sequential import metrics as M
from cegc_ros.tools import evaluate_seq as E


def line(n: int, step: float = 0.1, yaw_deg: float = 0.0) -> np.ndarray:
    """(n, 4, 4) poses along x, turning yaw_deg per step."""
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = step * np.arange(n)
    T[:, :3, :3] = Rotation.from_euler("z", yaw_deg * np.arange(n)[:, None], degrees=True).as_matrix()
    return T


def test_ate_is_zero_for_the_truth_and_measures_an_offset():
    gt = line(20)
    a = M.ate(gt, gt)
    assert a["rmse_first"] == 0.0 and a["rmse_aligned"] < 1e-12 and a["coverage"] == 1.0
    est = gt.copy()
    est[:, 1, 3] += 0.05
    est[0] = gt[0]
    assert M.ate(gt, est)["max_first"] == pytest.approx(0.05)


def test_aligned_ate_removes_a_rigid_motion_but_first_frame_ate_does_not():
    gt = line(30, 0.1, 2.0)
    gt[:, 2, 3] = np.sin(np.arange(30) / 5.0)                       # not a straight line
    W = np.eye(4)
    W[:3, :3] = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    W[:3, 3] = [1.0, 2.0, 3.0]
    a = M.ate(gt, W @ gt)
    assert a["rmse_aligned"] < 1e-9
    assert a["rmse_first"] > 1.0


def test_ate_skips_missing_poses():
    gt = line(10)
    est = gt.copy()
    est[3:5] = np.nan
    a = M.ate(gt, est)
    assert a["frames"] == 8 and a["coverage"] == 0.8 and a["rmse_first"] == 0.0


def test_rpe_of_a_scale_error():
    gt = line(41, 0.05)                                   # 2 m straight
    est = gt.copy()
    est[:, 0, 3] *= 1.02                                  # 2% too long
    r = M.rpe(gt, est, [0.5, 1.0, 5.0])
    assert r["0.5"]["trans_pct"] == pytest.approx(2.0, rel=1e-6)
    assert r["1"]["trans_pct"] == pytest.approx(2.0, rel=1e-6)
    assert r["1"]["segments"] == 21 and r["1"]["rot_deg_per_m"] < 1e-9
    assert r["5"]["segments"] == 0 and np.isnan(r["5"]["trans_pct"])


def test_rpe_and_step_errors_of_a_heading_drift():
    gt = line(21, 0.1)                                    # 2 m
    est = line(21, 0.1, 0.5)                              # turns 0.5 deg per 0.1 m = 5 deg/m
    r = M.rpe(gt, est, [1.0])["1"]
    assert r["rot_deg_per_m"] == pytest.approx(5.0, rel=1e-6)
    s = M.step_errors(gt, est)
    assert s["rot_mean"] == pytest.approx(0.5, rel=1e-6) and s["steps"] == 20


# --------------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def seq_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("bags") / "seq"
    B.write_sequence(path, make_room_sequence(3, 12, frame_step=3, pixel_stride=8))
    return path


def test_cli_scores_a_sequence_bag(seq_bag, tmp_path, capsys, monkeypatch):
    from cegc_ros.sequential import KeyframeOdometry
    warmed = []
    warm_start = KeyframeOdometry.warm_start
    monkeypatch.setattr(KeyframeOdometry, "warm_start", lambda self: warmed.append(1) or warm_start(self))
    out = tmp_path / "eval"
    rc = E.main([str(seq_bag), "--methods", "icp-only,kiss-icp", "--out", str(out), "--quiet",
                 "--set", "sequential.max_range=4.0", "--rpe-lengths", "0.25"])
    assert rc == 0
    summary = json.loads((out / "metrics.json").read_text())
    icp, kiss = summary["methods"]
    assert summary["sequence"]["clouds"] == 12
    assert summary["sequence"]["path_length_m"] == pytest.approx(0.44, abs=0.02)   # 0.4 m/s
    # The room-3 robot run (1.1 s, 0.44 m) is tracked to a centimetre.
    assert icp["ate"]["max_first"] < 0.03 and icp["ate"]["coverage"] == 1.0
    assert icp["rejected"] == 0 and icp["recoveries"] == 0 and icp["keyframes"] >= 1
    assert icp["rpe"]["0.25"]["segments"] > 0
    assert icp["latency_ms"]["median"] > 0
    assert warmed == [1]        # timed as the node runs it: warmed up, and the state untouched
    if E.kiss_icp_available():
        assert kiss["skipped"] == "" and kiss["ate"]["coverage"] == 1.0
        assert np.isfinite(kiss["ate"]["rmse_first"])
    else:
        assert "not installed" in kiss["skipped"]
    settings = json.loads((out / "settings.json").read_text())
    assert settings["sequential"]["max_range"] == 4.0
    rows = list(csv.DictReader((out / "frames.csv").open()))
    assert {r["method"] for r in rows} <= {"icp-only", "kiss-icp"}
    assert [r["status"] for r in rows if r["method"] == "icp-only"] == ["first"] + ["icp"] * 11
    assert (out / "trajectory.png").stat().st_size > 10_000
    report = (out / "report.md").read_text()
    assert "| icp-only |" in report and "Machine:" in report and "cegc-eval-seq" in report
    assert "| icp-only |" in capsys.readouterr().out


def test_cli_drop_and_save_bag(tmp_path):
    out, saved = tmp_path / "eval", tmp_path / "saved"
    rc = E.main(["--scene", "3", "--clouds", "8", "--pixel-stride", "8", "--drop", "2:3",
                 "--methods", "icp-only", "--save-bag", str(saved), "--out", str(out), "--quiet"])
    assert rc == 0
    frames = list(B.read_sequence(saved))
    assert len(frames) == 5
    assert B.read_sequence_info(saved)["kept_indices"] == [0, 1, 5, 6, 7]
    summary = json.loads((out / "metrics.json").read_text())
    assert summary["sequence"]["clouds"] == 5


@pytest.mark.parametrize("args,message", [
    (["/nonexistent/bag"], "does not exist"),
    (["--scene", "3", "--methods", "orb-slam"], "unknown method"),
    (["--scene", "3", "--set", "sequential.voxel"], "SECTION.FIELD=VALUE"),
    (["--scene", "3", "--set", "sequential.nope=1"], "unknown setting sequential.nope"),
    (["--scene", "3", "--set", "sequential.min_fitness=2"], "outside"),
    (["--scene", "3", "--set", "output.min_fitness=0.1"], "only preprocess"),
    (["--scene", "3", "--drop", "0:2"], "START must be >= 1"),
    (["--scene", "3", "--clouds", "3", "--drop", "1:5", "--methods", "icp-only"], "leaves 1"),
])
def test_cli_errors_are_one_line_and_exit_1(args, message, tmp_path, capsys):
    assert E.main([*args, "--out", str(tmp_path / "o"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("cegc-eval-seq: error:") and message in err[0]


def test_cli_usage_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as exc:
        E.main([])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        E.main(["bag", "--scene", "3"])
    assert exc.value.code == 2


def test_bag_without_ground_truth_is_refused(tmp_path, capsys):
    from cegc_ros.data.sequences import Sequence
    seq = make_room_sequence(3, 2, pixel_stride=8)
    path = tmp_path / "bare"
    B.write_sequence(path, Sequence(seq.clouds, None, seq.stamps_ns))
    assert E.main([str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    assert "no ground truth" in capsys.readouterr().err
