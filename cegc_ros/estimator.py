"""Pose from weighted correspondences: a spatial-compatibility estimator seeded by confidence.

Two estimators share one interface, ``estimate(src, tgt, weights, inlier_distance, cfg)``:

``compatibility`` (the default) follows SC2-PCR (Chen et al., CVPR 2022, "SC^2-PCR: A Second
Order Spatial Compatibility for Efficient and Robust Point Cloud Registration"), written from
the paper:

1. First-order compatibility of correspondences i, j (rigid motions keep lengths):
   ``d_ij = | ||p_i - p_j|| - ||q_i - q_j|| |``, hard ``C_ij = [d_ij < d_thr]`` and soft
   ``S_ij = max(0, 1 - d_ij^2 / d_thr^2)``, zero diagonal.
2. Seeds: the leading eigenvector of ``S`` (spectral matching) times the confidence ``w``,
   then non-maximum suppression in the source (a seed beats every correspondence within
   ``nms_radius`` of its source point); at most ``seed_ratio`` x K seeds. With
   ``sure_seeds`` > 0 and verification on, steps 3-5 first run on that many of the strongest
   seeds alone, and on the rest only when that choice is not sure: its fitness is below
   ``sure_fitness`` and it is not unambiguous either (its ambiguity, step 5, above
   ``sure_ambiguity``, or its fitness below ``sure_min_fitness``). A clean high-overlap pair is
   decided by its first few seeds, and a pair that is not sure gets every seed as before
   (docs/pipeline.md). When the choice of step 5 from these is not sure, a second pass adds
   ``explore_seeds`` drawn at random among the other correspondences (seeded by K) and
   verifies all hypotheses again, with the free-space check: at low overlap the spectral score
   gathers on the largest consistent cluster, often a wrong one (floor on floor), and 59% of
   the failed low-overlap validation pairs had no inlier among 200 spectral seeds while a
   random draw of 200 holds ~3 (docs/pipeline.md).
3. Second-order compatibility of a seed s with every j: ``SC2_sj = C_sj * (C C)_sj`` (how
   many correspondences both agree with), only for the seeds' rows.
4. Consensus per seed: its ``k1`` most compatible correspondences (by ``SC2_sj * w_j``); their
   local SC2 matrix's leading eigenvector times ``w`` weights a Kabsch solve; a second pass
   takes the ``k2`` nearest correspondences in residual among those within ``inlier_distance``
   and solves again (the paper's two-stage sampling).
5. Selection: every hypothesis is scored on all correspondences by
   ``sum_i w_i * max(0, 1 - r_i / inlier_distance)`` (a truncated, confidence-weighted count).
   With ``verify`` > 0 and the two point sets the correspondences come from (``clouds``; the
   engine passes them, with ``verify`` = ``engine.verify_hypotheses``; the ``sc2pcr`` peer does
   not), the ``verify`` best distinct hypotheses are re-ranked by that count times their
   geometric fitness: the share of source points that land within ``inlier_distance`` of a
   target point. In a room, a wrong pose that lays floor on floor and one wall on another
   explains many correspondences but leaves much of the cloud in free space; the true pose
   leaves less. Not in SC2-PCR; chosen on synthetic validation pairs (docs/pipeline.md).
   With ``free_space`` > 0 (in the second pass; in the first when ``explore_seeds`` is 0) and
   the clouds in their sensors' frames (``visibility``: the engine passes the bounded clouds),
   that score is multiplied by ``exp(-free_space x v)``, v the
   share of points each pose puts where the other cloud's sensor saw through
   (cegc_ros/visibility.py): the right low-overlap pose has few inliers and little fitness,
   but it puts nothing in front of what the other sensor saw. With a ``model`` (``engine.verify_score:
   learned``), that pass ranks by the learned verification of cegc_ros/verification.py
   instead: a log-linear score of the count, the feature agreement, the fitness and HOCE's
   confidence of the points each pose lands, fitted on generated training pairs, times its own
   free-space factor (docs/accuracy.md, "Learned verification"). The estimate's ``ambiguity``
   is the best verification score among the verified poses distinct from the chosen one
   (:func:`ambiguity`) over the chosen one's: near 1, the clouds' geometry does not settle the
   pair (docs/pipeline.md, "Ambiguity").
6. Refinement: the best hypothesis is re-solved ``refine_iterations`` times by weighted SVD over
   its inliers, weights ``w_i / (1 + (r_i / inlier_distance)^2)`` (the paper's post-refinement,
   with the learned confidence as prior).

With uniform weights this is SC2-PCR (the ``sc2pcr`` peer of ``cegc-eval`` calls exactly
this). Seeding it with CEGC's confidence is the fusion: seeds, consensus sets and the final
count all prefer what the network trusts, while the compatibility test keeps wrong but
confident matches out (a confidence never makes two correspondences compatible).

``svd`` is the paper's estimator: one confidence-weighted Kabsch over all correspondences.

Costs (K correspondences, S seeds): the compatibility matrix is K x K (K is capped by the
caller, ``engine.max_correspondences``), second order only for the S seed rows: one popcount
of two bit-packed rows (K / 64 words) per compatible (seed, j) pair, at most O(S K^2 / 64).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .refine import landing_evidence
from .verification import VerificationModel, features
from .visibility import FreeSpace

ESTIMATORS = ("compatibility", "svd")


@dataclass
class CompatibilityConfig:
    """Settings of the compatibility estimator; lengths in multiples of ``inlier_distance``.

    SC2-PCR's 3DMatch settings with a 5 cm voxel are inlier threshold = d_thr = NMS radius =
    0.10 m (2 voxels), seed ratio 0.2, k1 = 30, k2 = 20, 10 refinement iterations.
    """

    compat_factor: float = 1.0        # d_thr = compat_factor x inlier_distance
    nms_factor: float = 1.0           # NMS radius = nms_factor x inlier_distance
    seed_ratio: float = 0.2
    max_seeds: int = 200
    k1: int = 30
    k2: int = 20
    refine_iterations: int = 10
    verify: int = 0                   # distinct hypotheses re-ranked by count x fitness or feature
                                      # agreement (needs clouds; 0: off)
    explore_seeds: int = 0            # extra seeds drawn at random among the other correspondences
    free_space: float = 0.0           # verification x exp(-free_space x violations); needs sensor-frame clouds
    sure_fitness: float = 1.01        # second pass (exploring seeds, free space) below this fitness of the first choice
    # ... unless the choice's ambiguity is at most this (and its fitness >= sure_min_fitness)
    sure_ambiguity: float = -1.0
    sure_min_fitness: float = 0.3
    sure_seeds: int = 0               # first try only this many of the strongest seeds; the rest when not sure (0: all)


@dataclass
class Estimate:
    """R (3, 3), t (3,) with tgt ~ R src + t; ``inliers`` (K,) bool under the final pose."""

    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray
    valid: bool
    reason: str = ""
    #: (H, 4, 4) T_target_source of the hypotheses the verification ranked (``verify`` > 0,
    #: best-counted first; before the final refinement): which poses were on the table, for
    #: telling a verification failure from a candidate failure (select_weights --dump).
    hypotheses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    #: the best verification score among the verified poses distinct from the chosen one, over
    #: the chosen one's (:func:`ambiguity`): 0 when none is near it (or nothing was verified),
    #: 1 a tie. How much the clouds' geometry prefers the answer to another alignment.
    ambiguity: float = 0.0
    #: whether the choice took more than the first seeds (their choice was unsure: its fitness
    #: below sure_fitness and not unambiguous), i.e. the rest of the spectral seeds or the
    #: exploring pass (cegc_ros/second_draw.py reads it)
    explored: bool = False


def kabsch(src: np.ndarray, tgt: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Weighted Kabsch for (M, 3) point sets; None when the weights vanish or the points are
    collinear (rotation not determined)."""
    ws = float(w.sum())
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


