"""CEGC: Confidence Estimation under Global Context (the whole network).

Pipeline (paper section METHOD): AGNN local features -> interleaved self/cross attention ->
HOCE overlap confidence and top-N selection -> CAMS pair scores with CFM -> argmax
correspondences -> confidence-weighted SVD.

Deviations from the paper, each selectable or recorded (see also the module docstrings of
features.py, hoce.py and cams.py):

1. ``variant="ri"`` (default) feeds rotation-invariant encodings instead of raw coordinates:
   AGNN edges are point-pair features from estimated normals plus a per-point FPFH descriptor,
   and CAMS's spatial descriptor uses distances to the centroid and FPFH distances. Reason: the paper's encodings
   are rotation-variant, so the network must learn rotation equivariance from data over
   +-45 deg on three axes, which a CPU budget cannot pay for (shared/notes/TRAINING_FACTS.md:
   0% recall after 40 CPU-minutes). ``variant="paper"`` keeps the paper's encodings.
2. During training the correspondences are soft (softmax over each score row, temperature
   ``match_temperature``) so the pose loss reaches the scores; inference uses the paper's
   argmax. The loss adds a dense correspondence term (see losses.py).
3. The confidence head w_i is additionally supervised with match correctness (losses.py).
4. :meth:`CEGC.score_candidates` (the engine's path) scores, for every source point, k
   candidate partners (its nearest neighbours in the learned feature space, plus any the
   caller adds, e.g. FPFH neighbours) instead of all pairs of the top-N sets, and leaves the
   pose to the engine's estimator (cegc_ros/estimator.py). HOCE's overlap confidence becomes a
   per-point weight rather than a hard top-N cut, so low-overlap pairs keep their few true
   matches. ``forward`` keeps the paper's all-pairs path with argmax + weighted SVD.
Ground truth never enters forward(): labels are made in the loss code.

Both clouds go through the AGNN and the attention blocks as one batch when their shapes match
(:meth:`CEGC.features`; the engine feeds both ``preprocess.num_points``): the same function with
equal outputs (test_model), half the kernel launches and larger products (torch on 2 cores:
~20% less time for the network). The ONNX export keeps the per-cloud path (``stack=False``), so
that its graph takes any two point counts; stacked, ONNX Runtime gained only ~5%.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from .cams import CAMS
from .config import ModelConfig
from .features import AGNN, ContextEnhancer, knn, paper_edges, ppf_edges
from .hoce import HOCE, cosine_similarity, top_n_indices
from .svd import weighted_kabsch


@dataclass
class CEGCOutput:
    """What forward() returns. Indices refer to the input clouds' point order."""

    src_overlap_logits: Tensor   # (B, N)
    tgt_overlap_logits: Tensor   # (B, M)
    src_idx: Tensor              # (B, n1) top-N source points
    tgt_idx: Tensor              # (B, n2) top-N target points
    scores: Tensor               # (B, n1, n2) F''_H
    conf_logits: Tensor          # (B, n1) logits of w_i
    match: Tensor                # (B, n1) argmax partner, index into the target cloud
    weights: Tensor              # (B, n1) w_i in [0, 1]
    R: Tensor                    # (B, 3, 3) rotation of T_target_source
    t: Tensor                    # (B, 3)
    valid: Tensor                # (B,) bool


@dataclass
class CandidateOutput:
    """What score_candidates() returns. Indices refer to the input clouds' point order."""

    src_overlap_logits: Tensor   # (B, N) HOCE
    tgt_overlap_logits: Tensor   # (B, M)
    candidates: Tensor           # (B, N, k) target index of each source point's candidates
    scores: Tensor               # (B, N, k) CAMS/CFM pair logits F''_H
    conf_logits: Tensor          # (B, N) logits of w_i (row confidence)
    src_features: Tensor         # (B, N, C2) after self/cross attention
    tgt_features: Tensor         # (B, M, C2)
    similarity: Tensor | None = None   # (B, N, M) cosines of the two features (HOCE's M_S)


def _take(x: Tensor, idx: Tensor) -> Tensor:
    """x (B, N, C), idx (B, n) -> (B, n, C)."""
    return x.gather(1, idx.unsqueeze(-1).expand(-1, -1, x.shape[-1]))


