"""Benchmark: engine latency beside 0, 1 and 2 CPU-bound processes, per thread setting.

    python -m cegc_ros.tools.bench_contention [--settings api,ransac,default,omp1,passive,...]
        [--hogs 0,1,2] [--pairs 8] [--rounds 2] [--size 0] [--out runs/contention.json]

A robot's CPU is shared with SLAM, drivers and planners. Each (setting, hogs, round) starts
``hogs`` processes that spin (``while True: pass``), then a fresh engine process with the
setting's environment (libraries read it when they load, so it cannot change in-process),
which warms up on two pairs and times ``Registrar.register`` on ``--pairs`` generated
7Scenes-style test pairs (1536 points; ``--size N`` densifies them to N points), at the
node's default settings; then the hogs are stopped. Rounds go through all settings in turn,
so slow drifts of the machine's background load spread over all of them.

Settings (environment of the engine process, plus Open3D's thread limit):
  default       nothing set: torch uses one thread per core, OpenMP threads spin-wait
  omp1          OMP_NUM_THREADS=1: one torch intra-op thread
  passive       OMP_WAIT_POLICY=PASSIVE: OpenMP threads sleep instead of spinning
  omp1_o3d1     OMP_NUM_THREADS=1 and open3d.utility.set_max_threads(1) (Open3D uses TBB)
  passive_o3d1  OMP_WAIT_POLICY=PASSIVE and open3d.utility.set_max_threads(1)
  api           nothing set, and the engine made as a user's script makes it:
                ``from cegc_ros.engine import Registrar; Registrar.from_checkpoint()`` (what
                the engine sets itself on import is what it gets)
  api1          as ``api`` with one thread: ``EngineConfig(threads=1)`` (torch and ONNX
                Runtime) and open3d.utility.set_max_threads(1)
  ransac        the peer: Open3D RANSAC+FPFH (cegc_ros.baselines, its defaults) on the same
                pairs, nothing set, so the engine's slow-down is compared with the peer's

Prints a table of median latency (ms) and the slow-down against the same setting without
hogs, with the machine's load average. Errors: one line, exit code 1 (2 for usage).
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from cegc_ros.tools.replay import OneLineParser

REPO = Path(__file__).resolve().parents[2]

#: setting -> (environment, Open3D thread limit or 0 for its default)
SETTINGS: dict[str, tuple[dict[str, str], int]] = {
    "default": ({}, 0),
    "omp1": ({"OMP_NUM_THREADS": "1"}, 0),
    "passive": ({"OMP_WAIT_POLICY": "PASSIVE"}, 0),
    "omp1_o3d1": ({"OMP_NUM_THREADS": "1"}, 1),
    "passive_o3d1": ({"OMP_WAIT_POLICY": "PASSIVE"}, 1),
    "api": ({}, 0),
    "api1": ({}, 1),
    "ransac": ({}, 0),
}
#: Variables that would change what a setting means; removed from the child's environment.
THREAD_VARS = ("OMP_NUM_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "KMP_BLOCKTIME",
               "MKL_NUM_THREADS")


class BenchError(RuntimeError):
    """A child failed or the arguments make no sense."""


def _runner(setting: str) -> Any:
    """``register(source, target)`` of the setting: the peer, the engine as a script makes it,
    or the engine as the node's engine process makes it."""
    if setting == "ransac":
        from cegc_ros import baselines
        baselines.load_open3d()
        return lambda src, tgt: baselines.register("ransac", src, tgt)
    if setting in ("api", "api1"):
        from cegc_ros.config import EngineConfig
        from cegc_ros.engine import Registrar
        threads = 1 if setting == "api1" else 0
        return Registrar.from_checkpoint(device="cpu", engine=EngineConfig(threads=threads)).register
    from cegc_ros.node.engine_process import load_registrar
    from cegc_ros.node.params import SECTIONS
    return load_registrar(SECTIONS["preprocess"](), SECTIONS["engine"](device="cpu")).register


