"""cegc_ros.tools.average_weights: the mean of a run's snapshots, one line on bad input."""

import torch

from cegc_ros.engine import load_checkpoint, save_checkpoint
from cegc_ros.model import CEGC, ModelConfig
from cegc_ros.tools import average_weights

SMALL = dict(agnn_dims=(16, 16, 32), feat_dim=32, attn_heads=2, attn_layers=1, cams_dim=8, hoce_topk=4)


def _snapshots(folder, steps, **cfg):
    models = []
    for i, step in enumerate(steps):
        torch.manual_seed(i)
        model = CEGC(ModelConfig(**{**SMALL, **cfg}))
        save_checkpoint(folder / f"step_{step:07d}.pt", model, {"step": step, "validation": {"val_recall": 0.5}})
        models.append(model)
    return models


def test_average_is_the_mean_of_the_snapshots_in_the_range(tmp_path, capsys):
    snaps = tmp_path / "snapshots"
    models = _snapshots(snaps, (300, 600, 900))
    out = tmp_path / "avg.pt"
    assert average_weights.main([str(snaps), "--steps", "300:600", "--out", str(out)]) == 0
    assert "2 snapshots, steps 300-600" in capsys.readouterr().out
    avg, meta = load_checkpoint(out)
    a, b = (m.state_dict() for m in models[:2])
    name = next(k for k in a if k.endswith("weight"))
    assert not torch.allclose(a[name], b[name])                      # the snapshots differ ...
    for k, v in avg.state_dict().items():                           # ... the output is their mean
        torch.testing.assert_close(v, (a[k] + b[k]) / 2, rtol=0, atol=1e-6)
    assert meta["step"] == 600 and meta["averaged"]["steps"] == [300, 600]
    assert "validation" not in meta                                 # the last snapshot's, not the mean's


def test_bad_input_is_one_line_and_exit_1(tmp_path, capsys):
    snaps = tmp_path / "snapshots"
    _snapshots(snaps, (300,))
    _snapshots(snaps, (600,), feat_dim=16)
    out = str(tmp_path / "avg.pt")
    cases = [(["--steps", "700:900"], "no step_*.pt snapshots with steps 700-900"),
             (["--steps", "300:600"], "step_0000600.pt: its model configuration differs"),
             (["--steps", "3-6"], "--steps '3-6': expected FIRST:LAST")]
    for args, message in cases:
        assert average_weights.main([str(snaps), *args, "--out", out]) == 1
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1
    assert not (tmp_path / "avg.pt").exists()
