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

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from .cegc import CandidateOutput, CEGCOutput


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


def similarity_log_rows(out: CandidateOutput, temperature: float) -> Tensor:
    """Each source point's log-softmax over the target points of the cosine similarities of
    the attention features (what the engine's learned candidates are the top-k of), at
    ``temperature``: (B, N, M), fp32."""
    sim = F.normalize(out.src_features.float(), dim=-1) @ F.normalize(out.tgt_features.float(), dim=-1).transpose(1, 2)
    return torch.log_softmax(sim / temperature, dim=-1)


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


DESCRIPTOR_POSITIVES = ("nearest", "within")


@dataclass
class CandidateLossConfig:
    """Weights of the candidate-path loss (:func:`candidate_loss`); 0 turns a term off."""

    overlap: float = 0.5         # HOCE overlap BCE (the paper's L_O)
    inlier: float = 1.0          # BCE of each candidate pair's score against "is a true match"
    descriptor: float = 1.0      # InfoNCE pulling true partners together in feature space
    pose: float = 0.5            # the paper's L_R on the confidence-weighted Kabsch over candidates
    row: float = 0.2             # BCE of w_i against "one of row i's candidates is a true match"
    rank: float = 0.0            # within-pair ranking of the engine's confidences (rank_loss)
    rank_negatives: int = 256    # the pair's most confident false candidates each true one must beat
    #: within-cloud ranking of HOCE's overlap logits (:func:`rank_loss` on each cloud's points:
    #: every overlapping point above the cloud's ``overlap_rank_negatives`` most confident
    #: non-overlapping ones). Why: the overlap BCE pools a batch, so a low-overlap pair's few
    #: overlapping points weigh little and HOCE's estimate there is compressed (10th-90th
    #: percentiles 0.39-0.55 on the low-overlap validation pairs) with its errors on the points a
    #: wrong pose aligns (docs/accuracy.md); the engine uses only each pair's order of them.
    overlap_rank: float = 0.0
    overlap_rank_negatives: int = 128
    label_factor: float = 2.0    # match threshold = factor x median NN spacing of the target
    nce_temperature: float = 0.1
    #: The descriptor InfoNCE's positives for a source point: "nearest" (its nearest target point
    #: under the ground truth) or "within" (every target point within the match threshold, the
    #: candidates the inlier labels and the engine's evaluation count as true; multi-positive,
    #: log of their summed probability). With "nearest" the other target points within the
    #: threshold (about four: a median of five with the nearest on the validation pairs' 512
    #: network points) are negatives, though a candidate there is a true one (campaign_2026-12-05).
    descriptor_positives: str = "nearest"

    def __post_init__(self) -> None:
        if self.descriptor_positives not in DESCRIPTOR_POSITIVES:
            raise ValueError(f"candidate_loss.descriptor_positives must be one of "
                             f"{DESCRIPTOR_POSITIVES}, got {self.descriptor_positives!r}")


