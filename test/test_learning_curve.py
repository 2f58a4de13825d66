"""tools/learning_curve: engine recall of each training snapshot on a test bag, resumable."""

from __future__ import annotations

import csv

import numpy as np
import torch

from cegc_ros.data.bag import write_pairs
from cegc_ros.data.protocols import Pair
from cegc_ros.engine import save_checkpoint
from cegc_ros.model import CEGC, ModelConfig
from cegc_ros.tools import learning_curve
from test_training import room


def test_curve_rows_per_snapshot_and_resume(tmp_path, monkeypatch, capsys):
    pts = room(0)
    T_ok, T_far = np.eye(4), np.eye(4)
    T_far[:3, 3] = [5.0, 0.0, 0.0]                     # ground truth no registration can reach
    pairs = [Pair(pts, pts, T_ok, {"protocol": "fragments"}), Pair(pts, pts, T_far, {"protocol": "fragments"})]
    write_pairs(tmp_path / "bag", pairs, protocol="fragments", seed=0)
    snaps = tmp_path / "snapshots"
    torch.manual_seed(0)
    cfg = ModelConfig(agnn_dims=(16, 16, 32), feat_dim=32, attn_heads=2, attn_layers=1, cams_dim=8, hoce_topk=4)
    for step in (300, 600):
        save_checkpoint(snaps / f"step_{step:07d}.pt", CEGC(cfg),
                        {"step": step, "validation": {"val_recall": step / 1000}, "warm_start": {"pairs_seen": 50}})
    out = tmp_path / "curve"
    # identical clouds: the pipeline finds the identity whatever the network (the exact FPFH
    # candidates are in the default candidate set); the second pair's ground truth is 5 m off it
    assert learning_curve.main([str(snaps), "--bag", str(tmp_path / "bag"), "--out", str(out)]) == 0
    rows = list(csv.DictReader((out / "learning_curve.csv").open()))
    assert [int(r["step"]) for r in rows] == [300, 600]
    assert [int(r["pairs_seen"]) for r in rows] == [350, 650]
    assert [float(r["val_recall"]) for r in rows] == [0.3, 0.6]
    assert [(float(r["test_recall"]), r["test_pairs"]) for r in rows] == [(0.5, "2"), (0.5, "2")]
    assert (out / "learning_curve.png").stat().st_size > 1000
    capsys.readouterr()
    assert learning_curve.main([str(snaps), "--bag", str(tmp_path / "bag"), "--out", str(out)]) == 0
    assert "step" not in capsys.readouterr().out                # nothing evaluated twice
    assert learning_curve.main([str(tmp_path), "--bag", str(tmp_path / "bag")]) == 1


def test_low_overlap_validation_column_matches_select_weights(tmp_path, val_cache, capsys):
    """--val-cache scores each snapshot on the validation cache's pairs under --max-overlap at
    --seed, the same number select_weights prints for that checkpoint, pairs and seed."""
    import pytest

    from cegc_ros.tools import select_weights
    snaps = tmp_path / "snapshots"
    torch.manual_seed(0)
    cfg = ModelConfig(agnn_dims=(16, 16, 32), feat_dim=32, attn_heads=2, attn_layers=1, cams_dim=8, hoce_topk=4)
    save_checkpoint(snaps / "step_0000300.pt", CEGC(cfg), {"step": 300})
    out = tmp_path / "curve"
    assert learning_curve.main([str(snaps), "--val-cache", str(val_cache), "--max-overlap", "1",
                                "--val-pairs", "2", "--seed", "3", "--out", str(out)]) == 0
    rows = list(csv.DictReader((out / "learning_curve.csv").open()))
    assert [(r["step"], r["low_pairs"], r["test_recall"], r["test_pairs"]) for r in rows] == [("300", "2", "", "0")]
    capsys.readouterr()
    assert select_weights.main([str(val_cache), str(snaps / "step_0000300.pt"), "--pairs", "2",
                                "--seeds", "3"]) == 0
    printed = capsys.readouterr().out
    assert f"recall {float(rows[0]['low_recall']):.3f} on 2 pairs" in printed
    # neither set: a usage error, exit 2
    with pytest.raises(SystemExit) as exc:
        learning_curve.main([str(snaps), "--out", str(out)])
    assert exc.value.code == 2
    # a cache without pairs under the overlap asked for: one line, exit 1
    assert learning_curve.main([str(snaps), "--val-cache", str(val_cache), "--max-overlap", "0.0001",
                                "--out", str(tmp_path / "none")]) == 1
    assert "no kinect different-view pairs under" in capsys.readouterr().err
