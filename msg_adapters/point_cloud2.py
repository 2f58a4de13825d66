"""sensor_msgs/PointCloud2 <-> numpy (N, 3) float32, without a node and without torch.

Reading builds strided numpy views straight over ``msg.data`` (no per-point Python work,
no copy of the buffer): one view per coordinate, or a single (N, 3) view when x, y, z are
three adjacent FLOAT32 fields, which is what nearly every driver publishes. The only copy
is the one that drops non-finite points and hands back a contiguous array the caller owns.

Every layout the message definition allows is read: all eight ``PointField`` datatypes in
either byte order, padded ``point_step``, organized clouds (``height > 1``) with padding
at the end of each row (``row_step``), extra fields in any order. Organized clouds come out
in row-major (image) order: row 0 left to right, then row 1, ...

Anything inconsistent raises :class:`ValueError` naming the problem; no other exception type
escapes, and nothing is guessed.

Works on any object with the PointCloud2 attributes (rclpy messages, rosbags messages).
"""

from __future__ import annotations

import array
from collections.abc import Mapping
from typing import Any

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

__all__ = ["DATATYPES", "cloud_to_xyz", "xyz_to_cloud"]

#: PointField datatype constant -> numpy scalar type (byte order applied separately).
DATATYPES: dict[int, np.dtype] = {
    PointField.INT8: np.dtype(np.int8),
    PointField.UINT8: np.dtype(np.uint8),
    PointField.INT16: np.dtype(np.int16),
    PointField.UINT16: np.dtype(np.uint16),
    PointField.INT32: np.dtype(np.int32),
    PointField.UINT32: np.dtype(np.uint32),
    PointField.FLOAT32: np.dtype(np.float32),
    PointField.FLOAT64: np.dtype(np.float64),
}

_XYZ = ("x", "y", "z")
_F32_LE = np.dtype("<f4")


