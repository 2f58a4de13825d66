"""Benchmark: CEGC forward latency and peak memory per point count, and the engine's stages.

    python -m cegc_ros.tools.bench_model [--points 512,717,1024,2048] [--repeats 7] [--threads 0]
    python -m cegc_ros.tools.bench_model --compile

``--compile`` compares the whole engine (node defaults, both networks) with and without
``engine.compile``: start-up compile time with an empty inductor cache (a fresh temporary
``TORCHINDUCTOR_CACHE_DIR``, so the cold cost a user pays once per machine) and the median
``Registrar.register`` time on 10 synthetic 7Scenes test pairs (first network answers) and on 5
noisy resampled ones (both networks run), each setting in its own subprocess.

Each point count runs in a fresh subprocess so that its peak RSS (ru_maxrss) is its own.
Reports the median forward time of the shipped network (batch 1, fp32, torch.inference_mode),
the peak resident memory of that process, and a breakdown of one forward pass by stage.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys


def _one(points: int, repeats: int, threads: int) -> dict:
    import resource
    import time

    import numpy as np
    import torch

    from cegc_ros.engine import default_weights, load_checkpoint
    from cegc_ros.geometry import normals_and_fpfh
    from cegc_ros.model.cegc import _take
    from cegc_ros.model.hoce import top_n_indices

    if threads > 0:
        torch.set_num_threads(threads)
    model, _ = load_checkpoint(default_weights(), "cpu")
    rng = np.random.default_rng(0)
    # A box-room-like cloud: normals and FPFH as the engine computes them.
    pts = rng.uniform(-0.5, 0.5, (points, 3)).astype(np.float32)
    pts[: points // 3, 2] = -0.5
    pts[points // 3: 2 * points // 3, 0] = -0.5
    normals, desc = normals_and_fpfh(pts, model.cfg.normal_radius, model.cfg.fpfh_radius, model.cfg.fpfh_max_nn)

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(a).unsqueeze(0)

    args = (t(pts), t(pts[::-1].copy()), t(normals), t(normals[::-1].copy()), t(desc), t(desc[::-1].copy()))
    times = []
    with torch.inference_mode():
        model(*args)                                                    # warm-up
        for _ in range(repeats):
            t0 = time.perf_counter()
            model(*args)
            times.append(time.perf_counter() - t0)
        # Stage breakdown of one pass (same maths as CEGC.forward).
        st = {}
        t0 = time.perf_counter()
        fx = model.encode(args[0], args[2], args[4])
        fy = model.encode(args[1], args[3], args[5])
        st["agnn_ms"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        fx, fy = model.context(fx, fy, args[0], args[1])
        st["attention_ms"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        lx, ly = model.hoce(fx, fy)
        ix, iy = top_n_indices(lx, model.cfg.overlap_ratio), top_n_indices(ly, model.cfg.overlap_ratio)
        st["hoce_ms"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        model.cams(_take(args[0], ix), _take(args[1], iy), _take(fx, ix), _take(fy, iy),
                   _take(args[4], ix), _take(args[5], iy))
        st["cams_ms"] = time.perf_counter() - t0
    return {"points": points, "median_ms": 1e3 * float(np.median(times)),
            "p90_ms": 1e3 * float(np.percentile(times, 90)),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            **{k: round(1e3 * v, 1) for k, v in st.items()}}


def _engine(compile_: bool) -> dict:
    import numpy as np

    from cegc_ros.config import EngineConfig
    from cegc_ros.data.protocols import make_pair, sample_7scenes_pair
    from cegc_ros.engine import Registrar

    pairs = [make_pair("7scenes", "test", i) for i in range(10)]
    rng = np.random.default_rng(3)
    noisy = [sample_7scenes_pair(p.source, rng, noise_sigma=0.01, resample_target=True) for p in pairs[:5]]
    reg = Registrar.from_checkpoint(engine=EngineConfig(compile=compile_))
    row: dict = {"compile": compile_, "start_up_compile_s": round(reg.warm_up(), 1)}
    for name, ps in (("shared_point_ms", pairs), ("cascade_ms", noisy)):
        row[name] = round(1e3 * float(np.median([reg.register(p.source, p.target).timings["total"] for p in ps])))
    return row


def _compare_compile() -> int:
    import os
    import tempfile
    rows = []
    for flag in ("0", "1"):
        with tempfile.TemporaryDirectory() as cache:
            out = subprocess.run([sys.executable, "-m", "cegc_ros.tools.bench_model", "--child-engine", flag],
                                 capture_output=True, text=True, check=False,
                                 env={**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache})
        if out.returncode != 0:
            print(f"bench_model: engine.compile={flag} failed: {out.stderr.strip().splitlines()[-1:]}",
                  file=sys.stderr)
            return 1
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    print("| engine.compile | start-up compile s | median ms, first network answers | median ms, both networks |")
    print("|---|---|---|---|")
    for r in rows:
        print(f"| {str(r['compile']).lower()} | {r['start_up_compile_s']} | {r['shared_point_ms']} "
              f"| {r['cascade_ms']} |")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench_model", description=__doc__.splitlines()[0])
    ap.add_argument("--points", default="512,717,1024,2048")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch default)")
    ap.add_argument("--compile", action="store_true", help="the engine with and without engine.compile")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--child-engine", choices=("0", "1"), default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child_engine is not None:
        print(json.dumps(_engine(args.child_engine == "1")))
        return 0
    if args.compile:
        return _compare_compile()
    if args.child is not None:
        print(json.dumps(_one(args.child, args.repeats, args.threads)))
        return 0
    import torch
    rows = []
    for n in (int(x) for x in args.points.split(",")):
        out = subprocess.run([sys.executable, "-m", "cegc_ros.tools.bench_model", "--child", str(n),
                              "--repeats", str(args.repeats), "--threads", str(args.threads)],
                             capture_output=True, text=True, check=False)
        if out.returncode != 0:
            print(f"bench_model: {n} points failed: {out.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
            return 1
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    from cegc_ros.engine import default_weights, load_checkpoint
    model, _ = load_checkpoint(default_weights(), "cpu")
    params = sum(p.numel() for p in model.parameters())
    print(f"machine: {platform.machine()}, {torch.get_num_threads()} torch threads by default, "
          f"torch {torch.__version__}; network parameters: {params / 1e6:.2f} M")
    print("| points per cloud | median ms | p90 ms | peak RSS MB | AGNN ms | attention ms | HOCE ms | CAMS ms |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['points']} | {r['median_ms']:.0f} | {r['p90_ms']:.0f} | {r['peak_rss_mb']:.0f} | "
              f"{r['agnn_ms']:.0f} | {r['attention_ms']:.0f} | {r['hoce_ms']:.0f} | {r['cams_ms']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
