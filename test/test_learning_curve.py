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
