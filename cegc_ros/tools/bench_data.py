"""Benchmark of the synthetic data generator (a script, not a test).

    python -m cegc_ros.tools.bench_data [--pairs 100] [--protocol 7scenes] [--storage sqlite3]

Prints the time to make one fragment, one 7scenes pair from a cached fragment, and to write a
bag of N test pairs (the cegc-make-bag path: generation + serialisation), in a fresh process.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_data", description=__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=100)
    p.add_argument("--protocol", default="7scenes", choices=("7scenes", "fragments", "modelnet"))
    p.add_argument("--storage", default="sqlite3", choices=("sqlite3", "mcap"))
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    import numpy as np

    from cegc_ros.data import protocols, scenes
    from cegc_ros.data.bag import read_pairs, write_pairs

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"load {os.getloadavg()[0]:.2f}")
    t = time.perf_counter()
    scenes.make_fragment(protocols.scene_seed("train", 999_999, 0), 0)   # warm-up (imports)
    print(f"first fragment in process (Open3D import + room): {time.perf_counter() - t:.2f} s")
    times = []
    for k in range(1, 4):
        t = time.perf_counter()
        frag = scenes.make_fragment(protocols.scene_seed("train", 999_999, k), 0)
        times.append(time.perf_counter() - t)
    print(f"fragment (new room): {np.median(times):.2f} s median of 3 ({len(frag.points)} points)")
    rng = np.random.default_rng(0)
    t = time.perf_counter()
    for _ in range(50):
        protocols.sample_7scenes_pair(frag.points, rng)
    print(f"sample_7scenes_pair (2048 -> 1536 pts): {(time.perf_counter() - t) / 50 * 1e3:.1f} ms")

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bag"
        t = time.perf_counter()
        n = write_pairs(out, protocols.iter_pairs(args.protocol, "test", args.pairs, args.seed),
                        storage=args.storage, protocol=args.protocol, seed=args.seed)
        dt = time.perf_counter() - t
        size = sum(f.stat().st_size for f in out.iterdir()) / 2**20
        t = time.perf_counter()
        m = sum(1 for _ in read_pairs(out))
        dr = time.perf_counter() - t
    print(f"{n} {args.protocol} test pairs -> {args.storage} bag: {dt:.1f} s "
          f"({size:.1f} MiB); read back {m} pairs in {dr:.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
