"""msg_adapters.point_cloud2: every layout PointCloud2 allows, and malformed ones."""

from __future__ import annotations

import array
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from msg_adapters.point_cloud2 import DATATYPES, cloud_to_xyz, xyz_to_cloud

ALL_TYPES = sorted(DATATYPES)  # INT8 .. FLOAT64
FLOAT_TYPES = (PointField.FLOAT32, PointField.FLOAT64)


def header(frame: str = "cegc_source") -> Header:
    h = Header(frame_id=frame)
    h.stamp.sec, h.stamp.nanosec = 12, 345
    return h


def make_cloud(columns: dict[str, tuple[int, int, np.ndarray]], height: int, width: int,
               point_step: int, row_step: int | None = None, bigendian: bool = False,
               fill: int = 0xAB, data_type: str = "array") -> PointCloud2:
    """A hand-built cloud. columns: name -> (offset, datatype, (height*width,) values).

    Bytes not covered by a field (point padding, row padding) are set to ``fill``.
    """
    row_step = width * point_step if row_step is None else row_step
    size = max(0, (height - 1) * row_step + width * point_step) if height * width else 0
    buf = np.full(size, fill, np.uint8)
    order = ">" if bigendian else "<"
    for offset, datatype, values in columns.values():
        dtype = DATATYPES[datatype].newbyteorder(order)
        values = np.asarray(values).reshape(height, width)
        for r in range(height):
            for c in range(width):
                start = r * row_step + c * point_step + offset
                buf[start:start + dtype.itemsize] = np.frombuffer(
                    np.asarray(values[r, c], dtype=dtype).tobytes(), np.uint8)
    fields = [PointField(name=name, offset=off, datatype=dt, count=1)
              for name, (off, dt, _) in columns.items()]
    data: object = {"array": array.array("B", buf.tobytes()), "bytes": buf.tobytes(),
                    "numpy": buf, "list": buf.tolist()}[data_type]
    msg = PointCloud2(header=header(), height=height, width=width, fields=fields,
                      is_bigendian=bigendian, point_step=point_step, row_step=row_step,
                      is_dense=False)
    msg.data = data
    if data_type == "numpy":
        # rclpy's setter turns any sequence into array.array; rosbags messages carry numpy.
        return _duck(msg, data)
    return msg


def _duck(msg: PointCloud2, data) -> SimpleNamespace:
    """A rosbags-like stand-in with the same attributes and ``data`` as given."""
    fields = [SimpleNamespace(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
              for f in msg.fields]
    return SimpleNamespace(header=msg.header, height=msg.height, width=msg.width, fields=fields,
                           is_bigendian=msg.is_bigendian, point_step=msg.point_step,
                           row_step=msg.row_step, data=data, is_dense=msg.is_dense)


def xyz_columns(xyz: np.ndarray, datatype: int = PointField.FLOAT32, offsets=(0, 4, 8)):
    names = zip("xyz", offsets, strict=True)
    return {n: (o, datatype, xyz[:, i]) for i, (n, o) in enumerate(names)}


# --- round trips -------------------------------------------------------------------------


def test_round_trip_with_extra_fields_is_exact_and_serializable():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3)).astype(np.float32)
    overlap = rng.uniform(size=50).astype(np.float32)
    msg = xyz_to_cloud(xyz, header(), {"overlap": overlap, "intensity": np.arange(50)})
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, 50, 20, 1000)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "overlap", "intensity"]
    assert [f.offset for f in msg.fields] == [0, 4, 8, 12, 16]
    assert msg.is_dense and not msg.is_bigendian and msg.header.frame_id == "cegc_source"
    again = deserialize_message(serialize_message(msg), PointCloud2)
    out = cloud_to_xyz(again)
    np.testing.assert_array_equal(out, xyz)
    assert out.dtype == np.float32 and out.flags.c_contiguous and out.flags.writeable
    rec = np.frombuffer(bytes(again.data), dtype=np.dtype(
        [(n, "<f4") for n in ("x", "y", "z", "overlap", "intensity")]))
    np.testing.assert_array_equal(rec["overlap"], overlap)
    np.testing.assert_array_equal(rec["intensity"], np.arange(50, dtype=np.float32))


