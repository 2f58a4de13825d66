"""Benchmark of msg_adapters.point_cloud2 on a 300k-point XYZRGB cloud (target: < 5 ms).

Run: ``.venv/bin/python -m cegc_ros.tools.bench_adapters [--points N] [--runs R]``.
The cloud is what an RGB-D driver publishes: float32 x, y, z and a packed float32 rgb,
``point_step`` 16, with about 2% NaN points (invalid depth). Prints the median and spread of
``cloud_to_xyz`` and, for comparison, of ``xyz_to_cloud``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from collections.abc import Callable, Sequence


def _time(fn: Callable[[], object], runs: int) -> list[float]:
    fn()  # warm-up: page in the buffer, first-call imports
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def _summary(name: str, seconds: list[float]) -> str:
    ms = sorted(s * 1e3 for s in seconds)
    p10, p90 = ms[len(ms) // 10], ms[(9 * len(ms)) // 10]
    return (f"{name:<14} median {statistics.median(ms):7.2f} ms   p10 {p10:7.2f}   "
            f"p90 {p90:7.2f}   ({len(ms)} runs)")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=300_000, help="points in the cloud")
    parser.add_argument("--runs", type=int, default=200, help="timed runs per function")
    args = parser.parse_args(argv)

    import array

    import numpy as np
    from sensor_msgs.msg import PointCloud2, PointField
    from std_msgs.msg import Header

    from msg_adapters.point_cloud2 import cloud_to_xyz, xyz_to_cloud

    rng = np.random.default_rng(0)
    n = args.points
    rec = np.zeros(n, dtype=np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")]))
    xyz = rng.uniform(-5, 5, size=(n, 3)).astype(np.float32)
    xyz[rng.random(n) < 0.02] = np.nan  # invalid depth
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["rgb"] = rng.integers(0, 2**24, n, dtype=np.uint32).view(np.float32)
    msg = PointCloud2(header=Header(frame_id="camera"), height=1, width=n, is_bigendian=False,
                      point_step=16, row_step=16 * n, is_dense=False,
                      fields=[PointField(name=c, offset=4 * i, datatype=PointField.FLOAT32,
                                         count=1) for i, c in enumerate(("x", "y", "z", "rgb"))])
    msg.data = array.array("B", rec.tobytes())

    expected = xyz[np.isfinite(xyz).all(1)]
    assert np.array_equal(cloud_to_xyz(msg), expected), "cloud_to_xyz returned wrong points"
    finite = np.ascontiguousarray(expected)
    header = Header(frame_id="camera")

    print(f"cloud: {n} points XYZRGB, point_step 16, {n - len(expected)} NaN points")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"Python {platform.python_version()}, numpy {np.__version__}")
    print(_summary("cloud_to_xyz", _time(lambda: cloud_to_xyz(msg), args.runs)))
    print(_summary("xyz_to_cloud", _time(lambda: xyz_to_cloud(finite, header),
                                         max(10, args.runs // 4))))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
