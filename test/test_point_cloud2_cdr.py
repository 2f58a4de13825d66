"""msg_adapters.point_cloud2_cdr: serialized PointCloud2 bytes, read without rclpy's message.

The reference is rclpy's own (de)serializer: whatever ``serialize_message`` writes, the reader
must give the same fields, the same points through ``cloud_to_xyz`` and the same rejection
text for a bad layout. A hand-written encoder (checked against rclpy) adds what rclpy does not
write: big-endian encapsulation, non-zero padding, empty strings without their NUL.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2, PointField
from test_point_cloud2 import make_cloud, random_clouds, xyz_columns

from msg_adapters.point_cloud2 import cloud_to_xyz
from msg_adapters.point_cloud2_cdr import CdrError, CdrPointCloud2, parse_point_cloud2

INT32 = st.integers(-2**31, 2**31 - 1)
UINT32 = st.integers(0, 2**32 - 1)
# Frame ids of every length mod 4 (and multi-byte UTF-8) move everything after them. No NUL:
# rclpy passes strings through C, which ends them at the first NUL. No lone surrogates (codec
# utf-8): they have no UTF-8 encoding, so no message can carry them (rclpy cannot serialize one).
FRAMES = st.one_of(st.text(alphabet="abcxyz_/", max_size=13),
                   st.text(st.characters(codec="utf-8", exclude_characters="\x00"), max_size=6))


def encode(msg, big_endian: bool = False, pad: int = 0xAB, nul: bool = True) -> bytes:
    """A PointCloud2 as XCDR1 bytes, padding bytes set to ``pad`` (rclpy leaves them
    uninitialised); ``nul=False`` leaves the NUL off every string."""
    o = ">" if big_endian else "<"
    out = bytearray(b"\x00\x00\x00\x00" if big_endian else b"\x00\x01\x00\x00")

    def u32(value: int, code: str = "I") -> None:
        out.extend(bytes([pad]) * (-(len(out) - 4) % 4))
        out.extend(struct.pack(o + code, value))

    def string(text: str) -> None:
        raw = text.encode() + (b"\x00" if nul else b"")
        u32(len(raw))
        out.extend(raw)

    u32(msg.header.stamp.sec, "i")
    u32(msg.header.stamp.nanosec)
    string(msg.header.frame_id)
    u32(msg.height)
    u32(msg.width)
    u32(len(msg.fields))
    for f in msg.fields:
        string(f.name)
        u32(f.offset)
        out.append(f.datatype)
        u32(f.count)
    out.append(int(msg.is_bigendian))
    u32(msg.point_step)
    u32(msg.row_step)
    u32(len(msg.data))
    out.extend(bytes(msg.data))
    out.append(int(msg.is_dense))
    return bytes(out)


def as_message(msg) -> PointCloud2:
    """random_clouds gives rosbags-like stand-ins for numpy data: a real message of it."""
    if isinstance(msg, PointCloud2):
        return msg
    out = PointCloud2(header=msg.header, height=msg.height, width=msg.width,
                      fields=[PointField(name=f.name, offset=f.offset, datatype=f.datatype,
                                         count=f.count) for f in msg.fields],
                      is_bigendian=msg.is_bigendian, point_step=msg.point_step,
                      row_step=msg.row_step, is_dense=msg.is_dense)
    out.data = bytes(msg.data)
    return out


@st.composite
def messages(draw):
    """A valid cloud of any layout (test_point_cloud2.random_clouds) with any header, and
    the points cloud_to_xyz must give."""
    msg, xyz = draw(random_clouds())
    msg = as_message(msg)
    msg.header.frame_id = draw(FRAMES)
    msg.header.stamp.sec, msg.header.stamp.nanosec = draw(INT32), draw(st.integers(0, 10**9))
    msg.is_dense = draw(st.booleans())
    return msg, xyz


def assert_same(parsed: CdrPointCloud2, msg: PointCloud2) -> None:
    assert (parsed.header.stamp.sec, parsed.header.stamp.nanosec, parsed.header.frame_id) == \
        (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id)
    assert (parsed.height, parsed.width, parsed.is_bigendian, parsed.point_step,
            parsed.row_step, parsed.is_dense) == (msg.height, msg.width, msg.is_bigendian,
                                                   msg.point_step, msg.row_step, msg.is_dense)
    assert [(f.name, f.offset, f.datatype, f.count) for f in parsed.fields] == \
        [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
    assert parsed.data.dtype == np.uint8 and parsed.data.tobytes() == bytes(msg.data)


# --- against rclpy -----------------------------------------------------------------------


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(messages())
def test_property_rclpy_serialized_clouds_read_the_same(case):
    msg, expected = case
    buf = serialize_message(msg)
    parsed = parse_point_cloud2(buf)
    assert_same(parsed, msg)
    assert_same(parsed, deserialize_message(buf, PointCloud2))
    # The points are not copied: data is a view into the serialized buffer.
    assert parsed.data.size == 0 or np.shares_memory(parsed.data, np.frombuffer(buf, np.uint8))
    out = cloud_to_xyz(parsed)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, expected)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(messages(), st.booleans(), st.integers(0, 255))
def test_property_both_byte_orders_and_any_padding(case, big_endian, pad):
    msg, expected = case
    little = encode(msg, pad=pad)
    # The encoder writes what rclpy reads: it is a fair stand-in for a big-endian publisher.
    assert_same(parse_point_cloud2(serialize_message(deserialize_message(little, PointCloud2))),
                msg)
    parsed = parse_point_cloud2(encode(msg, big_endian=big_endian, pad=pad))
    assert_same(parsed, msg)
    np.testing.assert_array_equal(cloud_to_xyz(parsed), expected)


def test_float64_xyz_padded_point_step_and_a_big_endian_payload():
    xyz = np.array([[1.5, -2.0, 3.25], [1e300, 0.0, 0.0], [np.nan, 1, 2], [4, 5, 6]])
    msg = make_cloud({"intensity": (0, PointField.UINT16, np.arange(4)),
                      **xyz_columns(xyz, PointField.FLOAT64, (8, 16, 24))},
                     height=2, width=2, point_step=40, row_step=88, bigendian=True,
                     data_type="bytes")
    msg.header.frame_id = "odom"
    for buf in (serialize_message(msg), encode(msg, big_endian=True)):
        parsed = parse_point_cloud2(buf)
        assert_same(parsed, msg)
        # 1e300 overflows float32 to inf and is dropped with the NaN point.
        np.testing.assert_array_equal(cloud_to_xyz(parsed), [[1.5, -2.0, 3.25], [4, 5, 6]])


def test_empty_cloud_and_empty_strings_with_or_without_their_nul():
    msg = make_cloud(xyz_columns(np.zeros((0, 3), np.float32)), 0, 0, 12, data_type="bytes")
    msg.header.frame_id = ""
    for buf in (serialize_message(msg), encode(msg, nul=True), encode(msg, nul=False)):
        parsed = parse_point_cloud2(buf)
        assert parsed.header.frame_id == "" and parsed.data.shape == (0,)
        assert cloud_to_xyz(parsed).shape == (0, 3)
    msg.header.frame_id = "lidar"
    assert parse_point_cloud2(encode(msg, nul=False)).header.frame_id == "lidar"


def test_trailing_bytes_are_ignored_like_rclpy_ignores_them():
    msg = make_cloud(xyz_columns(np.ones((2, 3), np.float32)), 1, 2, 12, data_type="bytes")
    buf = serialize_message(msg) + b"\x07" * 9
    assert_same(parse_point_cloud2(buf), deserialize_message(buf, PointCloud2))


# --- the same rejection as for the message -------------------------------------------------

_LAYOUT_CORRUPTIONS = st.one_of(
    st.tuples(st.sampled_from(["height", "width", "point_step", "row_step"]),
              st.one_of(st.integers(0, 70), UINT32)),
    st.tuples(st.just("truncate"), st.integers(0, 200)),
    st.tuples(st.just("offset"), st.tuples(st.integers(0, 5), st.one_of(st.integers(0, 40),
                                                                       UINT32))),
    st.tuples(st.just("count"), st.tuples(st.integers(0, 5), st.one_of(st.integers(0, 3),
                                                                      UINT32))),
    st.tuples(st.just("datatype"), st.tuples(st.integers(0, 5), st.integers(0, 255))),
    st.tuples(st.just("name"), st.tuples(st.integers(0, 5),
                                         st.sampled_from(["x", "y", "z", "", "q"]))),
    st.tuples(st.just("drop_field"), st.integers(0, 5)),
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(messages(), st.lists(_LAYOUT_CORRUPTIONS, min_size=1, max_size=3))
def test_property_bad_layouts_are_rejected_with_the_same_text(case, corruptions):
    """Wrong fields, offsets, sizes, datatypes, truncated data: the node's rejection of a cloud
    it read from bytes names the same problem as for the message rclpy would have built."""
    msg, _ = case
    for kind, arg in corruptions:
        if kind == "truncate":
            msg.data = bytes(msg.data)[:arg]
        elif kind == "drop_field":
            if msg.fields:
                msg.fields = [f for i, f in enumerate(msg.fields) if i != arg % len(msg.fields)]
        elif kind in ("offset", "count", "datatype", "name"):
            if msg.fields:
                fields = list(msg.fields)
                setattr(fields[arg[0] % len(fields)], kind, arg[1])
                msg.fields = fields
        else:
            setattr(msg, kind, arg)
    buf = serialize_message(msg)
    outcomes = []
    for cloud in (deserialize_message(buf, PointCloud2), parse_point_cloud2(buf)):
        try:
            outcomes.append(cloud_to_xyz(cloud))
        except ValueError as err:
            outcomes.append(str(err))
    if isinstance(outcomes[0], str):
        event("rejected")
        assert outcomes[1] == outcomes[0]
    else:
        event("accepted")
        np.testing.assert_array_equal(outcomes[1], outcomes[0])


# --- buffers that are not a PointCloud2 ----------------------------------------------------


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(messages(), st.booleans())
def test_property_every_truncation_is_a_cdr_error(case, big_endian):
    msg, _ = case
    buf = serialize_message(msg) if not big_endian else encode(msg, big_endian=True)
    for k in range(len(buf)):
        with pytest.raises(CdrError):
            parse_point_cloud2(buf[:k])


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(messages(), st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), min_size=1,
                            max_size=6))
def test_property_corrupted_bytes_are_a_cdr_error_or_a_cloud(case, edits):
    """Random bytes overwritten anywhere (lengths, counts, bools, strings): the reader raises
    CdrError or returns a cloud, whose conversion raises ValueError or returns points."""
    msg, _ = case
    buf = bytearray(serialize_message(msg))
    for at, value in edits:
        buf[at % len(buf)] = value
    try:
        parsed = parse_point_cloud2(bytes(buf))
    except CdrError:
        event("CdrError")
        return
    event("parsed")
    assert parsed.data.size <= len(buf)
    try:
        out = cloud_to_xyz(parsed)
    except ValueError:
        return
    assert out.dtype == np.float32 and out.shape[1] == 3 and np.isfinite(out).all()


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=200))
def test_property_garbage_is_a_cdr_error_or_a_cloud(data):
    try:
        parse_point_cloud2(b"\x00\x01\x00\x00" + data)
    except CdrError:
        pass


def _valid() -> bytes:
    msg = make_cloud(xyz_columns(np.ones((2, 3), np.float32)), 1, 2, 12, data_type="bytes")
    msg.header.frame_id = "ab"     # 3 bytes with its NUL, then 1 byte of padding; see the asserts
    return serialize_message(msg)


def _put(buf: bytes, at: int, raw: bytes) -> bytes:
    return buf[:at] + raw + buf[at + len(raw):]


@pytest.mark.parametrize("edit, problem", [
    (lambda b: b"", "0 bytes has no encapsulation header"),
    (lambda b: b"\x00\x01\x00", "3 bytes has no encapsulation header"),
    (lambda b: _put(b, 0, b"\x00\x03"), "encapsulation 0x0003"),     # PL_CDR
    (lambda b: _put(b, 0, b"\x00\x07"), "encapsulation 0x0007"),     # XCDR2
    (lambda b: _put(b, 12, struct.pack("<I", 2**32 - 1)), "inside header.frame_id"),
    (lambda b: _put(b, 18, b"\xff"), "frame_id is not UTF-8"),
    (lambda b: _put(b, 28, struct.pack("<I", 2**32 - 1)), "declares 4294967295 fields"),
    (lambda b: _put(b, 28, struct.pack("<I", 4)), "ends inside"),
    (lambda b: b[:-1] + b"\x02", "is_dense at offset 132 is 2, a bool must be 0 or 1"),
    (lambda b: _put(b, 104, struct.pack("<I", 26)),
     "ends inside data: 26 bytes needed at offset 108"),
])
def test_malformed_buffers_name_the_problem(edit, problem):
    buf = _valid()
    assert len(buf) == 133 and struct.unpack_from("<I", buf, 104)[0] == 24   # the data length
    with pytest.raises(CdrError, match=problem):
        parse_point_cloud2(edit(buf))


@pytest.mark.parametrize("thing", [None, 3, "a string", [1, 2, 3], np.zeros((2, 2), np.uint8).T])
def test_what_is_not_a_byte_buffer_is_a_cdr_error(thing):
    with pytest.raises(CdrError, match="byte buffer|encapsulation"):
        parse_point_cloud2(thing)


def test_cdr_error_is_a_value_error_and_other_buffer_types_are_read():
    assert issubclass(CdrError, ValueError)
    buf = _valid()
    for kind in (bytearray(buf), memoryview(buf), np.frombuffer(buf, np.uint8)):
        np.testing.assert_array_equal(cloud_to_xyz(parse_point_cloud2(kind)), np.ones((2, 3)))
