"""Training of CEGC on synthetic pairs generated on the fly (never on real data).

One step: pick a cached synthetic fragment -> draw a 7Scenes-protocol pair (curriculum on
rotation magnitude, crop ratio and point count) -> the engine's own preprocessing
(:func:`cegc_ros.geometry.normalise_pair`, :func:`cegc_ros.geometry.prepare_cloud`) -> forward
-> loss (:mod:`cegc_ros.model.losses`) -> RAdam step (lr 1e-3, the paper's).

Resumable: ``last.pt`` holds model, optimizer, step, elapsed time and RNG state; ``best.pt`` is
an engine checkpoint (format, model config, state dict, metadata) of the best validation
score so far. Multi-GPU / multi-node through torch DistributedDataParallel under ``torchrun``.
"""

from __future__ import annotations

import csv
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .engine import save_checkpoint
from .geometry import normalise_pair, prepare_cloud
from .metrics import rotation_error_deg
from .model import CEGC, ModelConfig
from .model.losses import LossConfig, cegc_loss


@dataclass
class Stage:
    """Curriculum stage, active until ``until_step``."""

    until_step: int
    max_angle_deg: float
    points: int
    keep_ratio: float = 0.75
    resample_prob: float = 0.0   # probability that the target is an independent resample
    fragments_prob: float = 0.0  # probability of a two-fragment pair (different views, metres)
    noise_max: float = 0.0       # > data.noise_sigma: per-pair noise sigma uniform in [noise_sigma, noise_max]
    noise_prob: float = 1.0      # share of pairs that get that extra noise (the rest: data.noise_sigma)


@dataclass
class DataConfig:
    cache_dir: str = ".cache/fragments"
    num_scenes: int = 40
    fragments_per_scene: int = 4
    val_scenes: int = 4
    val_pairs: int = 24
    val_points: int = 1024
    val_resample_prob: float = 0.0   # share of validation pairs whose target is an independent resample
    noise_sigma: float = 0.002   # unit-box units (7Scenes protocol), on top of the rendered sensor noise
    val_noise_max: float = 0.0   # validation pairs' noise: as Stage.noise_max
    val_fragments_per_scene: int = 2   # fragments rendered per validation scene
    val_fragments_prob: float = 0.0    # share of validation pairs that are two-fragment pairs


@dataclass
class TrainConfig:
    out_dir: str = "runs/7scenes"
    seed: int = 0
    lr: float = 1e-3
    grad_clip: float = 1.0
    max_steps: int = 100000
    max_minutes: float = 60.0
    checkpoint_minutes: float = 5.0
    val_every: int = 250
    log_every: int = 10
    bf16: bool = False
    threads: int = 0
    workers: int = 0     # DataLoader processes preparing pairs while the network trains (0: in the loop)
    stages: list[Stage] = field(default_factory=lambda: [
        Stage(600, 15.0, 384), Stage(2000, 30.0, 512, resample_prob=0.3),
        Stage(10**9, 45.0, 512, resample_prob=0.5)])


@dataclass
class Config:
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    @classmethod
    def from_yaml(cls, path: str | Path) -> Config:
        import yaml
        with open(path, encoding="utf-8") as f:
            raw = yaml.safe_load(f) or {}
        return cls.from_dict(raw)

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> Config:
        unknown = set(raw) - {"model", "loss", "data", "train"}
        if unknown:
            raise ValueError(f"unknown config sections: {sorted(unknown)}")
        tr = dict(raw.get("train", {}))
        if "stages" in tr:
            tr["stages"] = [Stage(**s) for s in tr["stages"]]
        return cls(ModelConfig.from_dict(raw.get("model", {})), LossConfig(**raw.get("loss", {})),
                   DataConfig(**raw.get("data", {})), TrainConfig(**tr))

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model.to_dict(), "loss": asdict(self.loss), "data": asdict(self.data),
                "train": asdict(self.train)}