def child(pairs: int, size: int, o3d_threads: int, setting: str = "default") -> int:
    """The process of one measurement: prints one JSON line of per-pair seconds."""
    from cegc_ros.data.protocols import make_pairs
    from cegc_ros.tools.bench_node import densify

    if o3d_threads:
        import open3d as o3d
        o3d.utility.set_max_threads(o3d_threads)
    register = _runner(setting)
    import torch

    data = make_pairs("7scenes", "test", pairs)
    if size:
        data = [(densify(p.source, size, 1), densify(p.target, size, 2)) for p in data]
    else:
        data = [(p.source, p.target) for p in data]
    for src, tgt in data[:2]:                       # warm-up
        register(src, tgt)
    times = []
    for src, tgt in data:
        t0 = time.perf_counter()
        register(src, tgt)
        times.append(time.perf_counter() - t0)
    print(json.dumps({"times": times, "torch_threads": torch.get_num_threads()}), flush=True)
    return 0


@contextlib.contextmanager
def busy_processes(n: int) -> Iterator[None]:
    """``n`` CPU-bound processes (``while True: pass``) for the block, killed after it."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"], stdin=subprocess.DEVNULL)
             for _ in range(n)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def measure(setting: str, hogs: int, pairs: int, size: int) -> dict[str, Any]:
    env_add, o3d_threads = SETTINGS[setting]
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS}
    env.update(env_add)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    with busy_processes(hogs):
        load0 = os.getloadavg()[0]
        out = subprocess.run([sys.executable, "-m", "cegc_ros.tools.bench_contention", "--child",
                              str(pairs), str(size), str(o3d_threads), setting], env=env,
                             cwd=str(REPO),
                             capture_output=True, text=True, check=False, timeout=3600)
    if out.returncode != 0:
        tail = (out.stderr.strip().splitlines() or ["no output"])[-1]
        raise BenchError(f"{setting} with {hogs} hogs failed (exit {out.returncode}): {tail}")
    res = json.loads(out.stdout.strip().splitlines()[-1])
    return {"setting": setting, "hogs": hogs, "median_ms": float(np.median(res["times"]) * 1e3),
            "times_s": res["times"], "torch_threads": res["torch_threads"], "load1": load0}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--child"]:
        return child(int(argv[1]), int(argv[2]), int(argv[3]), argv[4])
    ap = OneLineParser(prog="bench_contention", description=__doc__.split("\n\n")[0])
    ap.add_argument("--settings", default=",".join(SETTINGS))
    ap.add_argument("--hogs", default="0,1,2", help="CPU-bound processes beside the engine")
    ap.add_argument("--pairs", type=int, default=8, help="timed pairs per measurement")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--size", type=int, default=0, help="points per cloud (0: 1536 as made)")
    ap.add_argument("--out", help="write every number as JSON here")
    args = ap.parse_args(argv)
    settings = [s for s in args.settings.split(",") if s]
    unknown = [s for s in settings if s not in SETTINGS]
    if unknown:
        ap.error(f"unknown setting {unknown[0]!r}; known: {', '.join(SETTINGS)}")
    hogs = [int(h) for h in args.hogs.split(",")]
    runs: list[dict[str, Any]] = []
    try:
        for rnd in range(args.rounds):
            for h in hogs:
                for s in settings:
                    r = measure(s, h, args.pairs, args.size)
                    r["round"] = rnd
                    runs.append(r)
                    print(f"round {rnd} hogs {h} {s:13s} {r['median_ms']:8.1f} ms "
                          f"(torch threads {r['torch_threads']}, load {r['load1']:.1f})",
                          file=sys.stderr, flush=True)
    except (BenchError, OSError, ValueError) as err:
        print(f"bench_contention: {' '.join(str(err).split())}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("bench_contention: interrupted", file=sys.stderr)
        return 130
    table = {(s, h): float(np.median([r["median_ms"] for r in runs
                                      if r["setting"] == s and r["hogs"] == h]))
             for s in settings for h in hogs}
    lines = ["| setting | " + " | ".join(f"{h} hogs (ms)" for h in hogs)
             + " | " + " | ".join(f"x{h}" for h in hogs if h) + " |",
             "|---|" + "---|" * (len(hogs) + len([h for h in hogs if h]))]
    for s in settings:
        base = table[(s, hogs[0])]
        lines.append(f"| {s} | " + " | ".join(f"{table[(s, h)]:.0f}" for h in hogs) + " | "
                     + " | ".join(f"{table[(s, h)] / base:.2f}" for h in hogs if h) + " |")
    print("\n".join(lines))
    report = {"command": " ".join(["python -m cegc_ros.tools.bench_contention", *argv]),
              "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, "
                         f"{platform.platform()}, python {platform.python_version()}",
              "table_median_ms": {f"{s}/{h}": v for (s, h), v in table.items()},
              "runs": runs}
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
