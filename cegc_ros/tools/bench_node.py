"""Benchmark of register_node over real DDS against the engine alone (a script, not a test).

    python -m cegc_ros.tools.bench_node [--pairs 20] [--checkpoint PATH] [--replay-seconds 120]
                                        [--rates 1,2,3,4,6,8] [--out bench.json]

Measures, at the parameters of ``params/register_node.yaml`` (the defaults):
  1. engine latency: ``Registrar.register`` on generated 7Scenes-style test pairs, in-process;
  2. end-to-end latency of a register_node subprocess on the same pairs, one pair at a time:
     from publishing the source cloud (the target follows at once) to receiving ``~/pose``
     (1 and 2 alternate pair by pair, so both see the same background load);
  3. sustained pair rate: pairs published at fixed rates; the highest rate at which the node's
     ``pairs_dropped`` counter stays 0;
  4. node memory: RSS sampled once a second while ``cegc-replay`` plays a bag of the pairs
     (repeated) at real time (2 pairs/s) for ``--replay-seconds``.

DDS stays on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in a domain derived from
the pid unless ROS_DOMAIN_ID is set.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[2]


def _env() -> dict[str, str]:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    paths = os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)
    if sys.prefix not in paths:
        os.environ["AMENT_PREFIX_PATH"] = os.pathsep.join(p for p in [sys.prefix, *paths] if p)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return env


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _pct(values: list[float]) -> dict[str, float]:
    if not values:
        return {}
    a = np.asarray(values) * 1e3
    return {"n": len(values), "p50_ms": round(float(np.percentile(a, 50)), 1),
            "p90_ms": round(float(np.percentile(a, 90)), 1),
            "mean_ms": round(float(a.mean()), 1), "max_ms": round(float(a.max()), 1)}


def load_engine(checkpoint: str) -> Any:
    """The Registrar with the default settings, warmed up like the node's."""
    from cegc_ros.config import EngineConfig, PreprocessConfig
    from cegc_ros.engine import Registrar

    reg = Registrar.from_checkpoint(checkpoint or None, device=EngineConfig().device,
                                    preprocess=PreprocessConfig(), engine=EngineConfig())
    cloud = np.random.default_rng(0).uniform(-1.0, 1.0, (512, 3)).astype(np.float32)
    reg.register(cloud, cloud[::-1].copy())
    return reg


