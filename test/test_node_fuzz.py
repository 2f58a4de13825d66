"""Property-based fuzz of register_node over DDS: corrupted PointCloud2 pairs, then a good one.

One register_node subprocess (the real engine, in its engine process) receives pairs whose
clouds hypothesis corrupts: missing, repeated or mistyped fields, offsets past the point,
wrong point/row steps, data shorter or longer than the layout, absurd widths and heights,
big-endian data, NaN/Inf/huge/identical coordinates, empty and large clouds, and bursts
of several pairs at once. After every example the node's /diagnostics must account for
each message and each pair (answered, rejected with a reason, or dropped by the one-slot
mailbox), and at the end the node is alive, its engine never crashed, and a valid pair
still gets its pose.

Bounded in time: a modest number of examples of small clouds (the large ones are 20k-150k
points), each waited for by counters, not by the clock.
"""

from __future__ import annotations

import array
import os
import subprocess
import sys

import numpy as np
import pytest
import ros_helpers as rh

rclpy = pytest.importorskip("rclpy")
hypothesis = pytest.importorskip("hypothesis")

from hypothesis import HealthCheck, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from cegc_ros.spinning import Spinner  # noqa: E402

SEC = 10**9
MAX_EXAMPLES = int(os.environ.get("CEGC_FUZZ_EXAMPLES", "30"))

READABLE = ("ok", "organized", "bigendian", "float64", "extra_fields", "long_data")
CORRUPT = ("drop_field", "duplicate_field", "datatype", "offset_past_point", "count",
           "short_data", "point_step_small", "huge_dims", "row_step_short", "no_frame", "empty")
VALUES = ("normal", "some_nan", "all_nan", "inf", "huge", "tiny", "identical", "flat")


