"""A serialized sensor_msgs/PointCloud2 (its CDR bytes) -> the same view ``cloud_to_xyz`` reads.

Why: rclpy turns each incoming PointCloud2 into a Python message, which for a 5M-point
cloud (60 MB) takes ~200 ms on the executor thread, most of it with the GIL held. A node that
subscribes with ``raw=True`` gets the serialized bytes instead; :func:`parse_point_cloud2`
reads the header and the layout from them (a few hundred bytes, whatever the cloud's size) and
leaves the points where they are: ``data`` is a zero-copy uint8 view into the buffer. The result
has the PointCloud2 attribute names, so :func:`msg_adapters.point_cloud2.cloud_to_xyz` checks
the layout and converts the points exactly as for a message.

The format is the one ROS 2 puts on the wire (XCDR1, "classic" CDR): a 4-byte encapsulation
header (``00 00``: big endian, ``00 01``: little endian, then two option bytes), then the
fields in their message order, each primitive aligned to its own size counted from the end of
the encapsulation header. Strings are a uint32 length that counts the terminating NUL, the
bytes, the NUL; sequences are a uint32 count and the elements::

    header:  int32 stamp.sec, uint32 stamp.nanosec, string frame_id
    uint32 height, uint32 width
    PointField[] fields:  string name, uint32 offset, uint8 datatype, uint32 count
    bool is_bigendian, uint32 point_step, uint32 row_step
    uint8[] data, bool is_dense

A buffer that does not hold that (too short for a length it declares, a bool that is not
0/1, a name that is not UTF-8, another encapsulation) raises :class:`CdrError`, a
ValueError naming what and where; nothing else escapes. Bytes after ``is_dense`` are ignored,
as the ROS deserializer ignores them. No ROS import: numpy and the standard library only.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["CdrError", "CdrHeader", "CdrPointCloud2", "CdrPointField", "CdrStamp",
           "header_stamp_ns", "parse_point_cloud2"]

#: Encapsulation identifiers of plain CDR (XCDR1): the first two bytes of the buffer.
_CDR_BE, _CDR_LE = b"\x00\x00", b"\x00\x01"
#: The smallest serialized PointField: empty name (length 4 + NUL), offset, datatype, count.
_MIN_FIELD_BYTES = 4 + 1 + 3 + 4 + 1 + 3 + 4


class CdrError(ValueError):
    """A buffer that is not a serialized PointCloud2; the text names the part and offset."""


@dataclass(frozen=True)
class CdrStamp:
    """builtin_interfaces/Time as read from the buffer."""

    sec: int
    nanosec: int


@dataclass(frozen=True)
class CdrHeader:
    """std_msgs/Header as read from the buffer."""

    stamp: CdrStamp
    frame_id: str


@dataclass(frozen=True)
class CdrPointField:
    """sensor_msgs/PointField as read from the buffer."""

    name: str
    offset: int
    datatype: int
    count: int


@dataclass
class CdrPointCloud2:
    """A PointCloud2 whose ``data`` is a read-only uint8 view into the serialized buffer.

    The attributes are the message's, so ``cloud_to_xyz`` reads it like a message. The view
    keeps the whole buffer alive. ``header`` may be replaced (the node puts an rclpy Header
    there for its outputs).
    """

    header: Any
    height: int
    width: int
    fields: list[CdrPointField]
    is_bigendian: bool
    point_step: int
    row_step: int
    data: np.ndarray = field(repr=False)   # (row_step * height,) uint8, a view
    is_dense: bool


class _Reader:
    """Reads aligned primitives from ``buf`` (alignment counted from offset 4)."""

    def __init__(self, buf: memoryview, order: str) -> None:
        self.buf = buf
        self.pos = 4
        self._u32 = struct.Struct(order + "I")
        self._i32 = struct.Struct(order + "i")

    def _need(self, size: int, what: str) -> None:
        if self.pos + size > len(self.buf):
            raise CdrError(f"serialized PointCloud2 ends inside {what}: {size} bytes needed at "
                           f"offset {self.pos}, the buffer has {len(self.buf)}")

    def _align(self, size: int) -> None:
        self.pos += -(self.pos - 4) % size

    def _scalar(self, kind: struct.Struct, what: str) -> int:
        self._align(kind.size)
        self._need(kind.size, what)
        (value,) = kind.unpack_from(self.buf, self.pos)
        self.pos += kind.size
        return value

    def u32(self, what: str) -> int:
        return self._scalar(self._u32, what)

    def i32(self, what: str) -> int:
        return self._scalar(self._i32, what)

    def u8(self, what: str) -> int:
        self._need(1, what)
        value = self.buf[self.pos]
        self.pos += 1
        return value

    def boolean(self, what: str) -> bool:
        at = self.pos
        value = self.u8(what)
        if value > 1:
            raise CdrError(f"serialized PointCloud2 {what} at offset {at} is {value}, "
                           "a bool must be 0 or 1")
        return bool(value)

    def string(self, what: str) -> str:
        length = self.u32(f"the length of {what}")
        self._need(length, what)
        raw = bytes(self.buf[self.pos:self.pos + length])
        self.pos += length
        if raw.endswith(b"\x00"):
            raw = raw[:-1]
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise CdrError(f"serialized PointCloud2 {what} is not UTF-8: {err}") from None


def _open(buffer: Any) -> _Reader:
    """A reader after the encapsulation header of ``buffer`` (plain CDR, either byte order)."""
    try:
        view = memoryview(buffer).cast("B")
    except TypeError as err:
        raise CdrError(f"serialized PointCloud2 must be a byte buffer, got "
                       f"{type(buffer).__name__}: {err}") from None
    if len(view) < 4:
        raise CdrError(f"serialized PointCloud2 of {len(view)} bytes has no encapsulation header")
    kind = bytes(view[:2])
    if kind not in (_CDR_BE, _CDR_LE):
        raise CdrError(f"serialized PointCloud2 has encapsulation 0x{kind.hex()}, expected "
                       "plain CDR (0x0000 big endian or 0x0001 little endian)")
    return _Reader(view, ">" if kind == _CDR_BE else "<")


def _stamp(r: _Reader) -> CdrStamp:
    return CdrStamp(r.i32("header.stamp.sec"), r.u32("header.stamp.nanosec"))


def header_stamp_ns(buffer: Any) -> int:
    """The header stamp in nanoseconds of a serialized PointCloud2 (the first field of the
    message), without reading the rest; CdrError as :func:`parse_point_cloud2`."""
    stamp = _stamp(_open(buffer))
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def parse_point_cloud2(buffer: Any) -> CdrPointCloud2:
    """Read a serialized sensor_msgs/PointCloud2 without copying its points.

    Args:
        buffer: the CDR bytes (``bytes``, ``bytearray``, ``memoryview``, a uint8 array), as
            an rclpy subscription with ``raw=True`` delivers them.

    Returns:
        The message's fields; ``data`` is a read-only (or, for a writable buffer, writable)
        uint8 view of the point bytes inside ``buffer``.

    Raises:
        CdrError: the buffer is not a serialized PointCloud2 (named part and offset). The
            layout itself (fields, steps, sizes) is not checked here: ``cloud_to_xyz`` does.
    """
    r = _open(buffer)
    view = r.buf
    stamp = _stamp(r)
    frame_id = r.string("header.frame_id")
    height = r.u32("height")
    width = r.u32("width")
    n_fields = r.u32("the length of fields")
    if n_fields * _MIN_FIELD_BYTES > len(view) - r.pos:
        raise CdrError(f"serialized PointCloud2 declares {n_fields} fields; the "
                       f"{len(view) - r.pos} bytes after offset {r.pos} cannot hold them")
    fields = []
    for i in range(n_fields):
        name = r.string(f"the name of field #{i}")
        fields.append(CdrPointField(name=name, offset=r.u32(f"field {name!r} offset"),
                                    datatype=r.u8(f"field {name!r} datatype"),
                                    count=r.u32(f"field {name!r} count")))
    is_bigendian = r.boolean("is_bigendian")
    point_step = r.u32("point_step")
    row_step = r.u32("row_step")
    size = r.u32("the length of data")
    r._need(size, "data")
    data = np.frombuffer(view, dtype=np.uint8, count=size, offset=r.pos)   # (size,) a view
    r.pos += size
    is_dense = r.boolean("is_dense")
    return CdrPointCloud2(header=CdrHeader(stamp, frame_id), height=height,
                          width=width, fields=fields, is_bigendian=is_bigendian,
                          point_step=point_step, row_step=row_step, data=data,
                          is_dense=is_dense)