def _as_int(value: Any, what: str) -> int:
    """An unsigned message integer, or ValueError (fields may hold anything when unchecked)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"PointCloud2 {what} must be an integer, got {type(value).__name__}")
    value = int(value)
    if value < 0:
        raise ValueError(f"PointCloud2 {what} must be >= 0, got {value}")
    return value


def _buffer(data: Any) -> np.ndarray:
    """``msg.data`` as a flat uint8 array, sharing memory where the type allows it."""
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8 or data.ndim != 1:
            raise ValueError(
                f"PointCloud2 data must be a 1-D uint8 array, got {data.dtype} {data.shape}")
        return data
    if isinstance(data, array.array) and data.typecode != "B":
        raise ValueError(f"PointCloud2 data must be an array of type 'B', got {data.typecode!r}")
    if isinstance(data, (bytes, bytearray, memoryview, array.array)):
        try:
            return np.frombuffer(data, dtype=np.uint8)
        except (TypeError, ValueError) as err:  # e.g. a multi-dimensional memoryview
            raise ValueError(f"PointCloud2 data is not a byte buffer: {err}") from err
    if isinstance(data, (list, tuple)):
        try:
            return np.asarray(data, dtype=np.uint8) if data else np.empty(0, np.uint8)
        except (TypeError, ValueError, OverflowError) as err:
            raise ValueError(f"PointCloud2 data is not a sequence of bytes: {err}") from err
    raise ValueError(f"PointCloud2 data has unsupported type {type(data).__name__}")


def _xyz_fields(msg: Any, point_step: int) -> dict[str, tuple[int, np.dtype]]:
    """Validate every PointField; return name -> (offset, dtype) for x, y and z."""
    try:
        fields = list(msg.fields)
    except TypeError as err:
        raise ValueError(f"PointCloud2 fields is not a sequence: {err}") from err
    found: dict[str, tuple[int, np.dtype]] = {}
    for i, field in enumerate(fields):
        name = getattr(field, "name", None)
        if not isinstance(name, str):
            raise ValueError(f"PointCloud2 field #{i} has no name")
        offset = _as_int(getattr(field, "offset", None), f"field {name!r} offset")
        count = _as_int(getattr(field, "count", None), f"field {name!r} count")
        datatype = getattr(field, "datatype", None)
        if isinstance(datatype, (bool, np.bool_)) or not isinstance(datatype, (int, np.integer)) \
                or int(datatype) not in DATATYPES:
            raise ValueError(f"PointCloud2 field {name!r} has unknown datatype {datatype!r} "
                             f"(expected 1..8, INT8..FLOAT64)")
        dtype = DATATYPES[int(datatype)]
        end = offset + dtype.itemsize * count
        if end > point_step:
            raise ValueError(f"PointCloud2 field {name!r} (offset {offset}, {count} x "
                             f"{dtype.itemsize} bytes) ends past point_step {point_step}")
        if name in _XYZ:
            if name in found:
                raise ValueError(f"PointCloud2 field {name!r} appears more than once")
            if count != 1:
                raise ValueError(f"PointCloud2 field {name!r} has count {count}, expected 1")
            found[name] = (offset, dtype)
    missing = [n for n in _XYZ if n not in found]
    if missing:
        raise ValueError(f"PointCloud2 has no field {', '.join(map(repr, missing))} "
                         f"(fields: {[getattr(f, 'name', None) for f in fields]})")
    return found


def cloud_to_xyz(msg: PointCloud2) -> np.ndarray:
    """The finite x, y, z of a PointCloud2 as a new (N, 3) float32 array.

    Points with any non-finite coordinate are dropped (so are FLOAT64 values beyond the
    float32 range, which become inf). Organized clouds are flattened in row-major order.
    An empty cloud (``width * height == 0``) with a valid field layout gives shape (0, 3).

    Raises:
        ValueError: missing x/y/z, unknown datatype, a field past ``point_step``, ``row_step``
            shorter than a row, ``data`` shorter than the layout needs, or a field that is not
            of the type the message definition says.
    """
    for attr in ("height", "width", "fields", "is_bigendian", "point_step", "row_step", "data"):
        if not hasattr(msg, attr):
            raise ValueError(f"expected a sensor_msgs/msg/PointCloud2, got {type(msg).__name__} "
                             f"without {attr!r}")
    height = _as_int(msg.height, "height")
    width = _as_int(msg.width, "width")
    point_step = _as_int(msg.point_step, "point_step")
    row_step = _as_int(msg.row_step, "row_step")
    if not isinstance(msg.is_bigendian, (bool, np.bool_, int, np.integer)) \
            or msg.is_bigendian not in (0, 1):
        raise ValueError(f"PointCloud2 is_bigendian must be a bool, got {msg.is_bigendian!r}")
    order = ">" if msg.is_bigendian else "<"
    xyz = _xyz_fields(msg, point_step)
    data = _buffer(msg.data)

    n = height * width
    if n == 0:
        return np.empty((0, 3), np.float32)
    row_bytes = width * point_step
    if height > 1 and row_step < row_bytes:
        raise ValueError(f"PointCloud2 row_step {row_step} is shorter than width * point_step "
                         f"= {row_bytes}")
    # A single row needs no row_step: some publishers leave it 0.
    stride_row = row_step if height > 1 else row_bytes
    needed = (height - 1) * stride_row + row_bytes
    if data.size < needed:
        raise ValueError(f"PointCloud2 data has {data.size} bytes, the layout needs {needed} "
                         f"(height {height}, width {width}, point_step {point_step}, "
                         f"row_step {row_step})")

    contiguous = stride_row == row_bytes
    shape = (n,) if contiguous else (height, width)
    strides = (point_step,) if contiguous else (stride_row, point_step)
    (ox, tx), (oy, ty), (oz, tz) = xyz["x"], xyz["y"], xyz["z"]
    f32 = np.dtype(np.float32)

    if tx == ty == tz == f32 and oy == ox + 4 and oz == ox + 8:
        # The common case, x y z as 12 adjacent bytes. Two views, no copy: the coordinates
        # (..., 3) float32 and the same bytes as one 12-byte record per point, which numpy
        # gathers far faster than strided rows of three floats.
        coords = np.ndarray(shape + (3,), dtype=np.dtype(order + "f4"), buffer=data,
                            offset=ox, strides=strides + (4,))  # (N, 3) or (H, W, 3)
        records = np.ndarray(shape, dtype=np.dtype((np.void, 12)), buffer=data, offset=ox,
                             strides=strides)  # (N,) or (H, W)
        with np.errstate(over="ignore", invalid="ignore"):
            # A point is finite iff x + y + z is, except when finite values overflow the
            # float32 sum: those rare points get the exact per-coordinate test.
            total = coords[..., 0] + coords[..., 1]
            total += coords[..., 2]
        keep = np.isfinite(total)  # (N,) or (H, W)
        if not keep.all():
            suspect = np.isinf(total)
            if suspect.any():
                keep[suspect] = np.isfinite(coords[suspect]).all(axis=-1)
        # Boolean indexing copies in row-major order; all-True skips the mask.
        picked = records.copy().reshape(n) if keep.all() else records[keep]
        return picked.view(np.dtype(order + "f4")).reshape(-1, 3).astype(f32, copy=False)

    out = np.empty((n, 3), np.float32)
    for col, (offset, dtype) in enumerate((xyz["x"], xyz["y"], xyz["z"])):
        column = np.ndarray(shape, dtype=dtype.newbyteorder(order), buffer=data, offset=offset,
                            strides=strides)  # (N,) or (H, W), a view
        with np.errstate(over="ignore", invalid="ignore"):
            out[:, col] = column.reshape(n)
    keep = np.isfinite(out).all(axis=1)  # (N,)
    return out if keep.all() else out[keep]


def xyz_to_cloud(xyz: np.ndarray, header: Header,
                 fields: Mapping[str, np.ndarray] | None = None) -> PointCloud2:
    """An unorganized little-endian PointCloud2 of float32 x, y, z and extra float32 fields.

    Args:
        xyz: (N, 3) coordinates in metres, in ``header.frame_id``; non-finite points are kept
            and make ``is_dense`` false.
        header: stamp and frame of the cloud.
        fields: optional extra per-point fields, name -> (N,) array (e.g. ``{"overlap": s}``),
            stored as FLOAT32 after x, y, z in the given order.

    Raises:
        ValueError: wrong shapes, non-numeric arrays, a field named x/y/z or twice, or a header
            that is not a std_msgs/Header.
    """
    if not isinstance(header, Header):
        raise ValueError(f"header must be a std_msgs/msg/Header, got {type(header).__name__}")
    points = _float32(xyz, "xyz")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"xyz must have shape (N, 3), got {points.shape}")
    n = points.shape[0]
    extras: dict[str, np.ndarray] = {}
    for name, values in (fields or {}).items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"field names must be non-empty strings, got {name!r}")
        if name in _XYZ:
            raise ValueError(f"extra field {name!r} clashes with the coordinates")
        column = _float32(values, f"field {name!r}")
        if column.shape != (n,):
            raise ValueError(f"field {name!r} must have shape ({n},), got {column.shape}")
        extras[name] = column

    names = list(_XYZ) + list(extras)
    record = np.empty(n, dtype=np.dtype([(name, _F32_LE) for name in names]))  # (N,) packed
    record["x"], record["y"], record["z"] = points[:, 0], points[:, 1], points[:, 2]
    for name, column in extras.items():
        record[name] = column

    msg = PointCloud2()
    msg.header = header
    msg.height = 1
    msg.width = n
    msg.fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, name in enumerate(names)]
    msg.is_bigendian = False
    msg.point_step = 4 * len(names)
    msg.row_step = msg.point_step * n
    data = array.array("B")
    data.frombytes(record.tobytes())
    msg.data = data
    msg.is_dense = bool(np.isfinite(points).all())
    return msg


def _float32(values: Any, what: str) -> np.ndarray:
    try:
        arr = np.asarray(values)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} is not an array: {err}") from err
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{what} must be numeric, got dtype {arr.dtype}")
    return arr.astype(np.float32, copy=False)