class PairSampler:
    """Training / validation pairs in the network's normalised frame, as tensors."""

    def __init__(self, fragments: list[Any], noise_sigma: float, features: dict[str, Any]) -> None:
        """``features``: :meth:`ModelConfig.features` of the network being trained."""
        if not fragments:
            raise ValueError("no fragments to sample from")
        self.fragments = fragments
        self.noise_sigma = noise_sigma
        self.features = dict(features)
        by_scene: dict[int, list[Any]] = {}
        for f in fragments:
            by_scene.setdefault(int(f.scene_seed), []).append(f)
        self.scenes = [v for v in by_scene.values() if len(v) >= 2]

    def sample(self, rng: np.random.Generator, stage: Stage) -> dict[str, torch.Tensor]:
        from .data.protocols import sample_7scenes_pair
        if self.scenes and rng.random() < stage.fragments_prob:
            pair = self._fragments_pair(rng)
            if pair is not None:
                return self.to_tensors(pair.source, pair.target, pair.T_target_source, stage.points, rng)
        frag = self.fragments[rng.integers(len(self.fragments))]
        sigma = self.noise_sigma
        if stage.noise_max > sigma and rng.random() < stage.noise_prob:   # breaks exact point pairs
            sigma = float(rng.uniform(sigma, stage.noise_max))
        pair = sample_7scenes_pair(frag.points, rng, num_points=2048, keep_ratio=stage.keep_ratio,
                                   max_angle_deg=stage.max_angle_deg, max_translation=0.5,
                                   noise_sigma=sigma,
                                   resample_target=bool(rng.random() < stage.resample_prob))
        return self.to_tensors(pair.source, pair.target, pair.T_target_source, stage.points, rng)

    def _fragments_pair(self, rng: np.random.Generator, min_overlap: float = 0.15) -> Any:
        """Two different fragments of one scene with at least min_overlap, or None."""
        from .data.protocols import sample_fragments_pair
        for _ in range(4):
            scene = self.scenes[rng.integers(len(self.scenes))]
            a, b = rng.choice(len(scene), 2, replace=False)
            pair = sample_fragments_pair(scene[a], scene[b])
            if pair.info["overlap"] >= min_overlap:
                return pair
        return None

    def to_tensors(self, source: np.ndarray, target: np.ndarray, T: np.ndarray, points: int,
                   rng: np.random.Generator) -> dict[str, torch.Tensor]:
        src_n, tgt_n, norm = normalise_pair(source, target)
        R, t_n = norm.to_normalised(T)
        ps = prepare_cloud(src_n, points, rng, **self.features)
        pt = prepare_cloud(tgt_n, points, rng, **self.features)

        def tt(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).unsqueeze(0)
        return {"src": tt(ps.points), "tgt": tt(pt.points), "src_n": tt(ps.normals), "tgt_n": tt(pt.normals),
                "src_d": tt(ps.desc), "tgt_d": tt(pt.desc), "R": tt(R), "t": tt(t_n)}


class PairStream(torch.utils.data.IterableDataset):
    """Training pairs from ``start`` on; pair ``step`` comes from a generator seeded by
    (seed, rank, step), so the stream is the same with or without DataLoader workers and
    after a resume. With W workers, worker k prepares steps start + k, start + k + W, ...;
    the DataLoader takes them round-robin, i.e. in step order."""

    def __init__(self, sampler: PairSampler, cfg: TrainConfig, rank: int, start: int) -> None:
        super().__init__()
        self.sampler, self.cfg, self.rank, self.start = sampler, cfg, rank, start

    def __iter__(self) -> Any:
        info = torch.utils.data.get_worker_info()
        k, w = (info.id, info.num_workers) if info is not None else (0, 1)
        step = self.start + k
        while True:
            rng = np.random.default_rng([self.cfg.seed, self.rank, step])
            yield self.sampler.sample(rng, _stage(self.cfg, step))
            step += w


def _stage(cfg: TrainConfig, step: int) -> Stage:
    for s in cfg.stages:
        if step < s.until_step:
            return s
    return cfg.stages[-1]


def _forward(model: torch.nn.Module, b: dict[str, torch.Tensor], device: str) -> Any:
    b = {k: v.to(device) for k, v in b.items()}
    return model(b["src"], b["tgt"], b["src_n"], b["tgt_n"], b["src_d"], b["tgt_d"]), b


