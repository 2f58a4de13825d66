"""Benchmark: the engine at node defaults from 1.5k to 5M input points, per stage, with the
peak memory, with and without jemalloc, and RANSAC and SC2-PCR on the same pairs.

    python -m cegc_ros.tools.bench_engine [--sizes 1500,20000,300000,5000000] [--pairs 3]
        [--repeats 2] [--methods cegc,ransac,sc2pcr] [--allocators jemalloc,system]
        [--threads 0] [--real DIR ...] [--cache .cache/bench] [--params FILE] [--json runs/bench_engine.json]

Pairs (generated once into ``--cache``, float32 .npy, metres): at 1.5k points the synthetic
7Scenes-protocol test pairs (1536-point crops, normalised units, what the paper's 7Scenes
benchmark feeds); from 20k up synthetic test-split fragment pairs of two Kinect-like views
(cegc_ros.data: 25-35k points each), subsampled to the size, or densified above it: each
point repeated with Gaussian jitter (sigma 3 mm, about a third of the fragments' spacing), the
way a denser sensor would sample the same surfaces. The ground truth is unchanged. ``--real
DIR`` adds the pairs of a real folder as they are (the Stanford bunny scans, ~35-40k points;
the LiDAR pair), labelled by the folder's name.

Each (size, allocator, method) runs in a fresh subprocess, so that its peak resident memory
(``ru_maxrss``) is its own: one loaded pair at a time (as a node holds it), torch, Open3D and
the registrations together. One cold registration (the process's first, after
``Registrar.from_checkpoint``: the table's "first call" column, and its ratio to the same pair
warm), then ``--pairs`` x ``--repeats`` timed ones; per stage the median and the 90th percentile
(``RegistrationResult.timings`` has one key per stage; the peers report features / registration),
and the process's CPU time per registration (all threads; on a loaded machine the wall time grows
with the load, the CPU time much less). ``jemalloc`` preloads libjemalloc.so.2 as the bootstrap
does (cegc_ros/allocator.py); ``system`` is glibc malloc. Prints a markdown table and the
machine's load; ``--json`` keeps every number. ``--threads N`` sets OMP_NUM_THREADS=N in the
workers (torch and Open3D; 0 keeps the libraries' defaults, as the node does with
``engine.threads: 0``). ``--params FILE`` runs the engine with another register_node parameter
file (a setting's cost beside the same peers); its path goes in the printed command.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

SIZES = (1500, 20000, 300000, 5000000)
METHODS = ("cegc", "ransac", "sc2pcr", "sc2pcr+icp")
#: Also accepted: RANSAC on 2 Open3D threads (not repeatable, see cegc_ros/baselines.py), to
#: measure what the one-thread default costs.
EXTRA_METHODS = ("ransac-2threads",)
ALLOCATORS = ("jemalloc", "system")
JITTER = 0.003                           # metres, densification noise
ENGINE_STAGES = ("bound", "features", "match", "estimate", "refine", "verify")
PEER_STAGES = ("features", "registration")


class BenchError(RuntimeError):
    """The benchmark cannot run as asked (bad sizes, no jemalloc, a worker failed)."""


def _resize(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(M, 3) -> (n, 3): a seeded subsample, or each point repeated with Gaussian jitter."""
    if n <= len(points):
        return points[np.sort(rng.choice(len(points), n, replace=False))]
    idx = rng.integers(0, len(points), n)
    idx[: len(points)] = np.arange(len(points))                # every original point is kept
    out = points[idx].astype(np.float32)
    out[len(points):] += rng.normal(0.0, JITTER, (n - len(points), 3)).astype(np.float32)
    return out


