"""Stages 5 and 6 of the engine: ICP polish on bounded clouds, then the verdict.

ICP runs on at most ``engine.icp_points`` points per cloud (a seeded subsample of the bounded
clouds), so its cost does not depend on the input size. The verdict measures ``fitness`` (the
share of the network's source points within ``inlier_distance`` of the network's target points
after the pose) and a covariance of the pose from the estimator's inlier correspondences.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import parallel


def icp(source: np.ndarray, target: np.ndarray, T: np.ndarray, max_distance: float, iterations: int,
        max_points: int, seed: int = 0) -> np.ndarray:
    """Open3D point-to-plane ICP of (N, 3) onto (M, 3) metres, started from T (4x4); at most
    max_points per cloud. Returns T unchanged when ICP produces a non-finite transform, or when
    Open3D finds its 6x6 system singular (it raises then: a plane, a line, a point, whose pose
    point-to-plane ICP cannot pin down; the legacy ICP returned its start instead).

    Open3D's tensor pipeline (``o3d.t``): the same poses as the legacy ``registration_icp`` to
    1e-9 (test_refine; 1e-14 on the benchmark pairs), in 0.5-0.9x its time (docs/performance.md)."""
    import open3d as o3d
    treg = o3d.t.pipelines.registration
    rng = np.random.default_rng(seed)

    def capped(p: np.ndarray) -> Any:
        p = p if len(p) <= max_points else p[np.sort(rng.choice(len(p), max_points, replace=False))]
        return o3d.t.geometry.PointCloud(o3d.core.Tensor(np.asarray(p, np.float64)))

    ps, pt = capped(source), capped(target)
    pt.estimate_normals(max_nn=30, radius=2.0 * max_distance)
    try:
        res = treg.icp(ps, pt, max_distance, o3d.core.Tensor(np.asarray(T, np.float64)),
                       treg.TransformationEstimationPointToPlane(),
                       treg.ICPConvergenceCriteria(max_iteration=iterations))
    except RuntimeError as err:
        if "Singular" not in str(err):
            raise
        return T
    out = np.asarray(res.transformation.numpy(), np.float64)
    return out if np.isfinite(out).all() else T


def fitness(source: np.ndarray, target: np.ndarray, T: np.ndarray, distance: float) -> float:
    """Fraction of source points within distance of the target after applying T (4, 4)."""
    return float(fitnesses(T[None, :3, :3], T[None, :3, 3], source, target, distance)[0])


def fitnesses(R: np.ndarray, t: np.ndarray, source: np.ndarray, target: np.ndarray, distance: float
              ) -> np.ndarray:
    """:func:`fitness` of H poses at once: R (H, 3, 3), t (H, 3), source (Ns, 3), target (Nt, 3) -> (H,)."""
    near, _ = _nearest(R, t, source, target, distance)
    return near.mean(1)


def landing_evidence(R: np.ndarray, t: np.ndarray, source: np.ndarray, target: np.ndarray,
                     similarity: np.ndarray | None, source_overlap: np.ndarray, distance: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The evidence of H poses R (H, 3, 3), t (H, 3) from one search of the source points
    (Ns, 3) landed on the target points (Nt, 3) -> four (H,) arrays (cegc_ros/verification.py):

    - fitness (:func:`fitnesses`);
    - feature agreement: for each source point the pose puts within ``distance`` of its nearest
      target point, the two points' descriptor similarity (``similarity`` (Ns, Nt): cosines),
      summed and floored at 0 (the fitness when ``similarity`` is None). A fitness that weighs
      each point the pose explains by whether the network sees the same place there: at low
      overlap a wrong pose (a floor laid on the other floor) can explain as many points as the
      right one, but of places the features tell apart (docs/pipeline.md);
    - what HOCE says of the landed points: the share of the source's overlap confidence
      (``source_overlap`` (Ns,) in [0, 1]) on them, and their mean confidence (0 when none lands)."""
    near, j = _nearest(R, t, source, target, distance)
    fit = near.mean(1)
    if similarity is None:
        agree = fit
    else:
        cos = np.asarray(similarity)[np.arange(near.shape[1])[None], j]                 # (H, Ns)
        agree = np.clip(np.where(near, cos, 0.0).sum(1, dtype=np.float64), 0.0, None)
    o = np.asarray(source_overlap, np.float64)
    on = near @ o                                                                        # (H,)
    landed = on / max(float(o.sum()), 1e-12)
    precision = np.divide(on, near.sum(1), out=np.zeros(len(near)), where=near.any(1))
    return fit, agree, landed, precision


