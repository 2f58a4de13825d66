"""Point-to-plane ICP on voxelized clouds, for tracking a cloud against a keyframe.

A keyframe is prepared once (:func:`prepare_cloud`: voxel grid, normals, k-d tree) and then
registered against many clouds. :func:`icp` runs Open3D's point-to-plane ICP (Tukey kernel)
from an initial guess and scores the answer on the same clouds: ``fitness`` (share of the
source within ``inlier_distance`` of the target), ``overlap`` (share of the target within it of
the aligned source) and a point-to-plane covariance of the pose.

Transforms are ``T_target_source``: ``p_target = R p_source + t``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..refine import UNCONSTRAINED_VARIANCE, covariance_from_information
from .se3 import exp_so3

#: Neighbourhood of the normal estimate, in voxels (radius) and points (at most).
NORMAL_RADIUS_VOXELS = 3.0
NORMAL_MAX_NN = 30



@dataclass
class PreparedCloud:
    """A voxelized cloud ready for ICP.

    points: (N, 3) float64 voxel means (metres, own frame); normals: (N, 3) unit, float64.
    pcd: the Open3D cloud (points + normals); tree: scipy cKDTree over ``points``.
    """

    points: np.ndarray
    normals: np.ndarray
    pcd: Any
    tree: Any

    def __len__(self) -> int:
        return len(self.points)


@dataclass
class IcpResult:
    """One ICP answer, scored on the prepared clouds.

    T_target_source: (4, 4) float64. fitness: share of source points within inlier_distance of
    the target after T; overlap: share of target points within inlier_distance of the aligned
    source; rmse: RMS point-to-plane residual of those source inliers (metres);
    covariance: (6, 6) of T, ROS order x y z roll pitch yaw (perturbation: translation added,
    rotation about the target frame's axes), from the point-to-plane Gauss-Newton Hessian.
    """

    T_target_source: np.ndarray
    fitness: float
    overlap: float
    rmse: float
    covariance: np.ndarray


def prepare_cloud(points: np.ndarray, voxel_size: float) -> PreparedCloud:
    """(N, 3) metres -> the voxel-mean cloud with normals and a k-d tree (voxel_size > 0)."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    if voxel_size <= 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pcd = pcd.voxel_down_sample(voxel_size)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(
        radius=NORMAL_RADIUS_VOXELS * voxel_size, max_nn=NORMAL_MAX_NN))
    pts = np.asarray(pcd.points, np.float64)
    return PreparedCloud(pts, np.asarray(pcd.normals, np.float64), pcd, cKDTree(pts))


