"""Choose weights on synthetic validation: engine recall of checkpoints on different-view pairs.

    python -m cegc_ros.tools.select_weights .cache/pairs/val cegc_ros/weights/cegc_views.pt \
        runs/views/best.pt --pairs 40

The engine at node defaults (each checkpoint in turn) on ``--pairs`` evenly spaced Kinect
(``--sensor lidar``: LiDAR) different-view pairs of a validation pair cache
(``cegc-make-pairs --split val``; rooms never trained on, never real data). Prints one line per
checkpoint: recall at 15 deg / 0.3 m, on the pairs under and over 30% overlap, median seconds per
pair. This is how the shipped weights are chosen (docs/model_card.md). ``--set key=value``
overrides an engine / preprocess setting (``engine.candidates=learned``,
``preprocess.support_points=4096``) for choosing settings;
``--points N`` thins every cloud to N points first (a sparser sensor);
``--peers sc2pcr+icp,ransac+icp`` adds classical peers (cegc_ros/baselines.py) on the same pairs.
The default ``engine.verify_score: learned`` uses weights fitted to the shipped network; compare
other networks with ``--set engine.verify_score=features``, or give one a model fitted to it with
``--set engine.verification=FILE`` (docs/training.md).
``--seeds 0,1`` runs each checkpoint at each sampling seed and pools its recall; from the second
method on a line says how many evaluations it won and lost against the first, with a sign test.
A checkpoint without its ONNX export (``python -m cegc_ros.tools.export_onnx CKPT``) runs
under torch, not ONNX Runtime as the shipped weights do; one line on stderr says so (their
roundings differ: about one verdict in a hundred flips).
``--dump FILE`` writes one row per evaluation, with how the learned confidences rank that pair's
correspondences against the ground truth (:func:`ranking`: true ones, true ones among the 100
most confident, AUC), the learned part's quality apart from the estimator's, how HOCE finds
each cloud's overlap (:func:`overlap_ranking`) and how much geometric evidence the ground truth
and the answer each have (:func:`pose_evidence`: a wrong answer the geometry prefers to the truth).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

import numpy as np


def evaluate(register, pairs, rows: list[dict] | None = None, evidence: Any = None) -> dict[str, Any]:
    """``register(source, target)`` -> a result with T_target_source, valid and timings["total"]
    (the engine's or a peer's) on every pair: recall overall / under 30% overlap / from 30% on,
    and the median seconds per pair. ``rows``: one dict per pair is appended (overlap, correct,
    valid, rotation and translation errors, fitness, ambiguity, whether the estimator explored,
    the draws, HOCE's predicted overlap, each stage's seconds, and the rank of the first right
    pose among those the estimator's verification ranked, -1 for none) for ``--dump``;
    with ``evidence`` (an EngineConfig) also :func:`pose_evidence`'s columns."""
    from cegc_ros.metrics import rotation_error_deg, within
    ok, low, secs, missed = [], [], [], []
    for p in pairs:
        res = register(p.source, p.target)
        T, E = p.T_target_source, res.T_target_source

        def errors(M: np.ndarray) -> tuple[float, float]:
            return float(rotation_error_deg(T[:3, :3], M[:3, :3])), float(np.linalg.norm(T[:3, 3] - M[:3, 3]))

        rot_deg, trans_m = errors(E)
        correct = within(T, E)
        ok.append(res.valid and correct)
        low.append(p.info["overlap"] < 0.3)
        secs.append(res.timings["total"])
        # which of the poses the estimator's verification ranked were right: a wrong result with
        # one there is the verification's miss, without one the candidates'
        hyp = getattr(res, "hypotheses", np.zeros((0, 4, 4)))
        right_ones = [i for i, H in enumerate(hyp) if within(T, H)]
        if len(hyp):
            missed.append(bool(right_ones) and not (res.valid and correct))
        if rows is not None:
            rows.append({"overlap": float(p.info["overlap"]), "correct": correct,
                         "hypotheses": len(hyp), "first_right_hypothesis": right_ones[0] if right_ones else -1,
                         "rotation_error_deg": rot_deg, "translation_error_m": trans_m,
                         "valid": bool(res.valid), "fitness": float(getattr(res, "fitness", float("nan"))),
                         "ambiguity": float(getattr(res, "ambiguity", float("nan"))),
                         **draw_columns(res),
                         **ranking(res, T), **overlap_ranking(res, p.source, p.target, T),
                         **(pose_evidence(E, p.source, p.target, T, evidence) if evidence is not None else {}),
                         **{f"{k}_s": float(v) for k, v in res.timings.items()}})
    return summary(np.array(ok, bool), np.array(low, bool), secs, missed)


def ranking(res: Any, T: np.ndarray, top: int = 100) -> dict[str, float]:
    """How the engine's confidences rank its correspondences against the ground truth T (4, 4):
    the true ones (residual under T below the result's inlier distance), how many of them are
    among the ``top`` most confident, and the ranking's AUC (the chance that a true
    correspondence is more confident than a false one; 0.5: no better than chance; NaN without
    both kinds). Empty for a peer's result, which has no weighted correspondences."""
    c = getattr(res, "correspondences", None)
    if c is None or not len(c):
        return {}
    from cegc_ros.metrics import rank_auc
    src = res.source_points[c[:, 0]].astype(np.float64)
    tgt = res.target_points[c[:, 1]].astype(np.float64)
    true = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - tgt, axis=1) < res.inlier_distance
    w = np.asarray(res.weights, np.float64)
    order = np.argsort(-w, kind="stable")
    return {"true_correspondences": int(true.sum()), f"true_in_top{top}": int(true[order[:top]].sum()),
            "ranking_auc": rank_auc(w, true)}