def batched_kabsch(src: np.ndarray, tgt: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """src, tgt (H, m, 3), w (H, m) -> R (H, 3, 3), t (H, 3). Degenerate sets give some rotation;
    callers score every hypothesis, so a bad one simply loses."""
    wn = w / np.maximum(w.sum(1, keepdims=True), 1e-12)                   # (H, m)
    cs = np.einsum("hm,hmi->hi", wn, src)
    ct = np.einsum("hm,hmi->hi", wn, tgt)
    Hm = np.einsum("hm,hmi,hmj->hij", wn, src - cs[:, None], tgt - ct[:, None])
    U, _, Vt = np.linalg.svd(Hm)
    V = np.transpose(Vt, (0, 2, 1))
    d = np.sign(np.linalg.det(V @ np.transpose(U, (0, 2, 1))))
    d[d == 0] = 1.0
    D = np.zeros((len(src), 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = V @ D @ np.transpose(U, (0, 2, 1))
    return R, ct - np.einsum("hij,hj->hi", R, cs)


def _leading_eigenvector(M: np.ndarray, iterations: int = 20, tol: float = 0.0) -> np.ndarray:
    """Power iteration on non-negative symmetric matrices, batched over leading axes: (..., n, n) -> (..., n).
    ``tol`` > 0: stop early once no entry of the unit iterate moves by more than ``tol``.

    One (n, n) matrix is multiplied on the calling thread (einsum), not by BLAS: a
    matrix-vector product is memory-bound, and beside busy processes each of BLAS's 20
    thread wake-ups waited for a time slice (7 ms idle, 170 ms beside two other jobs at
    n = 1500; docs/performance.md). Stacks of small matrices go to matmul."""
    v = np.ones(M.shape[:-1], M.dtype)                                      # (..., n)
    for _ in range(iterations):
        nxt = np.einsum("ij,j->i", M, v) if M.ndim == 2 else (M @ v[..., None])[..., 0]
        nxt /= np.maximum(np.linalg.norm(nxt, axis=-1, keepdims=True), 1e-12)
        moved = float(np.abs(nxt - v).max()) if tol > 0 else np.inf
        v = nxt
        if moved <= tol:
            break
    return v.astype(np.float64)


#: Rows of the K x K compatibility matrices computed at a time: each block's work stays
#: in the CPU's cache, so the full matrices are written once (float32) instead of being built
#: by a dozen passes over K x K arrays in memory (docs/performance.md).
COMPAT_BLOCK = 64
#: The spectral seed score's power iteration stops when no entry of the unit iterate moves by
#: more than this (at most 20 iterations, as before): 4-8 iterations on typical problems.
SPECTRAL_TOL = 1e-6


def compatibility_matrices(src: np.ndarray, tgt: np.ndarray, d_thr: float
                           ) -> tuple[np.ndarray, np.ndarray]:
    """(K, 3), (K, 3) correspondences -> hard ``[d_ij < d_thr]`` (K, K) bool and soft
    ``max(0, 1 - d_ij^2 / d_thr^2)`` (K, K) float32 compatibility, zero diagonal, with
    ``d_ij = | ||p_i - p_j|| - ||q_i - q_j|| |`` in row blocks of :data:`COMPAT_BLOCK`, in
    float32 from coordinates centred in float64 (a 5 m room: about 1e-6 m of rounding against
    a threshold of centimetres; 2-3x faster than float64 blocks)."""
    K = len(src)
    s = _centred_columns(src)                                              # (3, K) float32
    t = _centred_columns(tgt)
    hard = np.empty((K, K), bool)
    soft = np.empty((K, K), np.float32)
    d_thr32 = np.float32(d_thr)
    inv2 = np.float32(1.0 / (d_thr * d_thr))
    # d_ij = d_ji exactly in float32 (the same squares summed in the same order), so each block
    # computes its columns from its own first row on and the lower triangle is its mirror.
    for a in range(0, K, COMPAT_BLOCK):
        b = min(a + COMPAT_BLOCK, K)
        ds = _distances(s[:, a:b], s[:, a:])
        ds -= _distances(t[:, a:b], t[:, a:])
        np.abs(ds, out=ds)                                                 # d_ij, (b - a, K - a)
        np.less(ds, d_thr32, out=hard[a:b, a:])
        np.square(ds, out=ds)
        ds *= -inv2
        ds += np.float32(1.0)
        np.maximum(ds, np.float32(0.0), out=soft[a:b, a:])
        hard[b:, a:b] = hard[a:b, b:].T
        soft[b:, a:b] = soft[a:b, b:].T
    np.fill_diagonal(hard, False)
    np.fill_diagonal(soft, 0.0)
    return hard, soft


def second_order_rows(hard: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(K, K) bool symmetric compatibility, (S,) row indices -> (S, K) float32
    ``SC2 = C[rows] * (C[rows] @ C)``: for each compatible pair (r, j), how many
    correspondences agree with both.

    From bit-packed rows: only the pairs with ``C_rj = 1`` are counted, each as the popcount
    of two rows ANDed (K / 64 words), where the float32 product computes all S x K x K terms
    (200 x 1500 x 1500: 12-18 ms on two threads, 3-4 ms here on one; the same integers,
    tested)."""
    K = hard.shape[1]
    bits = np.packbits(hard, axis=1)
    bits = np.pad(bits, ((0, 0), (0, -bits.shape[1] % 8))).view(np.uint64)   # (K, ceil(K/64))
    out = np.zeros((len(rows), K), np.float32)
    rows = np.asarray(rows, np.int64)
    # SECOND_ORDER_CHUNK rows at a time: one pass over all their compatible pairs instead of a
    # loop per row (a few ms less at the ~400 rows of a pair in doubt)
    for a in range(0, len(rows), SECOND_ORDER_CHUNK):
        chunk = rows[a:a + SECOND_ORDER_CHUNK]
        i, j = np.nonzero(hard[chunk])                                     # pairs (chunk[i], j) with C = 1
        out[a + i, j] = _popcount_rows(bits[j] & bits[chunk[i]])
    return out


#: Rows of :func:`second_order_rows` counted in one pass (their pairs' words, ~25 x 8 bytes
#: each, stay a few MB).
SECOND_ORDER_CHUNK = 64


#: Set bits of every byte value: the popcount where numpy has no bitwise_count (numpy < 2.0, as
#: Ubuntu 24.04's python3-numpy 1.26 under a colcon build).
_BYTE_BITS = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(1).astype(np.int32)


def _popcount_rows(words: np.ndarray) -> np.ndarray:
    """(n, W) uint64 -> (n,) int32 set bits per row."""
    if hasattr(np, "bitwise_count"):
        return np.bitwise_count(words).sum(1, dtype=np.int32)
    return _BYTE_BITS[words.view(np.uint8)].sum(1, dtype=np.int32)


def _centred_columns(points: np.ndarray) -> np.ndarray:
    """(K, 3) -> (3, K) float32, centred on the mean in float64 first."""
    p = np.asarray(points, np.float64)
    return np.ascontiguousarray((p - p.mean(0)).T, dtype=np.float32)


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distances (n, m) between the columns of a (3, n) and b (3, m), coordinate by
    coordinate (a three-term product is too small for BLAS, whose threads cost more than it)."""
    d = np.subtract.outer(a[0], b[0])
    np.square(d, out=d)
    for axis in (1, 2):
        e = np.subtract.outer(a[axis], b[axis])
        np.square(e, out=e)
        d += e
    return np.sqrt(d, out=d)


def _residuals(R: np.ndarray, t: np.ndarray, src: np.ndarray, tgt: np.ndarray) -> np.ndarray:
    """R (H, 3, 3), t (H, 3) -> residuals (H, K) of every correspondence.

    Coordinates along the rows, (H, 3, K), so that each pass runs over K contiguous values:
    2.8x faster than (H, K, 3) at H = 400, K = 1500, equal to 2e-15 (test_estimator)."""
    diff = R @ np.ascontiguousarray(src.T)                                # (H, 3, K)
    diff += t[:, :, None]
    diff -= tgt.T[None]
    np.square(diff, out=diff)
    return np.sqrt(diff.sum(1))


def _hypotheses(hard: np.ndarray, seeds: np.ndarray, src: np.ndarray, tgt: np.ndarray, w: np.ndarray,
                thr: float, cfg: CompatibilityConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 3-4 for the seeds (S,): poses R (H, 3, 3), t (H, 3) and their residuals (H, K)
    on every correspondence, H = S plus the second-stage solves."""
    K = len(src)
    sc2 = second_order_rows(hard, seeds)                                   # (S, K) float32
    k1 = min(cfg.k1, K)
    rank = sc2 * w[None].astype(np.float32)
    rank[np.arange(len(seeds)), seeds] = np.inf                            # the seed is in its own set
    sets = np.argpartition(-rank, k1 - 1, axis=1)[:, :k1]                  # (S, k1)
    loc = hard[sets[:, :, None], sets[:, None, :]].astype(np.float32)      # (S, k1, k1)
    loc_sc2 = loc * (loc @ loc)
    lw = _leading_eigenvector(loc_sc2) * w[sets]                           # (S, k1)
    lw[lw.sum(1) <= 1e-12] = 1.0
    R, t = batched_kabsch(src[sets], tgt[sets], lw)
    # second stage: the k2 best-fitting correspondences among the hypothesis' inliers.
    res = _residuals(R, t, src, tgt)                                       # (S, K)
    k2 = min(cfg.k2, K)
    near2 = np.argpartition(res, k2 - 1, axis=1)[:, :k2]                   # (S, k2)
    w2 = w[near2] * (np.take_along_axis(res, near2, axis=1) < thr)
    ok2 = (w2 > 0).sum(1) >= 3
    if ok2.any():
        R2, t2 = batched_kabsch(src[near2[ok2]], tgt[near2[ok2]], w2[ok2])
        R, t = np.concatenate([R, R2]), np.concatenate([t, t2])
        res = np.concatenate([res, _residuals(R2, t2, src, tgt)])
    return R, t, res


def _counts(res: np.ndarray, w: np.ndarray, thr: float) -> np.ndarray:
    """Step 5's confidence-weighted truncated count of each hypothesis: residuals (H, K) -> (H,)."""
    return (w[None] * np.clip(1.0 - res / thr, 0.0, None)).sum(1)


def hypothesis_counts(R: np.ndarray, t: np.ndarray, src: np.ndarray, tgt: np.ndarray, w: np.ndarray,
                      inlier_distance: float) -> np.ndarray:
    """Step 5's count of poses R (H, 3, 3), t (H, 3) on correspondences src -> tgt ((K, 3) each)
    with confidences w (K,), as the estimator counts them -> (H,) (cegc_ros/second_draw.py)."""
    w = np.clip(np.nan_to_num(np.asarray(w, np.float64)), 0.0, None)
    res = _residuals(np.asarray(R, np.float64), np.asarray(t, np.float64), np.asarray(src, np.float64),
                     np.asarray(tgt, np.float64))
    return _counts(res, w, float(inlier_distance))


def _more_hypotheses(have: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], hard: np.ndarray,
                     seeds: np.ndarray, src: np.ndarray, tgt: np.ndarray, w: np.ndarray, thr: float,
                     cfg: CompatibilityConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The hypotheses so far, (R, t, residuals, counts), with those of more seeds appended (the
    earlier ones keep their indices)."""
    R, t, res, total = have
    R2, t2, res2 = _hypotheses(hard, seeds, src, tgt, w, thr, cfg)
    return (np.concatenate([R, R2]), np.concatenate([t, t2]), np.concatenate([res, res2]),
            np.concatenate([total, _counts(res2, w, thr)]))


def _verify(R: np.ndarray, t: np.ndarray, total: np.ndarray, thr: float, cfg: CompatibilityConfig,
            clouds: tuple[np.ndarray, np.ndarray], visibility: tuple[np.ndarray, np.ndarray] | None,
            known: dict[int, tuple[float, float, float, float]],
            similarity: np.ndarray | None = None, overlap: np.ndarray | None = None,
            model: VerificationModel | None = None) -> tuple[int, np.ndarray, float, np.ndarray]:
    """Step 5's verification: (the chosen hypothesis, the verified ones best-counted first, the
    chosen one's fitness, their verification scores: exact where they decide the choice or
    :func:`ambiguity`, see :func:`_free_space_scores`). Each score is count x fitness, or with
    ``similarity`` count x feature agreement (:func:`cegc_ros.refine.landing_evidence`); times the
    free-space factor unless ``visibility`` is None. With a ``model``, ``similarity``, the
    source's HOCE ``overlap`` (Ns,) and ``visibility`` (the pass with the free-space check), the
    learned score of cegc_ros/verification.py instead, its free-space weight in place of
    ``cfg.free_space``. ``known``: (fitness, agreement or fitness, overlap landed, overlap
    precision) of hypotheses (by index) an earlier call measured; this call's are added to it."""
    # distinct poses only (many seeds reach the same consensus set), the best-counted first
    key = np.round(np.concatenate([R.reshape(-1, 9) * 100.0, t * (10.0 / thr)], axis=1)).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    top = first[np.argsort(-total[first])][:cfg.verify]
    new = np.array([i for i in top if int(i) not in known], dtype=np.int64)
    if len(new):
        o = overlap if overlap is not None else np.ones(len(clouds[0]))
        evidence = landing_evidence(R[new], t[new], clouds[0], clouds[1], similarity, o, thr)
        known.update(zip(new.tolist(), zip(*(e.tolist() for e in evidence))))
    ev = np.array([known[int(i)] for i in top], np.float64).reshape(len(top), 4)
    fit = ev[:, 0]
    strength = cfg.free_space
    if model is not None and similarity is not None and overlap is not None and visibility is not None \
            and cfg.free_space > 0:
        rank = model.ranks(features(total[top], ev[:, 1], fit, ev[:, 2], ev[:, 3]))
        strength = model.free_space_strength
    else:
        rank = total[top] * ev[:, 1]
    if strength > 0 and visibility is not None:
        rank = _free_space_scores(rank, R[top], t[top], strength, FreeSpace(*visibility),
                                  np.asarray(clouds[0], np.float64), DISTINCT_FACTOR * thr)
    i = int(rank.argmax())
    return int(top[i]), top, float(fit[i]), rank


#: Poses whose free space :func:`_free_space_scores` checks at a time (vectorised over them).
FREE_SPACE_CHUNK = 8


def _free_space_scores(upper: np.ndarray, R: np.ndarray, t: np.ndarray, strength: float,
                       space: FreeSpace, source: np.ndarray, distance: float) -> np.ndarray:
    """Scores ``upper`` (H,) >= 0 times ``exp(-strength x violations)`` of the poses R (H, 3, 3),
    t (H, 3), computed where they can matter and -inf elsewhere: exact for the highest one and
    for every pose :func:`ambiguity` could take as the best distinct rival, so both read the
    same as from all H scores (test_estimator).

    The factor is at most 1, so a pose whose ``upper`` is below an exact score already found
    can beat it in neither role: poses are checked in chunks, highest ``upper`` first, until
    the rest cannot. (Synthetic 20k-point pairs that take the check need 13-33 of their 50.)"""
    rank = np.full(len(upper), -np.inf)
    # stable: among equal upper scores the lower index comes first, so a pose left unchecked
    # with an upper score equal to the best exact one could only tie it from a higher index,
    # where argmax (the first maximum) would not take it
    order = np.argsort(-upper, kind="stable")

    def check(idx: np.ndarray) -> None:
        rank[idx] = upper[idx] * np.exp(-strength * space.violations(R[idx], t[idx]))

    done = 0                                   # order[:done] checked
    while done < len(order) and (done == 0 or upper[order[done]] > rank.max()):
        check(order[done:done + FREE_SPACE_CHUNK])
        done += FREE_SPACE_CHUNK
    # the rest cannot beat the best score: the choice is made; now its best distinct rival
    distinct = _distinct(R, t, int(rank.argmax()), source, distance)
    rest = [int(i) for i in order[done:] if distinct[i]]
    while rest:
        rival = rank[distinct].max()           # rest holds distinct poses: never empty here
        rest = [i for i in rest if upper[i] > rival]
        if rest:
            check(np.array(rest[:FREE_SPACE_CHUNK], np.int64))
        rest = rest[FREE_SPACE_CHUNK:]
    return rank


#: Two poses are distinct alignments when they put the source points more than this many
#: inlier distances apart (root mean square; :func:`ambiguity`). Chosen on synthetic validation
#: pairs (docs/pipeline.md, "Ambiguity"): at 1 a right answer's own near variants count as its
#: rivals; 2 and 3 separate right from wrong answers about equally well.
DISTINCT_FACTOR = 2.0


def ambiguity(R: np.ndarray, t: np.ndarray, rank: np.ndarray, source: np.ndarray, distance: float
              ) -> float:
    """Verified poses R (H, 3, 3), t (H, 3) with their verification scores rank (H,) and the
    source points (Ns, 3) -> the best score among the poses that put the source points more
    than ``distance`` (root mean square) from where the best-scored pose puts them, over the
    best score: 0 (no distinct rival, or nothing scored) to 1 (a tie). A wrong answer at low
    overlap often has a rival close to it (a box-like room laid on itself two ways,
    docs/pipeline.md); a right one at high overlap rarely does."""
    if len(rank) < 2 or not rank.max() > 0:
        return 0.0
    b = int(rank.argmax())
    distinct = _distinct(R, t, b, source, distance)
    return float(rank[distinct].max() / rank[b]) if distinct.any() else 0.0


def _distinct(R: np.ndarray, t: np.ndarray, b: int, source: np.ndarray, distance: float) -> np.ndarray:
    """(H,) bool: pose h puts the source points (Ns, 3) more than ``distance`` (root mean
    square) from where pose b puts them.

    The mean square gap from the points' mean m and covariance C instead of point by point:
    with A = R_h - R_b and e = A m + t_h - t_b, mean_p |A p + t_h - t_b|^2 = tr(A C A^T) + |e|^2
    (both terms >= 0: no cancellation). Equal to the gaps point by point to 1e-12 relative
    (test_estimator), in O(H) instead of O(H Ns): 2.7 -> 0.1 ms at H = 100, Ns = 512."""
    p = np.asarray(source, np.float64)
    m = p.mean(0)
    q = p - m
    C = q.T @ q / len(p)                                                                  # (3, 3)
    A = R - R[b]                                                                          # (H, 3, 3)
    e = A @ m + (t - t[b])                                                                # (H, 3)
    square = np.einsum("hij,jk,hik->h", A, C, A) + np.einsum("hi,hi->h", e, e)
    return np.sqrt(np.maximum(square, 0.0)) > distance


def estimate_compatibility(src: np.ndarray, tgt: np.ndarray, w: np.ndarray, inlier_distance: float,
                           cfg: CompatibilityConfig | None = None,
                           clouds: tuple[np.ndarray, np.ndarray] | None = None,
                           visibility: tuple[np.ndarray, np.ndarray] | None = None,
                           similarity: np.ndarray | None = None, overlap: np.ndarray | None = None,
                           model: VerificationModel | None = None) -> Estimate:
    """Pose from correspondences src[i] -> tgt[i] ((K, 3) each) with confidences w (K,) >= 0.
    ``clouds``: the (Ns, 3) source and (Nt, 3) target point sets the correspondences were drawn
    from, for the geometric verification of step 5 (None: the count alone, as SC2-PCR);
    ``visibility``: the two clouds in their sensors' frames for its free-space check (None: no
    check); ``similarity``: (Ns, Nt) descriptor similarity (cosines) of the clouds' points: the
    verification weighs each hypothesis by its feature agreement instead of its fitness;
    ``overlap`` (Ns,): HOCE's confidence of the source points and ``model``: the learned
    verification (cegc_ros/verification.py) of the pass with the free-space check, which needs
    both and ``similarity``."""
    cfg = cfg or CompatibilityConfig()
    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    w = np.clip(np.nan_to_num(np.asarray(w, np.float64)), 0.0, None)
    K = len(src)
    none = Estimate(np.eye(3), np.zeros(3), np.zeros(K, bool), False)
    if K < 3 or w.sum() <= 1e-12:
        none.reason = f"{K} correspondences with positive confidence, at least 3 are needed"
        return none
    thr = float(inlier_distance)
    d_thr = cfg.compat_factor * thr
    hard, soft = compatibility_matrices(src, tgt, d_thr)                   # (K, K) bool, float32

    # 2. seeds: spectral score x confidence, non-maximum suppression in the source.
    score = _leading_eigenvector(soft, tol=SPECTRAL_TOL) * w
    # A seed beats every correspondence whose source point lies within the NMS radius: the
    # neighbour pairs from a k-d tree (a few per point) instead of a pass over the K x K matrix.
    from scipy.spatial import cKDTree
    pairs = cKDTree(src).query_pairs(cfg.nms_factor * thr, output_type="ndarray")   # (P, 2), i < j
    s32 = score.astype(np.float32)
    row_max = s32.copy()                                                   # each point's own score
    np.maximum.at(row_max, pairs[:, 0], s32[pairs[:, 1]])
    np.maximum.at(row_max, pairs[:, 1], s32[pairs[:, 0]])
    local_max = score >= row_max
    cand = np.flatnonzero(local_max & (score > 0))
    n_seeds = max(1, min(cfg.max_seeds, int(np.ceil(cfg.seed_ratio * K)), len(cand)))
    if len(cand) == 0:
        none.reason = "no correspondence is compatible with any other"
        return none
    seeds = cand[np.argsort(-score[cand])[:n_seeds]]                       # (S,)
    verifying = clouds is not None and cfg.verify > 0
    tried = len(seeds)
    if verifying and 0 < cfg.sure_seeds < len(seeds):
        tried = cfg.sure_seeds
    R, t, res = _hypotheses(hard, seeds[:tried], src, tgt, w, thr, cfg)

    # 5. selection by the confidence-weighted truncated count.
    total = _counts(res, w, thr)
    best = int(total.argmax())
    hypotheses = np.zeros((0, 4, 4))
    rivalry = 0.0
    explored = False
    if verifying:
        explore = cfg.explore_seeds > 0
        known: dict[int, tuple[float, float, float, float]] = {}
        source = np.asarray(clouds[0], np.float64)

        def verified(vis: tuple[np.ndarray, np.ndarray] | None) -> tuple[int, np.ndarray, float, float]:
            """_verify's choice, the verified ones and the choice's fitness, with its ambiguity."""
            best, top, fit, rank = _verify(R, t, total, thr, cfg, clouds, vis, known, similarity, overlap,
                                           model)
            return best, top, fit, ambiguity(R[top], t[top], rank, source, DISTINCT_FACTOR * thr)

        def unsure(fit: float, rivalry: float) -> bool:
            """Whether the choice needs more hypotheses: its fitness is below sure_fitness and
            it is not an unambiguous (ambiguity <= sure_ambiguity) fit one either."""
            return fit < cfg.sure_fitness and not (fit >= cfg.sure_min_fitness and 0 <= cfg.sure_ambiguity
                                                   and rivalry <= cfg.sure_ambiguity)
        best, top, fit, rivalry = verified(None if explore else visibility)
        if tried < len(seeds) and unsure(fit, rivalry):
            explored = True
            # the strongest seeds left the pair unsure: the rest of the spectral seeds
            R, t, res, total = _more_hypotheses((R, t, res, total), hard, seeds[tried:], src, tgt, w, thr, cfg)
            best, top, fit, rivalry = verified(None if explore else visibility)
        if explore and unsure(fit, rivalry):
            explored = True
            # not sure: more seeds drawn at random among the rest, all hypotheses verified again
            # with the free-space check
            rest = np.setdiff1d(np.flatnonzero(w > 0), seeds)
            if len(rest):
                pick = np.random.default_rng(K).choice(len(rest), min(cfg.explore_seeds, len(rest)),
                                                       replace=False)
                R, t, res, total = _more_hypotheses((R, t, res, total), hard, rest[np.sort(pick)], src, tgt, w,
                                                    thr, cfg)
            best, top, fit, rivalry = verified(visibility)
        hypotheses = np.tile(np.eye(4), (len(top), 1, 1))
        hypotheses[:, :3, :3], hypotheses[:, :3, 3] = R[top], t[top]
    Rb, tb, rb = R[best], t[best], res[best]

    # 6. refinement on the inliers with robust weights.
    for _ in range(cfg.refine_iterations):
        inl = rb < thr
        if inl.sum() < 3:
            break
        sol = kabsch(src[inl], tgt[inl], w[inl] / (1.0 + (rb[inl] / thr) ** 2))
        if sol is None:
            break
        Rn, tn = sol
        rn = np.linalg.norm(src @ Rn.T + tn - tgt, axis=1)
        if (w * np.clip(1.0 - rn / thr, 0, None)).sum() + 1e-12 < (w * np.clip(1.0 - rb / thr, 0, None)).sum():
            break
        Rb, tb, rb = Rn, tn, rn
    inliers = rb < thr
    if inliers.sum() < 3:
        return Estimate(Rb, tb, inliers, False, "fewer than 3 correspondences agree with any hypothesis",
                        hypotheses, rivalry, explored)
    return Estimate(Rb, tb, inliers, True, hypotheses=hypotheses, ambiguity=rivalry, explored=explored)


def estimate_svd(src: np.ndarray, tgt: np.ndarray, w: np.ndarray, inlier_distance: float,
                 cfg: CompatibilityConfig | None = None) -> Estimate:
    """The paper's estimator: one confidence-weighted Kabsch over all correspondences."""
    src = np.asarray(src, np.float64)
    tgt = np.asarray(tgt, np.float64)
    w = np.clip(np.nan_to_num(np.asarray(w, np.float64)), 0.0, None)
    sol = kabsch(src, tgt, w)
    if sol is None:
        return Estimate(np.eye(3), np.zeros(3), np.zeros(len(src), bool), False,
                        "degenerate correspondences (weights ~0 or collinear points)")
    R, t = sol
    inliers = np.linalg.norm(src @ R.T + t - tgt, axis=1) < inlier_distance
    return Estimate(R, t, inliers, True)


def estimate(name: str, src: np.ndarray, tgt: np.ndarray, w: np.ndarray, inlier_distance: float,
             cfg: CompatibilityConfig | None = None,
             clouds: tuple[np.ndarray, np.ndarray] | None = None,
             visibility: tuple[np.ndarray, np.ndarray] | None = None,
             similarity: np.ndarray | None = None, overlap: np.ndarray | None = None,
             model: VerificationModel | None = None) -> Estimate:
    """Dispatch by estimator name (``ESTIMATORS``); ``clouds``, ``visibility``, ``similarity``,
    ``overlap`` and ``model`` only matter to ``compatibility``."""
    if name == "compatibility":
        return estimate_compatibility(src, tgt, w, inlier_distance, cfg, clouds, visibility, similarity,
                                      overlap, model)
    if name == "svd":
        return estimate_svd(src, tgt, w, inlier_distance, cfg)
    raise ValueError(f"estimator must be one of {ESTIMATORS}, got {name!r}")
