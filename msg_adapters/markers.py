"""Registration results as visualization_msgs/MarkerArray for RViz.

Every array starts with a DELETEALL marker, so markers of an earlier pair never linger when
this one has fewer. Correspondences are one LINE_LIST marker (two vertices per line), overlap
scores one POINTS marker; each vertex is coloured by its value in [0, 1] from red (0) through
yellow to green (1). The number of lines and points per marker is capped, so a dense result
cannot flood the display.

Everything is drawn in the frame of the given header. For a registration result that is the
target frame: source points are first mapped by ``T_target_source`` (``p_t = R p_s + t``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point, Vector3
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

__all__ = [
    "MAX_LINES",
    "MAX_POINTS",
    "correspondence_markers",
    "delete_all_marker",
    "overlap_markers",
    "registration_markers",
    "score_colors",
]

#: Default caps: at most this many correspondence lines / overlap points per marker.
MAX_LINES = 500
MAX_POINTS = 5000
#: Scores may exceed [0, 1] by this much (float round-off) before they count as invalid.
_SCORE_ATOL = 1e-3


def score_colors(scores: np.ndarray) -> np.ndarray:
    """(N,) scores in [0, 1] -> (N, 4) RGBA float32: red (0), yellow (0.5), green (1), opaque."""
    s = np.clip(np.asarray(scores, dtype=np.float32), 0.0, 1.0)
    rgba = np.empty((s.shape[0], 4), np.float32)
    rgba[:, 0] = np.clip(2.0 * (1.0 - s), 0.0, 1.0)
    rgba[:, 1] = np.clip(2.0 * s, 0.0, 1.0)
    rgba[:, 2] = 0.0
    rgba[:, 3] = 1.0
    return rgba


def delete_all_marker(header: Header) -> Marker:
    """The DELETEALL marker that clears everything previously published on the topic."""
    return Marker(header=_header(header), action=Marker.DELETEALL)


def correspondence_markers(source_points: Any, target_points: Any, correspondences: Any,
                           weights: Any, header: Header, T_target_source: Any = None,
                           max_lines: int = MAX_LINES, line_width: float = 0.005,
                           ns: str = "cegc/correspondences") -> MarkerArray:
    """DELETEALL plus one LINE_LIST joining matched points, coloured by weight.

    Args:
        source_points: (Ns, 3) in the source frame (or already in the header's frame when
            ``T_target_source`` is None).
        target_points: (Nt, 3) in the header's frame.
        correspondences: (M, 2) integer rows (index into source_points, index into
            target_points).
        weights: (M,) confidences in [0, 1].
        header: stamp and frame (the target frame) of the markers.
        T_target_source: optional (4, 4) transform applied to the source points first.
        max_lines: cap; the ``max_lines`` highest-weight lines are kept.

    Raises:
        ValueError: inconsistent shapes, indices out of range, non-finite values, or weights
            outside [0, 1].
    """
    array = MarkerArray(markers=[delete_all_marker(header)])
    line = correspondence_marker(source_points, target_points, correspondences, weights, header,
                                 T_target_source, max_lines, line_width, ns)
    if line is not None:
        array.markers.append(line)
    return array


def overlap_markers(points: Any, scores: Any, header: Header, max_points: int = MAX_POINTS,
                    point_size: float = 0.01, ns: str = "cegc/overlap") -> MarkerArray:
    """DELETEALL plus one POINTS marker of ``points`` (N, 3) coloured by ``scores`` (N,).

    Above ``max_points`` an evenly spaced subset is drawn (deterministic, keeps the spatial
    spread of high and low scores alike).

    Raises:
        ValueError: inconsistent shapes, non-finite values, or scores outside [0, 1].
    """
    array = MarkerArray(markers=[delete_all_marker(header)])
    marker = overlap_marker(points, scores, header, max_points, point_size, ns)
    if marker is not None:
        array.markers.append(marker)
    return array


def registration_markers(result: Any, header: Header, max_lines: int = MAX_LINES,
                         max_points: int = MAX_POINTS, line_width: float = 0.005,
                         point_size: float = 0.01) -> MarkerArray:
    """One MarkerArray for a registration result, drawn in the target frame ``header``.

    ``result`` is anything with the :class:`cegc_ros.engine.RegistrationResult` attributes
    (``source_points``, ``target_points``, ``source_overlap``, ``target_overlap``,
    ``correspondences``, ``weights``, ``T_target_source``). Contents: DELETEALL, the
    correspondence lines (id 0), the target overlap (id 1) and the aligned source overlap
    (id 2); empty parts are left out.

    Raises:
        ValueError: as the builders above.
    """
    try:
        T = result.T_target_source
        src, tgt = result.source_points, result.target_points
        src_score, tgt_score = result.source_overlap, result.target_overlap
        corr, weights = result.correspondences, result.weights
    except AttributeError as err:
        raise ValueError(f"result lacks a registration attribute: {err}") from err
    src_in_target = _transform(_points(src, "source_points"), T)  # (Ns, 3), target frame
    parts = [
        correspondence_marker(src_in_target, tgt, corr, weights, header, None, max_lines,
                              line_width, "cegc/correspondences", marker_id=0),
        overlap_marker(tgt, tgt_score, header, max_points, point_size, "cegc/target_overlap",
                       marker_id=1),
        overlap_marker(src_in_target, src_score, header, max_points, point_size,
                       "cegc/source_overlap", marker_id=2),
    ]
    return MarkerArray(markers=[delete_all_marker(header)] + [m for m in parts if m is not None])


def correspondence_marker(source_points: Any, target_points: Any, correspondences: Any,
                          weights: Any, header: Header, T_target_source: Any = None,
                          max_lines: int = MAX_LINES, line_width: float = 0.005,
                          ns: str = "cegc/correspondences", marker_id: int = 0) -> Marker | None:
    """The LINE_LIST marker alone (None when there is nothing to draw); see above."""
    header = _header(header)
    src = _transform(_points(source_points, "source_points"), T_target_source)
    tgt = _points(target_points, "target_points")
    try:
        corr = np.asarray(correspondences)
    except (TypeError, ValueError) as err:
        raise ValueError(f"correspondences is not an array: {err}") from err
    if corr.size == 0:
        corr = corr.reshape(0, 2)
    if corr.ndim != 2 or corr.shape[1] != 2 or corr.dtype.kind not in "iu":
        raise ValueError(f"correspondences must be (M, 2) integers, got {corr.dtype} "
                         f"{corr.shape}")
    w = _scores(weights, corr.shape[0], "weights")
    if corr.shape[0] and (corr.min() < 0 or corr[:, 0].max() >= len(src)
                          or corr[:, 1].max() >= len(tgt)):
        raise ValueError(f"correspondence indices out of range (source has {len(src)} points, "
                         f"target {len(tgt)})")
    keep = _cap_top(w, _cap(max_lines, "max_lines"))  # (K,) indices, highest weight first
    if keep.size == 0:
        return None
    a, b = src[corr[keep, 0]], tgt[corr[keep, 1]]  # (K, 3) each
    vertices = np.empty((2 * keep.size, 3), np.float64)  # a0 b0 a1 b1 ...
    vertices[0::2], vertices[1::2] = a, b
    colors = np.repeat(score_colors(w[keep]), 2, axis=0)  # (2K, 4)
    width = _positive(line_width, "line_width")
    marker = _marker(header, ns, marker_id, Marker.LINE_LIST, width, 0.0)  # scale.x = width
    marker.points = _to_points(vertices)
    marker.colors = _to_colors(colors)
    return marker


def overlap_marker(points: Any, scores: Any, header: Header, max_points: int = MAX_POINTS,
                   point_size: float = 0.01, ns: str = "cegc/overlap",
                   marker_id: int = 0) -> Marker | None:
    """The POINTS marker alone (None when there is nothing to draw); see above."""
    header = _header(header)
    pts = _points(points, "points")
    s = _scores(scores, pts.shape[0], "scores")
    cap = _cap(max_points, "max_points")
    n = pts.shape[0]
    if n == 0 or cap == 0:
        return None
    idx = np.arange(n) if n <= cap else np.linspace(0, n - 1, cap).round().astype(np.int64)
    size = _positive(point_size, "point_size")
    marker = _marker(header, ns, marker_id, Marker.POINTS, size, size)
    marker.points = _to_points(pts[idx])
    marker.colors = _to_colors(score_colors(s[idx]))
    return marker


# --- helpers -----------------------------------------------------------------------------


def _header(header: Any) -> Header:
    if not isinstance(header, Header):
        raise ValueError(f"header must be a std_msgs/msg/Header, got {type(header).__name__}")
    return header


def _points(points: Any, what: str) -> np.ndarray:
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} is not a numeric array: {err}") from err
    if arr.size == 0:
        arr = arr.reshape(0, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{what} must have shape (N, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{what} has non-finite coordinates")
    return arr


def _scores(values: Any, n: int, what: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} is not a numeric array: {err}") from err
    if arr.shape != (n,):
        raise ValueError(f"{what} must have shape ({n},), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{what} has non-finite values")
    if n and (arr.min() < -_SCORE_ATOL or arr.max() > 1.0 + _SCORE_ATOL):
        raise ValueError(f"{what} must lie in [0, 1], got [{arr.min():.6g}, {arr.max():.6g}]")
    return np.clip(arr, 0.0, 1.0)


def _transform(points: np.ndarray, T: Any) -> np.ndarray:
    if T is None:
        return points
    try:
        M = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"T_target_source is not a numeric array: {err}") from err
    if M.shape != (4, 4) or not np.isfinite(M).all():
        raise ValueError(f"T_target_source must be a finite (4, 4) array, got {M.shape}")
    return points @ M[:3, :3].T + M[:3, 3]  # (N, 3)


def _cap(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ValueError(f"{what} must be a non-negative integer, got {value!r}")
    return int(value)


def _positive(value: Any, what: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} must be a number: {err}") from err
    if not np.isfinite(v) or v <= 0.0:
        raise ValueError(f"{what} must be a positive number, got {value!r}")
    return v


def _cap_top(weights: np.ndarray, cap: int) -> np.ndarray:
    """Indices of the ``cap`` largest weights, largest first, ties by index (deterministic)."""
    order = np.argsort(-weights, kind="stable")
    return order[:cap]


def _marker(header: Header, ns: str, marker_id: int, kind: int, sx: float, sy: float) -> Marker:
    marker = Marker(header=header, ns=str(ns), id=int(marker_id), type=kind, action=Marker.ADD)
    marker.pose.orientation.w = 1.0
    marker.scale = Vector3(x=float(sx), y=float(sy), z=0.0)
    marker.lifetime = Duration()  # forever; the next DELETEALL removes it
    marker.frame_locked = False
    return marker


def _to_points(xyz: np.ndarray) -> list[Point]:
    return [Point(x=x, y=y, z=z) for x, y, z in xyz.tolist()]


def _to_colors(rgba: np.ndarray) -> list[ColorRGBA]:
    return [ColorRGBA(r=r, g=g, b=b, a=a) for r, g, b, a in rgba.tolist()]