def make_pairs(size: int, pairs: int, cache: Path) -> list[Path]:
    """``pairs`` benchmark pairs of ``size`` points per cloud as .npz files in ``cache``."""
    from cegc_ros.data.protocols import make_pair

    cache.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(pairs):
        path = cache / f"pair_{size}_{i}.npz"
        if not path.is_file():
            if size <= 2048:
                p = make_pair("7scenes", "test", i)
                src, tgt = p.source, p.target
            else:
                p = make_pair("fragments", "test", i)
                rng = np.random.default_rng([size, i])
                src, tgt = _resize(p.source, size, rng), _resize(p.target, size, rng)
            tmp = path.with_suffix(".tmp.npz")
            np.savez(tmp, source=src.astype(np.float32), target=tgt.astype(np.float32),
                     T=p.T_target_source)
            tmp.replace(path)
        out.append(path)
    return out


def real_pair_files(real_dir: Path, pairs: int, cache: Path) -> list[Path]:
    """``pairs`` evenly spaced pairs of a real folder (``cegc-eval --real-dir`` layout, e.g. the
    bunny scans or the LiDAR pair) as .npz benchmark pairs in ``cache``; BenchError when the
    folder holds none."""
    from cegc_ros.evaluation import EvalError
    from cegc_ros.evaluation.datasets import real_pairs
    try:
        found = [p for p in real_pairs(real_dir) if p.T_gt is not None]
    except (OSError, ValueError, EvalError) as err:
        raise BenchError(f"--real {real_dir}: {err}") from err
    if not found:
        raise BenchError(f"--real {real_dir}: no pairs with ground truth")
    cache.mkdir(parents=True, exist_ok=True)
    out = []
    for i in np.unique(np.linspace(0, len(found) - 1, min(pairs, len(found))).astype(int)):
        p = found[int(i)]
        path = cache / f"real_{Path(real_dir).name}_{p.pair_id}.npz"
        np.savez(path, source=np.asarray(p.source, np.float32), target=np.asarray(p.target, np.float32),
                 T=p.T_gt)
        out.append(path)
    return out


def _stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, np.float64) * 1000.0
    return {"median_ms": float(np.median(a)), "p90_ms": float(np.percentile(a, 90))}