def draw_columns(res: Any) -> dict[str, Any]:
    """What a second draw gated by the predicted overlap would read: whether the estimator
    explored, the draws the pair took, and the mean of HOCE's overlap confidences over each
    cloud's network points ("source_", "target_" ``predicted_overlap``: the network's estimate of
    the share of each cloud that overlaps the other). Empty for a peer's result."""
    if getattr(res, "source_overlap", None) is None or not len(res.source_overlap):
        return {}
    return {"explored": bool(res.explored), "draws": int(res.draws),
            "source_predicted_overlap": float(np.mean(res.source_overlap)),
            "target_predicted_overlap": float(np.mean(res.target_overlap))}


def overlap_ranking(res: Any, source: np.ndarray, target: np.ndarray, T: np.ndarray,
                    keep: float = 0.4) -> dict[str, float]:
    """How well the HOCE overlap confidences find the overlap, per cloud ("source_", "target_"):
    ``overlap_share`` (the share of the network's points that lie in the overlap: within the
    result's inlier distance of the other full cloud under the ground truth T (4, 4)),
    ``overlap_auc`` (the chance that an overlap point is more confident than another), and
    ``overlap_kept`` (the share of the overlap points among the ``keep`` most confident
    fraction of the points: what a second pass focused on the predicted overlap would keep).
    source, target: the pair's full (N, 3), (M, 3) clouds in metres. Empty for a peer's result."""
    if getattr(res, "source_overlap", None) is None or not len(res.source_overlap):
        return {}
    from scipy.spatial import cKDTree

    from cegc_ros.data.protocols import transform_points
    from cegc_ros.metrics import rank_auc
    out: dict[str, float] = {}
    for side, pts, conf, other, M in (("source", res.source_points, res.source_overlap, target, T),
                                      ("target", res.target_points, res.target_overlap, source,
                                       np.linalg.inv(T))):
        moved = transform_points(M, np.asarray(pts, np.float64))
        d, _ = cKDTree(np.asarray(other, np.float64)).query(moved)
        true = d < res.inlier_distance
        conf = np.asarray(conf, np.float64)
        top = np.argsort(-conf, kind="stable")[:max(1, int(round(keep * len(conf))))]
        out[f"{side}_overlap_share"] = float(true.mean())
        out[f"{side}_overlap_auc"] = rank_auc(conf, true)
        out[f"{side}_overlap_kept"] = float(true[top].sum() / true.sum()) if true.any() else float("nan")
    return out


