"""4x4 rigid transforms <-> geometry_msgs poses.

A pose message built from ``T_target_source`` (maps source-frame points into the target frame,
``p_t = R p_s + t``) is stamped with the *target* frame: it is where the source frame's origin
and axes sit in the target frame.

Quaternions come out normalised with ``w >= 0``. Input that is not a finite proper rotation
plus translation raises :class:`ValueError`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from geometry_msgs.msg import Point, Pose, PoseStamped, PoseWithCovarianceStamped, Quaternion
from std_msgs.msg import Header

__all__ = [
    "RIGID_ATOL",
    "matrix_to_pose",
    "pose_stamped",
    "pose_to_matrix",
    "pose_with_covariance_stamped",
]

#: Tolerance on ``R^T R = I``, ``det R = 1`` and the bottom row; loose enough for matrices
#: that went through float32 (the network's SVD), tight enough to reject scale or shear.
RIGID_ATOL = 1e-4
#: Allowed deviation of a quaternion's norm from 1 before it counts as not a rotation.
QUATERNION_NORM_ATOL = 1e-3


def _finite_array(value: Any, n: int, what: str) -> np.ndarray:
    """``value`` as a finite (n, n) float64 array; ValueError naming ``what`` otherwise."""
    try:
        M = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} is not a numeric {n}x{n} array: {err}") from err
    if M.shape != (n, n):
        raise ValueError(f"{what} must have shape ({n}, {n}), got {M.shape}")
    if not np.isfinite(M).all():
        raise ValueError(f"{what} has non-finite entries")
    return M


def _matrix(T: Any) -> np.ndarray:
    """``T`` as a validated (4, 4) float64 rigid transform."""
    M = _finite_array(T, 4, "transform")
    if not np.allclose(M[3], (0.0, 0.0, 0.0, 1.0), rtol=0.0, atol=RIGID_ATOL):
        raise ValueError(f"transform bottom row is {M[3].tolist()}, expected [0, 0, 0, 1]")
    R = M[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > RIGID_ATOL:
        raise ValueError(f"transform rotation is not orthonormal (max |R^T R - I| = {err:.3g})")
    det = float(np.linalg.det(R))
    if det < 0.0:
        raise ValueError(f"transform rotation is a reflection (det R = {det:.6g})")
    return M


def _quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a (3, 3) rotation (Shepperd's method)."""
    m00, m11, m22 = R[0, 0], R[1, 1], R[2, 2]
    trace = m00 + m11 + m22
    if trace > max(m00, m11, m22):
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif m00 >= m11 and m00 >= m22:
        s = 2.0 * np.sqrt(1.0 + m00 - m11 - m22)
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif m11 >= m22:
        s = 2.0 * np.sqrt(1.0 + m11 - m00 - m22)
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m22 - m00 - m11)
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    quat = np.asarray(q, dtype=np.float64)
    quat /= np.linalg.norm(quat)
    return -quat if quat[3] < 0.0 else quat


def matrix_to_pose(T: Any) -> Pose:
    """A Pose from a (4, 4) rigid transform (translation in metres).

    Raises:
        ValueError: wrong shape, non-finite entries, scale/shear, reflection, or a bottom row
            other than [0, 0, 0, 1] (tolerance :data:`RIGID_ATOL`).
    """
    M = _matrix(T)
    qx, qy, qz, qw = (float(v) for v in _quaternion_xyzw(M[:3, :3]))
    tx, ty, tz = (float(v) for v in M[:3, 3])
    return Pose(position=Point(x=tx, y=ty, z=tz), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))


def pose_to_matrix(pose: Pose) -> np.ndarray:
    """The (4, 4) float64 rigid transform of a Pose.

    Raises:
        ValueError: non-finite values, or a quaternion whose norm differs from 1 by more than
            :data:`QUATERNION_NORM_ATOL` (within it, the quaternion is normalised).
    """
    try:
        p, o = pose.position, pose.orientation
        t = np.array([p.x, p.y, p.z], dtype=np.float64)
        q = np.array([o.x, o.y, o.z, o.w], dtype=np.float64)  # (x, y, z, w)
    except (AttributeError, TypeError, ValueError) as err:
        raise ValueError(f"expected a geometry_msgs/msg/Pose: {err}") from err
    if not (np.isfinite(t).all() and np.isfinite(q).all()):
        raise ValueError(f"pose has non-finite values (position {t.tolist()}, "
                         f"orientation {q.tolist()})")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_ATOL:
        raise ValueError(f"pose orientation is not a unit quaternion (norm {norm:.6g})")
    x, y, z, w = q / norm
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = t
    return T


def _header(header: Any) -> Header:
    if not isinstance(header, Header):
        raise ValueError(f"header must be a std_msgs/msg/Header, got {type(header).__name__}")
    return header


def pose_stamped(T: Any, header: Header) -> PoseStamped:
    """A PoseStamped of ``T`` (e.g. ``T_target_source`` with ``header.frame_id`` = target)."""
    return PoseStamped(header=_header(header), pose=matrix_to_pose(T))


def pose_with_covariance_stamped(T: Any, covariance: Any,
                                 header: Header) -> PoseWithCovarianceStamped:
    """A PoseWithCovarianceStamped of ``T`` with a (6, 6) covariance.

    Args:
        T: (4, 4) rigid transform.
        covariance: (6, 6) symmetric, finite, non-negative diagonal, in ROS order
            x, y, z (m^2), roll, pitch, yaw (rad^2) about the fixed axes; stored row-major.
        header: stamp and frame of the pose.

    Raises:
        ValueError: an invalid transform or covariance.
    """
    msg = PoseWithCovarianceStamped(header=_header(header))
    msg.pose.pose = matrix_to_pose(T)
    C = _finite_array(covariance, 6, "covariance")
    scale = max(float(np.abs(C).max()), 1e-300)
    if np.abs(C - C.T).max() > 1e-9 * scale:
        raise ValueError("covariance is not symmetric")
    if (np.diag(C) < 0.0).any():
        raise ValueError(f"covariance has negative variances {np.diag(C).tolist()}")
    msg.pose.covariance = [float(v) for v in C.reshape(36)]
    return msg
