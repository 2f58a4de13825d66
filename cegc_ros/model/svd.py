"""Confidence-weighted SVD (weighted Kabsch) with reflection handling and validity checks."""

from __future__ import annotations

import torch
from torch import Tensor


def weighted_kabsch(src: Tensor, tgt: Tensor, weights: Tensor, eps: float = 1e-6
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """Rigid (R, t) minimising sum_i w_i ||R src_i + t - tgt_i||^2.

    Args:
        src: (B, M, 3) source points.
        tgt: (B, M, 3) corresponding target points.
        weights: (B, M) non-negative weights.
    Returns:
        R (B, 3, 3), t (B, 3), valid (B,) bool. Where the problem is degenerate (weights sum to
        ~0, or the weighted points are collinear / coincident so the rotation is not determined)
        R = I, t = weighted centroid difference (or 0) and valid is False; nothing is NaN.

    The solve always runs in float32, autocast off (``torch.linalg.svd`` and ``torch.det`` have no
    bf16 kernel on CPU), so it is safe inside a bf16 autocast region.
    """
    with torch.autocast(device_type=src.device.type, enabled=False):
        return _weighted_kabsch_fp32(src, tgt, weights, eps)


def _weighted_kabsch_fp32(src: Tensor, tgt: Tensor, weights: Tensor, eps: float) -> tuple[Tensor, Tensor, Tensor]:
    src = src.float()
    tgt = tgt.float()
    w = weights.float().clamp_min(0.0)                                   # (B, M)
    wsum = w.sum(dim=1, keepdim=True)                                    # (B, 1)
    ok_w = wsum.squeeze(1) > eps
    wn = w / wsum.clamp_min(eps)                                         # (B, M)
    c_src = (wn.unsqueeze(-1) * src).sum(dim=1)                          # (B, 3)
    c_tgt = (wn.unsqueeze(-1) * tgt).sum(dim=1)                          # (B, 3)
    xs = src - c_src.unsqueeze(1)
    ys = tgt - c_tgt.unsqueeze(1)
    H = torch.einsum("bm,bmi,bmj->bij", wn, xs, ys)                      # (B, 3, 3)
    # A tiny isotropic term keeps the SVD gradient finite when singular values coincide.
    H_reg = H + 1e-9 * torch.eye(3, device=H.device, dtype=H.dtype)
    U, S, Vh = torch.linalg.svd(H_reg)
    V = Vh.transpose(-1, -2)
    d = torch.sign(torch.det(V @ U.transpose(-1, -2)))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    R = V @ D @ U.transpose(-1, -2)                                      # (B, 3, 3)
    # Rank check: the second singular value must be a meaningful fraction of the spread.
    spread = (wn.unsqueeze(-1) * xs.pow(2)).sum(dim=(1, 2)) + (wn.unsqueeze(-1) * ys.pow(2)).sum(dim=(1, 2))
    ok_rank = S[:, 1] > 1e-4 * spread.clamp_min(1e-12)
    valid = ok_w & ok_rank & torch.isfinite(R).all(dim=(1, 2))
    eye = torch.eye(3, device=R.device, dtype=R.dtype).expand_as(R)
    R = torch.where(valid.view(-1, 1, 1), R, eye)
    t = c_tgt - (R @ c_src.unsqueeze(-1)).squeeze(-1)
    t = torch.where(ok_w.view(-1, 1) & torch.isfinite(t), t, torch.zeros_like(t))
    return R, t, valid