def pose_evidence(T_result: np.ndarray, source: np.ndarray, target: np.ndarray, T: np.ndarray,
                  eng: Any, max_points: int = 5000) -> dict[str, float]:
    """Can the geometry alone tell the ground truth T (4, 4) from the answer T_result? The truth
    is refined by the engine's ICP (``eng``: EngineConfig; the answer is the engine's, already
    refined) and each pose is scored by the geometric part of the estimator's verification
    (fitness x free space, without the correspondence count), but on the pair's full clouds
    (source, target: (N, 3), (M, 3) metres, each in its sensor's frame): the share of (at most
    ``max_points``, seeded) source points within the ICP distance of a target point, times
    exp(-eng.free_space x the share put where the other sensor saw through,
    cegc_ros/visibility.py). ``gt_evidence`` and ``result_evidence``; a wrong answer with more
    evidence than the ground truth is a pair the geometry cannot settle (no verification picks
    the truth there), one with less a miss that better hypotheses or verification could fix."""
    from cegc_ros import refine
    from cegc_ros.geometry import normalise_pair
    from cegc_ros.visibility import free_space_violations
    src, tgt = np.asarray(source, np.float64), np.asarray(target, np.float64)
    dist = eng.icp_max_distance * normalise_pair(src, tgt)[2].scale
    truth = refine.icp(src, tgt, np.asarray(T, np.float64), dist, eng.icp_max_iterations, eng.icp_points)
    poses = np.stack([truth, np.asarray(T_result, np.float64)])
    keep = np.random.default_rng(0).permutation(len(src))[:max_points]
    fit = refine.fitnesses(poses[:, :3, :3], poses[:, :3, 3], src[keep], tgt, dist)
    free = np.exp(-eng.free_space * free_space_violations(poses[:, :3, :3], poses[:, :3, 3], src, tgt))
    score = fit * free
    return {"gt_evidence": float(score[0]), "result_evidence": float(score[1])}


def summary(ok: np.ndarray, low: np.ndarray, secs: list[float], missed: list[bool]) -> dict[str, Any]:
    """Per-pair outcomes (N,) ``ok`` and ``low`` (under 30% overlap) -> recall overall / under /
    from 30%, the median seconds, the verification misses (-1: none reported) and ``ok`` itself."""
    def share(mask: np.ndarray) -> float:
        return float(ok[mask].mean()) if mask.any() else float("nan")
    return {"recall": float(ok.mean()), "recall_low": share(low), "recall_high": share(~low),
            "n_low": int(low.sum()), "median_s": float(np.median(secs)),
            "verification_misses": int(sum(missed)) if missed else -1, "ok": ok, "low": low,
            "secs": list(secs), "missed": list(missed)}


def pooled(results: list[dict[str, Any]]) -> dict[str, Any]:
    """:func:`evaluate`'s results of one method on the same pairs at several seeds, as one."""
    cat = {k: [x for r in results for x in r[k]] for k in ("ok", "low", "secs", "missed")}
    return summary(np.array(cat["ok"], bool), np.array(cat["low"], bool), cat["secs"],
                   [bool(m) for m in cat["missed"]] if all(r["verification_misses"] >= 0 for r in results) else [])


def sign_test(ok: np.ndarray, reference: np.ndarray) -> tuple[int, int, float]:
    """(won, lost, two-sided sign-test p) of outcomes ``ok`` against ``reference`` on the same
    (pair, seed) evaluations; the pairs both got right or both missed do not count."""
    from math import comb
    won, lost = int((ok & ~reference).sum()), int((~ok & reference).sum())
    n, k = won + lost, min(won, lost)
    p = min(1.0, 2.0 * sum(comb(n, i) for i in range(k + 1)) / 2.0 ** n) if n else 1.0
    return won, lost, p