def _nearest(R: np.ndarray, t: np.ndarray, source: np.ndarray, target: np.ndarray, distance: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """(H, Ns) whether each source point lands within ``distance`` of a target point under each
    pose, and (H, Ns) that target point's index (a valid index that means nothing where not).
    From :data:`SIDE_BY_SIDE_QUERIES` query points on, the two halves of the queries are searched
    side by side (cegc_ros/parallel.py): the same answers."""
    from scipy.spatial import cKDTree
    moved = np.asarray(source, np.float64)[None] @ np.transpose(R, (0, 2, 1)) + np.asarray(t)[:, None]
    # The search stops at the distance itself (a hair beyond it, so that a neighbour at exactly
    # the distance still counts): the same answers as a wider bound, 1.5x faster.
    bound = float(distance) * (1.0 + 1e-9) if distance > 0 else np.nextafter(0.0, 1.0)
    target = np.asarray(target, np.float64)
    tree = cKDTree(target)
    queries = moved.reshape(-1, 3)

    def search(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return tree.query(q, k=1, distance_upper_bound=bound)

    half = len(queries) // 2
    (d0, j0), (d1, j1) = parallel.both(search, queries[:half], queries[half:],
                                       len(queries) >= SIDE_BY_SIDE_QUERIES)
    d, j = np.concatenate([d0, d1]), np.concatenate([j0, j1])
    return (d <= distance).reshape(len(R), -1), np.minimum(j, len(target) - 1).reshape(len(R), -1)


#: :func:`_nearest` searches its two halves side by side (cegc_ros/parallel.py) from this many
#: query points on: the verification's landing search of 32 or more poses.
SIDE_BY_SIDE_QUERIES = 16384


def median_spacing(points: np.ndarray) -> float:
    """Median nearest-neighbour distance within one cloud, over its distinct points (the
    network's points repeat when a cloud has fewer than preprocess.num_points)."""
    from scipy.spatial import cKDTree
    pts = np.unique(points, axis=0)
    if len(pts) < 2:
        raise ValueError("a cloud needs at least 2 distinct points")
    d, _ = cKDTree(pts).query(pts, k=2)
    return float(np.median(d[:, 1]))


#: Variance reported for a direction the data do not determine (m^2 or rad^2): large and finite,
#: so that a consumer's fusion (robot_localization, a pose graph) ignores it instead of failing.
UNCONSTRAINED_VARIANCE = 1e6
#: An eigenvalue of J^T W J below this share of the largest counts as undetermined (float64
#: rounding in the Hessian of a degenerate set is ~1e-16 of its scale; real constraints are far
#: above 1e-9 of the strongest one).
EIGEN_FLOOR = 1e-9


def covariance_from_information(H: np.ndarray, sigma2: float) -> np.ndarray:
    """(6, 6) symmetric positive semi-definite ``sigma2 * H^-1`` for a (6, 6) information matrix.

    From the eigendecomposition of the symmetrised H, not an inverse: each eigen-direction gets
    the variance ``sigma2 / lambda``, capped at :data:`UNCONSTRAINED_VARIANCE`; a direction whose
    eigenvalue is below ``EIGEN_FLOOR`` x the largest (a plane, a line, a few points) or not
    finite gets exactly that cap. Non-negative variances on every CPU, whatever its rounding
    (an inverse of a near-singular H came out with variances of -7e13 on one).
    """
    H = np.asarray(H, np.float64)
    if H.shape != (6, 6) or not np.isfinite(H).all() or not np.isfinite(sigma2):
        return np.diag([UNCONSTRAINED_VARIANCE] * 6)
    lam, V = np.linalg.eigh(0.5 * (H + H.T))                       # ascending, V orthonormal
    floor = EIGEN_FLOOR * max(float(lam[-1]), 1e-300)
    var = np.full(6, UNCONSTRAINED_VARIANCE)
    det = lam > floor
    var[det] = np.minimum(max(float(sigma2), 1e-12) / lam[det], UNCONSTRAINED_VARIANCE)
    cov = (V * var) @ V.T
    return 0.5 * (cov + cov.T)


def covariance(src: np.ndarray, tgt: np.ndarray, w: np.ndarray, T: np.ndarray) -> np.ndarray:
    """6x6 covariance (x y z roll pitch yaw) of the weighted point-to-point least squares at T.

    Gauss-Newton: residual r_i = R p_i + t - q_i, Jacobian [I, -[R p_i]x]; covariance =
    sigma^2 (J^T W J)^-1 with sigma^2 the weighted mean squared residual, through
    :func:`covariance_from_information` (always symmetric PSD; undetermined directions get
    :data:`UNCONSTRAINED_VARIANCE`). Rows (translation, rotation) are already ROS order.
    src, tgt: (K, 3) metres; w: (K,) weights; T: (4, 4).
    """
    R, t = T[:3, :3], T[:3, 3]
    rp = src @ R.T
    res = rp + t - tgt
    w = np.clip(np.nan_to_num(w.astype(np.float64)), 0.0, None)
    if w.sum() <= 1e-12 or len(src) < 3:
        return np.diag([UNCONSTRAINED_VARIANCE] * 6)
    J = np.zeros((len(src), 3, 6))
    J[:, :, :3] = np.eye(3)
    x, y, z = rp[:, 0], rp[:, 1], rp[:, 2]
    skew = np.zeros((len(src), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2] = -z, y
    skew[:, 1, 0], skew[:, 1, 2] = z, -x
    skew[:, 2, 0], skew[:, 2, 1] = -y, x
    J[:, :, 3:] = -skew
    H = np.einsum("n,nij,nik->jk", w, J, J)
    sigma2 = float((w * (res ** 2).sum(1)).sum() / (3.0 * w.sum()))
    return covariance_from_information(H, sigma2)
