"""Ablation table: several checkpoints x CEGC rows on the same synthetic and real pairs.

    python -m cegc_ros.tools.ablation --checkpoint "paper@200=runs/ablation_paper/best.pt" \
        --checkpoint "ri@200=runs/ablation_ri/best.pt" [--rows cegc+icp,cegc-uniform,cegc-paper] \
        [--pairs 20] [--real-dir ../shared/data/real/sun3d]

Rows are the CEGC rows of ``cegc-eval`` (cegc_ros/evaluation/methods.py: overrides of the node's
parameter file, e.g. ``cegc-paper`` = the paper's matching and SVD), so a checkpoint is judged
inside the pipeline that ships and inside the paper's. Synthetic pairs: the 7scenes test split
(held-out rooms), indices 100 .. 100 + pairs - 1. Real pairs: the 7Scenes protocol cut from the
real SUN3D fragments (seed 7), evaluation only; ``real`` as cut, ``real_noise`` with the
paper's Gaussian noise (sigma 0.01, each cloud) and ``real_resample`` with the target an
independent draw (no shared points); ``--sets`` picks. Prints one JSON line per
(checkpoint, row) and a markdown table of recall at 5 deg and Error(R) mean / median.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

SETS = ("synthetic", "real", "real_noise", "real_resample")
DEFAULT_ROWS = "cegc+icp,cegc-uniform,cegc-paper"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="ablation", description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", action="append", required=True, help="NAME=PATH (repeatable)")
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--rows", default=DEFAULT_ROWS,
                    help=f"comma-separated CEGC rows of cegc-eval (default {DEFAULT_ROWS})")
    ap.add_argument("--params", default=None, help="node parameter file the rows start from")
    ap.add_argument("--real-dir", default="../shared/data/real/sun3d")
    ap.add_argument("--sets", default=",".join(SETS), help=f"comma-separated subset of {','.join(SETS)}")
    args = ap.parse_args(argv)
    try:
        cks = dict(c.split("=", 1) for c in args.checkpoint)
    except ValueError:
        print("ablation: --checkpoint takes NAME=PATH", file=sys.stderr)
        return 2
    import numpy as np

    from cegc_ros.data.protocols import make_pair
    from cegc_ros.engine import CheckpointError
    from cegc_ros.evaluation import EvalError
    from cegc_ros.evaluation.datasets import real_7scenes_pairs
    from cegc_ros.evaluation.methods import CEGC_METHODS, parse_methods
    from cegc_ros.evaluation.runners import make_runners
    from cegc_ros.metrics import rotation_error_deg

    wanted = [s.strip() for s in args.sets.split(",") if s.strip()]
    unknown = set(wanted) - set(SETS)
    if unknown:
        print(f"ablation: unknown set(s) {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    try:
        rows = parse_methods(args.rows)
    except EvalError as err:
        print(f"ablation: {err}", file=sys.stderr)
        return 2
    if any(r not in CEGC_METHODS for r in rows):
        print(f"ablation: --rows takes CEGC rows only ({', '.join(CEGC_METHODS)})", file=sys.stderr)
        return 2
    sets = {}
    if "synthetic" in wanted:
        sets["synthetic"] = [(q.source, q.target, q.T_target_source)
                             for q in (make_pair("7scenes", "test", 100 + i) for i in range(args.pairs))]
    real_kw = {"real": {}, "real_noise": {"noise_sigma": 0.01}, "real_resample": {"resample_target": True}}
    for name, kw in real_kw.items():
        if name in wanted and (Path(args.real_dir) / "pairs.tsv").is_file():
            sets[name] = [(q.source, q.target, q.T_gt)
                          for q in real_7scenes_pairs(args.real_dir, args.pairs, 2048, 7, **kw)]
    table = []
    for model, path in cks.items():
        try:
            runners = make_runners(rows, checkpoint=path, params_file=args.params)
        except (CheckpointError, EvalError, ValueError) as err:
            print(f"ablation: {err}", file=sys.stderr)
            return 1
        for row_name, run in runners.items():
            row = {"model": model, "row": row_name}
            for sname, pairs in sets.items():
                e = np.array([float(rotation_error_deg(T[:3, :3], np.asarray(run(src, tgt)[0])[:3, :3]))
                              for src, tgt, T in pairs])
                row[sname] = {"recall5": float(np.mean(e < 5)), "mean": float(e.mean()),
                              "median": float(np.median(e))}
            print(json.dumps(row), flush=True)
            table.append(row)
    print("| network | row | " + " | ".join(f"{s} recall | {s} Error(R) mean / median" for s in sets) + " |")
    print("|---|---|" + "---|---|" * len(sets))
    for r in table:
        cells = " | ".join(f"{r[s]['recall5']:.2f} | {r[s]['mean']:.1f} / {r[s]['median']:.2f}" for s in sets)
        print(f"| {r['model']} | {r['row']} | {cells} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
