"""cegc-demo: the node on a small synthetic bag over DDS, with the Open3D baselines beside it.

    cegc-demo [--pairs 10] [--cache .cache/demo] [--methods cegc,cegc+icp,icp,fgr,ransac]

1. generates a deterministic 7Scenes-protocol test bag (``--pairs`` pairs of synthetic test
   rooms, seed 0) into the cache, unless it is there already;
2. starts ``register_node`` with ``params/register_node.yaml`` as a subprocess (DDS on
   localhost, a ROS domain of its own) and replays the bag into it in lockstep;
3. runs the Open3D baselines offline on the same pairs and prints a plain-text table
   (:func:`format_table`); the full report (report.md, metrics.json, pairs.csv, errors.png)
   goes to ``<cache>/report/``, the node's log to ``<cache>/logs/``.

The node publishes no fitness, so the demo measures it for the node's poses the way the
baselines measure theirs (:func:`pose_fitness`): one definition for every row.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

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
        node = {m: with_fitness(pairs, outs) for m, outs in node.items()}
        ev = E.evaluate(pairs, methods, node_outcomes=node, progress=progress,
                        title=f"cegc-demo: {bag.name}",
                        settings={"source": f"bag {bag}",
                                  "command": "cegc-demo " + " ".join(argv or sys.argv[1:])},
                        params_file=args.params, checkpoint=args.checkpoint)
        paths = E.write_outputs(ev, args.cache / "report")
    except Exception as err:  # noqa: BLE001 - CLI boundary: one line, non-zero exit
        print(f"cegc-demo: error: {_one_line(err)}", file=sys.stderr)
        return 1
    offline = [m for m in methods if m not in node_methods]
    print(f"\n{len(pairs)} generated pairs ({DEMO_PROTOCOL} protocol, synthetic test rooms), "
          f"{time.monotonic() - t0:.0f} s.")
    if node_methods:
        print(f"{', '.join(node_methods)}: register_node over DDS.", end=" ")
    print(f"{', '.join(offline)}: offline on the same pairs.\n" if offline else "\n")
    print(format_table(ev.summaries))
    print()
    print("\n".join(table_notes(ev.thresholds.describe(), through_node=bool(node_methods))))
    print(f"\nfull report: {paths['report']}"
          + (f"; node log: {args.cache / 'logs'}" if node_methods else ""))
    return 0


#: The terminal table: (summary key, header, unit, format). "t" = translation, in the units of
#: the clouds: the 7Scenes protocol scales each scene to a largest side of 1.
TABLE_COLUMNS = (
    ("error_r", "Error(R)", "deg", "{:.3f}"), ("error_t", "Error(t)", "scene", "{:.4f}"),
    ("rmse_r", "RMSE(R)", "deg", "{:.3f}"), ("rmse_t", "RMSE(t)", "scene", "{:.4f}"),
    ("mae_r", "MAE(R)", "deg", "{:.3f}"), ("mae_t", "MAE(t)", "scene", "{:.4f}"),
    ("recall", "recall", "", "{:.2f}"), ("mean_fitness", "fitness", "", "{:.3f}"),
    ("median_latency_ms", "time", "ms/pair", "{:.0f}"),
)


def format_table(summaries: dict[str, dict[str, Any]], columns=TABLE_COLUMNS) -> str:
    """The demo's metrics as a plain-text table: a header line, a units line, one row per
    method (right-aligned; "-" for a value that does not exist), failures last."""
    head = ["method"] + [c[1] for c in columns] + ["failures"]
    units = [""] + [c[2] for c in columns] + [""]
    rows = []
    for method, s in summaries.items():
        cells = [method]
        for key, _, _, fmt in columns:
            v = s.get(key)
            ok = v is not None and isinstance(v, (int, float)) and math.isfinite(float(v))
            cells.append(fmt.format(float(v)) if ok else "-")
        fails = int(s.get("n_invalid", 0)) + int(s.get("n_exception", 0))
        cells.append(f"{fails}/{int(s.get('n_pairs', 0))}")
        rows.append(cells)
    widths = [max(len(r[i]) for r in [head, units, *rows]) for i in range(len(head))]
    def line(cells: list[str]) -> str:
        return "  ".join([cells[0].ljust(widths[0])]
                         + [c.rjust(w) for c, w in zip(cells[1:], widths[1:])]).rstrip()
    return "\n".join(line(r) for r in [head, units, *rows])


def table_notes(recall: str, through_node: bool) -> list[str]:
    """What the table's columns mean, for people reading it in a terminal."""
    time_note = ("node rows: cloud published -> pose received, over DDS; baselines: one call"
                 if through_node else "one call")
    return [
        "Error(R), Error(t): mean rotation and translation error of each pose; RMSE and MAE: of",
        "  its Euler angles and translation components (as RPM-Net and DCP report them).",
        "scene: the translation unit; the 7Scenes protocol scales each room to a largest side of 1.",
        f"recall: {recall}.",
        "fitness: share of the source within 1.5 voxels of the target under the method's pose",
        "  (voxel = 2% of the scene; the baselines' definition, cegc_ros/baselines.py).",
        f"time: median per pair ({time_note}).",
        "failures: pairs with an invalid pose or none; they are scored as the identity.",
    ]


def pose_fitness(source: np.ndarray, target: np.ndarray, T: np.ndarray) -> float:
    """The baselines' fitness of pose ``T`` (4, 4) for clouds (N, 3), (M, 3): the share of the
    voxelized source within ``fitness_factor`` voxels of the voxelized target after T."""
    from cegc_ros.baselines import BaselineConfig, load_open3d, scale_of, voxel_for

    o3d = load_open3d(threads=0)
    config = BaselineConfig()
    voxel = voxel_for(scale_of(source, target), config)
    src, tgt = (o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(c, np.float64)))
                .voxel_down_sample(voxel) for c in (source, target))
    return float(o3d.pipelines.registration.evaluate_registration(
        src, tgt, config.fitness_factor * voxel, np.asarray(T, np.float64)).fitness)


def with_fitness(pairs: Sequence[Any], outcomes: Sequence[Any]) -> list[Any]:
    """The node's outcomes with the fitness of each pose that it published (:func:`pose_fitness`)."""
    return [o if o.T is None or not math.isnan(o.fitness) else
            dataclasses.replace(o, fitness=pose_fitness(p.source, p.target, o.T))
            for p, o in zip(pairs, outcomes)]


def _check_weights(checkpoint: str | None, params: Path | None) -> None:
    """Fail early, in one line, when the node would have no weights to load."""
    from cegc_ros.engine import default_weights
    from cegc_ros.tools.evaluate import EvalError, engine_configs

    _, eng = engine_configs(params)
    path = Path(checkpoint or eng.checkpoint or default_weights())
    if not path.is_file():
        raise EvalError(f"no CEGC weights at {path}: pass --checkpoint PATH, or run only the "
                        f"baselines with --methods icp,fgr,ransac")


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}".rstrip(": ")


if __name__ == "__main__":
    raise SystemExit(main())