def test_xyz_to_cloud_keeps_nan_points_and_marks_cloud_not_dense():
    xyz = np.array([[1, 2, 3], [np.nan, 0, 0], [4, 5, 6]], np.float64)
    msg = xyz_to_cloud(xyz, header())
    assert not msg.is_dense and msg.width == 3
    np.testing.assert_array_equal(cloud_to_xyz(msg), [[1, 2, 3], [4, 5, 6]])


def test_empty_clouds():
    msg = xyz_to_cloud(np.zeros((0, 3)), header())
    assert msg.width == 0 and len(msg.data) == 0
    assert cloud_to_xyz(msg).shape == (0, 3)
    for height, width in ((0, 5), (5, 0), (0, 0)):
        empty = make_cloud(xyz_columns(np.zeros((0, 3), np.float32)), height, width, 12)
        out = cloud_to_xyz(empty)
        assert out.shape == (0, 3) and out.dtype == np.float32


# --- hand-built layouts ------------------------------------------------------------------


@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("datatype", ALL_TYPES)
def test_every_datatype_and_byte_order(datatype, bigendian):
    signed = DATATYPES[datatype].kind in "if"
    xyz = np.array([[1, 2, 3], [-4, 5, -6], [100, -100, 0], [7, 127, 8]], np.float64)
    if not signed:
        xyz = np.abs(xyz)
    size = DATATYPES[datatype].itemsize
    msg = make_cloud(xyz_columns(xyz, datatype, (0, size, 2 * size)), 1, 4, 3 * size,
                     bigendian=bigendian)
    np.testing.assert_array_equal(cloud_to_xyz(msg), xyz.astype(np.float32))


def test_padded_point_step_extra_fields_any_order():
    # Velodyne/Ouster-like: intensity first, z before x, ring uint16, 7 bytes of padding.
    xyz = np.array([[1.5, -2.0, 0.25], [3.0, 4.0, 5.0], [-1.0, 0.0, 9.5]], np.float32)
    columns = {
        "intensity": (0, PointField.FLOAT32, np.array([10, 20, 30])),
        "z": (4, PointField.FLOAT32, xyz[:, 2]),
        "ring": (8, PointField.UINT16, np.array([1, 2, 3])),
        "x": (12, PointField.FLOAT32, xyz[:, 0]),
        "y": (20, PointField.FLOAT32, xyz[:, 1]),
        "t": (24, PointField.FLOAT64, np.array([0.1, 0.2, 0.3])),
    }
    msg = make_cloud(columns, 1, 3, point_step=40, fill=0xFF)
    np.testing.assert_array_equal(cloud_to_xyz(msg), xyz)


def test_xyzrgb_fast_path_with_padding_between_points():
    xyz = np.arange(30, dtype=np.float32).reshape(10, 3)
    columns = xyz_columns(xyz, PointField.FLOAT32, (4, 8, 12))
    columns["rgb"] = (16, PointField.FLOAT32, np.full(10, 0.5))
    msg = make_cloud(columns, 1, 10, point_step=32, fill=0xFF)  # 0xFF bytes are NaN floats
    np.testing.assert_array_equal(cloud_to_xyz(msg), xyz)


def test_organized_cloud_with_row_padding_is_row_major():
    """Pinned order: row 0 left to right, then row 1, ... (image order).

    x = row, y = column, z = a running index; the padding at the end of each row is 0xFF,
    which reads as NaN if a row is addressed with the wrong stride.
    """
    height, width, point_step = 3, 4, 16
    rows, cols = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    xyz = np.stack([rows.ravel(), cols.ravel(), np.arange(height * width)], 1).astype(np.float32)
    msg = make_cloud(xyz_columns(xyz), height, width, point_step,
                     row_step=width * point_step + 8, fill=0xFF)
    out = cloud_to_xyz(msg)
    np.testing.assert_array_equal(out, xyz)
    np.testing.assert_array_equal(out[:5], [[0, 0, 0], [0, 1, 1], [0, 2, 2], [0, 3, 3],
                                            [1, 0, 4]])
    # Same order on the general (per-coordinate) path.
    msg64 = make_cloud(xyz_columns(xyz, PointField.FLOAT64, (0, 8, 16)), height, width, 24,
                       row_step=width * 24 + 5, fill=0xFF)
    np.testing.assert_array_equal(cloud_to_xyz(msg64), xyz)


