"""A second draw of the network points for the pairs the first leaves in doubt
(``engine.redraw_ambiguity``).

At low overlap which few hundred points the seeded subsample hands the network decides much of
what it can match: on the 337 synthetic validation pairs under 30% overlap two draws (sampling
seeds s and s + :data:`SEED_OFFSET`) register 158 and 165 pairs alone but 188 together
(docs/accuracy.md). So when the estimator's choice needed its exploring pass and still has a
close distinct rival (ambiguity above the threshold), the engine draws the points again,
registers the pair a second time and keeps the answer the learned verification
(cegc_ros/verification.py) scores higher, each answer scored in both draws: its evidence summed
over the draws' correspondences and features, its free-space violations (one imaging of the
bounded clouds) once per draw. A pair the first draw settles pays nothing.

Pure functions of arrays: the engine (cegc_ros/engine.py) does the drawing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .estimator import hypothesis_counts
from .refine import landing_evidence
from .verification import VerificationModel, features
from .visibility import FreeSpace

#: The second draw samples with preprocess.seed + this (any fixed offset would do; a prime
#: keeps it clear of the small seeds users and the evaluation tools pick).
SEED_OFFSET = 7919


def wanted(explored: bool, ambiguity: float, threshold: float) -> bool:
    """Whether a first answer calls for a second draw: the estimator needed its exploring pass
    (``explored``) and the answer's ambiguity is above ``threshold`` (1 or more: never)."""
    return bool(explored) and float(ambiguity) > float(threshold)


@dataclass
class Draw:
    """What scoring a pose needs of one draw: its network points, the correspondences the
    estimator used (as points) with their confidences, the similarity and HOCE's source overlap
    of the network points, and its inlier distance. Metres."""

    source_points: np.ndarray            # (Ns, 3)
    target_points: np.ndarray            # (Nt, 3)
    source_matched: np.ndarray           # (K, 3) source ends of the correspondences
    target_matched: np.ndarray           # (K, 3) target ends
    weights: np.ndarray                  # (K,) confidences
    similarity: np.ndarray | None        # (Ns, Nt) cosines of the attention features
    source_overlap: np.ndarray           # (Ns,) in [0, 1]
    inlier_distance: float


def pose_features(T: np.ndarray, draw: Draw) -> np.ndarray:
    """The learned verification's evidence (:data:`cegc_ros.verification.FEATURES`) of poses T
    (H, 4, 4) on one draw -> (H, len(FEATURES)): the estimator's count and the landing evidence,
    as its verification reads them (also what tools/fit_verification.py fits on)."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    count = hypothesis_counts(R, t, draw.source_matched, draw.target_matched, draw.weights,
                              draw.inlier_distance)
    fit, agree, landed, precision = landing_evidence(R, t, draw.source_points, draw.target_points,
                                                     draw.similarity,
                                                     np.asarray(draw.source_overlap, np.float64),
                                                     draw.inlier_distance)
    return features(count, agree, fit, landed, precision)


def evidence(model: VerificationModel, T: np.ndarray, draw: Draw) -> np.ndarray:
    """The learned verification's linear score (before the free-space term and the scale) of
    poses T (H, 4, 4) on one draw -> (H,)."""
    return model.linear(pose_features(T, draw))


def scores(model: VerificationModel, T: np.ndarray, draws: list[Draw], space: FreeSpace | None) -> np.ndarray:
    """Each pose's score (H,) over all ``draws``: the sum of its :func:`evidence` in each, less
    the model's free-space weight x its violations once per draw (none without ``space``: clouds
    not in their sensors' frames). Higher is better; scores of the same draws compare across
    poses."""
    T = np.asarray(T, np.float64).reshape(-1, 4, 4)
    total = sum(evidence(model, T, d) for d in draws)
    if space is None:
        return total
    return total - len(draws) * model.free_space * space.violations(T[:, :3, :3], T[:, :3, 3])


def choose(model: VerificationModel, T: np.ndarray, valid: np.ndarray, draws: list[Draw],
           space: FreeSpace | None) -> int:
    """Index of the answer to keep among poses T (H, 4, 4) (one per draw, the first draw's
    first): the valid one :func:`scores` rates highest, the first on a tie; the first when none
    is valid."""
    valid = np.asarray(valid, bool)
    if not valid.any():
        return 0
    s = np.where(valid, scores(model, T, draws, space), -np.inf)
    return int(np.argmax(s))