class CEGC(nn.Module):
    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        if cfg.variant == "paper":
            c_edge, c_point = 6, 0
        else:
            c_edge, c_point = 4, cfg.desc_dim
        self.agnn = AGNN(c_edge, c_point, cfg.agnn_dims, cfg.feat_dim)
        self.context = ContextEnhancer(cfg.feat_dim, cfg.attn_heads, cfg.attn_layers, cfg.geo_embedding,
                                       cfg.geo_sigma)
        self.hoce = HOCE(cfg.feat_dim, cfg.hoce_topk)
        self.cams = CAMS(cfg.feat_dim, cfg.cams_dim, cfg.variant, cfg.chunk_rows, cfg.cams_centre,
                         cfg.cams_centre_power, cfg.cams_centre_gradient)

    def encode(self, xyz: Tensor, normals: Tensor | None, desc: Tensor | None) -> Tensor:
        """Per-point local features (B, N, C2) of one cloud."""
        k, d = self.cfg.k, self.cfg.dilation
        near = knn(xyz, k * d, exact=d > 1)                              # (B, N, k d), nearest first
        idx, far = near[..., :k], (near[..., ::d] if d > 1 else None)
        if self.cfg.variant == "paper":
            return self.agnn(paper_edges(xyz, idx), idx, None, far)
        if normals is None or desc is None:
            raise ValueError("variant 'ri' needs normals and descriptors for every cloud")
        return self.agnn(ppf_edges(xyz, normals, idx), idx, desc, far)

    def features(self, src: Tensor, tgt: Tensor, src_normals: Tensor | None, tgt_normals: Tensor | None,
                 src_desc: Tensor | None, tgt_desc: Tensor | None, stack: bool = True
                 ) -> tuple[Tensor, Tensor]:
        """Both clouds' features after self/cross attention: (B, N, C2), (B, M, C2). With
        ``stack`` and equal shapes, as one batch of 2B (the same function, less time)."""
        same = src.shape == tgt.shape and all(
            a is None and b is None or a is not None and b is not None and a.shape == b.shape
            for a, b in ((src_normals, tgt_normals), (src_desc, tgt_desc)))
        if not (stack and same):
            fx = self.encode(src, src_normals, src_desc)
            fy = self.encode(tgt, tgt_normals, tgt_desc)
            return self.context(fx, fy, src, tgt)

        def both(a: Tensor | None, b: Tensor | None) -> Tensor | None:
            return None if a is None else torch.cat([a, b])
        B = src.shape[0]
        f = self.encode(both(src, tgt), both(src_normals, tgt_normals), both(src_desc, tgt_desc))
        f = self.context.stacked(f, B, both(src, tgt))
        return f[:B], f[B:]

    def score_candidates(self, src: Tensor, tgt: Tensor, src_normals: Tensor | None = None,
                         tgt_normals: Tensor | None = None, src_desc: Tensor | None = None,
                         tgt_desc: Tensor | None = None, k_learned: int = 4,
                         extra: Tensor | None = None, stack: bool = True) -> CandidateOutput:
        """Overlap logits and the scores of each source point's candidate partners.

        src (B, N, 3), tgt (B, M, 3) normalised; normals / descriptors as in forward();
        ``k_learned`` nearest target points by cosine similarity of the attention features
        (0: none); ``extra`` (B, N, ke) more candidate indices into the target (e.g. FPFH
        neighbours), appended after the learned ones. Needs at least one candidate. ``stack``:
        see :meth:`features`.
        """
        fx, fy = self.features(src, tgt, src_normals, tgt_normals, src_desc, tgt_desc, stack)
        sim = cosine_similarity(fx, fy)                                  # (B, N, M), computed once
        lx, ly = self.hoce(fx, fy, sim)                                  # (B, N), (B, M)
        parts = []
        k = min(k_learned, tgt.shape[1])
        if k > 0:
            parts.append(sim.topk(k, dim=-1).indices)
        if extra is not None:
            parts.append(extra.to(device=src.device, dtype=torch.long))
        if not parts:
            raise ValueError("score_candidates needs k_learned > 0 or extra candidates")
        cand = torch.cat(parts, dim=-1)                                  # (B, N, k)
        scores, conf = self.cams.score_candidates(src, tgt, fx, fy, cand, src_desc, tgt_desc, lx, ly)
        return CandidateOutput(lx, ly, cand, scores, conf, fx, fy, sim)

    def forward(self, src: Tensor, tgt: Tensor,
                src_normals: Tensor | None = None, tgt_normals: Tensor | None = None,
                src_desc: Tensor | None = None, tgt_desc: Tensor | None = None) -> CEGCOutput:
        """src (B, N, 3), tgt (B, M, 3) in the normalised frame; normals (B, ., 3) and
        descriptors (B, ., desc_dim) for variant 'ri'."""
        fx, fy = self.features(src, tgt, src_normals, tgt_normals, src_desc, tgt_desc)
        lx, ly = self.hoce(fx, fy)                                       # (B, N), (B, M)
        ix = top_n_indices(lx, self.cfg.overlap_ratio)                   # (B, n1)
        iy = top_n_indices(ly, self.cfg.overlap_ratio)                   # (B, n2)
        ox, oy = _take(src, ix), _take(tgt, iy)
        dx = _take(src_desc, ix) if src_desc is not None else None
        dy = _take(tgt_desc, iy) if tgt_desc is not None else None
        scores, conf_logits = self.cams(ox, oy, _take(fx, ix), _take(fy, iy), dx, dy, lx.gather(1, ix),
                                        ly.gather(1, iy))
        weights = torch.sigmoid(conf_logits)                             # (B, n1)
        best = scores.argmax(dim=-1)                                     # (B, n1) into oy
        if self.training:
            p = torch.softmax(scores / self.cfg.match_temperature, dim=-1)
            partner = p @ oy                                             # (B, n1, 3) soft
        else:
            partner = _take(oy, best)
        R, t, valid = weighted_kabsch(ox, partner, weights)
        return CEGCOutput(lx, ly, ix, iy, scores, conf_logits, iy.gather(1, best), weights, R, t, valid)