def test_organized_cloud_without_row_padding():
    xyz = np.arange(24, dtype=np.float32).reshape(8, 3)
    msg = make_cloud(xyz_columns(xyz), 2, 4, 12)
    np.testing.assert_array_equal(cloud_to_xyz(msg), xyz)


def test_non_finite_points_dropped_in_order():
    xyz = np.array([[1, 1, 1], [np.nan, 0, 0], [2, 2, 2], [0, np.inf, 0], [0, 0, -np.inf],
                    [3, 3, 3]], np.float32)
    msg = make_cloud(xyz_columns(xyz), 1, 6, 12)
    np.testing.assert_array_equal(cloud_to_xyz(msg), [[1, 1, 1], [2, 2, 2], [3, 3, 3]])
    msg64 = make_cloud(xyz_columns(xyz.astype(np.float64), PointField.FLOAT64, (0, 8, 16)),
                       1, 6, 24)
    np.testing.assert_array_equal(cloud_to_xyz(msg64), [[1, 1, 1], [2, 2, 2], [3, 3, 3]])


def test_large_finite_values_are_kept_even_when_their_sum_overflows():
    xyz = np.array([[3e38, 3e38, 3e38], [-3e38, 1, 2]], np.float32)
    np.testing.assert_array_equal(cloud_to_xyz(make_cloud(xyz_columns(xyz), 1, 2, 12)), xyz)


def test_float64_beyond_float32_range_is_dropped():
    xyz = np.array([[1e300, 0, 0], [1, 2, 3]], np.float64)
    msg = make_cloud(xyz_columns(xyz, PointField.FLOAT64, (0, 8, 16)), 1, 2, 24)
    np.testing.assert_array_equal(cloud_to_xyz(msg), [[1, 2, 3]])


def test_non_adjacent_float32_coordinates():
    xyz = np.array([[1, 2, 3], [4, 5, 6]], np.float32)
    msg = make_cloud(xyz_columns(xyz, PointField.FLOAT32, (8, 0, 16)), 1, 2, 20)
    np.testing.assert_array_equal(cloud_to_xyz(msg), xyz)


@pytest.mark.parametrize("data_type", ["array", "bytes", "numpy", "list"])
def test_data_container_types(data_type):
    xyz = np.array([[1, 2, 3], [4, 5, 6]], np.float32)
    msg = make_cloud(xyz_columns(xyz), 1, 2, 12, data_type=data_type)
    np.testing.assert_array_equal(cloud_to_xyz(msg), xyz)


def test_single_row_ignores_row_step_and_trailing_bytes():
    xyz = np.array([[1, 2, 3], [4, 5, 6]], np.float32)
    msg = make_cloud(xyz_columns(xyz), 1, 2, 12)
    msg.row_step = 0  # some drivers leave it unset for unorganized clouds
    msg.data = array.array("B", bytes(msg.data) + b"\x00" * 7)
    np.testing.assert_array_equal(cloud_to_xyz(msg), xyz)


@pytest.mark.parametrize("data_type", ["bytes", "numpy"])
def test_result_does_not_alias_the_message_buffer(data_type):
    xyz = np.array([[1, 2, 3]], np.float32)
    msg = make_cloud(xyz_columns(xyz), 1, 1, 12, data_type=data_type)
    out = cloud_to_xyz(msg)
    assert out.flags.writeable and out.flags.owndata or out.base.flags.owndata
    out[0, 0] = 99.0
    np.testing.assert_array_equal(cloud_to_xyz(msg), xyz)


# --- malformed messages ------------------------------------------------------------------


def good_cloud() -> PointCloud2:
    return make_cloud(xyz_columns(np.arange(12, dtype=np.float32).reshape(4, 3)), 2, 2, 16,
                      row_step=36)


def _set_field(i: int, **kw):
    def apply(msg):
        for k, v in kw.items():
            setattr(msg.fields[i], k, v)
    return apply