def build(layout: str, values: str, n: int, seed: int, stamp: int, frame: str):
    """A PointCloud2 with the given corruption (every field within its message type)."""
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import PointCloud2, PointField
    from std_msgs.msg import Header

    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-2, 2, (n, 3))
    if values == "some_nan":
        xyz[rng.random(n) < 0.5] = np.nan
    elif values == "all_nan":
        xyz[:] = np.nan
    elif values == "inf":
        xyz[rng.random(n) < 0.3, rng.integers(0, 3)] = np.inf
    elif values == "huge":
        xyz *= 1e30
    elif values == "tiny":
        xyz *= 1e-30
    elif values == "identical":
        xyz[:] = xyz[:1]
    elif values == "flat":
        xyz[:, 2] = 0.0
    dtype, size, code = np.float32, 4, PointField.FLOAT32
    if layout == "float64":
        dtype, size, code = np.float64, 8, PointField.FLOAT64
    big = layout == "bigendian"
    order = ">" if big else "<"
    names = ["x", "y", "z"] + (["intensity", "ring"] if layout == "extra_fields" else [])
    cols = np.concatenate([xyz, rng.uniform(0, 1, (n, len(names) - 3))], 1)
    data = cols.astype(np.dtype(dtype).newbyteorder(order)).tobytes()
    point_step = size * len(names)
    fields = [PointField(name=nm, offset=size * i, datatype=code, count=1)
              for i, nm in enumerate(names)]
    height, width, row_step = 1, n, point_step * n
    if layout == "drop_field":
        del fields[int(rng.integers(0, 3))]
    elif layout == "duplicate_field":
        fields.append(PointField(name="x", offset=0, datatype=code, count=1))
    elif layout == "datatype":
        fields[int(rng.integers(0, 3))].datatype = int(rng.choice([0, 9, 77, 255]))
    elif layout == "offset_past_point":
        fields[int(rng.integers(0, 3))].offset = int(rng.choice([point_step, 2**31, 2**32 - 1]))
    elif layout == "count":
        fields[0].count = int(rng.choice([0, 2, 2**32 - 1]))
    elif layout == "short_data":
        data = data[: int(rng.integers(0, max(1, len(data))))]
    elif layout == "long_data":
        data += bytes(int(rng.integers(1, 1000)))
    elif layout == "point_step_small":
        point_step = int(rng.integers(0, size * 3))
    elif layout == "huge_dims":
        width, height = 2**32 - 1, int(rng.integers(1, 2**16))
    elif layout == "row_step_short" and n >= 4:
        height, width = 2, n // 2
        data = data[: 2 * width * point_step]
        row_step = int(rng.integers(0, width * point_step))
    elif layout == "organized" and n >= 4:
        height, width = 2, n // 2
        pad = bytes(int(rng.integers(1, 16)))
        row = width * point_step
        data = data[:row] + pad + data[row:2 * row] + pad
        row_step = row + len(pad)
    elif layout == "empty":
        width, data = 0, b""
    msg = PointCloud2()
    msg.header = Header(stamp=Time(sec=stamp // SEC, nanosec=stamp % SEC),
                        frame_id="" if layout == "no_frame" else frame)
    msg.height, msg.width = height, width
    msg.fields = fields
    msg.is_bigendian = big
    msg.point_step, msg.row_step = point_step, row_step
    buf = array.array("B")
    buf.frombytes(data)
    msg.data = buf
    msg.is_dense = False
    return msg


@pytest.fixture(scope="module")
def node():
    from rclpy.executors import SingleThreadedExecutor

    cmd = [sys.executable, "-m", "cegc_ros.node", "--ros-args", "--params-file",
           f"{rh.REPO}/params/register_node.yaml", "-p", "engine.device:=cpu", "-p", "input.reliable:=true",
           "-p", "input.queue_depth:=200", "-p", "preprocess.num_points:=256",
           "-p", "diagnostics.period:=0.2", "-p", "diagnostics.log_throttle:=60.0",
           "-r", "__ns:=/fuzz"]
    proc = subprocess.Popen(cmd, env=rh.ros_env(), cwd=rh.REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    context = rclpy.Context()
    rclpy.init(context=context)
    probe = rh.make_probe(namespace="/fuzz", context=context)
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(probe)
    spinner = Spinner(ex)
    try:
        ok = rh.wait_for(lambda: (probe.connected() and probe.diagnostics())
                         or proc.poll() is not None, 180.0)
        if not ok or proc.poll() is not None:
            proc.kill()
            pytest.fail(f"node did not come up:\n{proc.communicate()[0]}")
        yield proc, probe
    finally:
        if proc.poll() is None:
            proc.terminate()
        try:
            out = proc.communicate(timeout=30)[0]
        except subprocess.TimeoutExpired:
            proc.kill()
            out = proc.communicate()[0]
        spinner.stop()
        probe.destroy_node()
        rclpy.try_shutdown(context=context)
        assert "Traceback" not in out, out


_stamp = [10_000 * SEC]


def _settled(probe, sent_src: int, sent_pairs: int, base: dict[str, int]) -> bool:
    d = probe.diagnostics()
    if not d:
        return False
    c = {k: int(v) - base.get(k, 0) for k, v in d.items() if v.lstrip("-").isdigit()}
    return (c["messages_in.source"] == sent_src and c["pairs_in"] == sent_pairs
            and c["pairs_done"] + c["pairs_dropped"] == c["pairs_in"])


def _counts(probe) -> dict[str, int]:
    return {k: int(v) for k, v in probe.diagnostics().items() if v.lstrip("-").isdigit()}


def _fresh(probe) -> dict[str, int]:
    n = len(probe.outputs("diagnostics"))
    assert rh.wait_for(lambda: len(probe.outputs("diagnostics")) > n + 1, 30.0)
    return _counts(probe)


# Half of the clouds have a layout the node can read, so that hostile values reach the engine.
SIDE = st.tuples(st.one_of(st.sampled_from(READABLE), st.sampled_from(CORRUPT)),
                 st.sampled_from(VALUES),
                 st.one_of(st.integers(40, 3000), st.sampled_from([0, 1, 15, 16, 20_000,
                                                                   150_000])),
                 st.integers(0, 2**16))


@settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(source=SIDE, target=st.one_of(st.none(), SIDE), burst=st.sampled_from([1, 1, 1, 4]))
# Hostile values in readable layouts, so that they certainly reach the engine:
@example(source=("ok", "huge", 500, 1), target=None, burst=1)
@example(source=("ok", "tiny", 500, 2), target=None, burst=1)
@example(source=("ok", "identical", 500, 3), target=None, burst=1)
@example(source=("ok", "flat", 3000, 4), target=("ok", "flat", 3000, 5), burst=1)
@example(source=("bigendian", "some_nan", 3000, 6), target=("float64", "inf", 3000, 7), burst=1)
@example(source=("organized", "normal", 150_000, 8), target=("ok", "identical", 20, 9), burst=1)
@example(source=("ok", "normal", 16, 10), target=("extra_fields", "normal", 16, 11), burst=4)
def test_corrupted_pairs_are_all_counted_and_never_crash_the_node(node, source, target, burst):
    proc, probe = node
    assert proc.poll() is None
    base = _fresh(probe)
    for _ in range(burst):
        _stamp[0] += SEC
        t = _stamp[0]
        src = build(*source, stamp=t, frame="fuzz_source")
        tgt = (build(*target, stamp=t, frame="fuzz_target") if target is not None
               else build("ok", "normal", 500, 1, stamp=t, frame="fuzz_target"))
        probe.send(src, tgt)
    assert rh.wait_for(lambda: _settled(probe, burst, burst, base), 120.0), \
        (source, target, burst, base, probe.diagnostics())
    c = _counts(probe)
    # Every finished pair is a pose or a rejection with a reason; nothing is lost.
    assert c["pairs_done"] == c["pairs_out"] + c["pairs_rejected"]
    assert c["pairs_rejected"] == sum(v for k, v in c.items() if k.startswith("rejected."))
    assert c["engine_restarts"] == 0 and c["take_errors"] == 0
    assert proc.poll() is None


def test_after_the_fuzz_a_valid_pair_still_gets_its_pose(node):
    from cegc_ros.data.protocols import make_pairs

    proc, probe = node
    p = make_pairs("7scenes", "test", 1)[0]
    _stamp[0] += SEC
    t = _stamp[0]
    probe.send(rh.cloud(p.source, "fuzz_source", t), rh.cloud(p.target, "fuzz_target", t))
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 120.0)
    assert proc.poll() is None
    c = _fresh(probe)
    print("fuzz totals:", {k: v for k, v in c.items() if v})
    assert c["engine_restarts"] == 0 and c["take_errors"] == 0
    assert c["pairs_done"] == c["pairs_out"] + c["pairs_rejected"]
