"""4x4 rigid transforms <-> geometry_msgs Transform / TransformStamped, for /tf.

``transform_stamped(T_parent_child, header, child_frame_id)``: ``header.frame_id`` is the parent
(e.g. ``odom``), ``child_frame_id`` the frame whose points ``T`` maps into the parent (e.g. the
cloud's sensor frame), as tf2 expects. Input that is not a finite rigid transform raises
:class:`ValueError` (the same checks as :func:`msg_adapters.pose.matrix_to_pose`).

``tf2_msgs`` (the ``/tf`` message) is not on PyPI (``scripts/build_tf2_msgs.sh`` generates it;
the bootstrap does); :func:`tf_message_class` says whether it is importable, so that the node
publishes ``/tf`` only where it can.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Iterable
from typing import Any

import numpy as np
from geometry_msgs.msg import Point, Pose, Quaternion, Transform, TransformStamped, Vector3
from std_msgs.msg import Header

from .pose import matrix_to_pose, pose_to_matrix

__all__ = ["matrix_to_transform", "tf_message", "tf_message_class", "transform_stamped",
           "transform_to_matrix"]


def matrix_to_transform(T: Any) -> Transform:
    """A Transform from a (4, 4) rigid transform (metres; quaternion with w >= 0).

    Raises:
        ValueError: not a finite rigid transform (see :func:`msg_adapters.pose.matrix_to_pose`).
    """
    pose = matrix_to_pose(T)
    p, o = pose.position, pose.orientation
    return Transform(translation=Vector3(x=p.x, y=p.y, z=p.z),
                     rotation=Quaternion(x=o.x, y=o.y, z=o.z, w=o.w))


def transform_to_matrix(transform: Transform) -> np.ndarray:
    """The (4, 4) float64 matrix of a Transform.

    Raises:
        ValueError: non-finite values or a quaternion that is not unit length.
    """
    try:
        t, q = transform.translation, transform.rotation
        pose = Pose(position=Point(x=float(t.x), y=float(t.y), z=float(t.z)), orientation=q)
    except (AttributeError, TypeError, ValueError, AssertionError) as err:
        raise ValueError(f"expected a geometry_msgs/msg/Transform: {err}") from err
    return pose_to_matrix(pose)


def transform_stamped(T_parent_child: Any, header: Header, child_frame_id: str) -> TransformStamped:
    """A TransformStamped: ``header`` (stamp, parent frame) and the child frame.

    Raises:
        ValueError: an invalid transform, an empty frame id, or child == parent (tf2 rejects
            a frame that is its own parent).
    """
    if not isinstance(header, Header):
        raise ValueError(f"header must be a std_msgs/msg/Header, got {type(header).__name__}")
    if not header.frame_id or not child_frame_id:
        raise ValueError(f"TF needs both frame ids, got parent {header.frame_id!r} and child "
                         f"{child_frame_id!r}")
    if header.frame_id == child_frame_id:
        raise ValueError(f"TF parent and child are both {child_frame_id!r}")
    return TransformStamped(header=header, child_frame_id=str(child_frame_id),
                            transform=matrix_to_transform(T_parent_child))


def tf_message_class() -> type | None:
    """``tf2_msgs.msg.TFMessage`` where tf2_msgs is importable (a ROS 2 install, or the package
    ``scripts/build_tf2_msgs.sh`` generates, which the bootstrap puts on the path), else None."""
    if importlib.util.find_spec("tf2_msgs") is None:
        return None
    return importlib.import_module("tf2_msgs.msg").TFMessage


def tf_message(transforms: Iterable[TransformStamped]) -> Any:
    """A ``tf2_msgs/TFMessage`` holding ``transforms``.

    Raises:
        ModuleNotFoundError: tf2_msgs is not installed (check :func:`tf_message_class` first).
    """
    cls = tf_message_class()
    if cls is None:
        raise ModuleNotFoundError("tf2_msgs is not installed; /tf cannot be published")
    return cls(transforms=list(transforms))
