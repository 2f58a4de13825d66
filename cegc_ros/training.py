"""Training of CEGC on synthetic pairs (never on real data).

One step: draw a pair (mostly two different fragments of one room, 10-90% overlap, with a
curriculum over overlap; a minority of 7Scenes-protocol copies) -> the engine's own
preprocessing (:func:`cegc_ros.bounding.bound_pair`, :func:`cegc_ros.geometry.prepare_pair`,
FPFH candidates of :func:`cegc_ros.matching.fpfh_neighbours`) -> forward -> loss -> RAdam step.

``train.objective`` chooses what is trained:
- ``candidates`` (default): the engine's path, :meth:`CEGC.score_candidates`, with
  :func:`cegc_ros.model.losses.candidate_loss` (candidate inlier classification, descriptor
  InfoNCE, overlap BCE, pose loss);
- ``paper``: the paper's all-pairs forward with :func:`cegc_ros.model.losses.cegc_loss`.
With a ``distill`` section (candidates only) a frozen teacher checkpoint runs on the same pair
and :func:`cegc_ros.model.losses.distill_loss` adds its outputs as targets (a smaller student).
Validation runs the whole engine (cegc_ros/engine.py at its defaults, the model being trained
inside) on held-out synthetic pairs and keeps ``best.pt`` by registration recall.

Resumable: ``last.pt`` holds model, optimizer, step, elapsed time and RNG state; ``best.pt`` is
an engine checkpoint (format, model config, state dict, metadata) of the best validation
score so far. Multi-GPU / multi-node through torch DistributedDataParallel under ``torchrun``.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import math
import os
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .bounding import bound_pair
from .config import EngineConfig, PreprocessConfig
from .engine import Registrar, load_checkpoint, save_checkpoint
from .geometry import frame_viewpoints, prepare_pair
from .matching import fpfh_neighbours
from .metrics import rotation_error_deg
from .model import CEGC, ModelConfig
from .model.losses import (
    CandidateLossConfig,
    DistillConfig,
    LossConfig,
    candidate_loss,
    cegc_loss,
    distill_loss,
)
from .model.hoce import widened_refinement
from .model.narrowing import NarrowingError, narrowed_state

OBJECTIVES = ("candidates", "paper")


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
    min_overlap: float = 0.15    # two-fragment pairs: overlap range drawn from (curriculum)
    max_overlap: float = 1.0
    low_overlap_share: float = 0.0   # share of different-view draws made among the pair cache's
    low_overlap_max: float = 0.3     # pairs of overlap in [min_overlap, low_overlap_max] (0: off)
    # support points per cloud the network's ``points`` are drawn from (0: preprocess.support_points,
    # 1024); a network trained at 1024 points runs with 2048 (the engine's 2 : 1)
    support_points: int = 0


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
    pair_cache: str = ""               # a cegc_ros.data PairCache directory of different-view pairs
    val_pair_cache: str = ""           # its validation split (rooms never trained on)
    # 'sensor': the normals of a cached pair's clouds turned to their sensors, as the engine's
    # preprocess.normals 'sensor' does (PairSampler.viewpoints); 'centroid': to each cloud's centroid
    normals: str = "centroid"


@dataclass
class TrainConfig:
    out_dir: str = "runs/7scenes"
    seed: int = 0
    lr: float = 1e-3
    grad_clip: float = 1.0
    geo_lr: float = 0.0  # the rate of model.geo_embedding's maps (Trainer._param_groups); 0: lr
    max_steps: int = 100000
    max_minutes: float = 60.0
    checkpoint_minutes: float = 5.0
    val_every: int = 250
    log_every: int = 10
    bf16: bool = False   # bf16 autocast where the hardware has it (CUDA, AVX-512-BF16 / AMX CPUs); elsewhere fp32
    threads: int = 0
    workers: int = 0     # DataLoader processes preparing pairs while the network trains (0: in the loop)
    # every this many steps the pair cache takes in the shards written since (a cache rendered
    # while the network trains; PairStream); 0: the shards there were at the start
    refresh_steps: int = 500
    objective: str = "candidates"   # OBJECTIVES
    learned_candidates: int = 3     # as engine.learned_candidates
    fpfh_candidates: int = 2        # as engine.fpfh_candidates
    stages: list[Stage] = field(default_factory=lambda: [
        Stage(600, 15.0, 384), Stage(2000, 30.0, 512, resample_prob=0.3),
        Stage(10**9, 45.0, 512, resample_prob=0.5)])


@dataclass
class Config:
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    candidate_loss: CandidateLossConfig = field(default_factory=CandidateLossConfig)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    distill: DistillConfig = field(default_factory=DistillConfig)

    @classmethod
    def from_yaml(cls, path: str | Path) -> Config:
        import yaml
        with open(path, encoding="utf-8") as f:
            raw = yaml.safe_load(f) or {}
        return cls.from_dict(raw)

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> Config:
        unknown = set(raw) - {"model", "loss", "candidate_loss", "data", "train", "distill"}
        if unknown:
            raise ValueError(f"unknown config sections: {sorted(unknown)}")
        tr = dict(raw.get("train", {}))
        if "stages" in tr:
            tr["stages"] = [Stage(**s) for s in tr["stages"]]
        cfg = cls(ModelConfig.from_dict(raw.get("model", {})), LossConfig(**raw.get("loss", {})),
                  CandidateLossConfig(**raw.get("candidate_loss", {})), DataConfig(**raw.get("data", {})),
                  TrainConfig(**tr), DistillConfig(**raw.get("distill", {})))
        if cfg.train.objective not in OBJECTIVES:
            raise ValueError(f"train.objective must be one of {OBJECTIVES}, got {cfg.train.objective!r}")
        if cfg.distill.teacher and cfg.train.objective != "candidates":
            raise ValueError("distill.teacher needs train.objective candidates (the engine's path)")
        return cfg

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model.to_dict(), "loss": asdict(self.loss),
                "candidate_loss": asdict(self.candidate_loss), "data": asdict(self.data),
                "train": asdict(self.train), "distill": asdict(self.distill)}


class PairSampler:
    """Training / validation pairs, prepared exactly as the engine prepares them, as tensors.

    Pairs come from a :class:`cegc_ros.data.pair_cache.PairCache` of different-view pairs when
    one is given, otherwise from two fragments of one cached room; a share of them (1 -
    ``stage.fragments_prob``) are 7Scenes-protocol copies of one fragment.
    """

    def __init__(self, fragments: list[Any], noise_sigma: float, features: dict[str, Any],
                 pairs: Any = None, preprocess: PreprocessConfig | None = None,
                 candidates: tuple[int, int] = (3, 2), normals: str = "centroid") -> None:
        """``features``: :meth:`ModelConfig.features` of the network being trained; ``pairs``:
        an indexable of different-view pairs (source, target, T_target_source, info);
        ``normals``: :attr:`DataConfig.normals` (:meth:`viewpoints`; ``preprocess.normals`` is
        not read: the sampler knows each pair's frames)."""
        if not fragments and pairs is None:
            raise ValueError("no fragments or pairs to sample from")
        frame_viewpoints(normals)                       # ValueError on an unknown value
        self.normals = normals
        self.fragments = fragments
        self.pairs = pairs
        self.noise_sigma = noise_sigma
        self.features = dict(features)
        self.preprocess = preprocess or PreprocessConfig()
        self.fpfh_k = candidates[1]
        by_scene: dict[int, list[Any]] = {}
        for f in fragments:
            by_scene.setdefault(int(f.scene_seed), []).append(f)
        self.scenes = [v for v in by_scene.values() if len(v) >= 2]
        self._bands: dict[tuple[float, float], np.ndarray] = {}

    def raw(self, rng: np.random.Generator, stage: Stage) -> Any:
        """One pair in metres (source, target, T_target_source, info)."""
        from .data.protocols import sample_7scenes_pair
        if rng.random() < stage.fragments_prob or not self.fragments:
            pair = self._different_views(rng, stage)
            if pair is not None:
                return pair
        frag = self.fragments[rng.integers(len(self.fragments))]
        sigma = self.noise_sigma
        if stage.noise_max > sigma and rng.random() < stage.noise_prob:   # breaks exact point pairs
            sigma = float(rng.uniform(sigma, stage.noise_max))
        return sample_7scenes_pair(frag.points, rng, num_points=2048, keep_ratio=stage.keep_ratio,
                                   max_angle_deg=stage.max_angle_deg, max_translation=0.5,
                                   noise_sigma=sigma, resample_target=bool(rng.random() < stage.resample_prob))

    def sample(self, rng: np.random.Generator, stage: Stage) -> dict[str, torch.Tensor]:
        pair = self.raw(rng, stage)
        return self.to_tensors(pair.source, pair.target, pair.T_target_source, stage.points, rng,
                               stage.support_points, self.viewpoints(pair))

    def viewpoints(self, pair: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Where each cloud's normals are turned (prepare_pair's ``viewpoints``): under
        ``normals`` 'sensor', a cached pair's sensors: a different-view pair's clouds are each in
        its sensor's frame (the origins), a copy pair's target is its source's crop moved by
        T_target_source (its sensor at T's translation); other pairs (7Scenes-protocol copies,
        box-centred) and 'centroid': the centroids."""
        kind = pair.info.get("kind") if self.normals == "sensor" else None
        if kind == "views":
            return np.zeros(3), np.zeros(3)
        if kind == "copy":
            return np.zeros(3), np.asarray(pair.T_target_source, np.float64)[:3, 3].copy()
        return None, None

    def _different_views(self, rng: np.random.Generator, stage: Stage) -> Any:
        """A different-view pair with overlap in [stage.min_overlap, stage.max_overlap], or None."""
        from .data.protocols import sample_fragments_pair
        if self.pairs is not None and stage.low_overlap_share > 0 and rng.random() < stage.low_overlap_share:
            band = self._overlap_band(stage.min_overlap, min(stage.max_overlap, stage.low_overlap_max))
            if len(band):
                return self.pairs[int(band[rng.integers(len(band))])]
        for _ in range(8):
            if self.pairs is not None:
                pair = self.pairs[int(rng.integers(len(self.pairs)))]
            elif self.scenes:
                scene = self.scenes[rng.integers(len(self.scenes))]
                a, b = rng.choice(len(scene), 2, replace=False)
                pair = sample_fragments_pair(scene[a], scene[b])
            else:
                return None
            if stage.min_overlap <= pair.info["overlap"] <= stage.max_overlap:
                return pair
        return None

    def refresh(self) -> int:
        """Index the pair cache's shards written since it was opened or last refreshed (a cache
        that grows while the network trains) -> pairs added; the overlap bands are recomputed
        when any were."""
        added = int(self.pairs.refresh()) if hasattr(self.pairs, "refresh") else 0
        if added:
            self._bands.clear()
        return added

    def _overlap_band(self, lo: float, hi: float) -> np.ndarray:
        """Indices of the pair cache's pairs with overlap in [lo, hi] (computed once per band)."""
        key = (lo, hi)
        if key not in self._bands:
            overlaps = np.asarray(getattr(self.pairs, "overlaps", []), np.float64)
            self._bands[key] = np.flatnonzero((overlaps >= lo) & (overlaps <= hi))
        return self._bands[key]

    def to_tensors(self, source: np.ndarray, target: np.ndarray, T: np.ndarray, points: int,
                   rng: np.random.Generator, support_points: int = 0,
                   viewpoints: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
                   ) -> dict[str, torch.Tensor]:
        """The engine's bound + features stages (cegc_ros/engine.py) with ``points`` network points
        drawn from ``support_points`` (0: preprocess.support_points), normals turned to
        ``viewpoints`` (prepare_pair), then tensors with a batch axis."""
        pre = self.preprocess
        bounded = bound_pair(source, target, pre, Registrar.MIN_POINTS)
        ps, pt, norm = prepare_pair(bounded.source, bounded.target, points, support_points or pre.support_points,
                                    rng, self.features, pre.sampling, viewpoints)
        R, t_n = norm.to_normalised(T)
        extra = fpfh_neighbours(ps.desc, pt.desc, self.fpfh_k)

        def tt(a: np.ndarray, dtype: Any = np.float32) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(a, dtype=dtype)).unsqueeze(0)
        return {"src": tt(ps.points), "tgt": tt(pt.points), "src_n": tt(ps.normals), "tgt_n": tt(pt.normals),
                "src_d": tt(ps.desc), "tgt_d": tt(pt.desc), "R": tt(R), "t": tt(t_n), "extra": tt(extra, np.int64)}


