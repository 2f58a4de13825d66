"""Two training logs compared step by step: which arm learns faster on the same pairs.

    python -m cegc_ros.tools.compare_logs runs/views_orank_anneal/metrics.csv \
        docs/training/campaign_2026-12-06b/arm14_metrics.csv [--steps 10200:16500]

cegc-train draws its pairs by step (``training.PairStream``), so two arms with the same data
settings and the same pair cache contents (the trainer indexes the cache when it starts: an arm
started while the cache was still growing drew other pairs until it was restarted) see the same
pair at the same step, and the figures each logged step reports for its
one pair (match accuracy, the learned candidates' recall, the losses) differ between the arms by
what the arms change, not by which pairs they drew. The mean difference over the steps both
logs hold, with its standard error, then separates changes of a few thousandths that the
per-step spread (match accuracy 0.01-0.6 from one pair to the next) hides in either curve. It
compares what the arms do on training pairs: it picks which arm to pursue, never which weights
ship (that is select_weights on validation rooms, docs/training.md).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from dataclasses import dataclass
from pathlib import Path

#: Columns compared by default: the per-pair figures every candidate-objective log has.
COLUMNS = ("match_acc", "cand_recall", "top100_precision", "overlap_acc", "l_desc", "l_inlier",
           "l_overlap")


class LogError(ValueError):
    """A log that cannot be compared: missing, without the column, or no step in common."""


@dataclass
class Difference:
    column: str
    steps: int          # logged steps both runs hold (within the range) with the column filled
    mean_a: float
    mean_b: float
    diff: float         # mean of a - b over those steps
    se: float           # its standard error (sample std / sqrt(steps)); nan for one step


def read_log(path: str | Path) -> dict[int, dict[str, str]]:
    """A metrics.csv -> {step: row}."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            return {int(r["step"]): r for r in csv.DictReader(f) if r.get("step")}
    except OSError as err:
        raise LogError(f"cannot read {path}: {err.strerror}") from None
    except (KeyError, ValueError):
        raise LogError(f"{path} is not a cegc-train metrics.csv (no integer 'step' column)") from None


def paired(a: dict[int, dict[str, str]], b: dict[int, dict[str, str]], columns: tuple[str, ...],
           lo: int = 0, hi: int | None = None) -> list[Difference]:
    """Mean a - b of each column over the steps in [lo, hi) that both logs hold with it filled."""
    out = []
    for col in columns:
        steps = [s for s in sorted(a.keys() & b.keys()) if lo <= s and (hi is None or s < hi)
                 and a[s].get(col) and b[s].get(col)]
        if not steps:
            raise LogError(f"no step in [{lo}, {'end' if hi is None else hi}) where both logs have {col!r}")
        try:
            xa = [float(a[s][col]) for s in steps]
            xb = [float(b[s][col]) for s in steps]
        except ValueError:
            raise LogError(f"column {col!r} holds a value that is not a number") from None
        d = [x - y for x, y in zip(xa, xb)]
        n = len(d)
        mean = sum(d) / n
        se = math.sqrt(sum((x - mean) ** 2 for x in d) / (n - 1) / n) if n > 1 else math.nan
        out.append(Difference(col, n, sum(xa) / n, sum(xb) / n, mean, se))
    return out


def _range(text: str) -> tuple[int, int | None]:
    lo, _, hi = text.partition(":")
    try:
        return int(lo or 0), (int(hi) if hi else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--steps wants LO:HI (integers, either may be empty), got {text!r}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="compare_logs", description=__doc__.split("\n\n")[0])
    ap.add_argument("a", help="metrics.csv of arm A")
    ap.add_argument("b", help="metrics.csv of arm B (the reference)")
    ap.add_argument("--steps", type=_range, default=(0, None), help="LO:HI, the steps compared (default all)")
    ap.add_argument("--columns", default=",".join(COLUMNS), help="comma-separated log columns")
    args = ap.parse_args(argv)
    try:
        rows = paired(read_log(args.a), read_log(args.b), tuple(c for c in args.columns.split(",") if c),
                      *args.steps)
    except LogError as err:
        print(f"compare_logs: {err}", file=sys.stderr)
        return 1
    print(f"A = {args.a}\nB = {args.b}\n{rows[0].steps} common steps (first column)")
    print(f"{'column':18s} {'A - B':>9s} {'(se)':>9s} {'A':>8s} {'B':>8s} steps")
    for r in rows:
        print(f"{r.column:18s} {r.diff:+9.4f} ({r.se:7.4f}) {r.mean_a:8.3f} {r.mean_b:8.3f} {r.steps}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