def validation_pairs(cache_dir: Path, n: int, sensor: str, max_overlap: float = 1.0
                     ) -> tuple[list[Any], np.ndarray]:
    """At most ``n`` different-view pairs of one sensor model with overlap below
    ``max_overlap`` (1: all), spread evenly over those of a validation pair cache, and their
    indices in it; ValueError when it holds none."""
    from cegc_ros.data.pair_cache import PairCache
    cache = PairCache(cache_dir, kinds=("views",), sensors=(sensor,))
    usable = np.flatnonzero(cache.overlaps < max_overlap) if max_overlap < 1.0 else np.arange(len(cache))
    if len(usable) == 0:
        under = f" under {max_overlap:g} overlap" if max_overlap < 1.0 else ""
        raise ValueError(f"{cache_dir}: no {sensor} different-view pairs{under}")
    idx = usable[np.linspace(0, len(usable) - 1, min(n, len(usable))).astype(int)]
    return [cache[int(i)] for i in idx], idx


def add_pair_options(ap: argparse.ArgumentParser) -> None:
    """The options that choose the validation pairs (:func:`validation_pairs`)."""
    ap.add_argument("--pairs", type=int, default=40)
    ap.add_argument("--sensor", choices=("kinect", "lidar"), default="kinect",
                    help="the pairs of this sensor model (default kinect; a LiDAR cache: "
                         "cegc-make-pairs --split val --lidar-fraction 1 ...)")
    ap.add_argument("--max-overlap", type=float, default=1.0, metavar="X",
                    help="only the pairs under this overlap (e.g. 0.3: the low-overlap pairs, "
                         "where a few-point loss hides among all pairs; default 1: all)")


def parse_overrides(items: list[str]):
    """["engine.x=1", "preprocess.y=2", ...] -> (PreprocessConfig, EngineConfig) of the defaults
    with them set, each value converted to its field's type; ValueError naming a bad item."""
    from cegc_ros.config import EngineConfig, PreprocessConfig
    pre, eng = PreprocessConfig(), EngineConfig()
    for item in items:
        key, _, value = item.partition("=")
        section, _, name = key.partition(".")
        obj = {"preprocess": pre, "engine": eng}.get(section)
        if obj is None or not hasattr(obj, name) or not value:
            raise ValueError(f"--set {item!r}: expected preprocess.<field>=<value> or engine.<field>=<value>")
        setattr(obj, name, type(getattr(obj, name))(value))
    return pre, eng


