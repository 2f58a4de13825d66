"""Stages 5 and 6 of the engine: ICP polish on bounded clouds, then the verdict.

ICP runs on at most ``engine.icp_points`` points per cloud (a seeded subsample of the bounded
clouds), so its cost does not depend on the input size. The verdict measures ``fitness`` (the
share of the network's source points within ``inlier_distance`` of the network's target points
after the pose) and a covariance of the pose from the estimator's inlier correspondences.
"""

from __future__ import annotations

import numpy as np


def icp(source: np.ndarray, target: np.ndarray, T: np.ndarray, max_distance: float, iterations: int,
        max_points: int, seed: int = 0) -> np.ndarray:
    """Open3D point-to-plane ICP of (N, 3) onto (M, 3) metres, started from T (4x4); at most
    max_points per cloud. Returns T unchanged when ICP produces a non-finite transform."""
    import open3d as o3d
    reg = o3d.pipelines.registration
    rng = np.random.default_rng(seed)

    def capped(p: np.ndarray) -> np.ndarray:
        return p if len(p) <= max_points else p[np.sort(rng.choice(len(p), max_points, replace=False))]

    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(capped(source)))
    pt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(capped(target)))
    pt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * max_distance, max_nn=30))
    res = reg.registration_icp(ps, pt, max_distance, T, reg.TransformationEstimationPointToPlane(),
                               reg.ICPConvergenceCriteria(max_iteration=iterations))
    out = np.asarray(res.transformation, np.float64)
    return out if np.isfinite(out).all() else T


def fitness(source: np.ndarray, target: np.ndarray, T: np.ndarray, distance: float) -> float:
    """Fraction of source points within distance of the target after applying T (4, 4)."""
    return float(fitnesses(T[None, :3, :3], T[None, :3, 3], source, target, distance)[0])


def fitnesses(R: np.ndarray, t: np.ndarray, source: np.ndarray, target: np.ndarray, distance: float
              ) -> np.ndarray:
    """:func:`fitness` of H poses at once: R (H, 3, 3), t (H, 3), source (Ns, 3), target (Nt, 3) -> (H,)."""
    from scipy.spatial import cKDTree
    moved = np.asarray(source, np.float64)[None] @ np.transpose(R, (0, 2, 1)) + np.asarray(t)[:, None]
    d, _ = cKDTree(np.asarray(target, np.float64)).query(moved.reshape(-1, 3), k=1,
                                                          distance_upper_bound=2.0 * distance)
    return (d.reshape(len(R), -1) <= distance).mean(1)


def median_spacing(points: np.ndarray) -> float:
    """Median nearest-neighbour distance within one cloud, over its distinct points (the
    network's points repeat when a cloud has fewer than preprocess.num_points)."""
    from scipy.spatial import cKDTree
    pts = np.unique(points, axis=0)
    if len(pts) < 2:
        raise ValueError("a cloud needs at least 2 distinct points")
    d, _ = cKDTree(pts).query(pts, k=2)
    return float(np.median(d[:, 1]))


def covariance(src: np.ndarray, tgt: np.ndarray, w: np.ndarray, T: np.ndarray) -> np.ndarray:
    """6x6 covariance (x y z roll pitch yaw) of the weighted point-to-point least squares at T.

    Gauss-Newton: residual r_i = R p_i + t - q_i, Jacobian [I, -[R p_i]x]; covariance =
    sigma^2 (J^T W J)^-1 with sigma^2 the weighted mean squared residual. Rows (translation,
    rotation) are already ROS order. A diagonal of 1e6 when it is not determined.
    """
    R, t = T[:3, :3], T[:3, 3]
    rp = src @ R.T
    res = rp + t - tgt
    w = np.clip(w.astype(np.float64), 0.0, None)
    if w.sum() <= 1e-12 or len(src) < 3:
        return np.diag([1e6] * 6)
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
    try:
        cov = np.linalg.inv(H) * max(sigma2, 1e-12)
    except np.linalg.LinAlgError:
        return np.diag([1e6] * 6)
    cov = 0.5 * (cov + cov.T)
    if not np.isfinite(cov).all():
        return np.diag([1e6] * 6)
    return cov
