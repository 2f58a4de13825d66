"""HOCE: hybrid overlap confidence estimation (paper section "Overlap Estimation via HOCE").

S_X = sigmoid(MLP(F_X)) (semantic branch); M_S = cosine similarities between F_X and F_Y
(geometric branch); fusion M_S^X = M_S * S_X (row-wise); refinement S'_X = sigmoid(MLP(M_S^X));
top-N with N = floor(0.5 * points). The same for Y with M_S transposed.

Deviation (recorded here, where the code is): the paper's refinement MLP reads a whole row of
the N_X x N_Y matrix, which ties the layer to N_Y and to the order of Y's points. Here it reads
each row's ``hoce_topk`` largest fused similarities in descending order (plus S_X itself), so
HOCE works for any point count and is equivariant to permutations of either cloud.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .features import mlp


class HOCE(nn.Module):
    def __init__(self, dim: int, topk: int) -> None:
        super().__init__()
        self.topk = topk
        self.semantic = nn.Sequential(mlp([dim, dim // 2, dim // 4]), nn.Linear(dim // 4, 1))
        self.refine = nn.Sequential(mlp([topk + 1, 32, 32]), nn.Linear(32, 1))

    def _refine(self, fused: Tensor, s: Tensor) -> Tensor:
        """fused (B, N, M) rows of M_S^X, s (B, N) -> overlap logits (B, N)."""
        k = min(self.topk, fused.shape[-1])
        top = fused.topk(k, dim=-1).values                               # (B, N, k) descending
        if k < self.topk:
            top = torch.cat([top, top[..., -1:].expand(-1, -1, self.topk - k)], dim=-1)
        return self.refine(torch.cat([top, s.unsqueeze(-1)], dim=-1)).squeeze(-1)

    def forward(self, fx: Tensor, fy: Tensor, ms: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """fx (B, N, C), fy (B, M, C) -> overlap logits for X (B, N) and for Y (B, M). ``ms``:
        M_S when the caller has it (:func:`cosine_similarity` of fx and fy), else computed."""
        sx = torch.sigmoid(self.semantic(fx)).squeeze(-1)                # (B, N)  S_X
        sy = torch.sigmoid(self.semantic(fy)).squeeze(-1)                # (B, M)  S_Y
        if ms is None:
            ms = cosine_similarity(fx, fy)                               # (B, N, M)  M_S
        lx = self._refine(ms * sx.unsqueeze(-1), sx)
        ly = self._refine(ms.transpose(1, 2) * sy.unsqueeze(-1), sy)
        return lx, ly


def cosine_similarity(fx: Tensor, fy: Tensor) -> Tensor:
    """fx (B, N, C), fy (B, M, C) -> (B, N, M) cosines of every source and target feature
    (HOCE's M_S; the learned candidates' and the verification's feature space)."""
    return F.normalize(fx, dim=-1) @ F.normalize(fy, dim=-1).transpose(1, 2)


def top_n_indices(logits: Tensor, ratio: float) -> Tensor:
    """Indices (B, n) of the floor(ratio * N) most confident points, n >= 3."""
    n = max(3, min(logits.shape[1], int(ratio * logits.shape[1])))
    return logits.topk(n, dim=1).indices


def widened_refinement(state: dict[str, Tensor], old_topk: int, new_topk: int) -> dict[str, Tensor]:
    """A CEGC state dict whose HOCE reads ``old_topk`` sorted similarities, made to read
    ``new_topk`` > old_topk with the same outputs: the refinement's first linear map gets zero
    weights for the added similarities (its input is [top-k descending, S_X], so the first
    old_topk columns and S_X's column keep their weights). Training then learns to use them."""
    if not 0 < old_topk < new_topk:
        raise ValueError(f"widening HOCE needs 0 < old_topk < new_topk, got {old_topk} -> {new_topk}")
    key = "hoce.refine.0.0.weight"
    w = state[key]
    if w.shape[1] != old_topk + 1:
        raise ValueError(f"{key} reads {w.shape[1] - 1} similarities, not {old_topk}")
    wide = w.new_zeros((w.shape[0], new_topk + 1))
    wide[:, :old_topk] = w[:, :old_topk]
    wide[:, new_topk] = w[:, old_topk]
    return {**state, key: wide}