MALFORMED = {
    "no field 'z'": lambda m: m.fields.pop(2),
    "no field 'x', 'y', 'z'": lambda m: setattr(m, "fields", []),
    "data has 40 bytes": lambda m: setattr(m, "data", m.data[:40]),
    "ends past point_step": _set_field(2, offset=14),
    "unknown datatype 9": _set_field(0, datatype=9),
    "unknown datatype 0": _set_field(1, datatype=0),
    "has count 3": _set_field(0, count=3),
    "appears more than once": _set_field(1, name="x"),
    "row_step 20 is shorter": lambda m: setattr(m, "row_step", 20),
    "point_step must be >= 0": lambda m: setattr(m, "point_step", -1),
    "height must be an integer": lambda m: setattr(m, "height", 2.0),
    "is_bigendian must be a bool": lambda m: setattr(m, "is_bigendian", "yes"),
    "data has unsupported type": lambda m: setattr(m, "data", "abc"),
    "field 'y' offset must be >= 0": _set_field(1, offset=-4),
}


@pytest.mark.parametrize("problem", sorted(MALFORMED))
def test_malformed_message_raises_value_error_naming_the_problem(problem):
    msg = _duck(good_cloud(), None)  # any attribute value, as an unchecked message holds
    msg.data = array.array("B", good_cloud().data)
    assert cloud_to_xyz(msg).shape == (4, 3)
    MALFORMED[problem](msg)
    with pytest.raises(ValueError, match=problem.replace("(", r"\(")):
        cloud_to_xyz(msg)


def test_data_shorter_than_width_height_point_step():
    msg = make_cloud(xyz_columns(np.ones((6, 3), np.float32)), 2, 3, 12)
    msg.data = msg.data[:-1]
    with pytest.raises(ValueError, match="data has 71 bytes, the layout needs 72"):
        cloud_to_xyz(msg)


def test_numpy_data_of_the_wrong_dtype():
    msg = _duck(good_cloud(), np.zeros(80, np.float32))
    with pytest.raises(ValueError, match="1-D uint8 array"):
        cloud_to_xyz(msg)


def test_not_a_point_cloud():
    with pytest.raises(ValueError, match="expected a sensor_msgs/msg/PointCloud2"):
        cloud_to_xyz(Header())
    with pytest.raises(ValueError, match="expected a sensor_msgs/msg/PointCloud2"):
        cloud_to_xyz(None)


@pytest.mark.parametrize("xyz, fields, problem", [
    (np.zeros((4, 2)), None, r"shape \(N, 3\)"),
    (np.zeros(3), None, r"shape \(N, 3\)"),
    (np.array([["a", "b", "c"]]), None, "numeric"),
    (np.zeros((4, 3)), {"overlap": np.zeros(3)}, r"shape \(4,\)"),
    (np.zeros((4, 3)), {"x": np.zeros(4)}, "clashes"),
    (np.zeros((4, 3)), {"": np.zeros(4)}, "non-empty strings"),
    (np.zeros((4, 3)), {"s": ["a"] * 4}, "numeric"),
])
def test_xyz_to_cloud_rejects_bad_input(xyz, fields, problem):
    with pytest.raises(ValueError, match=problem):
        xyz_to_cloud(xyz, header(), fields)


def test_xyz_to_cloud_rejects_bad_header():
    with pytest.raises(ValueError, match="std_msgs/msg/Header"):
        xyz_to_cloud(np.zeros((1, 3)), "frame")


# --- properties --------------------------------------------------------------------------

_RANGES = {np.dtype(np.int8): (-128, 127), np.dtype(np.uint8): (0, 255),
           np.dtype(np.int16): (-2000, 2000), np.dtype(np.uint16): (0, 4000),
           np.dtype(np.int32): (-10**6, 10**6), np.dtype(np.uint32): (0, 10**6)}