class PairStream(torch.utils.data.IterableDataset):
    """Training pairs from ``start`` on; pair ``step`` comes from a generator seeded by
    (seed, rank, step), so the stream is the same with or without DataLoader workers and
    after a resume. With W workers, worker k prepares steps start + k, start + k + W, ...;
    the DataLoader takes them round-robin, i.e. in step order. ``curriculum_offset``: pairs the
    network saw before this run (a warm start), added to the step to pick the curriculum stage.

    At every multiple of ``cfg.refresh_steps`` the sampler's pair cache takes in the shards
    written since (each worker its own copy, at its first step past the multiple): a cache that
    is still being rendered feeds the run as it grows. The stream is then the same after a
    resume only for a cache that did not grow in between (the pairs a step draws depend on the
    cache's size)."""

    def __init__(self, sampler: PairSampler, cfg: TrainConfig, rank: int, start: int,
                 curriculum_offset: int = 0) -> None:
        super().__init__()
        self.sampler, self.cfg, self.rank, self.start = sampler, cfg, rank, start
        self.offset = int(curriculum_offset)

    def __iter__(self) -> Any:
        info = torch.utils.data.get_worker_info()
        k, w = (info.id, info.num_workers) if info is not None else (0, 1)
        step = self.start + k
        every = self.cfg.refresh_steps
        next_refresh = (step // every + 1) * every if every > 0 else None
        while True:
            if next_refresh is not None and step >= next_refresh:
                self.sampler.refresh()
                next_refresh = (step // every + 1) * every
            rng = np.random.default_rng([self.cfg.seed, self.rank, step])
            yield self.sampler.sample(rng, _stage(self.cfg, step + self.offset))
            step += w


def _worker_ignores_stop(_worker_id: int) -> None:
    """A DataLoader worker leaves SIGTERM and SIGINT to the trainer: ``pkill -f cegc-train`` and
    Ctrl-C reach the workers too, and a worker that died of it would make torch raise in the
    trainer in the middle of its step, before last.pt is saved (test_training). It keeps feeding
    until the trainer, its step finished and saved (:meth:`Trainer._stop_on_signals`), shuts
    the loader down."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def bf16_hardware(device: str, cpuinfo: str = "/proc/cpuinfo", capability: str | None = None) -> bool:
    """Whether bf16 autocast pays on ``device``: CUDA, or a CPU with AVX-512-BF16 or AMX-BF16
    (on an AVX2-only CPU torch emulates bf16 and runs slower than fp32) whose torch runs its
    AVX-512 kernels (``capability``: torch.backends.cpu.get_cpu_capability() by default). With
    ``ATEN_CPU_CAPABILITY=avx2`` on such a CPU, oneDNN's bf16 packing fails ("pack_vnni2 is only
    supported when avx512 is supported"), so training stays fp32 there."""
    if device.startswith("cuda"):
        return True
    try:
        flags = Path(cpuinfo).read_text().split()
    except OSError:
        return False
    if not ("avx512_bf16" in flags or "amx_bf16" in flags):
        return False
    if capability is None:
        import torch
        capability = torch.backends.cpu.get_cpu_capability()
    return capability.upper().startswith("AVX512")


def _stage(cfg: TrainConfig, step: int) -> Stage:
    for s in cfg.stages:
        if step < s.until_step:
            return s
    return cfg.stages[-1]


def _forward(model: torch.nn.Module, b: dict[str, torch.Tensor], device: str, train: TrainConfig) -> Any:
    b = {k: v.to(device) for k, v in b.items()}
    args = (b["src"], b["tgt"], b["src_n"], b["tgt_n"], b["src_d"], b["tgt_d"])
    if train.objective == "paper":
        return model(*args), b
    if isinstance(model, CEGC):
        return model.score_candidates(*args, k_learned=train.learned_candidates, extra=b["extra"]), b
    return model(*args, k_learned=train.learned_candidates, extra=b["extra"]), b


class _CandidatePath(torch.nn.Module):
    """forward() = CEGC.score_candidates, so DistributedDataParallel sees the path being trained."""

    def __init__(self, model: CEGC) -> None:
        super().__init__()
        self.model = model

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        return self.model.score_candidates(*args, **kwargs)


def _loss(cfg: Config, out: Any, b: dict[str, torch.Tensor], ref: Any = None
          ) -> tuple[torch.Tensor, dict[str, float]]:
    """The objective's loss; with ``ref``, the teacher's output on the same pair, plus
    ``distill.weight`` x :func:`distill_loss` against it."""
    if cfg.train.objective == "paper":
        return cegc_loss(out, b["src"], b["tgt"], b["R"], b["t"], cfg.loss, cfg.model.match_temperature)
    loss, parts = candidate_loss(out, b["src"], b["tgt"], b["R"], b["t"], cfg.candidate_loss)
    if ref is not None:
        l_kd, kd = distill_loss(out, ref, cfg.distill.temperature)
        loss = loss + cfg.distill.weight * l_kd
        parts = {**parts, **kd, "loss": float(loss.detach())}
    return loss, parts


def _is_distance_map(name: str) -> bool:
    """Whether a parameter of CEGC is a self-attention block's distance map (``model.geo_embedding``,
    cegc_ros/model/features.py ``AttentionBlock.geo``): the tensors a warm start adds at zero and
    ``train.geo_lr`` trains."""
    return name.startswith("context.self_blocks.") and name.endswith(".geo")


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
        self.net: torch.nn.Module = self.model if cfg.train.objective == "paper" else _CandidatePath(self.model)
        if self.distributed:
            from torch.nn.parallel import DistributedDataParallel
            self.net = DistributedDataParallel(self.net, find_unused_parameters=True)
        self.opt = torch.optim.RAdam(self._param_groups(), lr=cfg.train.lr)
        self.step = 0
        self.elapsed = 0.0
        self.best = math.inf
        self.stopped_by: int | None = None     # the signal that ended run() early, if one did
        self.warm_start: dict[str, Any] = {}
        self.out = Path(cfg.train.out_dir)
        if resume:
            self._resume(Path(resume))
        self.teacher = self._teacher(fresh=not resume) if cfg.distill.teacher else None
        features = cfg.model.features()
        from .data.pair_cache import PairCache
        pairs = PairCache(cfg.data.pair_cache) if cfg.data.pair_cache else None
        val_pairs = PairCache(cfg.data.val_pair_cache) if cfg.data.val_pair_cache else None
        if fragments is None:
            from .data.protocols import FragmentCache
            fragments = FragmentCache(cfg.data.cache_dir, cfg.data.num_scenes, cfg.data.fragments_per_scene,
                                      seed=0).load(progress=progress and self.rank == 0)
            val_fragments = FragmentCache(cfg.data.cache_dir, cfg.data.val_scenes, cfg.data.val_fragments_per_scene,
                                          seed=1).load(progress=progress and self.rank == 0)
        cands = (cfg.train.learned_candidates, cfg.train.fpfh_candidates)
        self.sampler = PairSampler(fragments, cfg.data.noise_sigma, features, pairs, candidates=cands,
                                   normals=cfg.data.normals)
        vs = PairSampler(val_fragments or fragments, 0.0, features, val_pairs, candidates=cands,
                         normals=cfg.data.normals)
        vrng = np.random.default_rng(12345)
        final = cfg.train.stages[-1]
        val_stage = Stage(0, 45.0, cfg.data.val_points, final.keep_ratio, cfg.data.val_resample_prob,
                          fragments_prob=cfg.data.val_fragments_prob, noise_max=cfg.data.val_noise_max,
                          min_overlap=0.1, max_overlap=1.0)
        self.val_pairs = [vs.raw(vrng, val_stage) for _ in range(cfg.data.val_pairs)]
        self.val_batches = [vs.to_tensors(p.source, p.target, p.T_target_source, cfg.data.val_points, vrng,
                                          viewpoints=vs.viewpoints(p))
                            for p in self.val_pairs]

    @property
    def curriculum_offset(self) -> int:
        """Pairs the network saw before this run (0 unless warm-started): the curriculum goes on
        where they left it instead of starting over at its first stage, so a campaign warm-started
        session after session reaches its last (lowest-overlap) stage."""
        return int(self.warm_start.get("pairs_seen", 0))

    def _resume(self, path: Path) -> None:
        """Continue from a trainer state (last.pt) or, warm-starting with a fresh optimizer,
        from an engine checkpoint (best.pt / shipped weights)."""
        state = torch.load(path, map_location=self.device, weights_only=True)
        changes = self._load_weights(state)
        if "optimizer" in state:
            saved, wanted = len(state["optimizer"]["param_groups"]), len(self.opt.param_groups)
            if saved != wanted:
                raise ValueError(f"{path}: its optimiser has {saved} parameter group(s), this config "
                                 f"{wanted} (train.geo_lr sets the distance maps' own): resume it under "
                                 f"the config it was written with, or warm-start a new out_dir from "
                                 f"a snapshot (snapshots/step_*.pt)")
            self.opt.load_state_dict(state["optimizer"])
            for group, ours in zip(self.opt.param_groups, self._param_groups(), strict=True):
                group["lr"] = ours["lr"]            # the config's rates win (an anneal resumes so)
            self.step = int(state["step"])
            self.elapsed = float(state["elapsed"])
            # a best score measured on other validation pairs does not compare
            self.best = float(state["best"]) if state.get("val_key") == self._val_key() else math.inf
            self.warm_start = dict(state.get("warm_start", {}))
        else:
            # Warm start: a new run (its curriculum starts at step 0, the best score afresh, since
            # the validation set may differ); what the checkpoint had seen is kept in the metadata.
            meta = state.get("metadata", {})
            prior = meta.get("warm_start") or {}       # the checkpoint's own warm start, if any
            self.warm_start = {"from": str(path),
                               "pairs_seen": int(meta.get("step", 0)) + int(prior.get("pairs_seen", 0))
                               if prior else int(meta.get("pairs_seen", meta.get("step", 0))),
                               "elapsed_minutes": float(meta.get("elapsed_minutes", 0.0))
                               + float(prior.get("elapsed_minutes", 0.0))}
            self.warm_start.update(changes)

    def _param_groups(self) -> list[dict[str, Any]]:
        """The optimiser's parameter groups: the self-attention's distance maps
        (``model.geo_embedding``) at ``train.geo_lr`` when set, everything else at ``train.lr``.
        Why a rate of their own: warm-started at zero beside trained weights at a fine-tuning rate
        (5e-5), they moved by 0.003 on average in 3000 steps (arm 22's first start) and the run
        stayed the network it started from."""
        named = list(self.model.named_parameters())
        geo = [p for n, p in named if _is_distance_map(n)]
        lr = self.cfg.train.lr
        if not geo or not self.cfg.train.geo_lr:
            return [{"params": [p for _, p in named], "lr": lr}]
        rest = [p for n, p in named if not _is_distance_map(n)]
        return [{"params": rest, "lr": lr}, {"params": geo, "lr": self.cfg.train.geo_lr}]

    def _load_weights(self, state: dict[str, Any]) -> dict[str, int]:
        """Load the checkpoint's weights into the model; returns what a warm start changed
        (``dropped_attention_layers``, ``hoce_topk_widened_from``, ``geo_embedding_added``;
        empty for none).

        A warm start from an engine checkpoint whose network has more (self, cross) attention
        layers than ``model.attn_layers`` keeps its first ones (the blocks are residual, so the
        shortened network starts close to the full one: the shipped weights cut from 2 layers
        to 1 register 0.536 of the 196 validation pairs before any training, against 0.566) and
        fine-tunes from there (issue: fast everywhere, fewer attention layers). One whose HOCE
        reads fewer sorted similarities than ``model.hoce_topk`` is widened with the same outputs
        (:func:`cegc_ros.model.hoce.widened_refinement`; issue 25, the overlap estimate). One
        without ``model.geo_embedding`` gains it with its maps at zero, the same function (issue
        25, arm 22). Any other difference fails as torch's strict load does."""
        theirs = dict(state.get("model_config") or {})
        ours = self.cfg.model.to_dict()
        weights = state["state_dict"]
        if "optimizer" in state:
            self.model.load_state_dict(weights)
            return {}
        changes: dict[str, int] = {}
        old_topk = int(theirs.get("hoce_topk", ours["hoce_topk"]))
        if old_topk < ours["hoce_topk"]:
            weights = widened_refinement(weights, old_topk, ours["hoce_topk"])
            theirs["hoce_topk"] = ours["hoce_topk"]
            changes["hoce_topk_widened_from"] = old_topk
        if int(theirs.get("geo_embedding", 0)) == 0 and ours["geo_embedding"] > 0:
            # the self-attention blocks' distance maps start at zero: the same network as theirs
            weights = {**weights, **{k: torch.zeros_like(v) for k, v in self.model.state_dict().items()
                                     if _is_distance_map(k)}}
            theirs.update(geo_embedding=ours["geo_embedding"], geo_sigma=ours["geo_sigma"])
            changes["geo_embedding_added"] = ours["geo_embedding"]
        extra = int(theirs.get("attn_layers", ours["attn_layers"])) - ours["attn_layers"]
        same_otherwise = {k: v for k, v in theirs.items() if k != "attn_layers"} == \
            {k: v for k, v in ours.items() if k != "attn_layers" and k in theirs}
        if extra <= 0 or not same_otherwise:
            self.model.load_state_dict(weights)
            return changes
        own = self.model.state_dict()
        self.model.load_state_dict({k: v for k, v in weights.items() if k in own}, strict=True)
        return {**changes, "dropped_attention_layers": extra}

    def _teacher(self, fresh: bool) -> CEGC:
        """The frozen teacher of ``distill.teacher``; at a fresh start with
        ``distill.init_from_teacher``, the student starts from the teacher's tensors: cut to
        its widths when it is a narrowing of the teacher (cegc_ros/model/narrowing.py), else
        those whose name and shape it shares. ValueError when the teacher was trained on other input features
        (each pair is prepared once, with the student's)."""
        teacher, _ = load_checkpoint(self.cfg.distill.teacher, self.device)
        if teacher.cfg.features() != self.cfg.model.features() or teacher.cfg.variant != self.cfg.model.variant:
            raise ValueError(f"distill.teacher {self.cfg.distill.teacher}: trained on other input "
                             f"features than model ({teacher.cfg.features()} against "
                             f"{self.cfg.model.features()})")
        teacher.requires_grad_(False).eval()
        if fresh and self.cfg.distill.init_from_teacher:
            own = self.model.state_dict()
            try:        # a narrower student: each tensor cut from the teacher's (model/narrowing.py)
                shared = narrowed_state(teacher.state_dict(), teacher.cfg, own, self.cfg.model)
                how = "narrowed"
            except NarrowingError:      # another design: the tensors of the same name and shape
                shared = {k: v for k, v in teacher.state_dict().items() if k in own and own[k].shape == v.shape}
                how = "same shape"
            self.model.load_state_dict(shared, strict=False)
            self.warm_start = {**self.warm_start, "from_teacher": self.cfg.distill.teacher,
                               "teacher_tensors": len(shared), "teacher_init": how}
        return teacher

    def _val_key(self) -> str:
        """What the validation set is made of: best scores compare only within one key."""
        d = self.cfg.data
        return json.dumps([d.val_pair_cache, d.val_scenes, d.val_fragments_per_scene, d.val_pairs,
                           d.val_fragments_prob, d.val_resample_prob, d.val_noise_max])

    def _save_last(self) -> None:
        if self.rank != 0:
            return
        self.out.mkdir(parents=True, exist_ok=True)
        state = {"format": 1, "model_config": self.cfg.model.to_dict(), "state_dict": self.model.state_dict(),
                 "optimizer": self.opt.state_dict(), "step": self.step, "elapsed": self.elapsed,
                 "best": self.best, "warm_start": self.warm_start, "val_key": self._val_key()}
        tmp = self.out / "last.pt.tmp"
        torch.save(state, tmp)
        tmp.replace(self.out / "last.pt")

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """The whole engine at its defaults (but ``engine.verify_score: features``) with the model
        being trained, on the validation pairs:
        registration recall (15 deg / 0.3 m on different-view pairs in metres, 5 deg on
        7Scenes-protocol copies), mean rotation error, and the training losses' match figures."""
        self.model.eval()
        # verify_score 'features', not the default 'learned': the learned verification's weights
        # were fitted to the shipped network's features and overlap scores, not this one's (and
        # the campaign's curves since the thirteenth session were measured so)
        reg = Registrar(self.model, self.device, "", {}, PreprocessConfig(),
                        EngineConfig(device=self.device, verify_score="features"))
        ok, errs, accs, precs, aucs = [], [], [], [], []
        for pair, b in zip(self.val_pairs, self.val_batches):
            # the engine's normals as the sampler turns this pair's: 'sensor' where both are turned
            # to the frames' origins, else the centroids (the engine has no other viewpoint)
            sensor = all(v is not None and not np.any(v) for v in self.sampler.viewpoints(pair))
            reg.update(preprocess=dataclasses.replace(reg.preprocess, normals="sensor" if sensor else "centroid"))
            res = reg.register(pair.source, pair.target)
            T = pair.T_target_source
            re = float(rotation_error_deg(T[:3, :3], res.T_target_source[:3, :3]))
            te = float(np.linalg.norm(T[:3, 3] - res.T_target_source[:3, 3]))
            views = pair.info.get("protocol") != "7scenes"
            ok.append(res.valid and (re < 15 and te < 0.3 if views else re < 5))
            errs.append(re)
            out, bb = _forward(self.model, b, self.device, self.cfg.train)
            _, parts = _loss(self.cfg, out, bb)
            accs.append(parts["match_acc"])
            precs.append(parts.get("top100_precision", math.nan))
            aucs.append(parts.get("overlap_auc", math.nan))
        self.model.train()
        e = np.array(errs)
        return {"val_recall": float(np.mean(ok)), "val_rre_median": float(np.median(e)),
                "val_rre_mean": float(e.mean()), "val_match_acc": float(np.mean(accs)),
                "val_top100_precision": float(np.mean(precs)),
                "val_overlap_auc": float(np.nanmean(aucs)) if np.isfinite(aucs).any() else math.nan}

    def run(self) -> dict[str, float]:
        cfg = self.cfg.train
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "config.json").write_text(json.dumps(self.cfg.to_dict(), indent=2))
        log_path = self.out / "metrics.csv"
        fields = ["step", "elapsed_min", "points", "max_angle", "min_overlap", "loss", "l_overlap", "l_pose",
                  "l_corr", "l_conf", "l_inlier", "l_desc", "l_row", "l_rank", "l_overlap_rank",
                  "match_acc", "cand_recall", "top100_precision", "inlier_frac", "overlap_acc", "overlap_auc",
                  "l_distill", "val_recall", "val_rre_median", "val_rre_mean", "val_match_acc",
                  "val_top100_precision", "val_overlap_auc"]
        new_log = not log_path.exists()
        if not new_log:     # a resumed run appends under the columns its log was started with
            with open(log_path, newline="", encoding="utf-8") as f:
                fields = next(csv.reader(f), None) or fields
        logf = open(log_path, "a", newline="", encoding="utf-8")
        writer = csv.DictWriter(logf, fieldnames=fields, extrasaction="ignore")
        if new_log:
            writer.writeheader()
        bar = None
        if self.progress and self.rank == 0:
            from tqdm import tqdm
            bar = tqdm(total=int(cfg.max_minutes * 60), initial=int(min(self.elapsed, cfg.max_minutes * 60)),
                       unit="s", desc="train")
        stream = PairStream(self.sampler, cfg, self.rank, self.step, self.curriculum_offset)
        if cfg.workers > 0:
            batches = iter(torch.utils.data.DataLoader(stream, batch_size=None, num_workers=cfg.workers,
                                                       prefetch_factor=4, worker_init_fn=_worker_ignores_stop))
        else:
            batches = iter(stream)
        self.model.train()
        last_ckpt = time.perf_counter()
        t_prev = time.perf_counter()
        acc: dict[str, list[float]] = {}
        val: dict[str, float] = {}
        bf16 = cfg.bf16 and bf16_hardware(self.device)
        if cfg.bf16 and not bf16:
            print("[cegc-train] train.bf16: this CPU has no bf16 hardware (it would run slower than "
                  "fp32, shared/notes/CPU_FACTS.md), training in fp32", flush=True)
        with self._stop_on_signals():
            while (self.step < cfg.max_steps and self.elapsed < cfg.max_minutes * 60
                   and self.stopped_by is None):
                stage = _stage(cfg, self.step + self.curriculum_offset)
                b = next(batches)
                with torch.autocast(device_type=self.device.split(":")[0], dtype=torch.bfloat16, enabled=bf16):
                    out, bb = _forward(self.net, b, self.device, cfg)
                ref = None
                if self.teacher is not None:
                    with torch.no_grad():
                        ref, _ = _forward(self.teacher, bb, self.device, cfg)
                loss, parts = _loss(self.cfg, out, bb, ref)
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
                    # best = highest recall, then lowest mean rotation error (stored negated-recall first)
                    score = -val["val_recall"] * 1000.0 + val["val_rre_mean"]
                    if self.rank == 0:      # every validated state, for the learning curve (tools/learning_curve.py)
                        save_checkpoint(self.out / "snapshots" / f"step_{self.step:07d}.pt", self.model,
                                        self.metadata(val))
                    if score < self.best:
                        self.best = score
                        if self.rank == 0:
                            save_checkpoint(self.out / "best.pt", self.model, self.metadata(val))
                if self.step % cfg.log_every == 0 or is_val:
                    row = {k: float(np.mean(v)) for k, v in acc.items()}
                    row.update(step=self.step, elapsed_min=self.elapsed / 60, points=stage.points,
                               max_angle=stage.max_angle_deg, min_overlap=stage.min_overlap)
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
        if self.stopped_by is not None and self.rank == 0:
            print(f"[cegc-train] stopped by {signal.Signals(self.stopped_by).name} after step "
                  f"{self.step}; {self.out / 'last.pt'} holds it", flush=True)
        return val

    @contextlib.contextmanager
    def _stop_on_signals(self) -> Iterator[None]:
        """SIGTERM or SIGINT (``kill``, Ctrl-C) end the run after the step in progress, with
        last.pt saved at that step, so a resume loses nothing and the log has no step twice
        (without it, the steps since the last periodic checkpoint were lost and logged again).
        Only from the main thread (where Python delivers signals) and not under torchrun (ranks
        that stopped after different steps would wait on each other's gradients); the previous
        handlers are restored on the way out."""
        self.stopped_by = None
        if self.distributed or threading.current_thread() is not threading.main_thread():
            yield
            return

        def stop(signum: int, _frame: Any) -> None:
            self.stopped_by = signum
        previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGTERM, signal.SIGINT)}
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    def metadata(self, val: dict[str, float]) -> dict[str, Any]:
        import platform
        return {"step": self.step, "elapsed_minutes": round(self.elapsed / 60, 2),
                "pairs_seen": self.step + int(self.warm_start.get("pairs_seen", 0)), "device": self.device,
                "machine": platform.processor() or platform.machine(), "torch": str(torch.__version__),
                "data": "synthetic different-view fragment pairs and 7scenes-protocol copies from procedural rooms",
                "train_config": self.cfg.to_dict(), "validation": val, "warm_start": self.warm_start,
                "saved": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
