"""CAMS: pairwise correspondence scores with Context Feature Modulation (paper section
"Correspondence Search via CAMS").

For every candidate pair (o_x_i, o_y_j) of the two top-N overlap subsets:
    F_S = [o_x, o_y, ||o_x - o_y||]          -> F'_S = f_C5(F_S)
    F_G = [f_x, f_y, ||f_x - f_y||]          -> F'_G = f_C5(F_G)
    F'_H = f_C5(F'_S * F'_G)
    F^o = f_C6([o_x, o_y, ||o_x - o_y||]),  m = mean_ij F^o
    gamma = sigmoid(f_mod(F^o, m)),  F''_H = f_C7(gamma * F'_H)  (a score per pair)
    w_i = sigmoid(f(max_j gamma * F'_H))     (confidence of row i's match)

Implementation choices (recorded here, where the code is):
- No (N, N, 513) tensor is ever built. The first linear layer of each descriptor MLP is split:
  W [a; b; d] = A a + B b + c d, so A f_x and B f_y are computed once per point and only the
  scalar norm term is per pair. Rows are processed in chunks of ``chunk_rows`` so that memory
  grows as chunk_rows x N x C5, not N^2 x 513.
- m needs every pair, so F^o is evaluated in two passes (one for m, one for gamma).
- ``variant == "ri"``: raw coordinates of two clouds in different frames carry no rotation-
  invariant information, so the spatial descriptor uses each point's distance to its cloud's
  centroid and the distance of the two points' FPFH descriptors,
  [rho_x, rho_y, |rho_x - rho_y|, ||FPFH_x - FPFH_y||]. The descriptor distance hands CAMS the
  classical matching cue from the first step (FPFH nearest neighbours alone are right for
  about 20-30% of overlapping points on our pairs), so training refines it instead of
  rediscovering it. ``variant == "paper"`` uses the paper's descriptor.
- ``centre == "overlap"`` (variant "ri"): rho is measured from the centroid of each cloud's
  points weighted by HOCE's overlap probability to the power ``centre_power`` (gradient
  stopped), not from the cloud's own centroid. Why: at low overlap the two clouds' own centroids
  lie far apart in the scene, so |rho_x - rho_y| of a true correspondence is as large as a false
  one's (on 60 validation pairs under 30% overlap it tells true from false correspondences at a
  median AUC of 0.53), where measured from the true overlap's centroids it would be a strong cue
  (0.92); HOCE's sharpened estimate of that centroid gives 0.64 at power 16 (0.57 at 4, 0.54 at
  1), about as much as the confidences themselves (0.65) (runs/s32/rho_study.py, a throwaway
  study; docs/training.md, arm 19). "own" is every checkpoint before arm 19. With
  ``centre_gradient`` (training only; the forward pass is the same) CAMS's losses also reach
  HOCE's logits through the centre, so HOCE learns to put the centre where CAMS needs it
  (arm 20); arm 19 trained with the gradient stopped.
- f_mod reads [F^o_ij, m] through a split linear layer (F^o_ij and m projected separately).
- No normalisation layers inside CAMS: they would run over N^2 x C5 elements for little gain.
- Candidates, not all pairs (:meth:`CAMS.score_candidates`, the engine's default): the same
  layers score, for each source point i, only its k candidate partners cand[i] (the learned
  feature space's nearest neighbours and FPFH's, chosen by the caller), so the pair embedding
  and CFM's global context m (the mean of F^o over the scored pairs) cost N x k instead of
  N x M. Why: the all-pairs grid grows as N^2 (CAMS took 381 of 762 ms at 2048 points) while
  a true partner almost always ranks among a few nearest neighbours in descriptor space, and
  the estimator downstream only ever uses a few candidates per point. :meth:`CAMS.forward`
  (all pairs of the top-N sets) stays the paper-faithful path.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .features import gather


class SplitPairLinear(nn.Module):
    """Linear layer over the pair descriptor [a_i, b_j, d_ij] without materialising it.

    ``d_ij`` holds ``n_dist`` per-pair scalars (distances), so the layer is
    W [a; b; d] = A a_i + B b_j + D d_ij.
    """

    def __init__(self, c_a: int, c_out: int, n_dist: int = 1) -> None:
        super().__init__()
        self.a = nn.Linear(c_a, c_out)
        self.b = nn.Linear(c_a, c_out, bias=False)
        self.d = nn.Parameter(torch.zeros(n_dist, c_out))
        nn.init.normal_(self.d, std=0.1)

    def project(self, a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
        """Per-point halves: a (B, N, c_a) -> (B, N, C), b (B, M, c_a) -> (B, M, C)."""
        return self.a(a), self.b(b)

    def combine(self, pa: Tensor, pb: Tensor, dist: Tensor) -> Tensor:
        """pa (B, r, C), pb (B, M, C), dist (B, r, M, n_dist) -> (B, r, M, C)."""
        return pa.unsqueeze(2) + pb.unsqueeze(1) + dist @ self.d


class CAMS(nn.Module):
    def __init__(self, feat_dim: int, c5: int, variant: str, chunk_rows: int, centre: str = "own",
                 centre_power: float = 16.0, centre_gradient: bool = False) -> None:
        super().__init__()
        self.variant = variant
        self.centre = centre
        self.centre_power = centre_power
        self.centre_gradient = centre_gradient
        self.chunk_rows = chunk_rows
        c_sp, n_sp = (3, 1) if variant == "paper" else (1, 2)
        self.sp1 = SplitPairLinear(c_sp, c5, n_sp)  # f_C5 on F_S, first layer
        self.sp2 = nn.Linear(c5, c5)
        self.ft1 = SplitPairLinear(feat_dim, c5)   # f_C5 on F_G, first layer
        self.ft2 = nn.Linear(c5, c5)
        self.fuse = nn.Linear(c5, c5)              # f_C5 on F'_S * F'_G
        self.ctx1 = SplitPairLinear(c_sp, c5, n_sp)  # f_C6 on the spatial descriptor
        self.ctx2 = nn.Linear(c5, c5)
        self.mod_pair = nn.Linear(c5, c5)          # f_mod(F^o_ij, m)
        self.mod_glob = nn.Linear(c5, c5, bias=False)
        self.mod_out = nn.Linear(c5, c5)
        self.score = nn.Linear(c5, 1)              # f_C7
        self.weight = nn.Linear(c5, 1)             # f in w_i = sigmoid(f(max_j gamma F'_H))

    def _spatial(self, ox: Tensor, oy: Tensor, lx: Tensor | None = None, ly: Tensor | None = None
                 ) -> tuple[Tensor, Tensor]:
        """The spatial descriptors of the points ox (B, N, 3), oy (B, M, 3): themselves
        (variant "paper") or their distances (B, N, 1), (B, M, 1) from their cloud's centre,
        which with ``centre`` "overlap" reads HOCE's overlap logits lx (B, N), ly (B, M)."""
        if self.variant == "paper":
            return ox, oy
        if self.centre == "overlap":
            if lx is None or ly is None:
                raise ValueError("CAMS centre 'overlap' needs HOCE's overlap logits of both clouds")
            return self._radius(ox, lx), self._radius(oy, ly)
        rx = (ox - ox.mean(dim=1, keepdim=True)).norm(dim=-1, keepdim=True)   # (B, N, 1)
        ry = (oy - oy.mean(dim=1, keepdim=True)).norm(dim=-1, keepdim=True)
        return rx, ry

    def _radius(self, o: Tensor, logits: Tensor) -> Tensor:
        """Distances (B, N, 1) of the points o (B, N, 3) from their centroid weighted by
        sigmoid(logits (B, N)) ** centre_power; no gradient reaches the logits unless
        ``centre_gradient``."""
        if not self.centre_gradient:
            logits = logits.detach()
        # the normalised weights in log space: no underflow when every logit is very negative
        w = torch.softmax(self.centre_power * torch.nn.functional.logsigmoid(logits), dim=1)
        c = (w.unsqueeze(-1) * o).sum(dim=1, keepdim=True)                    # (B, 1, 3)
        return (o - c).norm(dim=-1, keepdim=True)

    def forward(self, ox: Tensor, oy: Tensor, fx: Tensor, fy: Tensor,
                dx: Tensor | None = None, dy: Tensor | None = None,
                lx: Tensor | None = None, ly: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """ox (B, N, 3), oy (B, M, 3), fx (B, N, C), fy (B, M, C), descriptors dx (B, N, D),
        dy (B, M, D) (variant "ri"), HOCE's overlap logits lx (B, N), ly (B, M) (centre
        "overlap") -> scores (B, N, M) (F''_H) and row confidence logits (B, N)."""
        sx, sy = self._spatial(ox, oy, lx, ly)
        sdist_full = torch.cdist(sx, sy).unsqueeze(-1)                   # (B, N, M, 1)
        if self.variant != "paper":
            if dx is None or dy is None:
                raise ValueError("CAMS variant 'ri' needs the per-point descriptors")
            sdist_full = torch.cat([sdist_full, torch.cdist(dx, dy).unsqueeze(-1)], dim=-1)  # (B, N, M, 2)
        fdist_full = torch.cdist(fx, fy).unsqueeze(-1)                   # (B, N, M, 1)
        sp_a, sp_b = self.sp1.project(sx, sy)
        ft_a, ft_b = self.ft1.project(fx, fy)
        cx_a, cx_b = self.ctx1.project(sx, sy)
        relu = torch.relu
        rows = range(0, ox.shape[1], self.chunk_rows)

        def ctx_chunk(s: slice) -> Tensor:
            h = relu(self.ctx1.combine(cx_a[:, s], cx_b, sdist_full[:, s]))
            return relu(self.ctx2(h))                                    # (B, r, M, C)  F^o

        # Pass 1: the global summary m = mean over all pairs of F^o.
        m = sum(ctx_chunk(slice(r, r + self.chunk_rows)).sum(dim=(1, 2)) for r in rows)
        m = m / (ox.shape[1] * oy.shape[1])                              # (B, C)
        glob = self.mod_glob(m)[:, None, None, :]                        # (B, 1, 1, C)

        scores, conf = [], []
        for r in rows:
            s = slice(r, r + self.chunk_rows)
            fs = relu(self.sp2(relu(self.sp1.combine(sp_a[:, s], sp_b, sdist_full[:, s]))))
            fg = relu(self.ft2(relu(self.ft1.combine(ft_a[:, s], ft_b, fdist_full[:, s]))))
            fh = relu(self.fuse(fs * fg))                                # (B, r, M, C)  F'_H
            gamma = torch.sigmoid(self.mod_out(relu(self.mod_pair(ctx_chunk(s)) + glob)))
            g = gamma * fh
            scores.append(self.score(g).squeeze(-1))                     # (B, r, M)
            conf.append(self.weight(g.max(dim=2).values).squeeze(-1))    # (B, r)
        return torch.cat(scores, dim=1), torch.cat(conf, dim=1)

    def score_candidates(self, ox: Tensor, oy: Tensor, fx: Tensor, fy: Tensor, cand: Tensor,
                         dx: Tensor | None = None, dy: Tensor | None = None,
                         lx: Tensor | None = None, ly: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Scores of the candidate pairs only.

        ox (B, N, 3), oy (B, M, 3), fx (B, N, C), fy (B, M, C), cand (B, N, k) indices into the
        target, descriptors dx (B, N, D), dy (B, M, D) (variant "ri"), HOCE's overlap logits lx
        (B, N), ly (B, M) (centre "overlap") -> scores (B, N, k) (F''_H of pair (i, cand[i, j]))
        and row confidence logits (B, N).
        """
        B, N, k = cand.shape

        def pick(y: Tensor) -> Tensor:                                   # (B, M, C) -> (B, N, k, C)
            return gather(y, cand)

        sx, sy = self._spatial(ox, oy, lx, ly)
        sy_c = pick(sy)                                                  # (B, N, k, c_sp)
        sdist = (sx.unsqueeze(2) - sy_c).norm(dim=-1, keepdim=True)      # (B, N, k, 1)
        if self.variant != "paper":
            if dx is None or dy is None:
                raise ValueError("CAMS variant 'ri' needs the per-point descriptors")
            sdist = torch.cat([sdist, (dx.unsqueeze(2) - pick(dy)).norm(dim=-1, keepdim=True)], dim=-1)
        fdist = (fx.unsqueeze(2) - pick(fy)).norm(dim=-1, keepdim=True)  # (B, N, k, 1)
        relu = torch.relu

        def pair(layer: SplitPairLinear, a: Tensor, b: Tensor, dist: Tensor) -> Tensor:
            pa, pb = layer.project(a, b)
            return pa.unsqueeze(2) + pick(pb) + dist @ layer.d             # (B, N, k, C)

        fo = relu(self.ctx2(relu(pair(self.ctx1, sx, sy, sdist))))       # F^o over the candidates
        m = fo.mean(dim=(1, 2))                                          # (B, C)
        fs = relu(self.sp2(relu(pair(self.sp1, sx, sy, sdist))))
        fg = relu(self.ft2(relu(pair(self.ft1, fx, fy, fdist))))
        fh = relu(self.fuse(fs * fg))                                    # F'_H
        gamma = torch.sigmoid(self.mod_out(relu(self.mod_pair(fo) + self.mod_glob(m)[:, None, None, :])))
        g = gamma * fh
        return self.score(g).squeeze(-1), self.weight(g.max(dim=2).values).squeeze(-1)
