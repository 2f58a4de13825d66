"""Odometry poses <-> nav_msgs Odometry and Path.

``odometry(T_odom_child, covariance, header, child_frame_id)``: the pose of ``child_frame_id``
(e.g. the cloud's sensor frame) in ``header.frame_id`` (e.g. ``odom``); covariance (6, 6) in
ROS order x y z roll pitch yaw. ``path(poses, header)``: one PoseStamped per ``(stamp_ns, T)``,
all in ``header.frame_id``. Malformed input raises :class:`ValueError`.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from std_msgs.msg import Header

from .pose import matrix_to_pose, pose_to_matrix, pose_with_covariance_stamped

__all__ = ["odometry", "odometry_to_matrix", "path", "path_to_matrices", "time_from_ns",
           "time_to_ns"]


def time_from_ns(stamp_ns: int) -> Time:
    """builtin_interfaces/Time of a non-negative stamp in nanoseconds."""
    stamp_ns = int(stamp_ns)
    if stamp_ns < 0:
        raise ValueError(f"stamp must be >= 0 ns, got {stamp_ns}")
    return Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)


def time_to_ns(stamp: Time | Any) -> int:
    """Nanoseconds of a builtin_interfaces/Time (or anything with ``sec`` and ``nanosec``, such
    as the ``CdrStamp`` of a raw subscription's parsed PointCloud2)."""
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


def _header(header: Any) -> Header:
    if not isinstance(header, Header):
        raise ValueError(f"header must be a std_msgs/msg/Header, got {type(header).__name__}")
    return header


def odometry(T_odom_child: Any, covariance: Any, header: Header, child_frame_id: str,
             twist: Any = None, twist_covariance: Any = None) -> Odometry:
    """A nav_msgs/Odometry with the pose (and, when given, the twist) of ``child_frame_id``.

    Args:
        T_odom_child: (4, 4) rigid transform, child frame -> ``header.frame_id``.
        covariance: (6, 6) symmetric, non-negative variances, ROS order.
        header: stamp and the odometry frame.
        child_frame_id: the moving frame (must not be empty).
        twist: optional (6,) linear (m/s) and angular (rad/s) velocity in the child frame;
            without it the twist and its covariance stay zero (not measured).
        twist_covariance: optional (6, 6) of the twist (validated like ``covariance``).

    Raises:
        ValueError: an invalid transform, covariance, twist or frame id.
    """
    if not child_frame_id:
        raise ValueError("odometry child_frame_id must not be empty")
    msg = Odometry(header=_header(header), child_frame_id=str(child_frame_id))
    msg.pose = pose_with_covariance_stamped(T_odom_child, covariance, header).pose
    if twist is not None:
        v = np.asarray(twist, np.float64).reshape(-1)
        if v.shape != (6,) or not np.isfinite(v).all():
            raise ValueError(f"twist must be 6 finite numbers, got shape {v.shape}")
        lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
        lin.x, lin.y, lin.z, ang.x, ang.y, ang.z = (float(x) for x in v)
        if twist_covariance is not None:
            # Validated by the pose builder; only its covariance is kept.
            cov = pose_with_covariance_stamped(np.eye(4), twist_covariance, header).pose.covariance
            msg.twist.covariance = cov
    return msg


def odometry_to_matrix(msg: Odometry) -> tuple[np.ndarray, np.ndarray]:
    """(T_odom_child (4, 4), covariance (6, 6)) of a nav_msgs/Odometry."""
    T = pose_to_matrix(msg.pose.pose)
    cov = np.asarray(msg.pose.covariance, np.float64).reshape(6, 6)
    return T, cov


def path(poses: Iterable[tuple[int, Any]], header: Header) -> Path:
    """A nav_msgs/Path of ``(stamp_ns, T (4, 4))`` poses, oldest first, in ``header.frame_id``.

    Raises:
        ValueError: an invalid transform or a negative stamp (naming its index).
    """
    header = _header(header)
    out = Path(header=header)
    items = []
    for k, (stamp_ns, T) in enumerate(poses):
        try:
            h = Header(stamp=time_from_ns(stamp_ns), frame_id=header.frame_id)
            items.append(PoseStamped(header=h, pose=matrix_to_pose(T)))
        except ValueError as err:
            raise ValueError(f"path pose {k}: {err}") from err
    out.poses = items
    return out


def path_to_matrices(msg: Path) -> list[tuple[int, np.ndarray]]:
    """``(stamp_ns, T (4, 4))`` of each pose of a nav_msgs/Path."""
    return [(time_to_ns(p.header.stamp), pose_to_matrix(p.pose)) for p in msg.poses]
