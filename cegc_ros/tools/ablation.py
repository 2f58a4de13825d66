"""Ablation table: several checkpoints x solvers on the same synthetic and real pairs.

    python -m cegc_ros.tools.ablation --checkpoint "paper@200=runs/ablation_paper/best.pt" \
        --checkpoint "ri@200=runs/ablation_ri/best.pt" [--pairs 20] [--real-dir ../shared/data/real/sun3d]

Synthetic pairs: the 7scenes test split (held-out rooms), indices 100 .. 100 + pairs - 1.
Real pairs: the 7Scenes protocol cut from the real SUN3D fragments (seed 7), evaluation only;
``real`` as cut, ``real_noise`` with the paper's Gaussian noise (sigma 0.01, each cloud) and
``real_resample`` with the target an independent draw (no shared points); ``--sets`` picks.
Prints one JSON line per (checkpoint, solver) and a markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="ablation", description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", action="append", required=True, help="NAME=PATH (repeatable)")
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--solvers", default="svd,robust")
    ap.add_argument("--real-dir", default="../shared/data/real/sun3d")
    ap.add_argument("--sets", default="synthetic,real,real_noise,real_resample",
                    help="comma-separated subset of synthetic,real,real_noise,real_resample")
    args = ap.parse_args(argv)
    try:
        cks = dict(c.split("=", 1) for c in args.checkpoint)
    except ValueError:
        print("ablation: --checkpoint takes NAME=PATH", file=sys.stderr)
        return 2
    import numpy as np

    from cegc_ros.config import EngineConfig
    from cegc_ros.data.protocols import make_pair
    from cegc_ros.engine import CheckpointError, Registrar
    from cegc_ros.metrics import rotation_error_deg
    from cegc_ros.tools.evaluate import real_7scenes_pairs

    wanted = [s.strip() for s in args.sets.split(",") if s.strip()]
    unknown = set(wanted) - {"synthetic", "real", "real_noise", "real_resample"}
    if unknown:
        print(f"ablation: unknown set(s) {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    sets = {}
    if "synthetic" in wanted:
        sets["synthetic"] = [(q.source, q.target, q.T_target_source)
                             for q in (make_pair("7scenes", "test", 100 + i) for i in range(args.pairs))]
    real_kw = {"real": {}, "real_noise": {"noise_sigma": 0.01}, "real_resample": {"resample_target": True}}
    for name, kw in real_kw.items():
        if name in wanted and (Path(args.real_dir) / "pairs.tsv").is_file():
            sets[name] = [(q.source, q.target, q.T_gt) for q in real_7scenes_pairs(args.real_dir, args.pairs, 2048, 7, **kw)]
    rows = []
    for name, path in cks.items():
        for solver in args.solvers.split(","):
            try:
                # Each network alone: no cascade.
                reg = Registrar.from_checkpoint(path, device="cpu",
                                                engine=EngineConfig(solver=solver, second_checkpoint="none"))
            except (CheckpointError, ValueError) as err:
                print(f"ablation: {err}", file=sys.stderr)
                return 1
            row = {"model": name, "solver": solver}
            for sname, pairs in sets.items():
                e = np.array([float(rotation_error_deg(T[:3, :3], reg.register(src, tgt).T_target_source[:3, :3]))
                              for src, tgt, T in pairs])
                row[sname] = {"recall5": float(np.mean(e < 5)), "mean": float(e.mean()), "median": float(np.median(e))}
            print(json.dumps(row), flush=True)
            rows.append(row)
    print("| network | solver | " + " | ".join(f"{s} recall | {s} Error(R) mean / median" for s in sets) + " |")
    print("|---|---|" + "---|---|" * len(sets))
    for r in rows:
        cells = " | ".join(f"{r[s]['recall5']:.2f} | {r[s]['mean']:.1f} / {r[s]['median']:.2f}" for s in sets)
        print(f"| {r['model']} | {r['solver']} | {cells} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
