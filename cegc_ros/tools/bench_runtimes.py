"""Benchmark: the network's ONNX export under other runtimes, on the engine's own inputs.

    python -m cegc_ros.tools.bench_runtimes [--size 20000] [--pairs 6] [--repeats 10]
        [--runtimes onnxruntime,onnxruntime-parallel,openvino,openvino-static] [--hogs 0,2] [--rounds 2]
        [--json runs/bench_runtimes.json]

The engine (node defaults, the shipped weights) registers ``--pairs`` benchmark pairs of
``--size`` points (cegc_ros/tools/bench_engine.py's pairs) and the network's inputs are kept as
the engine fed them. Then each runtime scores those inputs ``--repeats`` times, each runtime in
a fresh process of its own (threads of one runtime's pool never wait beside another's), the
processes taking turns for ``--rounds`` rounds (the machine's drift falls on all alike), with subnormals
flushed as the engine flushes them (cegc_ros/denormals.py) and ``--hogs`` CPU-bound processes
running beside (0: idle). Per runtime, the median over rounds of: the median and minimum ms of one network call, and its
outputs against the engine's ONNX Runtime session (max |overlap logit| difference, share of
equal candidates).

- ``onnxruntime``: the engine's own session (cegc_ros/onnx_network.py), the reference;
- ``onnxruntime-parallel``: ONNX Runtime's parallel executor (the two clouds' branches side by
  side on two inter-op threads, one intra-op thread each);
- ``openvino`` / ``openvino-static``: OpenVINO's CPU plugin on the same file (its own
  subnormal flush on, latency hint, no thread pinning), with the point axes dynamic or fixed to
  the inputs' shapes (compiled once per shape). Needs ``pip install openvino`` (not a
  dependency of cegc_ros: docs/performance.md has the measurement that decided it).

``--ops N`` instead profiles the engine's own session on those inputs with ONNX Runtime's
profiler (N runs of every pair's inputs after one untimed run, this process, idle) and prints
the kernel time by operator type: ms a call, share, nodes (docs/performance.md).

Errors (an unknown runtime, one not installed): one line, exit code 1.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

RUNTIMES = ("onnxruntime", "onnxruntime-parallel", "openvino", "openvino-static")
#: The outputs held against the engine's session: both overlap logits and the candidates.
CHECKED = ("src_overlap_logits", "tgt_overlap_logits", "candidates")


class BenchError(RuntimeError):
    """The benchmark cannot run as asked."""


def capture_inputs(size: int, pairs: int, cache: Path) -> tuple[Any, list[dict[str, np.ndarray]]]:
    """(the engine's OnnxNetwork, the network's feeds on ``pairs`` benchmark pairs of ``size``
    points: one dict of input name -> array per pair, as the engine passed them)."""
    from cegc_ros.engine import Registrar
    from cegc_ros.evaluation.methods import engine_configs
    from cegc_ros.onnx_network import feeds_of
    from cegc_ros.tools.bench_engine import make_pairs

    pre, eng = engine_configs()
    registrar = Registrar.from_checkpoint(device="cpu", preprocess=pre, engine=eng, warm=False)
    net = registrar._onnx
    if net is None:
        raise BenchError(f"the engine does not run ONNX Runtime here: {registrar.runtime_note}")
    feeds: list[dict[str, np.ndarray]] = []

    class Capture:
        """The engine's network, keeping what it was fed."""
        learned_candidates = net.learned_candidates

        def score_candidates(self, *args: Any, **kwargs: Any) -> Any:
            feeds.append({k: v.copy() for k, v in feeds_of(*args, extra=kwargs["extra"]).items()})
            return net.score_candidates(*args, **kwargs)

    registrar._onnx = Capture()            # the engine's choice of network, observed
    for path in make_pairs(size, pairs, cache):
        with np.load(path) as z:
            registrar.register(z["source"], z["target"])
    registrar._onnx = net
    return net, feeds


def runner(name: str, net: Any) -> Any:
    """``feeds -> [overlap logits (src), (tgt), candidates, scores]`` for runtime ``name``."""
    from cegc_ros.denormals import flush_denormals
    from cegc_ros.onnx_network import OUTPUTS
    if name == "onnxruntime":
        return lambda f: net.session.run(list(OUTPUTS), f)
    if name == "onnxruntime-parallel":
        import onnxruntime as ort

        from cegc_ros.onnx_network import open_session, session_options
        opts = session_options(threads=1)               # the engine's, but for the executor:
        opts.execution_mode = ort.ExecutionMode.ORT_PARALLEL
        opts.inter_op_num_threads = 2
        opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
        session = open_session(net.path, opts)
        return lambda f: session.run(list(OUTPUTS), f)
    if name in ("openvino", "openvino-static"):
        try:
            import openvino as ov
        except ModuleNotFoundError as err:
            raise BenchError(f"--runtimes {name}: openvino is not installed (pip install openvino)") from err
        core = ov.Core()
        config = {"PERFORMANCE_HINT": "LATENCY", "INFERENCE_PRECISION_HINT": "f32",
                  "CPU_DENORMALS_OPTIMIZATION": True, "ENABLE_CPU_PINNING": False}
        compiled: dict[tuple, Any] = {}

        def run(f: dict[str, np.ndarray]) -> list[np.ndarray]:
            key = tuple(v.shape for v in f.values()) if name == "openvino-static" else ()
            if key not in compiled:
                model = core.read_model(str(net.path))
                if key:
                    model.reshape({k: list(v.shape) for k, v in f.items()})
                with flush_denormals(on=False):
                    model = core.compile_model(model, "CPU", config)
                compiled[key] = (model, model.create_infer_request())
            model, request = compiled[key]
            out = request.infer(f)
            return [out[model.output(o)] for o in OUTPUTS]
        return run
    raise BenchError(f"--runtimes: unknown runtime {name!r}, expected some of {', '.join(RUNTIMES)}")


