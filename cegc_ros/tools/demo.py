"""cegc-demo: the node on a small synthetic bag over DDS, with the Open3D baselines beside it.

    cegc-demo [--pairs 10] [--cache .cache/demo] [--methods cegc,cegc+icp,icp,fgr,ransac]

1. writes a deterministic 7Scenes-protocol test bag (``--pairs`` pairs, seed 0) into the cache,
   unless it is there already;
2. starts ``register_node`` with ``params/register_node.yaml`` as a subprocess (DDS on
   localhost, a ROS domain of its own) and replays the bag into it in lockstep;
3. runs the Open3D baselines offline on the same pairs and prints the table; the full report
   (report.md, metrics.json, pairs.csv, errors.png) goes to ``<cache>/report``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

DEMO_PROTOCOL = "7scenes"
DEMO_SPLIT = "test"
DEMO_SEED = 0


def demo_bag(cache: Path, pairs: int, progress: bool = True) -> Path:
    """The demo bag in ``cache`` (written once; see cegc_ros.tools.evaluate.cached_bag)."""
    from cegc_ros.tools.evaluate import cached_bag

    return cached_bag(cache, DEMO_PROTOCOL, DEMO_SPLIT, pairs, DEMO_SEED, progress)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cegc-demo", description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=10, help="pairs in the demo bag (default 10)")
    p.add_argument("--cache", type=Path, default=Path(".cache/demo"),
                   help="where the bag and the report go (default .cache/demo)")
    p.add_argument("--methods", default="cegc,cegc+icp,icp,fgr,ransac",
                   help="methods; cegc and cegc+icp run in register_node (default "
                        "cegc,cegc+icp,icp,fgr,ransac; cegc+icp is the node default)")
    p.add_argument("--params", type=Path, default=None,
                   help="register_node parameter file (default params/register_node.yaml)")
    p.add_argument("--checkpoint", default=None, help="CEGC checkpoint (default: shipped weights)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not 1 <= args.pairs <= 1000:
        print(f"cegc-demo: error: --pairs must be in 1..1000, got {args.pairs}", file=sys.stderr)
        return 2
    from cegc_ros.tools import evaluate as E

    progress = not args.no_progress
    t0 = time.monotonic()
    try:
        methods = E.parse_methods(args.methods)
        node_methods = [m for m in methods if m in E.CEGC_METHODS]
        if node_methods:
            _check_weights(args.checkpoint, args.params)
        bag = demo_bag(args.cache, args.pairs, progress)
        pairs = E.bag_pairs(bag)
        node = (E.run_through_node(bag, pairs, node_methods, params_file=args.params,
                                   checkpoint=args.checkpoint, progress=progress,
                                   log_dir=args.cache / "logs") if node_methods else {})
        ev = E.evaluate(pairs, methods, node_outcomes=node, progress=progress,
                        title=f"cegc-demo: {bag.name}",
                        settings={"source": f"bag {bag}",
                                  "command": "cegc-demo " + " ".join(argv or sys.argv[1:])},
                        params_file=args.params, checkpoint=args.checkpoint)
        paths = E.write_outputs(ev, args.cache / "report")
    except Exception as err:  # noqa: BLE001 - CLI boundary: one line, non-zero exit
        print(f"cegc-demo: error: {_one_line(err)}", file=sys.stderr)
        return 1
    print(f"\n{len(pairs)} pairs of {bag} ({time.monotonic() - t0:.0f} s); "
          f"{', '.join(node_methods) or 'no CEGC method'} ran in register_node over DDS, "
          f"baselines offline on the same pairs.\n")
    print(E.table_markdown(ev.summaries))
    print(f"\nrecall: {ev.thresholds.describe()}; full report: {paths['report']}")
    return 0


def _check_weights(checkpoint: str | None, params: Path | None) -> None:
    """Fail early, in one line, when the node would have no weights to load."""
    from cegc_ros.engine import DEFAULT_WEIGHTS
    from cegc_ros.tools.evaluate import EvalError, engine_configs

    _, eng = engine_configs(params)
    path = Path(checkpoint or eng.checkpoint or DEFAULT_WEIGHTS)
    if not path.is_file():
        raise EvalError(f"no CEGC weights at {path}: pass --checkpoint PATH, or run only the "
                        f"baselines with --methods icp,fgr,ransac")


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}".rstrip(": ")


if __name__ == "__main__":
    raise SystemExit(main())
