"""msg_adapters.pose: 4x4 <-> Pose, stamped builders, rejection of non-rigid input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from geometry_msgs.msg import Pose, PoseStamped, PoseWithCovarianceStamped, Quaternion
from hypothesis import given, settings
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import Header

from msg_adapters.pose import (
    matrix_to_pose,
    pose_stamped,
    pose_to_matrix,
    pose_with_covariance_stamped,
)


def rot(axis: str, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def transform(R: np.ndarray, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def quat(pose: Pose) -> list[float]:
    o = pose.orientation
    return [o.x, o.y, o.z, o.w]


def test_known_rotation_and_translation():
    T = transform(rot("z", math.pi / 2), (1.0, -2.0, 0.5))
    pose = matrix_to_pose(T)
    s = math.sqrt(0.5)
    np.testing.assert_allclose(quat(pose), [0, 0, s, s], atol=1e-15)
    assert (pose.position.x, pose.position.y, pose.position.z) == (1.0, -2.0, 0.5)
    np.testing.assert_allclose(pose_to_matrix(pose), T, atol=1e-15)
    # The matrix maps points: the x axis goes to the y axis, then the translation.
    np.testing.assert_allclose(pose_to_matrix(pose) @ [1, 0, 0, 1], [1, -1, 0.5, 1], atol=1e-15)


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_half_turns_use_every_quaternion_branch(axis):
    T = transform(rot(axis, math.pi))
    q = quat(matrix_to_pose(T))
    expected = {"x": [1, 0, 0, 0], "y": [0, 1, 0, 0], "z": [0, 0, 1, 0]}[axis]
    np.testing.assert_allclose(np.abs(q), expected, atol=1e-12)
    np.testing.assert_allclose(pose_to_matrix(matrix_to_pose(T)), T, atol=1e-12)


def test_identity_and_canonical_sign():
    assert quat(matrix_to_pose(np.eye(4))) == [0.0, 0.0, 0.0, 1.0]
    q = quat(matrix_to_pose(transform(rot("x", 1.5 * math.pi))))  # w would be negative
    assert q[3] >= 0.0
    np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-15)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3),
       st.lists(st.floats(-100, 100), min_size=3, max_size=3))
def test_property_round_trip(q, t):
    x, y, z, w = np.asarray(q) / np.linalg.norm(q)
    pose = Pose()
    pose.orientation = Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))
    pose.position.x, pose.position.y, pose.position.z = t
    T = pose_to_matrix(pose)
    assert T.dtype == np.float64 and T.shape == (4, 4)
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    back = pose_to_matrix(matrix_to_pose(T))
    np.testing.assert_allclose(back, T, atol=1e-12)
    # Same rotation, up to the quaternion's sign.
    q2 = quat(matrix_to_pose(T))
    assert min(np.abs(np.subtract(q2, [x, y, z, w])).max(),
               np.abs(np.add(q2, [x, y, z, w])).max()) < 1e-9


def test_float32_transform_is_accepted():
    T = transform(rot("y", 0.3) @ rot("x", 1.1), (0.1, 0.2, 0.3)).astype(np.float32)
    np.testing.assert_allclose(pose_to_matrix(matrix_to_pose(T)), T, atol=1e-6)


@pytest.mark.parametrize("make, problem", [
    (lambda: np.diag([2.0, 2.0, 2.0, 1.0]), "not orthonormal"),
    (lambda: transform(np.array([[1, 0.1, 0], [0, 1, 0], [0, 0, 1]])), "not orthonormal"),
    (lambda: np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
    (lambda: np.full((4, 4), np.nan), "non-finite"),
    (lambda: transform(np.eye(3), (np.inf, 0, 0)), "non-finite"),
    (lambda: np.eye(3), r"shape \(4, 4\)"),
    (lambda: np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]), "bottom row"),
    (lambda: "eye", "numeric 4x4"),
])
def test_non_rigid_input_raises_value_error(make, problem):
    with pytest.raises(ValueError, match=problem):
        matrix_to_pose(make())
    with pytest.raises(ValueError, match=problem):
        pose_stamped(make(), Header())


@pytest.mark.parametrize("q, problem", [
    ((0.0, 0.0, 0.0, 0.0), "unit quaternion"),
    ((0.0, 0.0, 0.0, 1.2), "unit quaternion"),
    ((0.0, 0.0, float("nan"), 1.0), "non-finite"),
])
def test_bad_pose_raises_value_error(q, problem):
    pose = Pose(orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))
    with pytest.raises(ValueError, match=problem):
        pose_to_matrix(pose)


def test_pose_non_finite_position_and_not_a_pose():
    pose = Pose()
    pose.position.y = float("inf")
    with pytest.raises(ValueError, match="non-finite"):
        pose_to_matrix(pose)
    with pytest.raises(ValueError, match="geometry_msgs/msg/Pose"):
        pose_to_matrix(Header())


def test_nearly_unit_quaternion_is_normalised():
    pose = Pose(orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0 + 5e-4))
    np.testing.assert_allclose(pose_to_matrix(pose), np.eye(4), atol=1e-15)


def test_pose_stamped_keeps_header_and_serializes():
    header = Header(frame_id="cegc_target")
    header.stamp.sec, header.stamp.nanosec = 7, 500
    T = transform(rot("x", 0.25), (3.0, 2.0, 1.0))
    msg = deserialize_message(serialize_message(pose_stamped(T, header)), PoseStamped)
    assert msg.header.frame_id == "cegc_target" and msg.header.stamp.nanosec == 500
    np.testing.assert_allclose(pose_to_matrix(msg.pose), T, atol=1e-15)


def test_pose_with_covariance_is_row_major_ros_order():
    C = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) * 1e-4
    C[0, 5] = C[5, 0] = 1e-5  # x-yaw
    header = Header(frame_id="cegc_target")
    msg = pose_with_covariance_stamped(transform(rot("z", 0.1)), C, header)
    msg = deserialize_message(serialize_message(msg), PoseWithCovarianceStamped)
    cov = np.asarray(msg.pose.covariance)
    assert cov.shape == (36,)
    assert cov[0] == C[0, 0] and cov[7] == C[1, 1] and cov[35] == C[5, 5] == 6.0 * 1e-4
    assert cov[5] == 1e-5 and cov[30] == 1e-5
    np.testing.assert_array_equal(cov.reshape(6, 6), C)
    assert msg.header.frame_id == "cegc_target"


@pytest.mark.parametrize("C, problem", [
    (np.eye(3), r"shape \(6, 6\)"),
    (np.triu(np.ones((6, 6))), "not symmetric"),
    (np.diag([1, 1, 1, 1, 1, -1.0]), "negative variances"),
    (np.full((6, 6), np.nan), "non-finite"),
    ([["a"] * 6] * 6, "numeric 6x6"),
])
def test_bad_covariance_raises_value_error(C, problem):
    with pytest.raises(ValueError, match=problem):
        pose_with_covariance_stamped(np.eye(4), C, Header())


def test_bad_header_raises_value_error():
    with pytest.raises(ValueError, match="std_msgs/msg/Header"):
        pose_stamped(np.eye(4), "cegc_target")
    with pytest.raises(ValueError, match="std_msgs/msg/Header"):
        pose_with_covariance_stamped(np.eye(4), np.eye(6), None)