class Trainer:
    def __init__(self, cfg: Config, resume: str | Path | None = None, device: str = "auto",
                 fragments: list[Any] | None = None, val_fragments: list[Any] | None = None,
                 progress: bool = True) -> None:
        self.cfg = cfg
        self.progress = progress
        self.distributed = int(os.environ.get("WORLD_SIZE", "1")) > 1
        self.rank = int(os.environ.get("RANK", "0"))
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        if self.distributed:
            import torch.distributed as dist
            dist.init_process_group("nccl" if device.startswith("cuda") else "gloo")
            if device.startswith("cuda"):
                device = f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}"
                torch.cuda.set_device(device)
        self.device = device
        if cfg.train.threads > 0:
            torch.set_num_threads(cfg.train.threads)
        torch.manual_seed(cfg.train.seed + self.rank)
        self.model = CEGC(cfg.model).to(device)
        self.net: torch.nn.Module = self.model
        if self.distributed:
            from torch.nn.parallel import DistributedDataParallel
            self.net = DistributedDataParallel(self.model, find_unused_parameters=True)
        self.opt = torch.optim.RAdam(self.model.parameters(), lr=cfg.train.lr)
        self.step = 0
        self.elapsed = 0.0
        self.best = math.inf
        self.out = Path(cfg.train.out_dir)
        if resume:
            self._resume(Path(resume))
        features = cfg.model.features()
        if fragments is None:
            from .data.protocols import FragmentCache
            fragments = FragmentCache(cfg.data.cache_dir, cfg.data.num_scenes, cfg.data.fragments_per_scene,
                                      seed=0).load(progress=progress and self.rank == 0)
            val_fragments = FragmentCache(cfg.data.cache_dir, cfg.data.val_scenes, cfg.data.val_fragments_per_scene,
                                          seed=1).load(progress=progress and self.rank == 0)
        self.sampler = PairSampler(fragments, cfg.data.noise_sigma, features)
        vs = PairSampler(val_fragments or fragments, 0.0, features)
        vrng = np.random.default_rng(12345)
        final = cfg.train.stages[-1]
        val_stage = Stage(0, 45.0, cfg.data.val_points, final.keep_ratio, cfg.data.val_resample_prob,
                          fragments_prob=cfg.data.val_fragments_prob, noise_max=cfg.data.val_noise_max)
        self.val_batches = [vs.sample(vrng, val_stage) for _ in range(cfg.data.val_pairs)]

    def _resume(self, path: Path) -> None:
        """Continue from a trainer state (last.pt) or, warm-starting with a fresh optimizer,
        from an engine checkpoint (best.pt / shipped weights)."""
        state = torch.load(path, map_location=self.device, weights_only=True)
        self.model.load_state_dict(state["state_dict"])
        if "optimizer" in state:
            self.opt.load_state_dict(state["optimizer"])
            self.step = int(state["step"])
            self.elapsed = float(state["elapsed"])
            self.best = float(state["best"])
        else:
            # Warm start: the validation set may differ from the one the checkpoint was chosen
            # on, so the best score starts afresh.
            meta = state.get("metadata", {})
            self.step = int(meta.get("step", 0))
            self.elapsed = 60.0 * float(meta.get("elapsed_minutes", 0.0))

    def _save_last(self) -> None:
        if self.rank != 0:
            return
        self.out.mkdir(parents=True, exist_ok=True)
        state = {"format": 1, "model_config": self.cfg.model.to_dict(), "state_dict": self.model.state_dict(),
                 "optimizer": self.opt.state_dict(), "step": self.step, "elapsed": self.elapsed,
                 "best": self.best}
        tmp = self.out / "last.pt.tmp"
        torch.save(state, tmp)
        tmp.replace(self.out / "last.pt")

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Median / mean rotation error (deg), recall at 5 deg and mean match accuracy."""
        self.model.eval()
        errs, terrs, accs = [], [], []
        for b in self.val_batches:
            out, bb = _forward(self.model, b, self.device)
            _, parts = cegc_loss(out, bb["src"], bb["tgt"], bb["R"], bb["t"], self.cfg.loss,
                                 self.cfg.model.match_temperature)
            errs.append(float(rotation_error_deg(bb["R"][0].cpu().double().numpy(), out.R[0].cpu().double().numpy())))
            terrs.append(float((out.t[0] - bb["t"][0]).norm()))
            accs.append(parts["match_acc"])
        self.model.train()
        e = np.array(errs)
        return {"val_rre_median": float(np.median(e)), "val_rre_mean": float(e.mean()),
                "val_recall5": float((e < 5).mean()), "val_rte_mean": float(np.mean(terrs)),
                "val_match_acc": float(np.mean(accs))}

    def run(self) -> dict[str, float]:
        cfg = self.cfg.train
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "config.json").write_text(json.dumps(self.cfg.to_dict(), indent=2))
        log_path = self.out / "metrics.csv"
        fields = ["step", "elapsed_min", "points", "max_angle", "loss", "l_overlap", "l_pose", "l_corr",
                  "l_conf", "match_acc", "inlier_frac", "overlap_acc", "val_rre_median", "val_rre_mean",
                  "val_recall5", "val_rte_mean", "val_match_acc"]
        new_log = not log_path.exists()
        logf = open(log_path, "a", newline="", encoding="utf-8")
        writer = csv.DictWriter(logf, fieldnames=fields, extrasaction="ignore")
        if new_log:
            writer.writeheader()
        bar = None
        if self.progress and self.rank == 0:
            from tqdm import tqdm
            bar = tqdm(total=int(cfg.max_minutes * 60), initial=int(min(self.elapsed, cfg.max_minutes * 60)),
                       unit="s", desc="train")
        stream = PairStream(self.sampler, cfg, self.rank, self.step)
        if cfg.workers > 0:
            batches = iter(torch.utils.data.DataLoader(stream, batch_size=None, num_workers=cfg.workers,
                                                       prefetch_factor=4))
        else:
            batches = iter(stream)
        self.model.train()
        last_ckpt = time.perf_counter()
        t_prev = time.perf_counter()
        acc: dict[str, list[float]] = {}
        val: dict[str, float] = {}
        while self.step < cfg.max_steps and self.elapsed < cfg.max_minutes * 60:
            stage = _stage(cfg, self.step)
            b = next(batches)
            with torch.autocast(device_type=self.device.split(":")[0], dtype=torch.bfloat16, enabled=cfg.bf16):
                out, bb = _forward(self.net, b, self.device)
            loss, parts = cegc_loss(out, bb["src"], bb["tgt"], bb["R"], bb["t"], self.cfg.loss,
                                    self.cfg.model.match_temperature)
            self.opt.zero_grad(set_to_none=True)
            if torch.isfinite(loss):
                loss.backward()
                torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.grad_clip)
                self.opt.step()
            self.step += 1
            now = time.perf_counter()
            self.elapsed += now - t_prev
            if bar is not None:
                bar.n = int(min(self.elapsed, cfg.max_minutes * 60))
                bar.set_postfix(step=self.step, loss=f"{parts['loss']:.3f}", acc=f"{parts['match_acc']:.2f}")
            t_prev = now
            for k, v in parts.items():
                acc.setdefault(k, []).append(v)
            is_val = self.step % cfg.val_every == 0
            if is_val:
                val = self.validate()
                t_prev = time.perf_counter()
                score = val["val_rre_mean"]
                if score < self.best:
                    self.best = score
                    if self.rank == 0:
                        save_checkpoint(self.out / "best.pt", self.model, self.metadata(val))
            if self.step % cfg.log_every == 0 or is_val:
                row = {k: float(np.mean(v)) for k, v in acc.items()}
                row.update(step=self.step, elapsed_min=self.elapsed / 60, points=stage.points,
                           max_angle=stage.max_angle_deg)
                if is_val:
                    row.update(val)
                if self.rank == 0:
                    writer.writerow(row)
                    logf.flush()
                acc = {}
            if now - last_ckpt > cfg.checkpoint_minutes * 60:
                self._save_last()
                last_ckpt = time.perf_counter()
        self._save_last()
        if bar is not None:
            bar.close()
        logf.close()
        return val

    def metadata(self, val: dict[str, float]) -> dict[str, Any]:
        import platform
        return {"step": self.step, "elapsed_minutes": round(self.elapsed / 60, 2),
                "pairs_seen": self.step, "device": self.device, "machine": platform.processor() or platform.machine(),
                "torch": str(torch.__version__), "data": "synthetic 7scenes-protocol pairs from procedural rooms",
                "train_config": self.cfg.to_dict(), "validation": val,
                "saved": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