def candidate_loss(out: CandidateOutput, src: Tensor, tgt: Tensor, R_gt: Tensor, t_gt: Tensor,
                   cfg: CandidateLossConfig) -> tuple[Tensor, dict[str, float]]:
    """Loss of :meth:`CEGC.score_candidates`: what the engine scores is what this teaches.

    - inlier classification of the candidate pairs (as PointDSC): the engine's pair confidence
      is sigmoid(score) x sigmoid(overlap), so the score must mean "this pair is a true match";
    - a descriptor loss: cross-entropy of each overlapping source point's cosine similarities
      to all target points (temperature ``nce_temperature``) against its true partner (or, with
      ``descriptor_positives: within``, all of them within the match threshold), so the learned
      candidates (nearest in feature space) contain it;
    - HOCE overlap BCE and the pose loss of the paper, the pose from a weighted Kabsch over all
      candidate pairs with the engine's weights (differentiable, so the weights learn to
      favour pairs that pull the pose right);
    - with ``rank`` > 0, :func:`rank_loss` on the engine's confidences: within each pair, every
      true candidate above that pair's most confident false ones;
    - with ``overlap_rank`` > 0, :func:`rank_loss` on HOCE's overlap logits of each cloud:
      every overlapping point above that cloud's most confident non-overlapping ones.
    All inputs in the normalised frame: src (B, N, 3), tgt (B, M, 3), R_gt (B, 3, 3), t_gt (B, 3).
    """
    from .svd import weighted_kabsch
    B, N, k = out.candidates.shape
    with torch.no_grad():
        thr = cfg.label_factor * spacing(tgt)                            # (B,)
        moved = transform(src, R_gt, t_gt)                               # (B, N, 3)
        lab_x, lab_y = overlap_labels(src, tgt, R_gt, t_gt, thr)
        cand_pts = tgt.gather(1, out.candidates.reshape(B, N * k, 1).expand(-1, -1, 3)).view(B, N, k, 3)
        inl = ((moved.unsqueeze(2) - cand_pts).norm(dim=-1) < thr[:, None, None]).float()   # (B, N, k)
        d = torch.cdist(moved, tgt)                                      # (B, N, M)
        dmin, partner = d.min(dim=-1)
        has = (dmin < thr[:, None]).float()                              # (B, N)
    l_o = 0.5 * F.binary_cross_entropy_with_logits(out.src_overlap_logits, lab_x) \
        + 0.5 * F.binary_cross_entropy_with_logits(out.tgt_overlap_logits, lab_y)
    # inliers are rare on different views: balance the two classes
    pos = inl.sum().clamp_min(1.0)
    neg = (1 - inl).sum().clamp_min(1.0)
    bce = F.binary_cross_entropy_with_logits(out.scores.float(), inl, reduction="none")
    l_i = 0.5 * (bce * inl).sum() / pos + 0.5 * (bce * (1 - inl)).sum() / neg
    logp = similarity_log_rows(out, cfg.nce_temperature)
    if cfg.descriptor_positives == "within":
        with torch.no_grad():     # the nearest always counts, so a row is never empty (finite)
            pos = (d < thr[:, None, None]).scatter(2, partner.unsqueeze(-1), True)
        log_pos = torch.logsumexp(logp.masked_fill(~pos, float("-inf")), dim=-1)   # (B, N)
    else:
        log_pos = logp.gather(2, partner.unsqueeze(-1)).squeeze(-1)
    l_d = -(log_pos * has).sum() / has.sum().clamp_min(1.0)
    w = torch.sigmoid(out.scores.float()) * torch.sigmoid(out.src_overlap_logits.float())[:, :, None]
    R, t, _ = weighted_kabsch(src.unsqueeze(2).expand(-1, -1, k, -1).reshape(B, N * k, 3),
                              cand_pts.reshape(B, N * k, 3), w.reshape(B, N * k))
    eye = torch.eye(3, device=R_gt.device).expand_as(R_gt)
    l_r = ((R_gt.transpose(1, 2) @ R - eye) ** 2).sum(dim=(1, 2)).mean() + ((t_gt - t) ** 2).sum(-1).mean()
    row_lab = inl.max(dim=-1).values
    l_w = F.binary_cross_entropy_with_logits(out.conf_logits.float(), row_lab)
    log_w = F.logsigmoid(out.scores.float()) + F.logsigmoid(out.src_overlap_logits.float())[:, :, None]
    l_k = rank_loss(log_w.reshape(B, N * k), inl.reshape(B, N * k), cfg.rank_negatives) \
        if cfg.rank > 0 else torch.zeros((), device=src.device)
    l_or = 0.5 * rank_loss(out.src_overlap_logits.float(), lab_x, cfg.overlap_rank_negatives) \
        + 0.5 * rank_loss(out.tgt_overlap_logits.float(), lab_y, cfg.overlap_rank_negatives) \
        if cfg.overlap_rank > 0 else torch.zeros((), device=src.device)
    total = cfg.overlap * l_o + cfg.inlier * l_i + cfg.descriptor * l_d + cfg.pose * l_r + cfg.row * l_w \
        + cfg.rank * l_k + cfg.overlap_rank * l_or
    with torch.no_grad():
        best = out.scores.argmax(dim=-1, keepdim=True)
        hit = inl.gather(2, best).squeeze(-1)
        top = (w.reshape(B, -1).topk(min(100, N * k), dim=-1).indices)
        top_prec = inl.reshape(B, -1).gather(1, top).mean()
        learned_recall = (inl.max(dim=-1).values * has).sum() / has.sum().clamp_min(1.0)
    parts = {
        "loss": float(total.detach()), "l_overlap": float(l_o.detach()), "l_inlier": float(l_i.detach()),
        "l_desc": float(l_d.detach()), "l_pose": float(l_r.detach()), "l_row": float(l_w.detach()),
        "l_rank": float(l_k.detach()), "l_overlap_rank": float(l_or.detach()),
        "inlier_frac": float(inl.mean()), "cand_recall": float(learned_recall),
        "match_acc": float((hit * has).sum() / has.sum().clamp_min(1.0)), "top100_precision": float(top_prec),
        "overlap_acc": float(((out.src_overlap_logits > 0).float() == lab_x).float().mean()),
        "overlap_auc": within_auc(out.src_overlap_logits.float(), lab_x),
    }
    return total, parts


@torch.no_grad()
def within_auc(scores: Tensor, labels: Tensor) -> float:
    """Mean over a batch's rows of :func:`cegc_ros.metrics.rank_auc` of scores (B, N) against
    labels (B, N) in {0, 1}: the chance that a positive of a row outscores a negative of the
    same row, ties counting half (bf16 logits tie), as select_weights' overlap_auc counts it.
    Rows without both classes are left out; nan when none has both. HOCE's within-pair quality,
    which the engine uses (it ranks each pair's points), where overlap_acc pools the batch."""
    from ..metrics import rank_auc
    rows = [rank_auc(s, t > 0) for s, t in zip(scores.float().cpu().numpy(), labels.cpu().numpy())]
    rows = [a for a in rows if not math.isnan(a)]
    return sum(rows) / len(rows) if rows else math.nan


