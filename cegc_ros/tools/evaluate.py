"""cegc-eval: CEGC's ablation rows and the classical peers on the same pairs, the paper's table.

Pairs come from one of three sources:

* a pair bag (``cegc-eval BAG``), as written by ``cegc-make-bag`` or recorded by a user;
* real pairs with ground truth (``--real-dir DIR``, layouts in
  :data:`cegc_ros.evaluation.datasets.REAL_LAYOUTS`: SUN3D fragments, range scans (bunny), one
  LiDAR pair), scored at 15 deg / 0.3 m unless ``--recall-rot/--recall-trans`` say otherwise;
* the 7Scenes protocol applied to those real fragments (``--real-dir DIR --real-protocol
  7scenes``): same-fragment crops, seeded, scored at 5 deg (the real-data proxy of the paper's
  7Scenes benchmark);

or all of the documented sets at once (``--suite``, :mod:`cegc_ros.evaluation.suite`).

Methods (:mod:`cegc_ros.evaluation.methods`): the CEGC rows ``cegc+icp`` (the node's settings),
``cegc``, ``cegc-uniform``, ``cegc-learned-cand``, ``cegc-fpfh-cand``, ``cegc-svd``,
``cegc-paper`` (each an override of the node's parameter file) and the peers ``icp``, ``fgr``,
``ransac``, ``ransac+icp``, ``sc2pcr``, ``sc2pcr+icp`` (:mod:`cegc_ros.baselines`); groups
``default`` (cegc+icp and the peers), ``ablation``, ``peers``, ``all``. With ``--through-node``
the CEGC rows run inside a ``register_node`` subprocess fed by replaying the bag over DDS.
Outputs in ``--out DIR``: ``metrics.json``, ``pairs.csv``, ``report.md``, ``errors.png``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from cegc_ros import metrics
from cegc_ros.evaluation import EvalError, EvalPair, Outcome
from cegc_ros.evaluation.datasets import (
    REAL_LAYOUTS,
    bag_pairs,
    cached_bag,
    real_7scenes_pairs,
    real_fragment_files,
    real_pairs,
)
from cegc_ros.evaluation.methods import (
    ALL_METHODS,
    BASELINE_METHODS,
    CEGC_METHODS,
    GROUPS,
    default_params_file,
    engine_configs,
    parse_methods,
)
from cegc_ros.evaluation.report import Evaluation, table_markdown, write_outputs
from cegc_ros.evaluation.runners import evaluate, make_runners
from cegc_ros.evaluation.suite import PARTS, SuiteSizes, run_suite
from cegc_ros.evaluation.through_node import run_through_node

# The names other tools and tests take from here (cegc-demo, the tests of cegc-eval).
__all__ = [
    "ALL_METHODS", "BASELINE_METHODS", "CEGC_METHODS", "EvalError", "EvalPair", "Evaluation",
    "Outcome", "bag_pairs", "cached_bag", "default_params_file", "engine_configs", "evaluate",
    "main", "make_runners", "metrics", "parse_methods", "real_7scenes_pairs",
    "real_fragment_files", "real_pairs", "run_through_node", "table_markdown", "write_outputs",
]

DEFAULT_REAL_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "sun3d"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="cegc-eval", description="Evaluate CEGC's ablation rows and the classical peers on "
        "the pairs of a bag or on real pairs; writes metrics.json, pairs.csv, report.md, errors.png.")
    p.add_argument("bag", nargs="?", help="pair bag (rosbag2 directory, sqlite3 or mcap)")
    p.add_argument("--real-dir", help="folder of real pairs with ground truth (instead of a bag): "
                                      + REAL_LAYOUTS)
    p.add_argument("--real-protocol", choices=("pairs", "7scenes"), default="pairs",
                   help="with --real-dir: the listed pairs (default) or the 7Scenes protocol on "
                        "their fragments")
    p.add_argument("--num-pairs", type=int, default=60, help="7scenes protocol: pairs (default 60)")
    p.add_argument("--num-points", type=int, default=2048,
                   help="7scenes protocol: points resampled before the 75%% crops (default 2048)")
    p.add_argument("--subsample", type=int, default=None,
                   help="7scenes protocol: thin each cloud independently to this many points")
    p.add_argument("--resample-target", action="store_true",
                   help="7scenes protocol: the target crops an independent draw of the fragment "
                        "(no shared points)")
    p.add_argument("--noise-sigma", type=float, default=0.0,
                   help="7scenes protocol: Gaussian noise (clipped at 5 sigma) added to each cloud "
                        "independently, normalised units; the paper's robustness test uses 0.01")
    p.add_argument("--flying-pixels", type=float, default=0.0, metavar="SHARE",
                   help="any set: move this share of each cloud's points along their rays out "
                        "to 3-12 m from the sensor (depth-edge flying pixels; "
                        "cegc_ros/data/corruption.py), seeded per pair; offline methods only")
    p.add_argument("--seed", type=int, default=0, help="7scenes protocol seed (default 0)")
    p.add_argument("--suite", action="store_true",
                   help="the documented evaluation in one run (cegc_ros/evaluation/suite.py): "
                        "synthetic 7scenes and fragments test bags (generated once into --cache), "
                        "the real pairs of --real-dir, the 7Scenes protocol on their fragments "
                        "(as cut, resampled, noisy), and the bunny and lidar folders next to "
                        "--real-dir; one sub-folder each in --out plus summary.md")
    p.add_argument("--parts", default=None,
                   help=f"suite: comma-separated subset of {','.join(PARTS)}")
    p.add_argument("--suite-pairs", type=int, default=100,
                   help="suite: pairs of the 7scenes test bag (default 100)")
    p.add_argument("--suite-fragment-pairs", type=int, default=50,
                   help="suite: pairs of the fragments test bag (default 50)")
    p.add_argument("--suite-hard-pairs", type=int, default=30,
                   help="suite: pairs of the resampled-target and noisy 7Scenes-protocol sets on the "
                        "real fragments (default 30)")
    p.add_argument("--cache", default=".cache/eval", help="suite: where its bags are kept")
    p.add_argument("--methods", default="default",
                   help=f"comma-separated methods ({','.join(ALL_METHODS)}) or groups "
                        + "; ".join(f"{g} = {','.join(ms)}" for g, ms in GROUPS.items())
                        + " (default: default)")
    p.add_argument("--through-node", action="store_true",
                   help="run the CEGC rows in a register_node subprocess fed by replaying the bag")
    p.add_argument("--params", default=None,
                   help="register_node parameter file: CEGC's settings offline and in the node "
                        "(default params/register_node.yaml); the rows override it")
    p.add_argument("--checkpoint", default=None, help="CEGC checkpoint (default: shipped weights)")
    p.add_argument("--voxel-ratio", type=float, default=None,
                   help="baselines: voxel as a fraction of the cloud extent (default "
                        "cegc_ros.baselines.BaselineConfig.voxel_ratio)")
    p.add_argument("--mutual-filter", action="store_true",
                   help="baselines: RANSAC with the mutual nearest-feature filter")
    p.add_argument("--sensor-normals", action="store_true",
                   help="baselines: turn each cloud's normals to its frame's origin (its sensor), "
                        "as CEGC's preprocess.normals 'sensor' does (Open3D leaves them unoriented)")
    p.add_argument("--recall-rot", type=float, default=None,
                   help="recall rotation threshold in degrees (default 5; 15 for real pairs)")
    p.add_argument("--recall-trans", type=float, default=None,
                   help="recall translation threshold (default none; 0.3 m for real pairs)")
    p.add_argument("--limit", type=int, default=None, help="evaluate only the first N pairs")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--out", required=True, help="output folder")
    return p


#: Bag protocols of two different scans in metres (fragments, different views with Kinect or
#: LiDAR): scored at the real-fragment recall (15 deg / 0.3 m), the others at 5 deg.
METRIC_PROTOCOLS = frozenset({"fragments", "views"})


def _thresholds(args: argparse.Namespace, real_fragments: bool) -> metrics.RecallThresholds:
    base = metrics.REAL_FRAGMENT_RECALL if real_fragments else metrics.SEVEN_SCENES_RECALL
    rot = args.recall_rot if args.recall_rot is not None else base.rot_deg
    trans = args.recall_trans if args.recall_trans is not None else base.trans
    return metrics.RecallThresholds(rot, trans)


def _baseline_config(args: argparse.Namespace) -> Any:
    from cegc_ros.baselines import BaselineConfig
    bcfg = BaselineConfig(ransac_mutual_filter=args.mutual_filter, sensor_normals=args.sensor_normals)
    if args.voxel_ratio is not None:
        if not args.voxel_ratio > 0:
            raise EvalError(f"--voxel-ratio must be > 0, got {args.voxel_ratio}")
        bcfg.voxel_ratio = args.voxel_ratio
    return bcfg


def _real_7scenes_source(args: argparse.Namespace) -> str:
    return (f"7Scenes protocol (sample_7scenes_pair) on {args.real_dir}: {args.num_pairs} pairs, "
            f"{args.num_points} points resampled, 75% crops, seed {args.seed}"
            + (f", each cloud thinned to {args.subsample}" if args.subsample else "")
            + (", target an independent resample" if args.resample_target else "")
            + (f", Gaussian noise sigma {args.noise_sigma}" if args.noise_sigma else "")
            + "; normalised units (largest bbox side 1)")


def run_cli(args: argparse.Namespace, argv: Sequence[str] = ()) -> Evaluation:
    """One evaluation (a bag or a real folder) as the command line describes it."""
    methods = parse_methods(args.methods)
    if (args.bag is None) == (args.real_dir is None):
        raise EvalError("give either a BAG or --real-dir DIR")
    settings: dict[str, Any] = {}
    node_outcomes: dict[str, list[Outcome]] = {}
    if args.bag is not None:
        pairs = bag_pairs(args.bag)
        if args.limit:
            pairs = pairs[: args.limit]
        title = f"cegc-eval: {Path(args.bag).name}"
        settings["source"] = f"bag {args.bag}"
        protocols = {p.info.get("protocol") for p in pairs}
        real_fragments = bool(protocols) and protocols <= METRIC_PROTOCOLS   # 15 deg / 0.3 m
        node_methods = [m for m in methods if m in CEGC_METHODS] if args.through_node else []
        if node_methods:
            node_outcomes = run_through_node(
                args.bag, pairs, node_methods, params_file=args.params,
                checkpoint=args.checkpoint, progress=not args.no_progress)
    else:
        if args.through_node:
            raise EvalError("--through-node needs a BAG (write one with cegc-make-bag)")
        if args.real_protocol == "pairs":
            pairs = real_pairs(args.real_dir)
            real_fragments = True
            title = f"cegc-eval: real pairs in {args.real_dir}"
            settings["source"] = f"real pairs {args.real_dir} (metres)"
        else:
            if not 0.0 <= args.noise_sigma < 0.5:
                raise EvalError(f"--noise-sigma must be in [0, 0.5), got {args.noise_sigma}")
            pairs = real_7scenes_pairs(args.real_dir, args.num_pairs, args.num_points, args.seed,
                                       args.subsample, args.resample_target, args.noise_sigma)
            real_fragments = False
            title = f"cegc-eval: 7Scenes protocol on the fragments of {args.real_dir}"
            settings["source"] = _real_7scenes_source(args)
        if args.limit:
            pairs = pairs[: args.limit]
    if not pairs:
        raise EvalError("no pairs to evaluate")
    if args.flying_pixels:
        if not 0.0 < args.flying_pixels <= 0.5:
            raise EvalError(f"--flying-pixels must be in (0, 0.5], got {args.flying_pixels}")
        if args.through_node:
            raise EvalError("--flying-pixels corrupts the clouds offline: not with --through-node")
        from cegc_ros.data.corruption import with_flying_pixels
        pairs = with_flying_pixels(pairs, args.flying_pixels, range(len(pairs)))
        settings["corruption"] = f"{args.flying_pixels:.1%} flying pixels per cloud (3-12 m)"
    settings["command"] = " ".join(["cegc-eval", *argv])
    return evaluate(pairs, methods, thresholds=_thresholds(args, real_fragments),
                    checkpoint=args.checkpoint, baseline_config=_baseline_config(args),
                    node_outcomes=node_outcomes, progress=not args.no_progress, title=title,
                    settings=settings, params_file=args.params)


def suite_cli(args: argparse.Namespace, argv: Sequence[str]) -> Path:
    """``--suite``: every documented set with the same methods; returns summary.md."""
    if args.bag is not None or args.through_node:
        raise EvalError("--suite makes its own bags and runs offline: no BAG, no --through-node")
    sizes = SuiteSizes(synthetic_7scenes=args.suite_pairs, synthetic_fragments=args.suite_fragment_pairs,
                       real_7scenes=args.num_pairs, real_7scenes_hard=args.suite_hard_pairs,
                       num_points=args.num_points, seed=args.seed, subsample=args.subsample)
    only = [p.strip() for p in args.parts.split(",") if p.strip()] if args.parts else None
    return run_suite(args.out, parse_methods(args.methods),
                     real_dir=Path(args.real_dir) if args.real_dir else DEFAULT_REAL_DIR,
                     cache=args.cache, sizes=sizes, only=only, limit=args.limit,
                     checkpoint=args.checkpoint, baseline_config=_baseline_config(args),
                     params_file=args.params, progress=not args.no_progress,
                     command=" ".join(["cegc-eval", *argv]))


def main(argv: Iterable[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    try:
        if args.suite:
            summary = suite_cli(args, argv)
            print(summary.read_text())
            print(f"wrote {summary.parent}")
            return 0
        ev = run_cli(args, argv)
        paths = write_outputs(ev, args.out)
    except Exception as err:
        from cegc_ros.data.bag import BagError
        from cegc_ros.engine import CheckpointError
        if isinstance(err, (EvalError, BagError, CheckpointError, FileNotFoundError, ValueError)):
            print(f"cegc-eval: error: {str(err).splitlines()[0] if str(err) else type(err).__name__}",
                  file=sys.stderr)
            return 2
        raise
    print(table_markdown(ev.summaries) if all(p.T_gt is not None for p in ev.pairs)
          else table_markdown(ev.summaries, columns=(("median_latency_ms", "median ms", True),
                                                     ("mean_fitness", "mean fitness", False))))
    print(f"wrote {', '.join(str(p) for p in paths.values())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
