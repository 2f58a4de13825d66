"""Stage 3 of the engine: CEGC turns two prepared clouds into weighted correspondences.

For each network source point, candidate partners in the target (``engine.candidates``):
- ``learned``: its ``engine.learned_candidates`` nearest target points in the network's feature
  space (cosine of the attention features, computed inside :meth:`CEGC.score_candidates`);
- ``fpfh``: its ``engine.fpfh_candidates`` nearest target points in FPFH space (the classical
  cue; on different views it is right more often than our CPU-trained features, see
  docs/pipeline.md), computed here with a k-d tree;
- ``both`` (default): the union, learned first;
- ``all``: the paper's path (every pair of the HOCE top-N sets, argmax per row).
CAMS with CFM scores every candidate pair; the confidence of pair (i, j) is
``sigmoid(HOCE overlap of i) x sigmoid(CAMS/CFM score of (i, j))`` (``engine.confidence =
learned``) or 1 (``uniform``, the ablation). For ``all`` it is the paper's row confidence w_i.

The ``engine.max_correspondences`` most confident pairs go on to the estimator; ties (all of
them under ``uniform``) are broken by candidate rank, so a point's first candidate comes before
anyone's second.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .config import EngineConfig
from .denormals import flush_denormals
from .geometry import PreparedCloud

CANDIDATE_SOURCES = ("learned", "fpfh", "both", "all")


@dataclass
class Matches:
    """Weighted correspondences between the two prepared clouds (indices into their points)."""

    correspondences: np.ndarray   # (K, 2) int64: (source index, target index)
    weights: np.ndarray           # (K,) float32 in [0, 1]
    rank: np.ndarray              # (K,) int64: the candidate's rank within its source point's list
    source_overlap: np.ndarray    # (Ns,) float32 HOCE overlap confidence
    target_overlap: np.ndarray    # (Nt,) float32
    #: (Ns, Nt) float32 cosine similarity of the network points' attention features (the
    #: learned candidates' feature space), for the verification's feature agreement
    #: (``engine.verify_score``); None on the paper's path (``engine.candidates: all``)
    similarity: np.ndarray | None = None


def fpfh_neighbours(desc_source: np.ndarray, desc_target: np.ndarray, k: int) -> np.ndarray:
    """(N, D), (M, D) descriptors -> (N, k) indices of the nearest target descriptors."""
    from scipy.spatial import cKDTree
    k = min(k, len(desc_target))
    _, idx = cKDTree(desc_target).query(desc_source, k=k)
    return np.asarray(idx, np.int64).reshape(len(desc_source), k)


def select(cand: np.ndarray, weights: np.ndarray, max_correspondences: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, k) candidate target indices and weights -> the most confident distinct pairs:
    correspondences (K, 2), weights (K,), rank (K,); ties broken by rank, then source index."""
    N, k = cand.shape
    rows = np.repeat(np.arange(N), k)
    ranks = np.tile(np.arange(k), N)
    cols = cand.reshape(-1)
    w = weights.reshape(-1)
    order = np.lexsort((rows, ranks, -w))
    pairs = rows[order] * (cand.max() + 1) + cols[order]
    _, first = np.unique(pairs, return_index=True)            # duplicates: keep the best-placed one
    keep = order[np.sort(first)][:max_correspondences]
    return (np.stack([rows[keep], cols[keep]], axis=1).astype(np.int64),
            w[keep].astype(np.float32), ranks[keep].astype(np.int64))


class NetworkOutputError(RuntimeError):
    """The network returned non-finite confidences or overlap scores (a broken checkpoint or
    runtime, e.g. a compiled graph built for other CPU kernels): the pair is not registered
    rather than registered from garbage (cegc_ros.engine re-raises it naming the runtime)."""


def finite_outputs(**arrays: np.ndarray) -> None:
    """NetworkOutputError naming how many values of each array are not finite; silent when all are."""
    bad = [f"{int((~np.isfinite(a)).sum())} of {a.size} {name.replace('_', ' ')}"
           for name, a in arrays.items() if not np.isfinite(a).all()]
    if bad:
        raise NetworkOutputError(f"returned non-finite values: {', '.join(bad)}")


def match(model: Any, ps: PreparedCloud, pt: PreparedCloud, eng: EngineConfig, device: str) -> Matches:
    """Run CEGC on the prepared clouds and return the weighted correspondences;
    NetworkOutputError when its confidences or overlap scores are not all finite."""
    import torch

    def tens(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).unsqueeze(0).to(device)

    args = (tens(ps.points), tens(pt.points), tens(ps.normals), tens(pt.normals), tens(ps.desc), tens(pt.desc))
    if eng.candidates not in CANDIDATE_SOURCES:
        raise ValueError(f"engine.candidates must be one of {CANDIDATE_SOURCES}, got {eng.candidates!r}")
    with torch.inference_mode():
        if eng.candidates == "all":
            with flush_denormals():     # cegc_ros/denormals.py
                out = model(*args)
            s_ov = torch.sigmoid(out.src_overlap_logits[0]).float().cpu().numpy()
            t_ov = torch.sigmoid(out.tgt_overlap_logits[0]).float().cpu().numpy()
            cand = out.match[0].cpu().numpy()[:, None]                          # (n1, 1)
            w = out.weights[0].float().cpu().numpy()[:, None]
            src_rows = out.src_idx[0].cpu().numpy()
            sim = None
        else:
            extra = None
            if eng.candidates in ("fpfh", "both"):
                extra = torch.from_numpy(fpfh_neighbours(ps.desc, pt.desc, eng.fpfh_candidates)).unsqueeze(0)
            k_learned = eng.learned_candidates if eng.candidates in ("learned", "both") else 0
            with flush_denormals():
                out = model.score_candidates(*args, k_learned=k_learned, extra=extra)
            s_ov = torch.sigmoid(out.src_overlap_logits[0]).float().cpu().numpy()
            t_ov = torch.sigmoid(out.tgt_overlap_logits[0]).float().cpu().numpy()
            cand = out.candidates[0].cpu().numpy()                             # (N, k)
            w = (torch.sigmoid(out.scores[0]) * torch.sigmoid(out.src_overlap_logits[0])[:, None]
                 ).float().cpu().numpy()
            src_rows = np.arange(len(cand))
            # the network's own (HOCE's M_S, computed once; in torch or ONNX Runtime, whose
            # threads the engine sets: a numpy product would wake OpenBLAS's)
            sim = out.similarity[0].float().cpu().numpy()                       # (N, M)
    finite_outputs(candidate_confidences=w, source_overlap_scores=s_ov, target_overlap_scores=t_ov,
                   **({} if sim is None else {"feature_similarities": sim}))
    if eng.confidence == "uniform":
        w = np.ones_like(w)
    corr, weights, rank = select(cand, w, eng.max_correspondences)
    corr[:, 0] = src_rows[corr[:, 0]]
    return Matches(corr, weights, rank, s_ov, t_ov, sim)
