"""Average a training run's snapshots into one checkpoint (stochastic weight averaging).

A run at a constant learning rate (the campaign's warm arms: lr 5e-5) does not settle: its
weights wander about a wide minimum, and the mean of its late snapshots lies nearer that
minimum's middle than any one of them (Izmailov et al. 2018, "Averaging Weights Leads to Wider
Optima and Better Generalization"). The network has LayerNorm and no BatchNorm, so the mean
needs no statistics recomputed. Which snapshots to average is chosen like any checkpoint, on
the validation pairs (docs/training.md, "How a checkpoint is chosen").

    python -m cegc_ros.tools.average_weights runs/views_centre/snapshots --steps 19500:31500 --out W.pt

Every snapshot in the step range (``step_*.pt``, written by cegc-train at each validation) is
read as the engine reads weights (``engine.load_checkpoint``); they must share one model
configuration. The output keeps the last snapshot's metadata (less its validation figures, which
are not the average's) with ``averaged`` added (the snapshots' steps), so the model card can say
what was averaged.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

SNAPSHOT = re.compile(r"step_(\d+)\.pt$")


def snapshots(directory: Path, first: int, last: int) -> list[tuple[int, Path]]:
    """(step, path) of the ``step_*.pt`` files in ``directory`` with first <= step <= last, by
    step; ValueError when there are none."""
    found = sorted((int(m.group(1)), p) for p in directory.glob("step_*.pt")
                   if (m := SNAPSHOT.search(p.name)) and first <= int(m.group(1)) <= last)
    if not found:
        raise ValueError(f"no step_*.pt snapshots with steps {first}-{last} in {directory}")
    return found


def average(paths: list[Path]) -> tuple[Any, dict[str, Any]]:
    """The model whose floating-point weights are the mean of the checkpoints' (any other
    buffers from the first), and the last checkpoint's metadata; ValueError when their model
    configurations differ, CheckpointError when one cannot be read."""
    import torch

    from cegc_ros.engine import load_checkpoint
    model, meta = load_checkpoint(paths[0])
    config = model.cfg.to_dict()
    total = {k: v.double().clone() for k, v in model.state_dict().items() if v.is_floating_point()}
    for path in paths[1:]:
        other, meta = load_checkpoint(path)
        if other.cfg.to_dict() != config:
            raise ValueError(f"{path}: its model configuration differs from {paths[0]}'s")
        for k, v in other.state_dict().items():
            if k in total:
                total[k] += v.double()
    with torch.no_grad():
        model.load_state_dict({k: (total[k] / len(paths)).to(v.dtype) if k in total else v
                               for k, v in model.state_dict().items()})
    return model, meta


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="average_weights", description=__doc__.splitlines()[0])
    ap.add_argument("snapshots", type=Path, help="a run's snapshots folder (OUT_DIR/snapshots)")
    ap.add_argument("--steps", required=True, metavar="FIRST:LAST",
                    help="the range of snapshot steps to average, both included")
    ap.add_argument("--out", type=Path, required=True, help="the averaged checkpoint")
    args = ap.parse_args(argv)
    try:
        from cegc_ros.engine import CheckpointError, save_checkpoint
        try:
            first, last = (int(s) for s in args.steps.split(":"))
        except ValueError:
            raise ValueError(f"--steps {args.steps!r}: expected FIRST:LAST, two step numbers") from None
        found = snapshots(args.snapshots, first, last)
        model, meta = average([p for _, p in found])
        # the last snapshot's own validation figures are not the average's: dropped
        meta = {k: v for k, v in meta.items() if k != "validation"}
        meta["averaged"] = {"snapshots": len(found), "steps": [s for s, _ in found], "folder": str(args.snapshots)}
        save_checkpoint(args.out, model, meta)
        print(f"average_weights: {len(found)} snapshots, steps {found[0][0]}-{found[-1][0]}; wrote {args.out}")
    except (OSError, ValueError, CheckpointError) as err:
        print(f"average_weights: {err}".splitlines()[0], file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
