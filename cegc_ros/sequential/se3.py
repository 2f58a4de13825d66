"""Rigid-motion helpers of the odometry: constant-velocity prediction and covariance chaining.

Covariances are 6x6 in ROS order (x, y, z, roll, pitch, yaw) with the perturbation the engine
uses (:func:`cegc_ros.engine.covariance_from_correspondences`): a pose ``(R, t)`` becomes
``(exp([phi]x) R, t + dt)``, i.e. the translation is perturbed additively and the rotation about
the axes of the frame the pose is expressed in.
"""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """(3,) -> (3, 3) cross-product matrix: ``skew(a) @ b == cross(a, b)``."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def exp_so3(phi: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) -> (3, 3) rotation matrix."""
    from scipy.spatial.transform import Rotation
    return Rotation.from_rotvec(np.asarray(phi, np.float64)).as_matrix()


def log_so3(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> rotation vector (3,)."""
    from scipy.spatial.transform import Rotation
    return Rotation.from_matrix(np.asarray(R, np.float64)).as_rotvec()


def rotation_angle_deg(T: np.ndarray) -> float:
    """Angle of the rotation of a (4, 4) transform, degrees."""
    return float(np.degrees(np.linalg.norm(log_so3(T[:3, :3]))))


def scale_motion(delta: np.ndarray, ratio: float) -> np.ndarray:
    """``delta`` (4, 4) scaled by ``ratio``: rotation vector and translation times ratio
    (constant velocity in the moving frame, to first order)."""
    out = np.eye(4)
    out[:3, :3] = exp_so3(ratio * log_so3(delta[:3, :3]))
    out[:3, 3] = ratio * delta[:3, 3]
    return out


def compose_covariance(T_a: np.ndarray, cov_a: np.ndarray, T_b: np.ndarray,
                       cov_b: np.ndarray) -> np.ndarray:
    """(6, 6) covariance of ``T_a @ T_b`` for independent ``T_a`` (cov_a) and ``T_b`` (cov_b).

    First order: with ``T_a = (R_a, t_a)``, ``T_b = (R_b, t_b)``, a perturbation of T_a moves the
    product by ``J_a = [[I, -[R_a t_b]x], [0, I]]`` and one of T_b (in T_b's own frame) by
    ``J_b = [[R_a, 0], [0, R_a]]``.
    """
    R_a = T_a[:3, :3]
    J_a = np.eye(6)
    J_a[:3, 3:] = -skew(R_a @ T_b[:3, 3])
    J_b = np.zeros((6, 6))
    J_b[:3, :3] = R_a
    J_b[3:, 3:] = R_a
    cov = J_a @ cov_a @ J_a.T + J_b @ cov_b @ J_b.T
    return 0.5 * (cov + cov.T)
