"""Benchmark: seconds per training step (forward + backward + RAdam step), fp32 against bf16 autocast.

    python -m cegc_ros.tools.bench_train [--points 256,384] [--steps 20] [--threads 0]
    python -m cegc_ros.tools.bench_train --loop CONFIG [--workers 0,1] [--steps 150]

Batch 1 on the same synthetic 7Scenes-protocol training pairs for every setting, the default
``ModelConfig`` and ``LossConfig`` (what ``cegc-train`` runs). Pair preparation (normals, FPFH)
happens before the clock starts. Prints one JSON line per (points, precision) and a markdown table.

``--loop`` measures the whole training loop instead (pair preparation included) of a training
config, once per DataLoader worker count (``train.workers``): steps per second over ``--steps``
steps after the trainer is built, no validation, into a temporary folder; the fragments come
from the config's cache (rendered there first when missing).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time


def measure(points: int, bf16: bool, steps: int, pairs: list) -> dict:
    import numpy as np
    import torch

    from cegc_ros.model import CEGC, ModelConfig
    from cegc_ros.model.losses import LossConfig, cegc_loss
    from cegc_ros.training import PairSampler

    torch.manual_seed(0)
    cfg = ModelConfig()
    model = CEGC(cfg)
    model.train()
    opt = torch.optim.RAdam(model.parameters(), lr=1e-3)
    from types import SimpleNamespace
    sampler = PairSampler([SimpleNamespace(scene_seed=0)], 0.0, cfg.features())   # to_tensors only
    rng = np.random.default_rng(0)
    batches = [sampler.to_tensors(p.source, p.target, p.T_target_source, points, rng) for p in pairs]
    times = []
    for i in range(steps + 2):                                        # 2 warm-up steps
        b = batches[i % len(batches)]
        t0 = time.perf_counter()
        with torch.autocast(device_type="cpu", dtype=torch.bfloat16, enabled=bf16):
            out = model(b["src"], b["tgt"], b["src_n"], b["tgt_n"], b["src_d"], b["tgt_d"])
        loss, _ = cegc_loss(out, b["src"], b["tgt"], b["R"], b["t"], LossConfig(), cfg.match_temperature)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if i >= 2:
            times.append(time.perf_counter() - t0)
    return {"points": points, "precision": "bf16 autocast" if bf16 else "fp32",
            "median_s": round(float(np.median(times)), 3), "p90_s": round(float(np.percentile(times, 90)), 3)}


def measure_loop(config: str, workers: int, steps: int) -> dict:
    import tempfile

    from cegc_ros.training import Config, Trainer

    cfg = Config.from_yaml(config)
    with tempfile.TemporaryDirectory() as tmp:
        cfg.train.out_dir, cfg.train.workers = tmp, workers
        cfg.train.max_steps, cfg.train.val_every = steps, 10**9
        cfg.train.max_minutes, cfg.data.val_pairs = 10**6, 1
        trainer = Trainer(cfg, progress=False)
        t0 = time.perf_counter()
        trainer.run()
        wall = time.perf_counter() - t0
    return {"config": config, "workers": workers, "steps": steps, "steps_per_s": round(steps / wall, 2),
            "s_per_step": round(wall / steps, 3)}


def _ints(flag: str, text: str, minimum: int) -> list[int] | None:
    """Comma-separated integers >= minimum, or None after a one-line error on stderr."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or min(values) < minimum:
        print(f"bench_train: {flag} takes comma-separated integers >= {minimum}, got {text!r}", file=sys.stderr)
        return None
    return values


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench_train", description=__doc__.splitlines()[0])
    ap.add_argument("--points", default="256,384")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch default)")
    ap.add_argument("--loop", metavar="CONFIG", help="time the whole training loop of this config instead")
    ap.add_argument("--workers", default="0,1", help="--loop: DataLoader worker counts to compare")
    args = ap.parse_args(argv)
    if args.steps < 1:
        print(f"bench_train: --steps must be >= 1, got {args.steps}", file=sys.stderr)
        return 2
    if args.loop:
        counts = _ints("--workers", args.workers, 0)
        if counts is None:
            return 2
        import torch
        print(f"machine: {platform.machine()}, {torch.get_num_threads()} torch threads, torch {torch.__version__}")
        rows = [measure_loop(args.loop, w, args.steps) for w in counts]
        for r in rows:
            print(json.dumps(r), flush=True)
        print("| workers | steps/s | s/step |\n|---|---|---|")
        for r in rows:
            print(f"| {r['workers']} | {r['steps_per_s']} | {r['s_per_step']} |")
        return 0
    points = _ints("--points", args.points, 16)
    if points is None:
        return 2
    import torch

    from cegc_ros.data.protocols import make_pair
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    pairs = [make_pair("7scenes", "train", i) for i in range(4)]
    print(f"machine: {platform.machine()}, {torch.get_num_threads()} torch threads, torch {torch.__version__}")
    rows = []
    for n in points:
        for bf16 in (False, True):
            row = measure(n, bf16, args.steps, pairs)
            print(json.dumps(row), flush=True)
            rows.append(row)
    print("| points | precision | median s/step | p90 s/step |\n|---|---|---|---|")
    for r in rows:
        print(f"| {r['points']} | {r['precision']} | {r['median_s']} | {r['p90_s']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
