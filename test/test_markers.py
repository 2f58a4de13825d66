"""msg_adapters.markers: DELETEALL first, colours from weights, caps, frames."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import Header
from visualization_msgs.msg import Marker, MarkerArray

from msg_adapters.markers import (
    correspondence_markers,
    overlap_markers,
    registration_markers,
    score_colors,
)

HEADER = Header(frame_id="cegc_target")


def xyz(marker: Marker) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in marker.points])


def rgba(marker: Marker) -> np.ndarray:
    return np.array([[c.r, c.g, c.b, c.a] for c in marker.colors])


def round_trip(array: MarkerArray) -> MarkerArray:
    return deserialize_message(serialize_message(array), MarkerArray)


def test_score_colors_red_yellow_green():
    np.testing.assert_array_equal(score_colors(np.array([0.0, 0.25, 0.5, 1.0])), [
        [1, 0, 0, 1], [1, 0.5, 0, 1], [1, 1, 0, 1], [0, 1, 0, 1]])


def test_correspondence_lines_in_target_frame_coloured_by_weight():
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    tgt = np.array([[5, 5, 5], [6, 6, 6]], np.float32)
    T = np.eye(4)
    T[:3, 3] = [10, 0, 0]  # source points shift by +10 in x when mapped into the target frame
    corr = np.array([[0, 1], [2, 0]])
    array = round_trip(correspondence_markers(src, tgt, corr, np.array([0.0, 1.0]), HEADER, T))
    assert [m.action for m in array.markers] == [Marker.DELETEALL, Marker.ADD]
    line = array.markers[1]
    assert line.type == Marker.LINE_LIST and line.header.frame_id == "cegc_target"
    assert line.scale.x == 0.005 and line.pose.orientation.w == 1.0
    # Highest weight first: (src 2 -> tgt 0, w=1), then (src 0 -> tgt 1, w=0).
    np.testing.assert_array_equal(xyz(line), [[10, 1, 0], [5, 5, 5], [10, 0, 0], [6, 6, 6]])
    np.testing.assert_array_equal(rgba(line), [[0, 1, 0, 1]] * 2 + [[1, 0, 0, 1]] * 2)


def test_correspondence_cap_keeps_highest_weights():
    rng = np.random.default_rng(1)
    src, tgt = rng.normal(size=(20, 3)), rng.normal(size=(20, 3))
    corr = np.stack([np.arange(20), np.arange(20)[::-1]], 1)
    weights = np.linspace(0, 1, 20)
    array = correspondence_markers(src, tgt, corr, weights, HEADER, max_lines=3)
    line = array.markers[1]
    assert len(line.points) == 6 and len(line.colors) == 6
    np.testing.assert_allclose(xyz(line)[0::2], src[[19, 18, 17]])
    np.testing.assert_allclose(xyz(line)[1::2], tgt[[0, 1, 2]])


def test_no_correspondences_gives_only_deleteall():
    array = correspondence_markers(np.zeros((3, 3)), np.zeros((3, 3)),
                                   np.zeros((0, 2), np.int64), np.zeros(0), HEADER)
    assert [m.action for m in array.markers] == [Marker.DELETEALL]
    assert len(correspondence_markers(np.zeros((3, 3)), np.zeros((3, 3)), [[0, 0]], [1.0],
                                      HEADER, max_lines=0).markers) == 1


@pytest.mark.parametrize("corr, weights, problem", [
    ([[0, 3]], [0.5], "out of range"),
    ([[-1, 0]], [0.5], "out of range"),
    ([[0, 0]], [1.5], r"in \[0, 1\]"),
    ([[0, 0]], [np.nan], "non-finite"),
    ([[0, 0]], [0.5, 0.5], r"shape \(1,\)"),
    ([[0.0, 0.0]], [0.5], r"\(M, 2\) integers"),
    ([0, 0], [0.5], r"\(M, 2\) integers"),
])
def test_bad_correspondences_raise_value_error(corr, weights, problem):
    with pytest.raises(ValueError, match=problem):
        correspondence_markers(np.zeros((2, 3)), np.zeros((3, 3)), np.asarray(corr), weights,
                               HEADER)


def test_bad_points_transform_and_sizes_raise_value_error():
    with pytest.raises(ValueError, match="source_points has non-finite"):
        correspondence_markers(np.full((2, 3), np.nan), np.zeros((2, 3)), [[0, 0]], [1], HEADER)
    with pytest.raises(ValueError, match=r"target_points must have shape \(N, 3\)"):
        correspondence_markers(np.zeros((2, 3)), np.zeros((2, 2)), [[0, 0]], [1], HEADER)
    with pytest.raises(ValueError, match="T_target_source"):
        correspondence_markers(np.zeros((2, 3)), np.zeros((2, 3)), [[0, 0]], [1], HEADER,
                               np.eye(3))
    with pytest.raises(ValueError, match="line_width"):
        correspondence_markers(np.zeros((2, 3)), np.zeros((2, 3)), [[0, 0]], [1], HEADER,
                               line_width=0)
    with pytest.raises(ValueError, match="max_lines"):
        correspondence_markers(np.zeros((2, 3)), np.zeros((2, 3)), [[0, 0]], [1], HEADER,
                               max_lines=-1)
    with pytest.raises(ValueError, match="std_msgs/msg/Header"):
        correspondence_markers(np.zeros((2, 3)), np.zeros((2, 3)), [[0, 0]], [1], "map")


def test_overlap_points_coloured_by_score_and_evenly_capped():
    pts = np.arange(30, dtype=np.float64).reshape(10, 3)
    scores = np.linspace(0, 1, 10)
    array = round_trip(overlap_markers(pts, scores, HEADER, max_points=4, point_size=0.02))
    assert [m.action for m in array.markers] == [Marker.DELETEALL, Marker.ADD]
    marker = array.markers[1]
    assert marker.type == Marker.POINTS and (marker.scale.x, marker.scale.y) == (0.02, 0.02)
    np.testing.assert_array_equal(xyz(marker), pts[[0, 3, 6, 9]])
    np.testing.assert_allclose(rgba(marker), score_colors(scores[[0, 3, 6, 9]]))
    uncapped = overlap_markers(pts, scores, HEADER).markers[1]
    assert len(uncapped.points) == 10


def test_overlap_rejects_bad_scores():
    with pytest.raises(ValueError, match=r"in \[0, 1\]"):
        overlap_markers(np.zeros((2, 3)), [0.5, -0.2], HEADER)
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        overlap_markers(np.zeros((2, 3)), [0.5], HEADER)


def test_registration_markers_one_deleteall_then_all_parts():
    rng = np.random.default_rng(2)
    T = np.eye(4)
    T[:3, 3] = [0, 0, 1]
    result = SimpleNamespace(
        T_target_source=T,
        source_points=rng.normal(size=(8, 3)).astype(np.float32),
        target_points=rng.normal(size=(6, 3)).astype(np.float32),
        source_overlap=rng.uniform(size=8).astype(np.float32),
        target_overlap=rng.uniform(size=6).astype(np.float32),
        correspondences=np.array([[0, 1], [7, 5], [3, 3]], np.int64),
        weights=np.array([0.2, 0.9, 0.5], np.float32),
    )
    array = round_trip(registration_markers(result, HEADER, max_points=100))
    assert [m.action for m in array.markers] == [Marker.DELETEALL] + [Marker.ADD] * 3
    assert [m.action for m in array.markers].count(Marker.DELETEALL) == 1
    assert [(m.ns, m.id, m.type) for m in array.markers[1:]] == [
        ("cegc/correspondences", 0, Marker.LINE_LIST),
        ("cegc/target_overlap", 1, Marker.POINTS),
        ("cegc/source_overlap", 2, Marker.POINTS)]
    assert all(m.header.frame_id == "cegc_target" for m in array.markers)
    aligned = result.source_points.astype(np.float64) + [0, 0, 1]
    np.testing.assert_allclose(xyz(array.markers[3]), aligned, atol=1e-6)
    np.testing.assert_allclose(xyz(array.markers[1])[0], aligned[7], atol=1e-6)
    with pytest.raises(ValueError, match="lacks a registration attribute"):
        registration_markers(SimpleNamespace(T_target_source=T), HEADER)