class _Client:
    """Publishes clouds to the node and records its poses and diagnostics."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("cegc_bench", context=self.context)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub_src = self.node.create_publisher(PointCloud2, "/source_cloud", qos)
        self.pub_tgt = self.node.create_publisher(PointCloud2, "/target_cloud", qos)
        self.cond = threading.Condition()
        self.poses: dict[int, float] = {}
        self.diag: dict[str, str] = {}
        self.node.create_subscription(PoseStamped, "/register_node/pose", self._on_pose, 100)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        threading.Thread(target=self.executor.spin, daemon=True).start()

    def _on_pose(self, msg: Any) -> None:
        now = time.perf_counter()
        with self.cond:
            self.poses[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec] = now
            self.cond.notify_all()

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            if st.name.startswith("register_node"):
                with self.cond:
                    self.diag = {kv.key: kv.value for kv in st.values}
                    self.cond.notify_all()

    def wait_connected(self, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.pub_src.get_subscription_count() and self.pub_tgt.get_subscription_count() \
                    and self.node.count_publishers("/register_node/pose") and self.diag:
                return True
            time.sleep(0.1)
        return False

    def send(self, src_msg: Any, tgt_msg: Any, stamp: int) -> float:
        for m in (src_msg, tgt_msg):
            m.header.stamp.sec, m.header.stamp.nanosec = stamp // 10**9, stamp % 10**9
        t0 = time.perf_counter()
        self.pub_src.publish(src_msg)
        self.pub_tgt.publish(tgt_msg)
        return t0

    def close(self) -> None:
        import rclpy
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _messages(pairs: list[Any]) -> list[tuple[Any, Any]]:
    from std_msgs.msg import Header

    from msg_adapters.point_cloud2 import xyz_to_cloud
    return [(xyz_to_cloud(p.source, Header(frame_id="cegc_source")),
             xyz_to_cloud(p.target, Header(frame_id="cegc_target"))) for p in pairs]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bench_node", description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--checkpoint", default="", help="default: the shipped weights")
    ap.add_argument("--params-file", default=str(REPO / "params" / "register_node.yaml"))
    ap.add_argument("--rates", default="1,2,3,4,6,8", help="pairs/s tried for the rate test")
    ap.add_argument("--rate-pairs", type=int, default=20, help="pairs published per rate")
    ap.add_argument("--replay-seconds", type=float, default=120.0)
    ap.add_argument("--out", help="write the figures as JSON here")
    args = ap.parse_args(argv)
    env = _env()

    from cegc_ros.data.protocols import make_pairs
    pairs = make_pairs("7scenes", "test", args.pairs)
    report: dict[str, Any] = {
        "command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else
                                                       sys.argv[1:])]),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}, "
                   f"python {platform.python_version()}",
        "load_avg_at_start": os.getloadavg(),
        "pairs": args.pairs, "points_per_cloud": int(np.median([len(p.source) for p in pairs])),
    }
    # 1. the engine alone, before anything else runs in this process: on a worker thread as
    # in the node, and on the main thread (torch's intra-op threads behave differently there;
    # on a loaded 2-core machine the main thread is several times slower).
    reg = load_engine(args.checkpoint)

    def run_engine(registrar: Any, out: list[float]) -> None:
        for p in pairs:
            t0 = time.perf_counter()
            registrar.register(p.source, p.target)
            out.append(time.perf_counter() - t0)

    eng: list[float] = []
    worker = threading.Thread(target=run_engine, args=(reg, eng))
    worker.start()
    worker.join()
    eng_main: list[float] = []
    run_engine(reg, eng_main)
    report["engine"] = {"device": reg.device, "checkpoint": reg.checkpoint_path,
                        "thread": "worker (as in the node)", **_pct(eng)}
    report["engine_main_thread"] = _pct(eng_main)
    print("engine", report["engine"], "main thread", report["engine_main_thread"], flush=True)
    del reg

    cmd = [sys.executable, "-m", "cegc_ros.node", "--ros-args", "--params-file",
           args.params_file]
    if args.checkpoint:
        cmd += ["-p", f"engine.checkpoint:={Path(args.checkpoint).resolve()}"]
    log_path = Path(tempfile.mkdtemp(prefix="bench_node_")) / "register_node.log"
    with log_path.open("w") as log:
        proc = subprocess.Popen(cmd, env=env, cwd=str(REPO), stdout=log,
                                stderr=subprocess.STDOUT)
    client = _Client()
    try:
        if not client.wait_connected(120.0):
            raise SystemExit(f"register_node did not come up; see {log_path}")
        report["node_rss_mb_idle"] = round(_rss_mb(proc.pid), 1)
        msgs = _messages(pairs)
        stamp = 1_000 * 10**9

        # 2. end-to-end latency, one pair at a time; the node's own engine time on the same
        # pairs comes from its diagnostics (engine_p50_ms), measured in the same conditions.
        lat = []
        for src, tgt in msgs:
            stamp += 10**9 // 2
            t0 = client.send(src, tgt, stamp)
            with client.cond:
                if client.cond.wait_for(lambda s=stamp: s in client.poses, 60.0):
                    lat.append(client.poses[stamp] - t0)
        time.sleep(1.5)
        with client.cond:
            diag = dict(client.diag)
        report["end_to_end"] = _pct(lat)
        report["node_engine_p50_ms"] = float(diag.get("engine_p50_ms", "nan"))
        report["node_internal_latency_p50_ms"] = float(diag.get("latency_p50_ms", "nan"))
        if lat:
            e2e = report["end_to_end"]["p50_ms"]
            report["end_to_end_over_node_engine_p50"] = round(
                e2e / report["node_engine_p50_ms"], 3)
            report["end_to_end_over_engine_p50"] = round(e2e / report["engine"]["p50_ms"], 3)
        print("end_to_end", report["end_to_end"], "node engine p50",
              report["node_engine_p50_ms"], flush=True)

        # 3. sustained rate: the highest rate with no dropped pair.
        rates = []
        for rate in (float(r) for r in args.rates.split(",")):
            time.sleep(1.5)   # let the node go idle and publish fresh diagnostics
            with client.cond:
                dropped0 = int(client.diag.get("pairs_dropped", 0))
                done0 = int(client.diag.get("pairs_done", 0))
            t_start = time.perf_counter()
            sent = []
            for k in range(args.rate_pairs):
                src, tgt = msgs[k % len(msgs)]
                stamp += 10**9 // 2
                delay = t_start + k / rate - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
                client.send(src, tgt, stamp)
                sent.append(stamp)
            with client.cond:
                client.cond.wait_for(lambda s=sent[-1]: s in client.poses, 30.0)
            time.sleep(1.5)
            with client.cond:
                dropped = int(client.diag.get("pairs_dropped", 0)) - dropped0
                done = int(client.diag.get("pairs_done", 0)) - done0
                got = sum(s in client.poses for s in sent)
            rates.append({"rate_hz": rate, "sent": len(sent), "poses": got,
                          "dropped": dropped, "done": done})
            print("rate", rates[-1], flush=True)
        report["rates"] = rates
        ok = [r["rate_hz"] for r in rates if r["dropped"] == 0 and r["poses"] == r["sent"]]
        report["sustained_rate_hz"] = max(ok) if ok else 0.0

        # 4. RSS over a replay at real time.
        from cegc_ros.data.bag import write_pairs
        from cegc_ros.tools.replay import replay_bag
        n_replay = max(1, int(args.replay_seconds * 2))
        bag = Path(tempfile.mkdtemp(prefix="bench_bag_")) / "pairs"
        write_pairs(bag, [pairs[k % len(pairs)] for k in range(n_replay)])
        samples: list[tuple[float, float]] = []
        stop = threading.Event()

        def sample() -> None:
            t0 = time.monotonic()
            while not stop.is_set():
                samples.append((time.monotonic() - t0, _rss_mb(proc.pid)))
                stop.wait(1.0)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        res = replay_bag(bag, rate=1.0, timeout=10.0)
        stop.set()
        sampler.join()
        rss = np.array([s[1] for s in samples])
        t = np.array([s[0] for s in samples])
        half = len(rss) // 2
        report["replay"] = {
            "seconds": round(res.wall_s, 1), "pairs": len(res.records),
            "poses": sum(r.T_est is not None for r in res.records),
            "dropped": int(res.diagnostics.get("pairs_dropped", -1)),
            "rss_mb_start": round(float(rss[0]), 1), "rss_mb_end": round(float(rss[-1]), 1),
            "rss_mb_max": round(float(rss.max()), 1),
            "rss_mb_second_half_slope_per_min": round(float(
                np.polyfit(t[half:], rss[half:], 1)[0] * 60.0), 2) if len(rss) - half > 2 else None,
            "latency": _pct([r.latency_s for r in res.records if r.latency_s is not None]),
            "rss_mb_every_10s": [round(float(v), 1) for v in rss[::10]],
        }
        print("replay", report["replay"], flush=True)
        report["node_diagnostics"] = res.diagnostics
    finally:
        client.close()
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
        report["node_exit_code"] = proc.returncode
        report["load_avg_at_end"] = os.getloadavg()
    text = json.dumps(report, indent=1)
    if args.out:
        Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
