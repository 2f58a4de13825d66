"""Export a checkpoint's network for ONNX Runtime (``engine.runtime``), beside the checkpoint.

    python -m cegc_ros.tools.export_onnx                          # the shipped weights
    python -m cegc_ros.tools.export_onnx runs/views/best.pt [--out best.onnx]

Writes ``<checkpoint>.onnx`` (cegc_ros/onnx_network.py: the candidate path, its point axes
dynamic, the checkpoint's SHA-256 recorded), then runs both on a synthetic pair and prints one
line: the largest difference of the overlap logits, the features' cosine similarities and the pair scores,
and whether every candidate index agrees. Re-export whenever the weights change: the engine ignores an export of other
weights. Needs the ``onnx`` package. Errors: one line, exit 1.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path


def parity(checkpoint: str | Path, onnx_path: str | Path, num_points: int = 1024, seed: int = 0
           ) -> dict[str, float]:
    """Torch and ONNX Runtime on one synthetic room-corner pair of ``num_points`` network points:
    max |difference| of the overlap logits, of the attention features' cosine similarities (the
    verification's ``engine.verify_score: features``) and of the scores of the candidates both chose, the
    share of candidate indices that agree, and ``tie_gap``: where a source point's learned
    candidates differ as sets, how far (in torch's cosine similarity) the one ONNX Runtime took
    lies below torch's weakest (0 when none differ). A different rounding of the features can
    only swap near-tied candidates, which the CPU decides (AVX2 and AVX-512 kernels round
    differently): a small ``tie_gap`` says every difference is such a tie."""
    import numpy as np
    import torch

    from cegc_ros.config import EngineConfig, PreprocessConfig
    from cegc_ros.engine import load_checkpoint
    from cegc_ros.geometry import prepare_pair
    from cegc_ros.matching import fpfh_neighbours
    from cegc_ros.onnx_network import OnnxNetwork

    model, _ = load_checkpoint(checkpoint, "cpu")
    net = OnnxNetwork(onnx_path, model.cfg)
    rng = np.random.default_rng(seed)
    k = 3000
    room = np.concatenate([np.c_[rng.uniform(0, 4, (k, 2)), np.zeros(k)],
                           np.c_[np.zeros(k), rng.uniform(0, 4, k), rng.uniform(0, 2.5, k)],
                           np.c_[rng.uniform(0, 4, k), np.zeros(k), rng.uniform(0, 2.5, k)],
                           np.c_[rng.uniform(1, 2, k), rng.uniform(1, 2, k), np.full(k, 0.7)]])
    a = np.radians(25.0)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    pre, eng = PreprocessConfig(num_points=num_points), EngineConfig()
    ps, pt, _ = prepare_pair(room[: 3 * k], room[k:] @ R.T, pre.num_points, pre.support_points,
                             np.random.default_rng(pre.seed), model.cfg.features(), pre.sampling)

    def t(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x)).unsqueeze(0)
    extra = t(fpfh_neighbours(ps.desc, pt.desc, eng.fpfh_candidates))
    args = (t(ps.points), t(pt.points), t(ps.normals), t(pt.normals), t(ps.desc), t(pt.desc))
    with torch.inference_mode():
        ref = model.score_candidates(*args, k_learned=net.learned_candidates, extra=extra)
    got = net.score_candidates(*args, k_learned=net.learned_candidates, extra=extra)
    diff = max(float((ref.src_overlap_logits - got.src_overlap_logits).abs().max()),
               float((ref.tgt_overlap_logits - got.tgt_overlap_logits).abs().max()))
    same = ref.candidates == got.candidates        # a near-tie in the learned top-k may swap
    k = net.learned_candidates
    sim = ref.similarity[0]                                                         # torch's (N, M)
    mine, theirs = ref.candidates[0, :, :k], got.candidates[0, :, :k]
    weakest = sim.gather(1, mine).min(dim=1).values                                 # (N,)
    gap = (weakest[:, None] - sim.gather(1, theirs)).clamp_min(0.0)                 # 0 where theirs is in torch's top-k
    return {"overlap_logits": diff,
            "similarity": float((ref.similarity - got.similarity).abs().max()),
            "scores": float((ref.scores - got.scores).abs()[same].max()),
            "candidates_equal": float(same.float().mean()),
            "tie_gap": float(gap.max())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="export_onnx", description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", nargs="?", default=None, help="a CEGC checkpoint (default: the shipped weights)")
    ap.add_argument("--out", type=Path, default=None, help="the .onnx file (default: beside the checkpoint)")
    ap.add_argument("--learned-candidates", type=int, default=None,
                    help="learned candidates baked into the graph (default: engine.learned_candidates)")
    args = ap.parse_args(argv)
    try:
        from cegc_ros.config import EngineConfig
        from cegc_ros.engine import CheckpointError, default_weights, load_checkpoint
        from cegc_ros.onnx_network import OnnxExportError, export_onnx
        ckpt = args.checkpoint or default_weights()
        k = args.learned_candidates or EngineConfig().learned_candidates
        model, _ = load_checkpoint(ckpt, "cpu")
        with warnings.catch_warnings():     # the tracer's notes on Python ints in the graph
            warnings.simplefilter("ignore")
            out = export_onnx(model, ckpt, args.out, k)
        p = parity(ckpt, out)
    except (OSError, ValueError, CheckpointError, OnnxExportError) as err:
        print(f"export_onnx: {err}".splitlines()[0], file=sys.stderr)
        return 1
    print(f"{out}: overlap logits within {p['overlap_logits']:.1e}, similarities within {p['similarity']:.1e}, "
          f"scores within {p['scores']:.1e}, "
          f"candidates equal {p['candidates_equal']:.4f}, the others tied within {p['tie_gap']:.1e} "
          f"(torch vs ONNX Runtime, 1024 points)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
