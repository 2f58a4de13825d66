"""Training losses. Ground-truth labels are made here from the GT transform, never in forward().

Paper: L = lambda * L_O + (1 - lambda) * L_R with lambda = 0.5, where
    L_O = BCE(overlap of X) / 2 + BCE(overlap of Y) / 2
    L_R = ||R*^T R - I||^2 + ||t* - t||^2.
Added (recorded in cegc.py; weights in LossConfig, 0 turns a term off):
    L_C  dense correspondence: cross-entropy of each top-N source point's score row against
         its ground-truth partner (nearest transformed neighbour in the target's top-N set,
         counted when closer than the threshold). Without it the argmax never reaches the scores.
    L_W  confidence: BCE of w_i against "row i's argmax partner is correct".
Distance thresholds are ``label_factor`` times the target's median nearest-neighbour spacing,
so they follow the point density.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from .cegc import CEGCOutput


@dataclass
class LossConfig:
    overlap_lambda: float = 0.5      # lambda (paper: 0.5)
    corr_weight: float = 1.0         # L_C
    conf_weight: float = 0.5         # L_W
    label_factor: float = 2.0        # threshold = factor x median NN spacing of the target


def transform(points: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """points (B, N, 3) -> R points + t."""
    return points @ R.transpose(1, 2) + t.unsqueeze(1)


def spacing(points: Tensor) -> Tensor:
    """Median nearest-neighbour distance per cloud: (B, N, 3) -> (B,)."""
    d = torch.cdist(points, points)
    d = d + torch.eye(points.shape[1], device=points.device) * 1e9
    return d.min(dim=-1).values.median(dim=-1).values


def overlap_labels(src: Tensor, tgt: Tensor, R: Tensor, t: Tensor, thr: Tensor) -> tuple[Tensor, Tensor]:
    """1 where a point has a partner within thr in the other cloud under the GT: (B, N), (B, M)."""
    d = torch.cdist(transform(src, R, t), tgt)                           # (B, N, M)
    return ((d.min(dim=2).values < thr[:, None]).float(),
            (d.min(dim=1).values < thr[:, None]).float())


def _take(x: Tensor, idx: Tensor) -> Tensor:
    return x.gather(1, idx.unsqueeze(-1).expand(-1, -1, x.shape[-1]))


def cegc_loss(out: CEGCOutput, src: Tensor, tgt: Tensor, R_gt: Tensor, t_gt: Tensor,
              cfg: LossConfig, temperature: float) -> tuple[Tensor, dict[str, float]]:
    """Total loss and its parts (floats, for logging). All inputs in the normalised frame;
    ``temperature`` is the model's match_temperature (the scale of the score rows)."""
    with torch.no_grad():
        thr = cfg.label_factor * spacing(tgt)                            # (B,)
        lab_x, lab_y = overlap_labels(src, tgt, R_gt, t_gt, thr)
        ox = _take(src, out.src_idx)                                     # (B, n1, 3)
        oy = _take(tgt, out.tgt_idx)                                     # (B, n2, 3)
        d = torch.cdist(transform(ox, R_gt, t_gt), oy)                   # (B, n1, n2)
        dmin, partner = d.min(dim=-1)                                    # (B, n1)
        has_partner = dmin < thr[:, None]
        pred = out.scores.argmax(dim=-1)
        correct = (d.gather(2, pred.unsqueeze(-1)).squeeze(-1) < thr[:, None]).float()
    l_o = 0.5 * F.binary_cross_entropy_with_logits(out.src_overlap_logits, lab_x) \
        + 0.5 * F.binary_cross_entropy_with_logits(out.tgt_overlap_logits, lab_y)
    eye = torch.eye(3, device=R_gt.device).expand_as(R_gt)
    l_r = ((R_gt.transpose(1, 2) @ out.R - eye) ** 2).sum(dim=(1, 2)).mean() \
        + ((t_gt - out.t) ** 2).sum(-1).mean()
    logp = torch.log_softmax(out.scores / temperature, dim=-1)
    nll = -logp.gather(2, partner.unsqueeze(-1)).squeeze(-1)             # (B, n1)
    mask = has_partner.float()
    l_c = (nll * mask).sum() / mask.sum().clamp_min(1.0)
    l_w = F.binary_cross_entropy_with_logits(out.conf_logits, correct)
    total = cfg.overlap_lambda * l_o + (1 - cfg.overlap_lambda) * l_r \
        + cfg.corr_weight * l_c + cfg.conf_weight * l_w
    parts = {
        "loss": float(total.detach()), "l_overlap": float(l_o.detach()), "l_pose": float(l_r.detach()),
        "l_corr": float(l_c.detach()), "l_conf": float(l_w.detach()),
        "match_acc": float((correct * mask).sum() / mask.sum().clamp_min(1.0)),
        "inlier_frac": float(correct.mean()),
        "overlap_acc": float(((out.src_overlap_logits > 0).float() == lab_x).float().mean()),
    }
    return total, parts
