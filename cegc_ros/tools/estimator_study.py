"""Study the estimate / refine / verify stages offline: the validation pairs are matched once, then
finished under each variant of the engine settings those stages read.

    python -m cegc_ros.tools.estimator_study .cache/pairs/val --pairs 196 --seeds 14,15 \\
        --variant engine.explore_seeds=100 --variant engine.icp_points=3000,engine.explore_seeds=100

The bound, features and match stages (the network) run once per pair and seed
(:meth:`Registrar.match_pair`); each variant then costs only :meth:`Registrar.finish`, the same
code :meth:`Registrar.register` runs, so the defaults' line reproduces ``select_weights`` on the
same pairs and seeds verdict for verdict (test_estimator_study), about 5x faster per variant.
Only the settings of :data:`Registrar.FINISH_SETTINGS` can vary; a setting that acts earlier
(the candidates, the network's runtime, any ``preprocess`` one) needs ``select_weights``.
A checkpoint without its ONNX export runs under torch, not ONNX Runtime as shipped; one line on
stderr says so, as in ``select_weights``.
Each line: recall overall, under and from 30% overlap, won / lost against the defaults (sign
test), the right poses left unchosen, the estimate and refine stages' median milliseconds, and
the median rotation and translation errors of the pairs registered right.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

import numpy as np

from cegc_ros.tools.select_weights import add_pair_options


def capture(registrar: Any, pairs: list[Any], seeds: list[int]) -> list[list[Any]]:
    """Match every pair at every sampling seed: per seed, the pairs' engine.Matched in their
    order. The memory freed after each pair goes back to the system
    (allocator.release_free_memory): jemalloc would keep it beside the matched arrays."""
    from cegc_ros.allocator import release_free_memory
    out = []
    for seed in seeds:
        registrar.update(preprocess=dataclasses.replace(registrar.preprocess, seed=seed))
        per_seed = []
        for p in pairs:
            per_seed.append(registrar.match_pair(p.source, p.target))
            release_free_memory()
        out.append(per_seed)
    return out


def finish_all(registrar: Any, pairs: list[Any], matched: list[list[Any]], engine: Any) -> dict[str, Any]:
    """Finish every pair's :func:`capture` under ``engine`` settings: select_weights' pooled
    summary (recall, under / from 30% overlap, ``ok`` per evaluation, ...) plus the stages'
    medians and the errors of the right ones."""
    from cegc_ros.allocator import release_free_memory
    from cegc_ros.metrics import pair_errors
    from cegc_ros.tools.select_weights import evaluate, pooled
    registrar.update(engine=engine)
    results, stages, right_errors = [], {"estimate": [], "refine": []}, []
    for per_seed in matched:
        by_cloud = {id(p.source): m for p, m in zip(pairs, per_seed)}
        finished = []

        def finish(source: np.ndarray, target: np.ndarray) -> Any:
            res = registrar.finish(by_cloud[id(source)])
            finished.append(res)
            release_free_memory()
            return res
        summary = evaluate(finish, pairs)
        results.append(summary)
        for p, res, ok in zip(pairs, finished, summary["ok"]):
            for k in stages:
                stages[k].append(res.timings.get(k, 0.0))
            if ok:
                e = pair_errors(p.T_target_source, res.T_target_source)
                right_errors.append((float(e.rot_error_deg[0]), float(e.trans_error[0])))
    out = pooled(results)
    out.update({f"{k}_ms": 1e3 * float(np.median(v)) for k, v in stages.items()})
    errs = np.array(right_errors).reshape(-1, 2)
    out["rot_error_deg"], out["trans_error_m"] = (np.median(errs, axis=0) if len(errs) else (np.nan, np.nan))
    return out


def parse_variant(text: str) -> Any:
    """"engine.a=1,engine.b=2" -> the default EngineConfig with them set (select_weights'
    parser); ValueError naming the item for anything but a :data:`Registrar.FINISH_SETTINGS`
    setting."""
    from cegc_ros.engine import Registrar
    from cegc_ros.tools.select_weights import parse_overrides
    items = [x.strip() for x in text.split(",") if x.strip()]
    for item in items:
        key, _, value = item.partition("=")
        section, _, name = key.partition(".")
        if section != "engine" or name not in Registrar.FINISH_SETTINGS or not value:
            raise ValueError(f"--variant {item!r}: expected engine.<setting>=<value> with a setting "
                             f"of the estimate, refine or verify stage ({', '.join(Registrar.FINISH_SETTINGS)})")
    return parse_overrides(items)[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="estimator_study", description=__doc__.splitlines()[0])
    ap.add_argument("cache", type=Path, help="a validation pair cache (cegc-make-pairs --split val)")
    ap.add_argument("checkpoint", nargs="?", default=None, help="weights (default: the shipped ones)")
    add_pair_options(ap)
    ap.add_argument("--seeds", default="0", metavar="LIST", help="comma-separated preprocess.seed values")
    ap.add_argument("--variant", action="append", default=[], metavar="KEY=VALUE[,KEY=VALUE]",
                    help="engine settings of the later stages to finish the pairs under (repeatable)")
    args = ap.parse_args(argv)
    try:
        from cegc_ros.data.pair_cache import PairCacheError
        from cegc_ros.engine import CheckpointError, Registrar
        from cegc_ros.tools.select_weights import note_torch_runtime, sign_test, validation_pairs
        variants = [("defaults", parse_variant(""))] + [(v, parse_variant(v)) for v in args.variant]
        pairs, _ = validation_pairs(args.cache, args.pairs, args.sensor, args.max_overlap)
        seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
        registrar = Registrar.from_checkpoint(args.checkpoint, device="cpu")   # None: the shipped weights
        note_torch_runtime("estimator_study", registrar)
        matched = capture(registrar, pairs, seeds)
        reference = None
        for name, eng in variants:
            r = finish_all(registrar, pairs, matched, eng)
            vs = ""
            if reference is None:                    # the defaults, first
                reference = r["ok"]
            else:
                won, lost, p = sign_test(r["ok"], reference)
                vs = f", {won} won / {lost} lost (p = {p:.2g})"
            print(f"{name}: recall {r['recall']:.3f} on {len(pairs)} pairs x {len(seeds)} seeds "
                  f"(<30% overlap: {int(round(r['recall_low'] * r['n_low']))} of {r['n_low']}, "
                  f">=30%: {r['recall_high']:.2f}){vs}; right poses left unchosen "
                  f"{r['verification_misses']}; estimate {r['estimate_ms']:.0f} ms, refine "
                  f"{r['refine_ms']:.0f} ms; right pairs' errors {r['rot_error_deg']:.3f} deg, "
                  f"{100 * r['trans_error_m']:.2f} cm", flush=True)
    except (ValueError, OSError, CheckpointError, PairCacheError) as err:
        print(f"estimator_study: {err}".splitlines()[0], file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