def rank_loss(log_w: Tensor, inl: Tensor, negatives: int) -> Tensor:
    """Within-pair ranking of the engine's confidences: log_w (B, K) = log of the confidence
    the engine ranks correspondences by, inl (B, K) in {0, 1} the ground-truth labels. (The
    overlap ranking term passes HOCE's overlap logits and labels of one cloud's points instead.)

    Each true correspondence of a pair must outrank that pair's ``negatives`` most confident
    false ones: mean over (true, hard false) of softplus(log_w_false - log_w_true), each pair
    weighted alike (pairs without a true candidate add nothing). Why: the balanced inlier BCE
    above pools a batch's classes, so a low-overlap pair's 1-2% true candidates weigh little,
    and a classifier can be calibrated over the batch while ranking a hard pair's few true
    matches little better than chance, which is what the estimator's seeds then see (docs/pipeline.md). The
    estimator needs only the head of each pair's ranking right, hence the hard negatives.
    """
    B, K = log_w.shape
    h = min(negatives, K)
    with torch.no_grad():
        masked = log_w.detach().masked_fill(inl > 0, float("-inf"))
        top = masked.topk(h, dim=-1)
        valid = torch.isfinite(top.values).float()                     # (B, h): fewer false ones
    hard = log_w.gather(1, top.indices)                                # (B, h)
    margin = F.softplus(hard[:, None, :] - log_w[:, :, None])          # (B, K, h)
    pair_w = inl[:, :, None] * valid[:, None, :]
    per_pair = (margin * pair_w).sum(dim=(1, 2)) / pair_w.sum(dim=(1, 2)).clamp_min(1.0)
    has = (pair_w.sum(dim=(1, 2)) > 0).float()
    return (per_pair * has).sum() / has.sum().clamp_min(1.0)


@dataclass
class DistillConfig:
    """Distillation (issue: fast everywhere, a smaller network): besides the ground-truth terms, a
    student learns a frozen teacher's outputs on the same pair (:func:`distill_loss`). The
    teacher is an engine checkpoint trained with the same input features (the shipped weights).
    """

    teacher: str = ""            # engine checkpoint of the teacher; "" = no distillation
    weight: float = 1.0          # of distill_loss's sum
    temperature: float = 0.1     # of the feature-similarity rows (as nce_temperature)
    #: at a fresh start (not a resume), start from the teacher's tensors: a narrower student
    #: (fewer channels, the same design) gets each cut to its widths (cegc_ros/model/narrowing.py),
    #: any other student every teacher tensor whose name and shape it shares
    init_from_teacher: bool = True


def distill_loss(student: CandidateOutput, teacher: CandidateOutput, temperature: float
                 ) -> tuple[Tensor, dict[str, float]]:
    """The student's :meth:`CEGC.score_candidates` output against the teacher's on the same
    inputs (the same FPFH candidates appended): HOCE overlap logits and row confidences by
    BCE against the teacher's probabilities; each source point's feature-similarity row over the
    target points (softmax at ``temperature``) by KL to the teacher's, so that the student's
    learned candidates (its nearest targets in feature space) become the teacher's; and the
    pair scores by BCE against the teacher's, wherever a student candidate is one the teacher
    scored too (every FPFH candidate, the learned ones the two share)."""
    def soft_bce(logits: Tensor, target_logits: Tensor) -> Tensor:
        return F.binary_cross_entropy_with_logits(logits.float(), torch.sigmoid(target_logits.float()))

    l_ov = 0.5 * soft_bce(student.src_overlap_logits, teacher.src_overlap_logits) \
        + 0.5 * soft_bce(student.tgt_overlap_logits, teacher.tgt_overlap_logits)
    l_conf = soft_bce(student.conf_logits, teacher.conf_logits)
    lt = similarity_log_rows(teacher, temperature)                        # (B, N, M)
    l_sim = (lt.exp() * (lt - similarity_log_rows(student, temperature))).sum(-1).mean()
    same = student.candidates.unsqueeze(-1) == teacher.candidates.unsqueeze(-2)   # (B, N, ks, kt)
    shared = same.any(-1)
    target = (same.float() * torch.sigmoid(teacher.scores.float()).unsqueeze(-2)).sum(-1) \
        / same.sum(-1).clamp_min(1)
    bce = F.binary_cross_entropy_with_logits(student.scores.float(), target, reduction="none")
    l_score = (bce * shared).sum() / shared.sum().clamp_min(1)
    total = l_ov + l_conf + l_sim + l_score
    return total, {"l_distill": float(total.detach()), "distill_shared": float(shared.float().mean())}