def worker(name: str, feeds_file: Path, repeats: int) -> dict[str, Any]:
    """Time runtime ``name`` on the saved feeds (this process only): median / min ms of a call
    and its outputs against the engine's session's."""
    from cegc_ros.denormals import flush_denormals
    from cegc_ros.engine import Registrar
    from cegc_ros.evaluation.methods import engine_configs
    pre, eng = engine_configs()
    net = Registrar.from_checkpoint(device="cpu", preprocess=pre, engine=eng, warm=False)._onnx
    with np.load(feeds_file) as z:
        count = int(z["pairs"])
        feeds = [{k[len(f"{i}/"):]: z[k] for k in z.files if k.startswith(f"{i}/")} for i in range(count)]
    ref = [[f.pop(f"ref_{o}") for o in CHECKED] for f in feeds]
    run = runner(name, net)
    outs = [run(f) for f in feeds]                     # also the first calls (compiles), untimed
    times = []
    with flush_denormals():
        for _ in range(repeats):
            for f in feeds:
                t0 = time.perf_counter()
                run(f)
                times.append(time.perf_counter() - t0)
    return {"median_ms": 1e3 * float(np.median(times)), "min_ms": 1e3 * float(np.min(times)),
            "logit_diff": max(float(np.abs(o[i] - r[i]).max()) for o, r in zip(outs, ref) for i in (0, 1)),
            "candidates_equal": float(np.mean([(o[2] == r[2]).mean() for o, r in zip(outs, ref)])),
            "calls": len(times)}


def save_feeds(net: Any, feeds: list[dict[str, np.ndarray]], path: Path) -> Path:
    """The feeds and the engine session's outputs on them, in one .npz."""
    from cegc_ros.onnx_network import OUTPUTS
    arrays: dict[str, np.ndarray] = {"pairs": np.array(len(feeds))}
    for i, f in enumerate(feeds):
        out = dict(zip(OUTPUTS, net.session.run(list(OUTPUTS), f)))
        arrays.update({f"{i}/{k}": v for k, v in f.items()})
        arrays.update({f"{i}/ref_{k}": out[k] for k in CHECKED})
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return path


