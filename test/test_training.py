"""cegc-train's trainer: configs, a tiny run with validation, checkpoints, CSV and resume, and
the noise curriculum."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from cegc_ros.engine import load_checkpoint
from cegc_ros.training import Config, PairSampler, Stage, Trainer

PARAMS = Path(__file__).resolve().parents[1] / "params"


def room(seed: int, n: int = 3000) -> np.ndarray:
    """A corner of a room with a few boxes, metres: enough structure for normals and FPFH."""
    rng = np.random.default_rng(seed)
    parts = []
    for axis in range(3):
        p = rng.uniform(0, 3, (n // 4, 3))
        p[:, axis] = 0.0
        parts.append(p)
    c = rng.uniform(0.5, 2.0, 3)
    parts.append(c + rng.uniform(-0.3, 0.3, (n // 4, 3)) * np.array([1, 1, 0.2]))
    return np.concatenate(parts).astype(np.float32)


def fragments(k: int = 4) -> list[SimpleNamespace]:
    return [SimpleNamespace(points=room(i), T_world_fragment=np.eye(4), scene_seed=i // 2, index=i % 2)
            for i in range(k)]


@pytest.mark.parametrize("path", sorted(PARAMS.glob("train_*.yaml")) + sorted(PARAMS.glob("ablation_*.yaml")),
                         ids=lambda p: p.name)
def test_every_shipped_training_config_loads(path):
    cfg = Config.from_yaml(path)
    assert cfg.train.stages and all(isinstance(s, Stage) for s in cfg.train.stages)
    assert cfg.train.lr > 0 and cfg.model.variant in ("ri", "paper")


def tiny_config(out: Path, max_steps: int) -> Config:
    return Config.from_dict({
        "model": {"agnn_dims": [16, 16, 32], "feat_dim": 32, "attn_layers": 1, "attn_heads": 2,
                  "cams_dim": 8, "hoce_topk": 4},
        "data": {"val_pairs": 2, "val_points": 64, "val_noise_max": 0.01},
        "train": {"out_dir": str(out), "max_steps": max_steps, "val_every": 2, "log_every": 1,
                  "threads": 1, "stages": [{"until_step": 10**9, "max_angle_deg": 45, "points": 64,
                                            "resample_prob": 0.5, "noise_max": 0.01}]},
    })


def test_tiny_run_logs_validates_checkpoints_and_resumes(tmp_path):
    frags = fragments()
    cfg = tiny_config(tmp_path / "run", max_steps=4)
    trainer = Trainer(cfg, device="cpu", fragments=frags, val_fragments=frags, progress=False)
    before = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    val = trainer.run()
    assert trainer.step == 4 and 0.0 <= val["val_recall"] <= 1.0 and val["val_rre_mean"] >= 0.0
    with open(tmp_path / "run" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4]
    assert all(np.isfinite(float(r["loss"])) for r in rows)
    assert [r["step"] for r in rows if r["val_rre_mean"]] == ["2", "4"]
    after = trainer.model.state_dict()
    assert any(not torch.equal(before[k], after[k]) for k in before)     # it learned something

    # best.pt is an engine checkpoint that carries the feature radii it was trained with
    model, meta = load_checkpoint(tmp_path / "run" / "best.pt")
    assert model.cfg.fpfh_radius == cfg.model.fpfh_radius and meta["step"] in (2, 4)
    # every validated state is kept as an engine checkpoint for the learning curve
    snaps = sorted((tmp_path / "run" / "snapshots").glob("step_*.pt"))
    assert [p.name for p in snaps] == ["step_0000002.pt", "step_0000004.pt"]
    assert load_checkpoint(snaps[1])[1]["validation"]["val_recall"] == val["val_recall"]

    # resume: the step count, the CSV and the weights continue from last.pt
    cfg2 = tiny_config(tmp_path / "run", max_steps=6)
    again = Trainer(cfg2, resume=tmp_path / "run" / "last.pt", device="cpu", fragments=frags,
                    val_fragments=frags, progress=False)
    assert again.step == 4
    for k, v in again.model.state_dict().items():
        assert torch.equal(v, after[k])
    # a resume under a config with another learning rate (an anneal) takes the config's rate
    # and keeps the optimizer's moments
    slow = tiny_config(tmp_path / "run", max_steps=6)
    slow.train.lr = 1e-5
    annealed = Trainer(slow, resume=tmp_path / "run" / "last.pt", device="cpu", fragments=frags,
                       val_fragments=frags, progress=False)
    assert [g["lr"] for g in annealed.opt.param_groups] == [1e-5]
    assert [g["lr"] for g in again.opt.param_groups] == [cfg2.train.lr] != [1e-5]
    m_again, m_slow = again.opt.state_dict()["state"], annealed.opt.state_dict()["state"]
    assert m_slow.keys() == m_again.keys() and len(m_slow) > 0
    assert all(torch.equal(m_slow[i]["exp_avg"], m_again[i]["exp_avg"]) for i in m_slow)
    # a log begun under other columns (an older version's, without l_rank) keeps them: the rows
    # appended on resume line up under its header
    log = tmp_path / "run" / "metrics.csv"
    with open(log) as fh:
        old = list(csv.DictReader(fh))
    cols = [c for c in old[0] if c != "l_rank"]
    with open(log, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(old)
    again.run()
    with open(log) as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5, 6]
    assert all(None not in r and np.isfinite(float(r["loss"])) for r in rows)


_STOPPABLE_RUN = """
import sys
from pathlib import Path
sys.path.insert(0, {test_dir!r})
from test_training import fragments, tiny_config
from cegc_ros.training import Trainer
cfg = tiny_config(Path({out!r}), max_steps=10**6)
cfg.train.workers, cfg.train.val_every = {workers}, 10**6
trainer = Trainer(cfg, device="cpu", fragments=fragments(), val_fragments=fragments(), progress=False)
trainer.run()
print("stopped after step", trainer.step, "by", trainer.stopped_by, flush=True)
"""


@pytest.mark.parametrize("workers", [0, 1])
def test_sigterm_ends_the_run_after_its_step_with_last_pt_saved(tmp_path, workers):
    """A run in its own process group gets SIGTERM, as ``pkill -f cegc-train`` or Ctrl-C send it
    to the trainer and its DataLoader worker alike: it exits 0 after the step in progress, its
    last.pt holds that step and its log ends there, so a resume goes on without a gap or a
    repeat."""
    import os
    import signal
    import subprocess
    import sys
    import time
    out = tmp_path / "run"
    code = _STOPPABLE_RUN.format(test_dir=str(Path(__file__).parent), out=str(out), workers=workers)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    log = out / "metrics.csv"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if log.exists() and len(log.read_text().splitlines()) > 4:      # a few steps done
            break
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 0, stderr[-2000:]
    step = int(stdout.split("stopped after step ")[1].split()[0])
    assert f"by {int(signal.SIGTERM)}" in stdout and step >= 4
    state = torch.load(out / "last.pt", map_location="cpu", weights_only=True)
    assert int(state["step"]) == step
    with open(log) as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh)] == list(range(1, step + 1))


def _exact_shared(batch: dict[str, torch.Tensor]) -> float:
    """Share of source points that land exactly (1e-5) on a target point under the ground truth."""
    from scipy.spatial import cKDTree
    src, tgt = batch["src"][0].numpy(), batch["tgt"][0].numpy()
    R, t = batch["R"][0].numpy(), batch["t"][0].numpy()
    d, _ = cKDTree(tgt).query(src @ R.T + t)
    return float((d < 1e-5).mean())


def test_noise_curriculum_breaks_exact_point_pairs_only_for_its_share():
    sampler = PairSampler(fragments(2), 0.0, {"with_features": True})
    clean = Stage(10**9, 45.0, 2048)
    noisy = Stage(10**9, 45.0, 2048, noise_max=0.01, noise_prob=1.0)
    never = Stage(10**9, 45.0, 2048, noise_max=0.01, noise_prob=0.0)
    assert _exact_shared(sampler.sample(np.random.default_rng(0), clean)) > 0.3
    assert _exact_shared(sampler.sample(np.random.default_rng(0), never)) > 0.3
    assert _exact_shared(sampler.sample(np.random.default_rng(0), noisy)) == 0.0


def test_bf16_autocast_training_runs_with_the_svd_kept_in_fp32(tmp_path):
    frags = fragments(2)
    cfg = tiny_config(tmp_path / "bf16", max_steps=2)
    cfg.train.bf16 = True
    trainer = Trainer(cfg, device="cpu", fragments=frags, val_fragments=frags, progress=False)
    trainer.run()
    with open(tmp_path / "bf16" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 and all(np.isfinite(float(r["loss"])) for r in rows)


def test_weighted_kabsch_inside_bf16_autocast_matches_fp32():
    from cegc_ros.model.svd import weighted_kabsch
    g = torch.Generator().manual_seed(0)
    src = torch.rand(1, 50, 3, generator=g)
    R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    tgt = src @ R.T + 0.1
    w = torch.rand(1, 50, generator=g)
    with torch.autocast(device_type="cpu", dtype=torch.bfloat16):
        R_est, t_est, valid = weighted_kabsch(src, tgt, w)
    assert R_est.dtype == torch.float32 and bool(valid[0])
    assert torch.allclose(R_est[0], R, atol=1e-4) and torch.allclose(t_est[0], torch.full((3,), 0.1), atol=1e-4)


def test_validation_mixes_in_two_fragment_pairs_with_their_relative_pose(tmp_path):
    from scipy.spatial.transform import Rotation
    pts = room(7)
    T_b = np.eye(4)
    T_b[:3, :3] = Rotation.from_euler("xyz", [10, -20, 70], degrees=True).as_matrix()
    T_b[:3, 3] = [0.2, -0.1, 0.3]
    local_b = ((pts - T_b[:3, 3]) @ T_b[:3, :3]).astype(np.float32)     # same surfaces, fragment b's frame
    scene = [SimpleNamespace(points=pts, T_world_fragment=np.eye(4), scene_seed=5, index=0),
             SimpleNamespace(points=local_b, T_world_fragment=T_b, scene_seed=5, index=1)]
    rel = {0: T_b[:3, :3].T, 1: T_b[:3, :3]}        # source 0 -> target 1, or 1 -> 0

    def val_rotations(prob: float) -> list[np.ndarray]:
        cfg = tiny_config(tmp_path / f"v{prob}", max_steps=1)
        cfg.data.val_fragments_prob = prob
        cfg.data.val_noise_max = 0.0
        cfg.data.val_pairs = 4
        trainer = Trainer(cfg, device="cpu", fragments=scene, val_fragments=scene, progress=False)
        return [b["R"][0].double().numpy() for b in trainer.val_batches]

    def is_fragment_pose(R: np.ndarray) -> bool:
        return any(np.allclose(R, r, atol=1e-5) for r in rel.values())

    assert all(is_fragment_pose(R) for R in val_rotations(1.0))
    assert not any(is_fragment_pose(R) for R in val_rotations(0.0))


def test_dataloader_workers_feed_the_same_pairs_in_the_same_order(tmp_path):
    frags = fragments()
    losses = {}
    for workers in (0, 2):
        cfg = tiny_config(tmp_path / f"w{workers}", max_steps=5)
        cfg.train.workers = workers
        Trainer(cfg, device="cpu", fragments=frags, val_fragments=frags, progress=False).run()
        with open(tmp_path / f"w{workers}" / "metrics.csv") as fh:
            losses[workers] = [float(r["loss"]) for r in csv.DictReader(fh)]
    assert len(losses[0]) == 5
    np.testing.assert_allclose(losses[2], losses[0], rtol=1e-6)


def test_pair_stream_is_keyed_by_step_so_a_resume_continues_it():
    from cegc_ros.training import PairStream, TrainConfig
    sampler = PairSampler(fragments(2), 0.002, {"with_features": True})
    cfg = TrainConfig(stages=[Stage(10**9, 45.0, 64, resample_prob=0.5)])
    whole = PairStream(sampler, cfg, rank=0, start=0)
    it = iter(whole)
    first = [next(it) for _ in range(4)]
    later = next(iter(PairStream(sampler, cfg, rank=0, start=3)))
    for k in first[3]:
        assert torch.equal(first[3][k], later[k])
    assert not torch.equal(first[2]["R"], first[3]["R"])


def test_pair_stream_takes_in_shards_written_while_it_trains(tmp_path):
    """A pair cache rendered while the network trains: the stream refreshes it every
    refresh_steps steps (counted from step 0, so a resume keeps the rhythm) and the sampler's
    overlap bands then include the new pairs."""
    from cegc_ros.data.pair_cache import PairCache
    from cegc_ros.tools import make_pairs
    from cegc_ros.training import PairStream, TrainConfig

    class Counting:
        """A sampler that records at which steps the stream refreshed it."""
        def __init__(self) -> None:
            self.refreshed: list[int] = []
            self.step = -1

        def refresh(self) -> int:
            self.refreshed.append(self.step + 1)
            return 0

        def sample(self, rng, stage):
            self.step += 1
            return self.step

    counting = Counting()
    cfg = TrainConfig(refresh_steps=4, stages=[Stage(10**9, 45.0, 64)])
    stream = iter(PairStream(counting, cfg, rank=0, start=6))
    counting.step = 5
    assert [next(stream) for _ in range(9)] == list(range(6, 15))
    assert counting.refreshed == [8, 12]
    cfg.refresh_steps = 0
    never = Counting()
    stream = iter(PairStream(never, cfg, rank=0, start=0))
    [next(stream) for _ in range(9)]
    assert never.refreshed == []

    out = tmp_path / "pairs"
    base = ["--split", "val", "--rooms-per-shard", "1", "--fragments", "3", "--pairs", "3",
            "--max-points", "1500", "--quiet", "--out", str(out)]
    assert make_pairs.main(base + ["--rooms", "1"]) == 0
    sampler = PairSampler([], 0.0, {"with_features": True}, pairs=PairCache(out))
    before = len(sampler.pairs)
    band = sampler._overlap_band(0.0, 1.0)
    assert len(band) == before >= 1
    assert sampler.refresh() == 0
    assert make_pairs.main(base + ["--rooms", "3"]) == 0
    added = sampler.refresh()
    assert added >= 1 and len(sampler.pairs) == before + added
    np.testing.assert_array_equal(sampler._overlap_band(0.0, 1.0), np.arange(before + added))


def test_the_paper_objective_stays_trainable(tmp_path):
    frags = fragments(2)
    cfg = tiny_config(tmp_path / "paper", max_steps=2)
    cfg.train.objective = "paper"
    trainer = Trainer(cfg, device="cpu", fragments=frags, val_fragments=frags, progress=False)
    before = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    trainer.run()
    with open(tmp_path / "paper" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 and all(r["l_corr"] for r in rows) and not any(r["l_inlier"] for r in rows)
    assert any(not torch.equal(before[k], v) for k, v in trainer.model.state_dict().items())
    with pytest.raises(ValueError, match="train.objective"):
        Config.from_dict({"train": {"objective": "nope"}})


def test_candidate_loss_labels_the_true_partner_as_the_inlier():
    """Candidates that are the true partner get label 1, the others 0: a score that says so has a
    lower inlier loss than the reverse, and the match accuracy counts it."""
    from cegc_ros.model.cegc import CandidateOutput
    from cegc_ros.model.losses import CandidateLossConfig, candidate_loss
    g = torch.Generator().manual_seed(0)
    N = 64
    src = torch.rand(1, N, 3, generator=g)
    R, t = torch.eye(3)[None], torch.tensor([[0.1, 0.0, 0.0]])
    tgt = src + t[:, None]                                             # partner of i is i
    wrong = torch.cdist(src, src)[0].argmax(dim=1)                      # the farthest point
    cand = torch.stack([torch.arange(N), wrong], dim=-1)[None]         # (1, N, 2): true first
    feats = torch.randn(1, N, 8, generator=g)

    def loss(scores: torch.Tensor) -> dict[str, float]:
        out = CandidateOutput(torch.zeros(1, N), torch.zeros(1, N), cand, scores, torch.zeros(1, N), feats, feats)
        return candidate_loss(out, src, tgt, R, t, CandidateLossConfig())[1]

    right = loss(torch.tensor([4.0, -4.0]).expand(1, N, 2).contiguous())
    flipped = loss(torch.tensor([-4.0, 4.0]).expand(1, N, 2).contiguous())
    assert right["inlier_frac"] == pytest.approx(0.5)
    assert right["match_acc"] == 1.0 and flipped["match_acc"] == 0.0
    assert right["l_inlier"] < 0.05 < 3.0 < flipped["l_inlier"]
    assert right["top100_precision"] == pytest.approx(64 / 100)          # all 64 inliers ranked first
    assert flipped["top100_precision"] == pytest.approx(36 / 100) and right["cand_recall"] == 1.0


def test_candidate_objective_learns_one_pair(tmp_path):
    """Forty steps on one different-view-like pair (two samplings of one room corner) raise the
    precision of the most confident candidates: the loss reaches the scores."""
    from cegc_ros.engine import save_checkpoint  # noqa: F401  (engine imported as the trainer does)
    from cegc_ros.model import CEGC, ModelConfig
    from cegc_ros.model.losses import CandidateLossConfig, candidate_loss
    from cegc_ros.training import _forward, TrainConfig
    torch.manual_seed(0)
    model = CEGC(ModelConfig(agnn_dims=(16, 16, 32), feat_dim=32, attn_layers=1, attn_heads=2, cams_dim=8,
                             hoce_topk=4))
    sampler = PairSampler(fragments(2), 0.0, model.cfg.features())
    b = sampler.to_tensors(room(3), room(3) + np.float32(0.05), np.array(
        [[1, 0, 0, 0.05], [0, 1, 0, 0.05], [0, 0, 1, 0.05], [0, 0, 0, 1.0]]), 128, np.random.default_rng(0))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    cfg = TrainConfig()
    first = last = None
    for _ in range(40):
        out, bb = _forward(model, b, "cpu", cfg)
        loss, parts = candidate_loss(out, bb["src"], bb["tgt"], bb["R"], bb["t"], CandidateLossConfig())
        opt.zero_grad()
        loss.backward()
        opt.step()
        first = first or parts
        last = parts
    assert last["loss"] < 0.7 * first["loss"]
    assert last["top100_precision"] > first["top100_precision"] + 0.2


def test_a_warm_start_from_a_warm_started_checkpoint_counts_every_pair_seen(tmp_path):
    """The campaign resumes from its shipped checkpoint: pairs seen accumulate along the chain."""
    from cegc_ros.engine import save_checkpoint
    from cegc_ros.model import CEGC
    frags = fragments(2)
    cfg = tiny_config(tmp_path / "chain", max_steps=2)
    save_checkpoint(tmp_path / "shipped.pt", CEGC(cfg.model),
                    {"step": 1500, "pairs_seen": 6994, "elapsed_minutes": 20.0,
                     "warm_start": {"pairs_seen": 5494, "elapsed_minutes": 57.8}})
    trainer = Trainer(cfg, resume=tmp_path / "shipped.pt", device="cpu", fragments=frags, val_fragments=frags,
                      progress=False)
    assert trainer.step == 0 and trainer.warm_start["pairs_seen"] == 6994
    assert trainer.warm_start["elapsed_minutes"] == pytest.approx(77.8)
    trainer.run()
    _, meta = load_checkpoint(tmp_path / "chain" / "snapshots" / "step_0000002.pt")
    assert meta["pairs_seen"] == 6996 and meta["warm_start"]["pairs_seen"] == 6994


def _warm_start_across(tmp_path, name: str, field: str, ours, theirs, **train):
    """A tiny run (out dir ``name``) whose network has ModelConfig ``field`` = ``ours``,
    warm-started from a checkpoint whose network has ``theirs``: (config, fragments, trainer, the
    checkpoint's network)."""
    from cegc_ros.engine import save_checkpoint
    from cegc_ros.model import CEGC, ModelConfig
    frags = fragments(2)
    cfg = tiny_config(tmp_path / name, max_steps=2)
    cfg.model = ModelConfig.from_dict({**cfg.model.to_dict(), field: ours})
    for key, value in train.items():
        setattr(cfg.train, key, value)
    old = CEGC(ModelConfig.from_dict({**cfg.model.to_dict(), field: theirs})).eval()
    save_checkpoint(tmp_path / f"{name}_from.pt", old, {"step": 10, "pairs_seen": 10})
    trainer = Trainer(cfg, resume=tmp_path / f"{name}_from.pt", device="cpu", fragments=frags,
                      val_fragments=frags, progress=False)
    return cfg, frags, trainer, old


def test_a_warm_start_into_a_wider_hoce_keeps_its_overlap_logits(tmp_path):
    """A checkpoint whose HOCE reads 4 sorted similarities, warm-started into hoce_topk 8: every
    weight but the refinement's first map is kept, and HOCE's logits are the same (the added
    similarities start at weight 0); the run then trains them and records the widening."""
    from cegc_ros.engine import save_checkpoint
    cfg, frags, trainer, narrow = _warm_start_across(tmp_path, "wide", "hoce_topk", 8, 4)
    assert trainer.warm_start["hoce_topk_widened_from"] == 4
    got, want = trainer.model.state_dict(), narrow.state_dict()
    key = "hoce.refine.0.0.weight"
    assert got[key].shape == (32, 9) and want[key].shape == (32, 5)
    assert all(torch.equal(got[k], want[k]) for k in want if k != key)
    fx, fy = torch.randn(1, 40, 32), torch.randn(1, 50, 32)
    model = trainer.model.eval()
    with torch.no_grad():
        for a, b in zip(model.hoce(fx, fy), narrow.hoce(fx, fy), strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
    trainer.run()
    assert trainer.model.state_dict()[key][:, 4:8].abs().sum() > 0           # now in use
    _, meta = load_checkpoint(tmp_path / "wide" / "snapshots" / "step_0000002.pt")
    assert meta["warm_start"]["hoce_topk_widened_from"] == 4
    # Narrower is not a widening: it fails as a strict load does.
    save_checkpoint(tmp_path / "eight.pt", trainer.model, {"step": 2})
    with pytest.raises(RuntimeError):
        Trainer(tiny_config(tmp_path / "four", max_steps=1), resume=tmp_path / "eight.pt",
                device="cpu", fragments=frags, val_fragments=frags, progress=False)


def test_a_warm_start_into_the_distance_attention_starts_as_its_checkpoint(tmp_path):
    """A checkpoint without model.geo_embedding, warm-started into a network with it: every
    weight is kept, the added maps start at zero (the same features), the run records it and
    trains them; a trainer state (last.pt) must match exactly."""
    cfg, frags, trainer, plain = _warm_start_across(tmp_path, "geo", "geo_embedding", 8, 0, geo_lr=0.01)
    assert trainer.warm_start["geo_embedding_added"] == 8
    got, want = trainer.model.state_dict(), plain.state_dict()
    assert set(got) - set(want) == {"context.self_blocks.0.geo"}
    assert all(torch.equal(got[k], want[k]) for k in want)
    assert not got["context.self_blocks.0.geo"].any()
    g = torch.Generator().manual_seed(1)
    xyz = [torch.rand(1, 60, 3, generator=g) - 0.5 for _ in range(2)]
    nrm = [torch.nn.functional.normalize(torch.randn(1, 60, 3, generator=g), dim=-1) for _ in range(2)]
    desc = [torch.rand(1, 60, 33, generator=g) for _ in range(2)]
    with torch.no_grad():
        a = trainer.model.eval().features(xyz[0], xyz[1], *nrm, *desc)
        b = plain.features(xyz[0], xyz[1], *nrm, *desc)
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    trainer.model.train()
    trainer.run()
    assert trainer.model.state_dict()["context.self_blocks.0.geo"].abs().sum() > 0      # now in use
    model, meta = load_checkpoint(tmp_path / "geo" / "snapshots" / "step_0000002.pt")
    assert meta["warm_start"]["geo_embedding_added"] == 8 and model.cfg.geo_embedding == 8
    # the maps learn at train.geo_lr, the rest at train.lr, after a resume too
    groups = [(len(g["params"]), g["lr"]) for g in trainer.opt.param_groups]
    assert groups == [(len(want), cfg.train.lr), (1, 0.01)]
    again = Trainer(cfg, resume=tmp_path / "geo" / "last.pt", device="cpu", fragments=frags,
                    val_fragments=frags, progress=False)
    assert [(len(g["params"]), g["lr"]) for g in again.opt.param_groups] == groups
    # a state saved with two groups, resumed under a config with one (or the other way): one line
    cfg.train.geo_lr = 0.0
    with pytest.raises(ValueError, match=r"last.pt: its optimiser has 2 parameter group\(s\), this config 1"):
        Trainer(cfg, resume=tmp_path / "geo" / "last.pt", device="cpu", fragments=frags,
                val_fragments=frags, progress=False)


def test_a_warm_start_continues_the_curriculum_where_the_weights_left_it(tmp_path):
    from cegc_ros.engine import save_checkpoint
    from cegc_ros.model import CEGC
    from cegc_ros.training import PairStream, _stage
    frags = fragments(2)
    cfg = tiny_config(tmp_path / "cont", max_steps=1)
    cfg.train.stages = [Stage(100, 45.0, 64, min_overlap=0.4), Stage(10**9, 45.0, 48, min_overlap=0.1)]
    save_checkpoint(tmp_path / "shipped.pt", CEGC(cfg.model), {"step": 150, "pairs_seen": 150})
    warm = Trainer(cfg, resume=tmp_path / "shipped.pt", device="cpu", fragments=frags,
                   val_fragments=frags, progress=False)
    fresh = Trainer(cfg, device="cpu", fragments=frags, val_fragments=frags, progress=False)
    assert (warm.step, warm.curriculum_offset, fresh.curriculum_offset) == (0, 150, 0)
    assert _stage(cfg.train, warm.step + warm.curriculum_offset).min_overlap == 0.1
    # The pairs it trains on are the last stage's (48 points), not the first's (64).
    pair = next(iter(PairStream(warm.sampler, cfg.train, 0, warm.step, warm.curriculum_offset)))
    assert pair["src"].shape[1] == 48
    assert next(iter(PairStream(fresh.sampler, cfg.train, 0, 0)))["src"].shape[1] == 64


def test_bf16_autocast_only_where_the_hardware_has_it(tmp_path):
    from cegc_ros.training import bf16_hardware
    amd = tmp_path / "amd"
    amd.write_text("flags\t\t: fpu sse avx2 fma\nflags\t\t: fpu sse avx2 fma\n")
    xeon = tmp_path / "xeon"
    xeon.write_text("flags\t\t: fpu avx2 avx512f avx512_bf16 amx_bf16 amx_tile\n")
    assert not bf16_hardware("cpu", str(amd), "AVX2")
    assert bf16_hardware("cpu", str(xeon), "AVX512")
    # the same CPU with torch held to its AVX2 kernels (ATEN_CPU_CAPABILITY=avx2): fp32
    assert not bf16_hardware("cpu", str(xeon), "AVX2")
    assert bf16_hardware("cuda:0", str(amd))
    assert not bf16_hardware("cpu", str(tmp_path / "missing"))


def test_low_overlap_share_draws_that_share_from_the_low_overlap_band():
    class FakeCache:
        """A pair cache of 100 pairs, overlaps 0.00 .. 0.99; a pair's info carries its own."""
        overlaps = np.arange(100) / 100.0

        def __len__(self):
            return 100

        def __getitem__(self, i):
            return SimpleNamespace(info={"overlap": self.overlaps[i]}, index=i)

    sampler = PairSampler([], 0.0, {"with_features": True}, pairs=FakeCache())
    base = dict(until_step=10**9, max_angle_deg=45.0, points=64, fragments_prob=1.0, min_overlap=0.1)
    rng = np.random.default_rng(0)
    plain = [sampler.raw(rng, Stage(**base)).info["overlap"] for _ in range(2000)]
    low = [sampler.raw(rng, Stage(**base, low_overlap_share=0.5)).info["overlap"] for _ in range(2000)]
    assert min(plain) >= 0.1 and min(low) >= 0.1              # the curriculum's floor holds
    share_plain = np.mean(np.array(plain) <= 0.3)              # 21 of 90 eligible pairs: ~0.23
    share_low = np.mean(np.array(low) <= 0.3)                  # half drawn from the band: ~0.62
    assert share_plain == pytest.approx(21 / 90, abs=0.04)
    assert share_low == pytest.approx(0.5 + 0.5 * 21 / 90, abs=0.04)


def test_a_warm_start_into_fewer_attention_layers_keeps_the_first_ones(tmp_path):
    """Cutting the network from 2 (self, cross) attention layers to 1 keeps every other weight
    and the first layers; a trainer state (last.pt) or any other difference must match exactly."""
    from cegc_ros.engine import save_checkpoint
    from cegc_ros.model import CEGC, ModelConfig
    frags = fragments(2)
    cfg = tiny_config(tmp_path / "cut", max_steps=2)                  # attn_layers 1
    big_cfg = ModelConfig.from_dict({**cfg.model.to_dict(), "attn_layers": 2})
    big = CEGC(big_cfg)
    save_checkpoint(tmp_path / "big.pt", big, {"step": 10, "pairs_seen": 10})
    trainer = Trainer(cfg, resume=tmp_path / "big.pt", device="cpu", fragments=frags,
                      val_fragments=frags, progress=False)
    assert trainer.warm_start["dropped_attention_layers"] == 1
    got, want = trainer.model.state_dict(), big.state_dict()
    assert set(got) < set(want) and "context.self_blocks.1.merge.weight" in want
    assert all(torch.equal(got[k], want[k]) for k in got)
    trainer.run()
    _, meta = load_checkpoint(tmp_path / "cut" / "snapshots" / "step_0000002.pt")
    assert meta["warm_start"]["dropped_attention_layers"] == 1
    # A wider network is not a cut: it fails as a strict load does.
    wide = ModelConfig.from_dict({**cfg.model.to_dict(), "attn_layers": 2, "feat_dim": 64})
    save_checkpoint(tmp_path / "wide.pt", CEGC(wide), {"step": 1})
    with pytest.raises(RuntimeError, match="size mismatch|Unexpected"):
        Trainer(cfg, resume=tmp_path / "wide.pt", device="cpu", fragments=frags, val_fragments=frags,
                progress=False)


def test_rank_loss_asks_each_pair_to_rank_its_true_candidates_above_its_hardest_false_ones():
    """The ranking term: near 0 when every true candidate outranks the pair's hard false ones,
    large when one false candidate outranks them; a pair with 1 true candidate weighs as much
    as one with many (the batch-pooled BCE does not), and a pair with none adds nothing."""
    from cegc_ros.model.losses import rank_loss
    K = 100
    inl = torch.zeros(2, K)
    inl[0, :50] = 1.0                      # an easy, high-overlap pair: half true
    inl[1, 0] = 1.0                        # a low-overlap pair: one true candidate
    good = torch.where(inl > 0, torch.tensor(0.0), torch.tensor(-10.0))
    assert float(rank_loss(good, inl, 8)) < 1e-3
    bad = good.clone()
    bad[1, 5] = 5.0                        # one false candidate of the hard pair on top
    # pair 1's loss: mean over its 8 hard negatives, one of them 5 above the true one
    expected = 0.5 * (float(torch.nn.functional.softplus(torch.tensor(5.0))) / 8)
    assert float(rank_loss(bad, inl, 8)) == pytest.approx(expected, rel=1e-3)
    # the same false candidate on top of the easy pair costs that pair the same mean
    easy = good.clone()
    easy[0, 60] = 5.0
    assert float(rank_loss(easy, inl, 8)) == pytest.approx(expected, rel=1e-3)
    none = torch.zeros(1, K)
    assert float(rank_loss(torch.zeros(1, K), none, 8)) == 0.0
    # gradients reach the scores: the false candidate on top is pushed down, the true one up
    x = bad.clone().requires_grad_(True)
    rank_loss(x, inl, 8).backward()
    assert x.grad[1, 5] > 0 > x.grad[1, 0]


def test_within_auc_scores_each_rows_order_and_leaves_out_rows_of_one_class():
    """within_auc: 1 when every positive of a row outscores its negatives, 0 reversed, the mean
    over rows; a row with one class only is left out, and nan when no row has both."""
    from cegc_ros.model.losses import within_auc
    labels = torch.tensor([[1.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]])
    right = torch.tensor([[0.9, 0.8, 0.2, 0.1], [0.5, 0.4, 0.3, 0.2], [0.1, 0.2, 0.3, 0.4]])
    assert within_auc(right, labels) == pytest.approx(1.0)
    assert within_auc(-right, labels) == pytest.approx(0.0)
    half = torch.tensor([[0.9, 0.1, 0.5, 0.0], [0.5, 0.4, 0.3, 0.2], [0.0, 0.0, 0.0, 0.0]])
    # row 0: positive 0.9 beats both negatives, 0.1 beats only 0.0 -> 3 of 4; row 1: 1
    assert within_auc(half, labels) == pytest.approx((0.75 + 1.0) / 2)
    assert math.isnan(within_auc(right[2:], labels[2:]))
    # ties count half, as select_weights' overlap_auc counts them (bf16 logits tie)
    assert within_auc(torch.zeros(1, 4), labels[:1]) == pytest.approx(0.5)


def test_candidate_loss_overlap_ranking_term_asks_overlapping_points_above_the_others():
    """candidate_loss with overlap_rank > 0: HOCE logits that put each cloud's overlapping
    points above its non-overlapping ones score a small l_overlap_rank and overlap_auc 1, the
    reversed order a large one and 0, and the term enters the total with its weight."""
    from cegc_ros.model.cegc import CandidateOutput
    from cegc_ros.model.losses import CandidateLossConfig, candidate_loss
    g = torch.Generator().manual_seed(0)
    n = 32
    shared = torch.rand(1, n, 3, generator=g)
    src = torch.cat([shared, torch.rand(1, n, 3, generator=g) + torch.tensor([5.0, 0, 0])], dim=1)
    R, t = torch.eye(3)[None], torch.tensor([[0.1, 0.0, 0.0]])
    tgt = torch.cat([shared, torch.rand(1, n, 3, generator=g) - torch.tensor([5.0, 0, 0])], dim=1) + t[:, None]
    N = 2 * n                                       # the first n points of each cloud overlap
    cand = torch.arange(N)[None, :, None]
    feats = torch.randn(1, N, 8, generator=g)
    lab = torch.cat([torch.ones(n), torch.zeros(n)])[None]

    def parts(sign: float, weight: float) -> dict[str, float]:
        logits = sign * (4.0 * lab - 2.0)
        out = CandidateOutput(logits, logits, cand, torch.zeros(1, N, 1), torch.zeros(1, N), feats, feats)
        return candidate_loss(out, src, tgt, R, t, CandidateLossConfig(overlap_rank=weight))[1]

    right, flipped = parts(1.0, 1.0), parts(-1.0, 1.0)
    assert right["overlap_auc"] == 1.0 and flipped["overlap_auc"] == 0.0
    # every pair of (overlapping, hard non-overlapping) points 4 apart: softplus(-4), softplus(4)
    assert right["l_overlap_rank"] == pytest.approx(0.0181, abs=1e-3)
    assert flipped["l_overlap_rank"] == pytest.approx(4.0181, abs=1e-3)
    off = parts(-1.0, 0.0)
    assert off["l_overlap_rank"] == 0.0
    assert flipped["loss"] - off["loss"] == pytest.approx(flipped["l_overlap_rank"], rel=1e-4)


def test_candidate_loss_with_the_ranking_term_prefers_the_right_order():
    """candidate_loss with rank > 0 logs l_rank, and a score order with the true partner on
    top scores a lower l_rank than the reversed order."""
    from cegc_ros.model.cegc import CandidateOutput
    from cegc_ros.model.losses import CandidateLossConfig, candidate_loss
    g = torch.Generator().manual_seed(0)
    N = 64
    src = torch.rand(1, N, 3, generator=g)
    R, t = torch.eye(3)[None], torch.tensor([[0.1, 0.0, 0.0]])
    tgt = src + t[:, None]
    wrong = torch.cdist(src, src)[0].argmax(dim=1)
    cand = torch.stack([torch.arange(N), wrong], dim=-1)[None]
    feats = torch.randn(1, N, 8, generator=g)
    cfg = CandidateLossConfig(rank=1.0, rank_negatives=16)

    def parts(scores: torch.Tensor) -> dict[str, float]:
        out = CandidateOutput(torch.zeros(1, N), torch.zeros(1, N), cand, scores, torch.zeros(1, N), feats, feats)
        return candidate_loss(out, src, tgt, R, t, cfg)[1]

    right = parts(torch.tensor([4.0, -4.0]).expand(1, N, 2).contiguous())
    flipped = parts(torch.tensor([-4.0, 4.0]).expand(1, N, 2).contiguous())
    # log w = logsigmoid(+-4): 4 apart, softplus(-4) = 0.018 against softplus(4) = 4.018
    assert right["l_rank"] == pytest.approx(0.0181, abs=1e-3)
    assert flipped["l_rank"] == pytest.approx(4.018, abs=1e-2)
    off = candidate_loss(CandidateOutput(torch.zeros(1, N), torch.zeros(1, N), cand,
                                         torch.zeros(1, N, 2), torch.zeros(1, N), feats, feats),
                         src, tgt, R, t, CandidateLossConfig())[1]
    assert off["l_rank"] == 0.0


def test_descriptor_positives_within_the_threshold_count_as_partners():
    """64 points on a line 1 cm apart, the target the same points shifted: each source point's
    nearest partner is its own copy, and the copies of its two neighbours lie within the match
    threshold (2 x the spacing). Features that point each source point at its neighbour's copy
    cost the "nearest" InfoNCE about 1/temperature and the "within" one almost nothing; features
    that point at the copy itself cost both little, "within" never more."""
    from cegc_ros.model.cegc import CandidateOutput
    from cegc_ros.model.losses import CandidateLossConfig, candidate_loss
    N = 64
    src = torch.zeros(1, N, 3)
    src[0, :, 0] = torch.arange(N) * 0.01
    R, t = torch.eye(3)[None], torch.tensor([[0.0, 0.0, 0.5]])
    tgt = src + t[:, None]
    eye = torch.eye(N)[None]
    cand = torch.arange(N).reshape(1, N, 1)

    def l_desc(src_features: torch.Tensor, positives: str) -> float:
        out = CandidateOutput(torch.zeros(1, N), torch.zeros(1, N), cand, torch.zeros(1, N, 1),
                              torch.zeros(1, N), src_features, eye)
        cfg = CandidateLossConfig(descriptor_positives=positives)
        return candidate_loss(out, src, tgt, R, t, cfg)[1]["l_desc"]
    nxt = torch.arange(1, N + 1)
    nxt[-1] = N - 2
    neighbour = eye[:, nxt]                                # source i looks like target i + 1
    assert l_desc(neighbour, "nearest") > 0.8 / 0.1
    assert l_desc(neighbour, "within") < 0.1
    assert l_desc(eye, "within") <= l_desc(eye, "nearest") < 0.1
    with pytest.raises(ValueError, match="descriptor_positives"):
        CandidateLossConfig(descriptor_positives="all")


def test_distill_loss_matches_the_student_to_the_teacher_where_their_candidates_agree():
    """The similarity term is the KL between the two clouds' feature-similarity rows (0 for the
    teacher's own features); the score term pairs candidates by target index, not by position,
    and ignores a student candidate the teacher did not score: at the teacher's logits of the
    shared candidates every score's gradient is 0, and moving the unshared one costs nothing."""
    from cegc_ros.model.cegc import CandidateOutput
    from cegc_ros.model.losses import distill_loss
    torch.manual_seed(0)
    N, M = 4, 6
    fx, fy = torch.randn(1, N, 8), torch.randn(1, M, 8)
    t_cand = torch.tensor([[[2, 0, 5]] * N])
    t_scores = torch.randn(1, N, 3)
    teacher = CandidateOutput(torch.randn(1, N), torch.randn(1, M), t_cand, t_scores, torch.randn(1, N), fx, fy)
    s_cand = torch.tensor([[[0, 1, 2]] * N])                       # 0 and 2 shared (teacher's 2nd and 1st)
    s_scores = torch.stack([t_scores[..., 1], torch.full((1, N), 7.0), t_scores[..., 0]], -1).requires_grad_()
    student = CandidateOutput(teacher.src_overlap_logits, teacher.tgt_overlap_logits, s_cand, s_scores,
                              teacher.conf_logits, fx, fy)
    total, parts = distill_loss(student, teacher, 0.1)
    total.backward()
    assert torch.allclose(s_scores.grad, torch.zeros_like(s_scores), atol=1e-7)
    assert parts["distill_shared"] == pytest.approx(2 / 3)
    other = CandidateOutput(student.src_overlap_logits, student.tgt_overlap_logits, s_cand, s_scores.detach(),
                            student.conf_logits, torch.randn(1, N, 8), fy)
    assert distill_loss(other, teacher, 0.1)[0] > total + 0.05             # other features: a positive KL


def test_a_distilled_student_starts_from_the_teachers_tensors_and_leaves_it_frozen(tmp_path):
    """A narrower student (feat_dim 16 against the teacher's 32) takes the teacher's AGNN layers
    (same names and shapes) and the rest cut to its widths (model/narrowing.py) at a fresh
    start, trains with the distillation term logged, and the teacher does not change; a
    teacher trained on other input features is refused."""
    from cegc_ros.engine import save_checkpoint
    from cegc_ros.model import CEGC
    frags = fragments(2)
    teacher_cfg = tiny_config(tmp_path / "t", max_steps=1)
    torch.manual_seed(1)
    teacher = CEGC(teacher_cfg.model)
    save_checkpoint(tmp_path / "teacher.pt", teacher, {"step": 10})
    raw = tiny_config(tmp_path / "student", max_steps=2).to_dict()
    raw["model"]["feat_dim"] = 16
    raw["distill"] = {"teacher": str(tmp_path / "teacher.pt"), "weight": 1.0}
    trainer = Trainer(Config.from_dict(raw), device="cpu", fragments=frags, val_fragments=frags, progress=False)
    own = trainer.model.state_dict()
    theirs = teacher.state_dict()
    agnn_layers = [k for k in own if k.startswith("agnn.layers.")]
    assert agnn_layers and all(torch.equal(own[k], theirs[k]) for k in agnn_layers)
    assert torch.equal(own["agnn.head.0.weight"], theirs["agnn.head.0.weight"][:16])   # the head: cut
    assert torch.equal(own["hoce.semantic.0.0.weight"], theirs["hoce.semantic.0.0.weight"][:8, :16])
    assert trainer.warm_start["teacher_init"] == "narrowed"
    assert trainer.warm_start["teacher_tensors"] == len(own)                          # every tensor
    trainer.run()
    with open(tmp_path / "student" / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert all(np.isfinite(float(r["l_distill"])) and float(r["l_distill"]) > 0 for r in rows)
    assert all(torch.equal(v, theirs[k]) for k, v in trainer.teacher.state_dict().items())
    raw["model"]["fpfh_radius"] = 0.3
    with pytest.raises(ValueError, match="other input features"):
        Trainer(Config.from_dict(raw), device="cpu", fragments=frags, val_fragments=frags, progress=False)


def test_a_stage_draws_its_network_points_from_its_own_support_points(monkeypatch):
    """Stage.support_points reaches the features stage (a network trained at 1024 points runs
    on 2048 support points, as the engine's 2 : 1); 0 keeps preprocess.support_points."""
    from cegc_ros import training
    from cegc_ros.config import PreprocessConfig
    seen = []
    real = training.prepare_pair

    def spy(source, target, points, support, *args, **kwargs):
        seen.append((points, support))
        return real(source, target, points, support, *args, **kwargs)
    monkeypatch.setattr(training, "prepare_pair", spy)
    sampler = PairSampler(fragments(2), 0.0, {"with_features": True})
    wide = sampler.sample(np.random.default_rng(0), Stage(10**9, 45.0, 256, support_points=512))
    plain = sampler.sample(np.random.default_rng(0), Stage(10**9, 45.0, 256))
    assert seen == [(256, 512), (256, PreprocessConfig().support_points)]
    assert wide["src"].shape == plain["src"].shape == (1, 256, 3)
    # the same seed, other support points: other network points
    assert not torch.equal(wide["src"], plain["src"])


def test_sensor_normals_follow_each_cached_pairs_sensors():
    """data.normals 'sensor': a different-view pair's clouds are each in its sensor's frame (the
    origins); a copy pair's target is its source moved by T, its sensor at T's translation, and
    turned there its normals agree with the source's at the same surface points, where turned to
    the target frame's origin a share of them flip; 7Scenes-protocol copies keep their centroids."""
    from cegc_ros.data.protocols import Pair
    from cegc_ros.data.protocols import transform_points
    src = room(0).astype(np.float64) - [1.5, 1.5, 2.5]        # the sensor above the room's middle
    T = np.eye(4)
    a = np.radians(120)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = T[:3, :3] @ [4.0, 0.0, 4.0]     # the target frame's origin behind a wall, below the floor
    copy = Pair(src.astype(np.float32), transform_points(T, src).astype(np.float32), T, {"kind": "copy"})
    views = Pair(copy.source, copy.source, np.eye(4), {"kind": "views"})
    protocol = Pair(copy.source, copy.source, np.eye(4), {"protocol": "7scenes"})
    sensor = PairSampler(fragments(2), 0.0, {"with_features": True}, normals="sensor")
    centroid = PairSampler(fragments(2), 0.0, {"with_features": True})
    vs, vt = sensor.viewpoints(copy)
    assert np.array_equal(vs, np.zeros(3)) and np.allclose(vt, T[:3, 3])
    assert all(np.array_equal(v, np.zeros(3)) for v in sensor.viewpoints(views))
    assert sensor.viewpoints(protocol) == (None, None) and centroid.viewpoints(copy) == (None, None)
    with pytest.raises(ValueError, match="normals must be"):
        PairSampler(fragments(2), 0.0, {"with_features": True}, normals="up")

    def agreement(viewpoints):
        b = sensor.to_tensors(copy.source, copy.target, T, 256, np.random.default_rng(0), 512, viewpoints)
        R, t = b["R"][0].numpy(), b["t"][0].numpy()
        s_in_t = b["src"][0].numpy() @ R.T + t
        tgt = b["tgt"][0].numpy()
        j = np.argmin(((s_in_t[:, None] - tgt[None]) ** 2).sum(2), axis=1)
        near = np.linalg.norm(s_in_t - tgt[j], axis=1) < 0.03
        dots = ((b["src_n"][0].numpy() @ R.T) * b["tgt_n"][0].numpy()[j]).sum(1)
        sure = near & (np.abs(dots) > 0.9)
        assert sure.sum() > 50
        return float((dots[sure] > 0).mean())
    assert agreement((vs, vt)) > 0.97
    assert agreement((np.zeros(3), np.zeros(3))) < 0.9


def test_cli_names_a_missing_pair_cache_in_one_line(tmp_path, monkeypatch, capsys):
    """A config whose pair caches are not there (a fresh clone) exits 2 at once with one line
    naming the directory and how to make it, not a traceback after minutes of rendering."""
    from cegc_ros.tools import train as train_cli
    monkeypatch.chdir(tmp_path)                          # the config's relative caches are absent
    rc = train_cli.main(["--config", str(PARAMS / "train_views_centre.yaml"), "--out-dir", str(tmp_path / "run"),
                         "--device", "cpu"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert ".cache/pairs/train_v" in err[0] and "not a directory" in err[0] and "cegc-make-pairs" in err[0]
    assert not (tmp_path / ".cache" / "fragments").exists()     # nothing rendered first