@st.composite
def random_clouds(draw):
    """A valid cloud of any layout, plus the points cloud_to_xyz must return."""
    height = draw(st.integers(0, 4))
    width = draw(st.integers(0, 6))
    n = height * width
    extras = draw(st.lists(st.sampled_from(["rgb", "intensity", "ring", "t"]), unique=True,
                           max_size=3))
    # Half the clouds have x, y, z as adjacent FLOAT32 (the fast path), half any layout.
    packed_xyz = draw(st.booleans())
    if packed_xyz:
        names = draw(st.permutations(["xyz"] + extras))
        i = names.index("xyz")
        names[i:i + 1] = ["x", "y", "z"]
    else:
        names = draw(st.permutations(["x", "y", "z"] + extras))
    columns, offset = {}, 0
    values = {}
    for name in names:
        packed = packed_xyz and name in "xyz"
        datatype = PointField.FLOAT32 if packed else draw(st.sampled_from(ALL_TYPES))
        dtype = DATATYPES[datatype]
        offset += 0 if packed and name != "x" else draw(st.integers(0, 3))  # gaps
        if dtype.kind == "f":
            elem = st.floats(width=32, allow_nan=True, allow_infinity=True)
        else:
            elem = st.integers(*_RANGES[dtype])
        vals = np.array(draw(st.lists(elem, min_size=n, max_size=n)), dtype=np.float64)
        columns[name] = (offset, datatype, vals)
        values[name] = vals
        offset += dtype.itemsize
    point_step = offset + draw(st.integers(0, 5))
    row_step = width * point_step + (draw(st.integers(0, 9)) if height > 1 else 0)
    msg = make_cloud(columns, height, width, point_step, row_step,
                     bigendian=draw(st.booleans()), fill=draw(st.integers(0, 255)),
                     data_type=draw(st.sampled_from(["array", "bytes", "numpy"])))
    xyz = np.stack([values["x"], values["y"], values["z"]], 1).astype(np.float32) \
        if n else np.zeros((0, 3), np.float32)
    return msg, xyz[np.isfinite(xyz).all(1)]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(random_clouds())
def test_property_random_valid_clouds_round_trip(case):
    msg, expected = case
    out = cloud_to_xyz(msg)
    assert out.dtype == np.float32 and out.shape == expected.shape
    np.testing.assert_array_equal(out, expected)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6, width=32), min_size=0, max_size=60).map(
    lambda v: np.array(v[: len(v) // 3 * 3], np.float32).reshape(-1, 3)))
def test_property_xyz_to_cloud_round_trip(xyz):
    msg = deserialize_message(serialize_message(xyz_to_cloud(xyz, header())), PointCloud2)
    np.testing.assert_array_equal(cloud_to_xyz(msg), xyz)


_INTS = st.one_of(st.integers(-3, 70), st.integers(-2**33, 2**33), st.sampled_from([2**32 - 1]))
_CORRUPTIONS = st.one_of(
    st.tuples(st.sampled_from(["height", "width", "point_step", "row_step"]), _INTS),
    st.tuples(st.just("truncate"), st.integers(0, 200)),
    st.tuples(st.just("is_bigendian"), st.sampled_from([True, False, 2, None, "x"])),
    st.tuples(st.sampled_from(["offset", "datatype", "count"]),
              st.tuples(st.integers(0, 5), _INTS)),
    st.tuples(st.just("name"), st.tuples(st.integers(0, 5), st.sampled_from(["x", "y", "z", "",
                                                                              "q", None]))),
    st.tuples(st.just("drop_field"), st.integers(0, 5)),
    st.tuples(st.just("data"), st.sampled_from([None, 3, "abc", [1, 2, 300], b"", [],
                                                np.zeros(5, np.int64)])),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(random_clouds(), st.lists(_CORRUPTIONS, min_size=1, max_size=3))
def test_property_corruptions_give_only_value_error(case, corruptions):
    msg, _ = case
    if isinstance(msg, PointCloud2):
        msg = _duck(msg, msg.data)
    for kind, arg in corruptions:
        if kind == "truncate":
            if hasattr(msg.data, "__getitem__"):
                msg.data = msg.data[:arg]
        elif kind in ("offset", "datatype", "count", "name"):
            i, value = arg
            if msg.fields:
                setattr(msg.fields[i % len(msg.fields)], kind, value)
        elif kind == "drop_field":
            if msg.fields:
                msg.fields.pop(arg % len(msg.fields))
        elif kind == "data":
            msg.data = arg
        else:
            setattr(msg, kind, arg)
    try:
        out = cloud_to_xyz(msg)
    except ValueError:
        event("rejected with ValueError")
        return
    event("accepted")
    # Whatever is accepted is a well-formed answer from a consistent layout.
    assert out.dtype == np.float32 and out.ndim == 2 and out.shape[1] == 3
    assert np.isfinite(out).all()
    assert out.shape[0] <= msg.height * msg.width