def note_torch_runtime(tool: str, registrar: Any) -> None:
    """One stderr line, prefixed by ``tool``, when ``registrar`` runs its network under torch,
    not ONNX Runtime as shipped: torch rounds differently, which flips about one verdict in a
    hundred, so a candidate is judged as it would ship only once exported. Silent otherwise."""
    if registrar.runtime_note:
        name = registrar.engine.checkpoint           # the path it was loaded from
        print(f"{tool}: {name}: the network runs under torch, not ONNX Runtime as shipped "
              f"({registrar.runtime_note}); export it first: python -m "
              f"cegc_ros.tools.export_onnx {name}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="select_weights", description=__doc__.splitlines()[0])
    ap.add_argument("cache", type=Path, help="a validation pair cache (cegc-make-pairs --split val)")
    ap.add_argument("checkpoints", nargs="+", help="checkpoints to compare")
    add_pair_options(ap)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--peers", default="", help="comma-separated classical peers to score on the same pairs")
    ap.add_argument("--flying-pixels", type=float, default=0.0, metavar="SHARE",
                    help="move this share of each cloud's points out along their rays to 3-12 m "
                         "(cegc_ros/data/corruption.py; seeded per pair)")
    ap.add_argument("--points", type=int, default=0, metavar="N",
                    help="thin each cloud to at most N points first (cegc_ros/data/corruption.py; "
                         "seeded per pair): a sparser sensor's view of the same pairs")
    ap.add_argument("--seeds", default="", metavar="LIST",
                    help="comma-separated preprocess.seed values: each checkpoint runs at each "
                         "and its recall is pooled over them (a new seed redraws the grid "
                         "sampling, which alone flips ~10%% of the verdicts: docs/pipeline.md); "
                         "default: the one seed of --set or the defaults")
    ap.add_argument("--dump", type=Path, default=None,
                    help="write one CSV row per run and pair (overlap, correct, errors, valid, fitness, the "
                         "confidences' ranking of the true correspondences, how HOCE finds the overlap and "
                         "what it predicts of it, whether the estimator explored, the draws, stage seconds)")
    args = ap.parse_args(argv)
    try:
        from cegc_ros.data.pair_cache import PairCacheError
        from cegc_ros.engine import CheckpointError, Registrar
        pre, eng = parse_overrides(args.set)
        pairs, idx = validation_pairs(args.cache, args.pairs, args.sensor, args.max_overlap)
        if args.points > 0:
            from cegc_ros.data.corruption import thinned
            pairs = thinned(pairs, args.points, idx)                     # seeded by cache index
        if args.flying_pixels > 0:
            from cegc_ros.data.corruption import with_flying_pixels
            pairs = with_flying_pixels(pairs, args.flying_pixels, idx)   # seeded by cache index
        from cegc_ros import baselines
        peers = [m for m in args.peers.split(",") if m]
        for m in peers:
            if m not in baselines.METHODS:
                raise ValueError(f"--peers: unknown method {m!r}, expected some of {', '.join(baselines.METHODS)}")
        seeds = [int(x) for x in args.seeds.split(",") if x.strip()] or [pre.seed]
        rows: list[dict] = []
        # the per-pair rows (their ranking and overlap columns search the full clouds) only
        # when they are written
        dumped = rows if args.dump is not None else None
        first: dict[str, Any] | None = None
        for name in list(args.checkpoints) + peers:
            per_seed = []
            registrar = (Registrar.from_checkpoint(name, device="cpu", preprocess=pre, engine=eng)
                         if name in args.checkpoints else None)
            if registrar is not None:
                note_torch_runtime("select_weights", registrar)
            for seed in (seeds if registrar else [pre.seed]):
                if registrar:
                    registrar.update(preprocess=dataclasses.replace(pre, seed=seed))
                    register = registrar.register
                else:
                    register = lambda s, t, m=name: baselines.register(m, s, t)   # noqa: E731
                start = len(rows)
                per_seed.append(evaluate(register, pairs, dumped, eng if dumped is not None else None))
                for row in rows[start:]:
                    row["run"], row["seed"] = name, seed
            r = pooled(per_seed)
            times = f" x {len(per_seed)} seeds" if len(per_seed) > 1 else ""
            print(f"{name}: recall {r['recall']:.3f} on {len(pairs)} pairs{times} (<30% overlap: {r['recall_low']:.2f}"
                  f" of {r['n_low']}, >=30%: {r['recall_high']:.2f}), median {r['median_s']:.2f} s"
                  + (f"; wrong with a right pose among the verified: {r['verification_misses']}"
                     if r["verification_misses"] >= 0 else ""), flush=True)
            if first is None:
                first = {"name": name, **r}
            elif len(r["ok"]) == len(first["ok"]):
                won, lost, p = sign_test(r["ok"], first["ok"])
                print(f"  against {first['name']}: won {won}, lost {lost} (sign test p = {p:.3f})", flush=True)
        if args.dump is not None:
            _write_csv(args.dump, rows)
    except (OSError, ValueError, PairCacheError, CheckpointError) as err:
        print(f"select_weights: {err}".splitlines()[0], file=sys.stderr)
        return 1
    return 0


def _write_csv(path: Path, rows: list[dict]) -> None:
    import csv
    keys = list(dict.fromkeys(k for row in rows for k in row))
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    sys.exit(main())