def measure(name: str, feeds_file: Path, repeats: int, hogs: int) -> dict[str, Any]:
    """One worker process for ``name`` with ``hogs`` busy processes beside it."""
    from cegc_ros.tools.bench_contention import busy_processes
    with busy_processes(hogs):
        out = subprocess.run([sys.executable, "-m", "cegc_ros.tools.bench_runtimes", "--worker", name,
                              "--feeds", str(feeds_file), "--repeats", str(repeats)],
                             capture_output=True, text=True, check=False)
    if out.returncode != 0:
        tail = (out.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise BenchError(f"{name} with {hogs} hogs failed (exit {out.returncode}): {tail}")
    return {"runtime": name, "hogs": hogs, **json.loads(out.stdout.strip().splitlines()[-1])}


def _median_of_rounds(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (runtime, hogs): the median over rounds of each number."""
    keys = list(dict.fromkeys((r["runtime"], r["hogs"]) for r in rows))
    out = []
    for name, hogs in keys:
        mine = [r for r in rows if (r["runtime"], r["hogs"]) == (name, hogs)]
        out.append({"runtime": name, "hogs": hogs, "rounds": len(mine),
                    **{k: float(np.median([r[k] for r in mine]))
                       for k in ("median_ms", "min_ms", "logit_diff", "candidates_equal")}})
    return out


def op_profile(path: str | Path, feeds: list[dict[str, np.ndarray]], runs: int
               ) -> list[dict[str, Any]]:
    """The engine's session options with ONNX Runtime's profiler on: every feed run once
    untimed, then ``runs`` times; per operator type, kernel ms per network call (a pair's
    feeds), share of the kernels' total and node count, the largest first."""
    import tempfile

    from cegc_ros.onnx_network import OUTPUTS, open_session, session_options

    opts = session_options()
    opts.enable_profiling = True
    with tempfile.TemporaryDirectory() as tmp:
        opts.profile_file_prefix = str(Path(tmp) / "ort")
        session = open_session(path, opts)
        for f in feeds:
            session.run(list(OUTPUTS), f)
        for _ in range(runs):
            for f in feeds:
                session.run(list(OUTPUTS), f)
        events = json.loads(Path(session.end_profiling()).read_text())
    # the untimed first runs end where the len(feeds)-th "model_run" event ends
    model_runs = sorted((e["ts"] + e["dur"]) for e in events if e.get("name") == "model_run")
    warm_from = model_runs[len(feeds) - 1] if len(model_runs) >= len(feeds) else 0
    total: dict[str, float] = {}
    nodes: dict[str, set] = {}
    for e in events:
        if (e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time")
                and e.get("ts", 0) >= warm_from):
            op = e.get("args", {}).get("op_name", "?")
            total[op] = total.get(op, 0.0) + float(e["dur"])
            nodes.setdefault(op, set()).add(e["name"])
    whole = sum(total.values()) or 1.0
    calls = runs * len(feeds)
    return [{"op": op, "ms": us / 1000.0 / calls, "share": us / whole, "nodes": len(nodes[op])}
            for op, us in sorted(total.items(), key=lambda kv: -kv[1])]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench_runtimes", description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=20000, help="input points per cloud")
    ap.add_argument("--pairs", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--runtimes", default=",".join(RUNTIMES))
    ap.add_argument("--hogs", default="0", help="comma-separated: CPU-bound processes beside, per run")
    ap.add_argument("--cache", type=Path, default=Path(".cache/bench"))
    ap.add_argument("--rounds", type=int, default=2, help="each runtime's worker runs this many times, in turn")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--ops", type=int, default=0, metavar="N",
                    help="profile the engine's session by operator type over N runs instead")
    ap.add_argument("--worker", default="", help=argparse.SUPPRESS)
    ap.add_argument("--feeds", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        try:
            print(json.dumps(worker(args.worker, args.feeds, args.repeats)))
        except BenchError as err:
            print(f"bench_runtimes: {err}".splitlines()[0], file=sys.stderr)
            return 1
        return 0
    try:
        names = [n for n in args.runtimes.split(",") if n]
        for n in names:
            if n not in RUNTIMES:
                raise BenchError(f"--runtimes: unknown runtime {n!r}, expected some of {', '.join(RUNTIMES)}")
        if args.size < 16 or min(args.pairs, args.repeats, args.rounds) < 1:
            raise BenchError("--size must be >= 16, --pairs, --repeats and --rounds >= 1")
        hogs = [int(h) for h in args.hogs.split(",") if h]
        if "onnxruntime" not in names:
            names.insert(0, "onnxruntime")          # the reference of the ratios
        net, feeds = capture_inputs(args.size, args.pairs, args.cache)
        if args.ops > 0:
            ops = op_profile(net.path, feeds, args.ops)
            print("| operator | ms a call | share | nodes |\n|---|---|---|---|")
            for r in ops:
                print(f"| {r['op']} | {r['ms']:.2f} | {r['share']:.1%} | {r['nodes']} |")
            print(f"\n{len(feeds)} pairs of {args.size} points, {args.ops} runs\ncommand: python -m "
                  f"cegc_ros.tools.bench_runtimes {shlex.join(argv if argv is not None else sys.argv[1:])}")
            if args.json is not None:
                args.json.parent.mkdir(parents=True, exist_ok=True)
                args.json.write_text(json.dumps({"ops": ops}, indent=1))
            return 0
        feeds_file = save_feeds(net, feeds, args.cache / f"network_feeds_{args.size}.npz")
        rows = [measure(n, feeds_file, args.repeats, h) for _ in range(args.rounds) for h in hogs
                for n in names]
        results = _median_of_rounds(rows)
    except (BenchError, OSError, ValueError) as err:
        print(f"bench_runtimes: {err}".splitlines()[0], file=sys.stderr)
        return 1
    from cegc_ros.evaluation.report import machine_line
    print("| runtime | hogs | median ms | min ms | x onnxruntime | max logit diff | candidates equal |")
    print("|---|---|---|---|---|---|---|")
    base = {r["hogs"]: r["median_ms"] for r in results if r["runtime"] == "onnxruntime"}
    for r in results:
        ratio = f"{r['median_ms'] / base[r['hogs']]:.2f}x" if r["hogs"] in base else "-"
        print(f"| {r['runtime']} | {r['hogs']} | {r['median_ms']:.1f} | {r['min_ms']:.1f} | {ratio} | "
              f"{r['logit_diff']:.1e} | {r['candidates_equal']:.3f} |")
    machine = machine_line()
    print(f"\n{machine}; {len(feeds)} pairs of {args.size} points, {args.repeats} repeats\n"
          f"command: python -m cegc_ros.tools.bench_runtimes {shlex.join(argv if argv is not None else sys.argv[1:])}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"machine": machine, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
