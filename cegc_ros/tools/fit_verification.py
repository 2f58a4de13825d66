"""Fit the learned verification (cegc_ros/verification.py) on generated training pairs.

    python -m cegc_ros.tools.fit_verification .cache/pairs/train_v --pairs 1000 \
        --out cegc_ros/weights/verification.json

The engine (the shipped weights or ``--checkpoint``, node defaults but
``engine.verify_score: features``) registers
``--pairs`` evenly spaced Kinect different-view pairs of a pair cache, ``--low-share`` of them
under 30% overlap (where the choice matters), at one sampling seed. For every hypothesis its
verification ranked it records the evidence of :data:`cegc_ros.verification.FEATURES`, the
free-space violations and whether it is right (15 deg / 0.3 m before ICP), then fits the
conditional logit (:func:`cegc_ros.verification.fit`) and writes the model with how it was made.
Prints one line: evaluations, those with a right hypothesis, and how often count x agreement x
exp(-engine.free_space x violations) and the fitted score choose a right one on these pairs
(the fit's own data: choose on validation pairs, ``select_weights --set
engine.verify_score=learned``). Training pairs only: never the validation or real pairs.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import sys
from pathlib import Path
from collections.abc import Iterator
from typing import Any

import numpy as np


def training_pairs(cache_dir: Path, n: int, low_share: float) -> Iterator[Any]:
    """``n`` Kinect different-view pairs of a pair cache, ``low_share`` of them under 30% overlap,
    each part evenly spread over the cache, read one at a time (memory stays one pair's);
    ValueError when it holds none."""
    from cegc_ros.data.pair_cache import PairCache
    cache = PairCache(cache_dir, kinds=("views",), sensors=("kinect",))
    if len(cache) == 0:
        raise ValueError(f"{cache_dir}: no kinect different-view pairs")
    picked = []
    for part, k in ((cache.overlaps < 0.3, round(n * low_share)), (cache.overlaps >= 0.3, n - round(n * low_share))):
        idx = np.flatnonzero(part)
        if len(idx) and k > 0:
            picked += idx[np.linspace(0, len(idx) - 1, min(k, len(idx))).astype(int)].tolist()
    return (cache[int(i)] for i in picked)


def evidence(registrar: Any, pair: Any) -> dict[str, np.ndarray]:
    """Register one pair; the evidence of each hypothesis its verification ranked -> x (H, F),
    violations (H,), right (H,) bool (H = 0 when none was ranked)."""
    from cegc_ros import second_draw, verification
    from cegc_ros.metrics import within
    from cegc_ros.visibility import FreeSpace
    m = registrar.match_pair(pair.source, pair.target)
    res = registrar.finish(m)
    H = res.hypotheses
    if len(H) == 0:
        return {"x": np.zeros((0, len(verification.FEATURES))), "violations": np.zeros(0), "right": np.zeros(0, bool)}
    return {"x": second_draw.pose_features(H, registrar.draw_evidence(m, res.inlier_distance)),
            "violations": FreeSpace(m.bounded.source, m.bounded.target).violations(H[:, :3, :3], H[:, :3, 3]),
            "right": np.array([within(pair.T_target_source, T) for T in H], bool)}


def chosen_right(score: np.ndarray, group: np.ndarray, right: np.ndarray) -> int:
    """How many groups' best-scored hypothesis is right."""
    order = np.lexsort((score, group))
    last = np.r_[group[order][1:] != group[order][:-1], True]
    return int(right[order[last]].sum())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="fit_verification", description=__doc__.splitlines()[0])
    ap.add_argument("cache", type=Path, help="a training pair cache (cegc-make-pairs --split train)")
    ap.add_argument("--pairs", type=int, default=1000)
    ap.add_argument("--low-share", type=float, default=0.7, metavar="X",
                    help="share of the pairs under 30%% overlap (default 0.7)")
    ap.add_argument("--checkpoint", default="", help="the network's weights (default: the shipped ones)")
    ap.add_argument("--seed", type=int, default=0, help="preprocess.seed of the registrations")
    ap.add_argument("--l2", type=float, default=1e-3, help="L2 penalty on the standardised weights")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    try:
        from cegc_ros import verification
        from cegc_ros.config import EngineConfig, PreprocessConfig
        from cegc_ros.data.pair_cache import PairCacheError
        from cegc_ros.engine import CheckpointError, Registrar
        if not 0.0 <= args.low_share <= 1.0 or args.pairs < 1:
            raise ValueError("--pairs must be >= 1 and --low-share in [0, 1]")
        eng = EngineConfig(verify_score="features")
        registrar = Registrar.from_checkpoint(args.checkpoint or None, device="cpu", engine=eng,
                                              preprocess=PreprocessConfig(seed=args.seed))
        parts = [evidence(registrar, p) for p in training_pairs(args.cache, args.pairs, args.low_share)]
        if not parts:
            raise ValueError(f"{args.cache}: no pairs on the side of 30% overlap that --low-share "
                             f"{args.low_share:g} asks for")
        x = np.concatenate([p["x"] for p in parts])
        v = np.concatenate([p["violations"] for p in parts])
        right = np.concatenate([p["right"] for p in parts])
        group = np.repeat(np.arange(len(parts)), [len(p["right"]) for p in parts])
        weights, free = verification.fit(x, v, group, right, args.l2)
        model = verification.VerificationModel(weights, free)
        # the score it replaces, count x agreement x exp(-engine.free_space x v), as a model
        plain = verification.VerificationModel({f: float(f in ("log_count", "log_agreement"))
                                                for f in verification.FEATURES}, eng.free_space)
        n_right = int((np.bincount(group, right, len(parts)) > 0).sum())
        stats = {"evaluations": len(parts), "with_a_right_hypothesis": n_right,
                 "chosen_right_before": chosen_right(plain.log_scores(x, v), group, right),
                 "chosen_right_fitted": chosen_right(model.log_scores(x, v), group, right)}
        model = dataclasses.replace(model, meta={
            "fitted": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "cache": str(args.cache), "pairs": len(parts), "low_share": args.low_share, "seed": args.seed,
            "l2": args.l2, "weights": Path(registrar.checkpoint_path).name, **stats,
            "command": "python -m cegc_ros.tools.fit_verification " + " ".join(sys.argv[1:] if argv is None else argv)})
        args.out.parent.mkdir(parents=True, exist_ok=True)
        model.save(args.out)
        print(f"fit_verification: {len(parts)} evaluations, {n_right} with a right hypothesis; chosen right: "
              f"{stats['chosen_right_before']} by count x agreement x free space, {stats['chosen_right_fitted']} "
              f"fitted; wrote {args.out}", flush=True)
    except (OSError, ValueError, PairCacheError, CheckpointError) as err:
        print(f"fit_verification: {err}".splitlines()[0], file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
