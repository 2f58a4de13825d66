"""Learning curve of a training run: engine recall of each snapshot against pairs seen.

    python -m cegc_ros.tools.learning_curve runs/views/snapshots --bag .cache/bags/views_test_100 \
        --real-dir ../shared/data/real/sun3d --every 2 --out docs/training
    python -m cegc_ros.tools.learning_curve runs/views_low/snapshots --val-cache .cache/pairs/val_big \
        --val-pairs 336 --max-overlap 0.3 --seed 38 --every 7 --out runs/curve_low

Each snapshot (``snapshots/step_*.pt``, written by cegc-train at every validation) runs the
engine at node defaults on the same pairs: a synthetic different-view test bag (rooms never
trained on, ``--bag``), the low-overlap pairs of a validation pair cache (``--val-cache``: the
Kinect different-view pairs under ``--max-overlap``, spread over the cache as select_weights
takes them, at sampling seed ``--seed``), or both; and, when given, real pairs (``--real-dir``,
a report, never used to choose). Recall at 15 deg / 0.3 m. Writes ``learning_curve.csv`` (one
row per snapshot: step, pairs seen, the training run's own validation recall, recall per set)
and ``learning_curve.png``. Snapshots already in the CSV are not evaluated again, so the command
can follow a running campaign.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import sys
from pathlib import Path

import numpy as np

FIELDS = ["step", "pairs_seen", "val_recall", "test_recall", "test_pairs", "low_recall", "low_pairs",
          "real_recall", "real_pairs"]


def recall(registrar, pairs) -> float:
    """Share of pairs registered within 15 deg / 0.3 m (valid results only)."""
    from cegc_ros.metrics import within
    ok = 0
    for p in pairs:
        res = registrar.register(p.source, p.target)
        ok += bool(res.valid and within(p.T_gt, res.T_target_source))
    return ok / max(1, len(pairs))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="learning_curve", description=__doc__.splitlines()[0])
    ap.add_argument("snapshots", type=Path, help="a run's snapshots/ folder")
    ap.add_argument("--bag", type=Path, default=None, help="synthetic different-view test bag")
    ap.add_argument("--val-cache", type=Path, default=None,
                    help="a validation pair cache (cegc-make-pairs --split val): its low-overlap pairs")
    ap.add_argument("--val-pairs", type=int, default=200, help="at most this many of them (default 200)")
    ap.add_argument("--max-overlap", type=float, default=0.3, metavar="X",
                    help="--val-cache: the pairs under this overlap (default 0.3)")
    ap.add_argument("--seed", type=int, default=0, help="--val-cache: the engine's sampling seed (default 0)")
    ap.add_argument("--real-dir", type=Path, default=None, help="real pairs (pairs.tsv + gt/), report only")
    ap.add_argument("--every", type=int, default=1, help="evaluate every n-th snapshot (the last always)")
    ap.add_argument("--out", type=Path, default=Path("runs/learning_curve"))
    args = ap.parse_args(argv)
    if args.bag is None and args.val_cache is None:
        ap.error("give --bag, --val-cache or both")
    try:
        from cegc_ros.data.pair_cache import PairCacheError
        from cegc_ros.engine import Registrar
        from cegc_ros.evaluation.datasets import bag_pairs, real_pairs
        from cegc_ros.tools.select_weights import evaluate, validation_pairs
        snaps = sorted(args.snapshots.glob("step_*.pt"))
        if not snaps:
            raise ValueError(f"no step_*.pt snapshots in {args.snapshots}")
        chosen = snaps[::max(1, args.every)]
        if chosen[-1] != snaps[-1]:
            chosen.append(snaps[-1])
        test = bag_pairs(args.bag) if args.bag else []
        low = (validation_pairs(args.val_cache, args.val_pairs, "kinect", args.max_overlap)[0]
               if args.val_cache else [])
        real = real_pairs(args.real_dir) if args.real_dir else []
        args.out.mkdir(parents=True, exist_ok=True)
        path = args.out / "learning_curve.csv"
        rows = list(csv.DictReader(path.open())) if path.exists() else []
        done = {int(r["step"]) for r in rows}
        for snap in chosen:
            reg = Registrar.from_checkpoint(snap, device="cpu")
            step = int(reg.metadata.get("step", 0))
            if step in done:
                continue
            seen = step + int((reg.metadata.get("warm_start") or {}).get("pairs_seen", 0))
            row = {"step": step, "pairs_seen": seen,
                   "val_recall": reg.metadata.get("validation", {}).get("val_recall", ""),
                   "test_recall": round(recall(reg, test), 4) if test else "", "test_pairs": len(test),
                   "real_recall": round(recall(reg, real), 4) if real else "", "real_pairs": len(real)}
            if low:
                reg.update(preprocess=dataclasses.replace(reg.preprocess, seed=args.seed))
                # select_weights' own scoring (its pairs carry T_target_source, a bag's T_gt)
                row.update(low_recall=round(float(evaluate(reg.register, low)["recall"]), 4),
                           low_pairs=len(low))
            rows.append(row)
            print(f"step {step}: test {row['test_recall']} low-overlap {row.get('low_recall', '')} "
                  f"real {row['real_recall']}", flush=True)
            rows.sort(key=lambda r: int(r["step"]))
            with path.open("w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=FIELDS, restval="")
                w.writeheader()
                w.writerows(rows)
        _plot(rows, args.out / "learning_curve.png")
    except (OSError, ValueError, KeyError, PairCacheError) as err:
        print(f"learning_curve: {err}".splitlines()[0], file=sys.stderr)
        return 1
    return 0


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    x = [int(r["pairs_seen"]) for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for key, label in (("val_recall", "validation (synthetic, selects)"), ("test_recall", "synthetic test bag"),
                       ("low_recall", "low-overlap validation pairs (synthetic, --max-overlap)"),
                       ("real_recall", "real SUN3D pairs (report)")):
        y = [float(r[key]) if r.get(key) not in ("", None) else np.nan for r in rows]
        if not np.isnan(y).all():
            ax.plot(x, y, marker="o", label=label)
    ax.set_xlabel("training pairs seen (warm start included)")
    ax.set_ylabel("recall (15 deg / 0.3 m)")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