def icp(source: PreparedCloud, target: PreparedCloud, T_init: np.ndarray, max_distance: float,
        inlier_distance: float, max_iterations: int = 30, prior: float = 0.01) -> IcpResult:
    """Point-to-plane ICP of ``source`` onto ``target`` from ``T_init`` (4, 4), then scored.

    ``max_distance``: correspondence distance (metres; how far the guess may be off);
    ``inlier_distance``: the Tukey kernel's width, and what counts as "on the target" for
    fitness, overlap and covariance.

    Gauss-Newton on the Tukey-weighted point-to-plane residuals plus a prior that holds the
    pose at ``T_init`` with weight ``prior`` per point (translation in metres, rotation in
    radians times the source's RMS radius). Along directions the geometry constrains well
    the prior is negligible; along one it does not (a wall and the floor leave the direction
    along both free), the answer stays near the guess (the constant-velocity prediction)
    instead of sliding on depth noise. Open3D's ICP solves the plain normal equations, which
    moved such directions by decimetres per frame on the Kinect-like sequences
    (docs/sequential.md); a hard cut of those directions instead never learns a motion along
    them, since the prediction's velocity comes from earlier answers.
    """
    T = np.asarray(T_init, np.float64).copy()
    src = source.points                                                  # (N, 3)
    length = max(float(np.sqrt(((src - src.mean(0)) ** 2).sum(1).mean())), 1e-9)
    xi = np.zeros(6)
    for _ in range(int(max_iterations)):
        R = T[:3, :3]
        rotated = src @ R.T                                              # (N, 3) R p
        d, j = target.tree.query(rotated + T[:3, 3], k=1, distance_upper_bound=max_distance)
        m = np.isfinite(d)
        if m.sum() < 6:
            break
        q, n = target.points[j[m]], target.normals[j[m]]                 # (M, 3)
        r = ((rotated[m] + T[:3, 3] - q) * n).sum(1)                     # (M,)
        w = np.clip(1.0 - (r / inlier_distance) ** 2, 0.0, None) ** 2    # Tukey biweight
        # Rotation as angle x the cloud's RMS radius (metres of arc): all six unknowns in
        # metres, so that one prior weight fits translation and rotation.
        J = np.concatenate([n, np.cross(rotated[m], n) / length], axis=1)   # (M, 6)
        H = (J * w[:, None]).T @ J / max(float(w.sum()), 1e-12)
        g = (J * w[:, None]).T @ r / max(float(w.sum()), 1e-12)
        # xi: the update from T_init so far (scaled like J), which the prior pulls back.
        step = -np.linalg.solve(H + prior * np.eye(6), g + prior * xi)
        xi = xi + step
        dt, phi = step[:3], step[3:] / length
        T[:3, :3] = exp_so3(phi) @ R
        T[:3, 3] = T[:3, 3] + dt
        if np.linalg.norm(dt) < 1e-5 and np.linalg.norm(phi) < 1e-5:
            break
    return score(source, target, T, inlier_distance)


def score(source: PreparedCloud, target: PreparedCloud, T: np.ndarray,
          inlier_distance: float) -> IcpResult:
    """Fitness, overlap, residual and covariance of ``T_target_source`` on prepared clouds."""
    from scipy.spatial import cKDTree

    moved = source.points @ T[:3, :3].T + T[:3, 3]                     # (N, 3) target frame
    d, j = target.tree.query(moved, k=1, distance_upper_bound=inlier_distance)
    inl = np.isfinite(d)
    fitness = float(inl.mean()) if len(inl) else 0.0
    d_back, _ = cKDTree(moved).query(target.points, k=1, distance_upper_bound=inlier_distance)
    overlap = float(np.isfinite(d_back).mean()) if len(d_back) else 0.0
    q, n = target.points[j[inl]], target.normals[j[inl]]                # (M, 3) each
    p = moved[inl]
    r = ((p - q) * n).sum(1)                                            # (M,) point-to-plane
    rmse = float(np.sqrt((r ** 2).mean())) if len(r) else float("inf")
    rotated = source.points[inl] @ T[:3, :3].T                          # R p, without t
    return IcpResult(T, fitness, overlap, rmse, point_to_plane_covariance(rotated, n, r))


def point_to_plane_covariance(rotated: np.ndarray, normals: np.ndarray,
                              residuals: np.ndarray) -> np.ndarray:
    """(6, 6) covariance, ROS order, of a pose fitted by point-to-plane least squares.

    With the residual ``r_i = n_i . (exp(phi) R p_i + t + dt - q_i)``, the Jacobian is
    ``[n_i, (R p_i) x n_i]`` (``rotated`` = R p_i, (M, 3)); covariance ``sigma^2 (J^T J)^-1``
    with ``sigma^2`` the residual variance. Unconstrained directions (fewer than 6 matches, a
    singular Hessian: a plane, a corridor) get :data:`~cegc_ros.refine.UNCONSTRAINED_VARIANCE`
    (cegc_ros.refine.covariance_from_information).
    """
    m = len(residuals)
    if m <= 6:
        return np.diag([UNCONSTRAINED_VARIANCE] * 6)
    J = np.concatenate([normals, np.cross(rotated, normals)], axis=1)   # (M, 6)
    sigma2 = max(float((residuals ** 2).sum() / (m - 6)), 1e-12)
    return covariance_from_information(J.T @ J, sigma2)
