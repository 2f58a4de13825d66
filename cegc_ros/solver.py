"""Confidence-guided robust pose from CEGC's weighted correspondences (numpy, batched).

The paper solves one confidence-weighted SVD over all argmax correspondences. When fewer than
about half of them are right (typical on real data after CPU-budget training), that least-
squares solution is pulled away by the wrong ones. This solver keeps the network's confidences
in charge and adds hypothesis testing:

1. draw ``hypotheses`` (5000) minimal sets of 3 correspondences, each drawn with probability
   proportional to its confidence w_i;
2. solve each with Kabsch (batched), reject sets whose point triangles disagree in shape;
3. score each hypothesis by the summed confidence of the correspondences it explains
   (residual < ``inlier_distance``);
4. refine the best with confidence-weighted SVD on its inliers, re-selecting inliers a few
   times (the paper's estimator, on the set it should see).

Seeded, so a given input always gives the same answer.

Measured and dropped: re-ranking the 10 best hypotheses by how many points of the whole clouds
they align (geometric verification) lowered recall@5 on 40 synthetic 7Scenes test pairs from
0.90 to 0.78 (boxy rooms: wrong hypotheses still align walls). More hypotheses helped
(2000 -> 5000: 0.90 -> 0.95).
"""

from __future__ import annotations

import numpy as np


def kabsch_weighted(src: np.ndarray, tgt: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Weighted Kabsch for (M, 3) point sets; None when degenerate."""
    ws = w.sum()
    if ws <= 1e-12 or len(src) < 3:
        return None
    wn = w / ws
    cs, ct = wn @ src, wn @ tgt
    H = (src - cs).T @ ((tgt - ct) * wn[:, None])
    U, S, Vt = np.linalg.svd(H)
    if S[1] < 1e-9 * max(S[0], 1e-12):
        return None
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, ct - R @ cs


def _batched_kabsch(src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """src, tgt (H, 3, 3) triplets -> R (H, 3, 3), t (H, 3)."""
    cs, ct = src.mean(1, keepdims=True), tgt.mean(1, keepdims=True)
    Hm = np.einsum("hki,hkj->hij", src - cs, tgt - ct)
    U, _, Vt = np.linalg.svd(Hm)
    V = np.transpose(Vt, (0, 2, 1))
    d = np.sign(np.linalg.det(V @ np.transpose(U, (0, 2, 1))))
    d[d == 0] = 1.0
    D = np.zeros((len(src), 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = V @ D @ np.transpose(U, (0, 2, 1))
    t = ct[:, 0] - np.einsum("hij,hj->hi", R, cs[:, 0])
    return R, t


def robust_pose(src: np.ndarray, tgt: np.ndarray, w: np.ndarray, inlier_distance: float,
                hypotheses: int = 5000, seed: int = 0, refine_iters: int = 3,
                max_hypotheses: int = 0, confidence: float = 0.999,
                stats: dict | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Best rigid (R, t) for correspondences src[i] -> tgt[i] with confidences w.

    Hypotheses are drawn in rounds of ``hypotheses``. With ``max_hypotheses`` above that,
    rounds continue until the usual RANSAC stopping rule is met for the best hypothesis so
    far: with q = sampling probability of drawing one of its inliers, a round count giving an
    all-inlier triplet with probability ``confidence`` (N >= log(1 - confidence) / log(1 - q^3)),
    or until ``max_hypotheses`` were drawn. Easy pairs (many inliers) stop after one round.

    Args:
        src, tgt: (M, 3) corresponding points; w: (M,) confidences >= 0.
        inlier_distance: residual under which a correspondence counts as explained.
        stats: when given, receives ``drawn`` (hypotheses drawn).
    Returns:
        R (3, 3), t (3,), inlier mask (M,), valid.
    """
    M = len(src)
    w = np.clip(np.nan_to_num(np.asarray(w, np.float64)), 0.0, None)
    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    none = (np.eye(3), np.zeros(3), np.zeros(M, bool), False)
    if M < 3 or w.sum() <= 1e-12:
        return none
    rng = np.random.default_rng(seed)
    p = (w + 1e-6 * w.max()) / (w + 1e-6 * w.max()).sum()
    budget = max(hypotheses, max_hypotheses)
    drawn, best_score = 0, -1.0
    Rb = tb = inl = None
    while drawn < budget:
        n = min(hypotheses, budget - drawn)
        drawn += n
        idx = rng.choice(M, size=(n, 3), replace=True, p=p)
        a, b = src[idx], tgt[idx]                                       # (H, 3, 3)
        # Shape check: a rigid motion keeps the triangle's edge lengths.
        ea = np.linalg.norm(a - np.roll(a, 1, axis=1), axis=2)
        eb = np.linalg.norm(b - np.roll(b, 1, axis=1), axis=2)
        ok = (np.abs(ea - eb) < 2 * inlier_distance).all(1) & (ea > 2 * inlier_distance).all(1)
        if ok.any():
            R, t = _batched_kabsch(a[ok], b[ok])
            res = np.linalg.norm(np.einsum("hij,mj->hmi", R, src) + t[:, None] - tgt[None], axis=2)
            score = ((res < inlier_distance) * w[None]).sum(1)                      # (H,)
            k = int(score.argmax())
            if score[k] > best_score:
                best_score, Rb, tb, inl = float(score[k]), R[k], t[k], res[k] < inlier_distance
        if inl is not None:
            q = float(p[inl].sum())
            if q >= 1.0 or drawn >= np.log(1.0 - confidence) / np.log(max(1.0 - q ** 3, 1e-12)):
                break
    if stats is not None:
        stats["drawn"] = drawn
    if inl is None:
        return none
    for _ in range(refine_iters):
        sol = kabsch_weighted(src[inl], tgt[inl], w[inl])
        if sol is None:
            break
        Rb, tb = sol
        new = np.linalg.norm(src @ Rb.T + tb - tgt, axis=1) < inlier_distance
        if new.sum() < 3 or (new == inl).all():
            inl = new if new.sum() >= 3 else inl
            break
        inl = new
    return Rb, tb, inl, bool(inl.sum() >= 3)