def worker(method: str, files: list[str], repeats: int, params: str = "") -> dict[str, Any]:
    """Time ``method`` on the pairs in ``files`` (this process only); peak RSS included."""
    import resource

    from cegc_ros import baselines
    from cegc_ros.metrics import rotation_error_deg

    def pair(f: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with np.load(f) as z:                             # one pair in memory at a time, as in the node
            return z["source"], z["target"], z["T"]

    first = pair(files[0])
    rss_loaded = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    if method == "cegc":
        from cegc_ros.engine import Registrar
        from cegc_ros.evaluation.methods import engine_configs
        pre, eng = engine_configs(params or None)          # default: the node's shipped parameter file
        t_load = time.perf_counter()
        registrar = Registrar.from_checkpoint(device="cpu", preprocess=pre, engine=eng)
        startup = time.perf_counter() - t_load              # weights, runtime session, warm_start

        def run(src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
            r = registrar.register(src, tgt)
            return r.T_target_source, r.timings
    else:
        t_load = time.perf_counter()
        baselines.load_open3d()
        startup = time.perf_counter() - t_load
        name, config = method, baselines.BaselineConfig()
        if method == "ransac-2threads":
            name, config.ransac_threads = "ransac", 2

        def run(src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
            r = baselines.register(name, src, tgt, config)
            return r.T_target_source, r.timings
    t0 = time.perf_counter()
    run(first[0], first[1])              # the cold call (lazy imports, first kernels), not in the stats
    first_call = time.perf_counter() - t0
    n_points = len(first[0])
    del first
    timings: dict[str, list[float]] = {}
    errors = []
    warm_first_pair = []                 # the same pair warm, for the cold call's ratio
    for _ in range(repeats):
        for f in files:
            src, tgt, T = pair(f)
            t0, c0 = time.perf_counter(), time.process_time()
            T_est, stages = run(src, tgt)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            if f == files[0]:
                warm_first_pair.append(wall)
            for k, v in stages.items():
                timings.setdefault(k, []).append(v)
            timings.setdefault("wall", []).append(wall)
            timings.setdefault("cpu", []).append(cpu)         # CPU time of all threads
            errors.append(float(rotation_error_deg(T[:3, :3], T_est[:3, :3])))
            del src, tgt
    return {
        "method": method, "points": n_points, "runs": len(timings["wall"]),
        "stages": {k: _stats(v) for k, v in timings.items()},
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "rss_after_loading_mb": rss_loaded,
        "startup_s": startup,                             # Registrar.from_checkpoint / Open3D import
        "first_call_ms": 1000.0 * first_call,
        "first_call_ratio": first_call / float(np.median(warm_first_pair)),   # cold / warm, one pair
        "median_rotation_error_deg": float(np.median(errors)),
        "jemalloc": _jemalloc_loaded(),
    }


def _jemalloc_loaded() -> bool:
    from cegc_ros.allocator import jemalloc_loaded
    return jemalloc_loaded()


def _environment(allocator: str, threads: int = 0) -> dict[str, str]:
    from cegc_ros.allocator import allocator_environment, jemalloc_path

    env = {k: v for k, v in os.environ.items() if k not in ("LD_PRELOAD", "MALLOC_CONF")}
    env.pop("CEGC_NO_JEMALLOC", None)
    if threads > 0:
        env["OMP_NUM_THREADS"] = str(threads)
    if allocator == "system":
        env["CEGC_NO_JEMALLOC"] = "1"
        return env
    path = jemalloc_path()
    if path is None:
        raise BenchError("jemalloc is not installed (libjemalloc.so.2); use --allocators system")
    return allocator_environment(env, path)


def load_line() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def run_one(method: str, files: list[Path], repeats: int, allocator: str, threads: int = 0,
            params: str = "") -> dict[str, Any]:
    """One worker subprocess; its JSON result plus the load around it."""
    cmd = [sys.executable, "-m", "cegc_ros.tools.bench_engine", "--worker", method,
           "--repeats", str(repeats), *(["--params", params] if params else []), *[str(f) for f in files]]
    before = load_line()
    proc = subprocess.run(cmd, env=_environment(allocator, threads), capture_output=True, text=True,
                          check=False)
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise BenchError(f"{method} worker on {files[0].name} failed ({proc.returncode}): {tail}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    result.update(allocator=allocator, threads=threads, load_before=before, load_after=load_line())
    if (allocator == "jemalloc") != result["jemalloc"]:
        raise BenchError(f"{method}: asked for {allocator}, the worker had jemalloc={result['jemalloc']}")
    return result


def table(results: list[dict[str, Any]]) -> str:
    """Markdown: one row per (size, allocator, method)."""
    head = ("| input points | allocator | method | total median ms | total p90 ms | "
            + " | ".join(f"{s} ms" for s in ENGINE_STAGES)
            + " | CPU ms | peak RSS MB | first call ms (x warm) | median Error(R) deg |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in results:
        st = r["stages"]
        cells = []
        for s in ENGINE_STAGES:
            peer = {"features": "features", "estimate": "registration", "refine": "refine"}
            key = s if r["method"] == "cegc" else peer.get(s)
            cells.append(f"{st[key]['median_ms']:.0f} / {st[key]['p90_ms']:.0f}" if key in st else "-")
        cells.append(f"{st['cpu']['median_ms']:.0f}" if "cpu" in st else "-")
        label = f"{r['points']:,}" + (f" ({r['set']})" if r.get("set") else "")
        lines.append(f"| {label} | {r['allocator']} | {r['method']} | "
                     f"{st['total']['median_ms']:.0f} | {st['total']['p90_ms']:.0f} | "
                     + " | ".join(cells) + f" | {r['peak_rss_mb']:.0f} | "
                     f"{r['first_call_ms']:.0f} ({r['first_call_ratio']:.2f}x) | "
                     f"{r['median_rotation_error_deg']:.2f} |")
    return "\n".join(lines)


def ratios(results: list[dict[str, Any]]) -> str:
    """One line per (size, allocator): the engine's median total over each peer's, same run."""
    out = []
    groups: dict[tuple[int, str, str], dict[str, float]] = {}
    for r in results:
        key = (r["points"], r.get("set", ""), r["allocator"])
        groups.setdefault(key, {})[r["method"]] = r["stages"]["total"]["median_ms"]
    for (points, name, allocator), med in groups.items():
        if "cegc" in med and len(med) > 1:
            parts = [f"{m} {med['cegc'] / v:.2f}x" for m, v in med.items() if m != "cegc" and v > 0]
            what = f"{points:,} points" + (f", {name}" if name else "")
            out.append(f"{what} ({allocator}): cegc / " + ", ".join(parts))
    return "\n".join(out)


def _csv(text: str, cast: Any, known: tuple | None = None) -> list:
    items = [x.strip() for x in text.split(",") if x.strip()]
    if known is not None and (bad := [x for x in items if x not in known]):
        raise BenchError(f"unknown value(s) {', '.join(bad)}; choose from {', '.join(known)}")
    try:
        return [cast(x) for x in items]
    except ValueError as err:
        raise BenchError(str(err)) from err


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench_engine", description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)))
    ap.add_argument("--pairs", type=int, default=3, help="distinct pairs per size (default 3)")
    ap.add_argument("--repeats", type=int, default=2, help="timed runs of each pair (default 2)")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--allocators", default=",".join(ALLOCATORS))
    ap.add_argument("--threads", type=int, default=0, help="OMP_NUM_THREADS of the workers (0: default)")
    ap.add_argument("--real", action="append", default=[], type=Path, metavar="DIR",
                    help="also time the pairs of this real folder (cegc-eval --real-dir layout: the "
                         "bunny scans, the LiDAR pair); repeatable")
    ap.add_argument("--cache", default=".cache/bench", help="where the generated pairs are kept")
    ap.add_argument("--params", default="", metavar="FILE",
                    help="register_node parameter file of the cegc runs (default params/register_node.yaml)")
    ap.add_argument("--json", default=None, help="write every number to this file")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("files", nargs="*", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker, args.files, args.repeats, args.params)))
        return 0
    try:
        sizes = _csv(args.sizes, int)
        methods = _csv(args.methods, str, METHODS + EXTRA_METHODS)
        allocators = _csv(args.allocators, str, ALLOCATORS)
        if (not sizes and not args.real) or min(sizes, default=64) < 64 or args.pairs < 1 or args.repeats < 1:
            raise BenchError("--sizes must be >= 64 points (empty only with --real), --pairs and --repeats >= 1")
        results = []
        from cegc_ros.evaluation.report import host_line
        header = f"{host_line()}; start: {load_line()}"
        print(header, flush=True)
        sets = [(str(size), "", make_pairs(size, args.pairs, Path(args.cache))) for size in sizes]
        sets += [(d.name, d.name, real_pair_files(d, args.pairs, Path(args.cache))) for d in args.real]
        for label, name, files in sets:
            for allocator in allocators:
                for method in methods:
                    r = run_one(method, files, args.repeats, allocator, args.threads, args.params)
                    if name:
                        r["set"] = name
                    print(f"{label} {allocator} {method}: total median {r['stages']['total']['median_ms']:.0f} ms, "
                          f"peak RSS {r['peak_rss_mb']:.0f} MB ({r['load_after']})", flush=True)
                    results.append(r)
    except BenchError as err:
        print(f"bench_engine: error: {err}", file=sys.stderr)
        return 2 if "unknown" in str(err) or "must be" in str(err) else 1
    print()
    print(table(results))
    print()
    print(ratios(results))
    print(f"\n{header}; end: {load_line()}")
    import shlex
    print("command: python -m cegc_ros.tools.bench_engine " + shlex.join(argv if argv is not None else sys.argv[1:]))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"machine": header, "results": results}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
