"""Benchmark of register_node over real DDS (a script, not a test).

    python -m cegc_ros.tools.bench_node [--pairs 20] [--checkpoint PATH] [--rates 1,2,3]
        [--rate-pairs 16] [--responsiveness 300000,1000000,5000000] [--repeats 1]
        [--responsiveness-mode pairs|sequential] [--sequence-frames 10] [--sequence-rate 2]
        [--memory-minutes 10] [--memory-sizes 1500,20000,300000] [--skip latency,rate]
        [--fastdds-profile default|none|PATH] [--out bench.json]

Sections (each can be skipped with ``--skip``; responsiveness and memory run only when asked):
  latency         ``Registrar.register`` in-process on generated 7Scenes-style test pairs, then
                  the node (a subprocess at the params file's settings) on the same pairs one
                  at a time: publish -> ``~/pose``.
  rate            pairs published at fixed rates: the highest rate at which the node's
                  ``pairs_dropped`` counter stays 0.
  responsiveness  one huge pair (each size of ``--responsiveness``: a 7Scenes pair densified
                  with 0.3%-of-extent jitter) into a node whose engine runs in its own process
                  (the node as shipped) and into one whose engine runs on a thread of the node's
                  process (the design before issue 15). While the engine works, the bench calls
                  ``describe_parameters`` back to back and records the answer times and the gaps
                  between /diagnostics messages.
                  ``--responsiveness-mode sequential``: instead, a node started with
                  ``input.mode:=sequential`` (engine in its own process, as shipped) gets, per
                  size, ``--sequence-frames`` clouds on ``cloud`` at ``--sequence-rate`` Hz (a
                  robot's depth camera moving through a generated room, ~70k points per cloud
                  densified like the pairs; a fresh node per size), with the same
                  measurements from the first cloud until the node has taken the last.
                  The same clouds are then fed to ``KeyframeOdometry`` in the bench's process,
                  which gives the time of each odometry stage (what the node's worker runs).
  memory          ``--memory-minutes`` of pairs cycling through ``--memory-sizes`` points, one
                  pair per second, with the resident memory of the node process and of its engine
                  process sampled every second.

DDS stays on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in a domain derived from
the pid unless ROS_DOMAIN_ID is set. The bench's client publishes the clouds (and calls the
services) with the Fast DDS profile of ``--fastdds-profile``: by default
FASTRTPS_DEFAULT_PROFILES_FILE if set, else the shipped ``params/fastdds_large_clouds.xml``, as a
driver publishing huge clouds should; ``none``: Fast DDS's defaults (the comparison of
docs/node.md). The node gets the environment the bench was started with. Errors end the
benchmark with one line and exit code 1.
"""

from __future__ import annotations

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

from cegc_ros.tools.replay import OneLineParser

REPO = Path(__file__).resolve().parents[2]
SEC = 10**9


class BenchError(RuntimeError):
    """The benchmark cannot go on (the node did not come up, ...)."""


def _env() -> dict[str, str]:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    paths = os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)
    if sys.prefix not in paths:
        os.environ["AMENT_PREFIX_PATH"] = os.pathsep.join(p for p in [sys.prefix, *paths] if p)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return env


def _rss_mb(pid: int | None) -> float:
    if not pid:
        return float("nan")
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _pct(values: list[float]) -> dict[str, float]:
    if not values:
        return {"n": 0}
    a = np.asarray(values) * 1e3
    return {"n": len(values), "p50_ms": round(float(np.percentile(a, 50)), 1),
            "p90_ms": round(float(np.percentile(a, 90)), 1),
            "mean_ms": round(float(a.mean()), 1), "max_ms": round(float(a.max()), 1)}


def densify(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """(M, 3) -> (n, 3): every point kept, the rest repeated with jitter (0.3% of the extent);
    or a seeded subsample when n < M."""
    rng = np.random.default_rng(seed)
    if n <= len(points):
        return points[np.sort(rng.choice(len(points), n, replace=False))].astype(np.float32)
    idx = rng.integers(0, len(points), n)
    idx[: len(points)] = np.arange(len(points))
    out = points[idx].astype(np.float32)
    sigma = 0.003 * float(np.ptp(points, axis=0).max())
    out[len(points):] += rng.normal(0.0, sigma, (n - len(points), 3)).astype(np.float32)
    return out


class _Client:
    """Publishes clouds to a node and records its poses, diagnostics and service answers."""

    def __init__(self, namespace: str = "/", sequential: bool = False) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rcl_interfaces.srv import DescribeParameters
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        from cegc_ros.spinning import Spinner

        base = namespace.rstrip("/")
        self.status_name = f"{base}/register_node: registration"
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("cegc_bench", context=self.context)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        topics = ("cloud",) if sequential else ("source_cloud", "target_cloud")
        self.pubs = [self.node.create_publisher(PointCloud2, f"{base}/{t}", qos) for t in topics]
        self.pose_topic = f"{base}/register_node/pose"
        self.describe = self.node.create_client(
            DescribeParameters, f"{base}/register_node/describe_parameters")
        self.cond = threading.Condition()
        self.poses: dict[int, float] = {}
        self.diag: dict[str, str] = {}
        self.diag_times: list[float] = []
        self.node.create_subscription(PoseStamped, self.pose_topic, self._on_pose, 100)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.spinner = Spinner(self.executor)

    def _on_pose(self, msg: Any) -> None:
        now = time.perf_counter()
        with self.cond:
            self.poses[msg.header.stamp.sec * SEC + msg.header.stamp.nanosec] = now
            self.cond.notify_all()

    def _on_diag(self, msg: Any) -> None:
        now = time.perf_counter()
        for st in msg.status:
            if st.name == self.status_name:
                with self.cond:
                    self.diag = {kv.key: kv.value for kv in st.values}
                    self.diag_times.append(now)
                    self.cond.notify_all()

    def wait_connected(self, timeout: float, proc: subprocess.Popen) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end and proc.poll() is None:
            if all(p.get_subscription_count() for p in self.pubs) \
                    and self.node.count_publishers(self.pose_topic) and self.diag:
                return True
            time.sleep(0.1)
        return False

    def send(self, *msgs: Any, stamp: int) -> float:
        """Publish one message per input topic (source, target; or the one cloud), stamped."""
        for m in msgs:
            m.header.stamp.sec, m.header.stamp.nanosec = stamp // SEC, stamp % SEC
        t0 = time.perf_counter()
        for pub, m in zip(self.pubs, msgs, strict=True):
            pub.publish(m)
        return t0

    def describe_s(self, timeout: float = 60.0) -> float | None:
        """Round trip of one describe_parameters call (s), None if unanswered in time."""
        from rcl_interfaces.srv import DescribeParameters

        t0 = time.perf_counter()
        fut = self.describe.call_async(DescribeParameters.Request(names=["sync.slop"]))
        end = time.monotonic() + timeout
        while not fut.done() and time.monotonic() < end:
            time.sleep(0.002)
        return time.perf_counter() - t0 if fut.done() else None

    def close(self) -> None:
        import rclpy
        self.spinner.stop()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _messages(pairs: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[Any, Any]]:
    from std_msgs.msg import Header

    from msg_adapters.point_cloud2 import xyz_to_cloud
    return [(xyz_to_cloud(s, Header(frame_id="cegc_source")),
             xyz_to_cloud(t, Header(frame_id="cegc_target"))) for s, t in pairs]


def node_command(args: Any, engine: str, namespace: str, extra: tuple[str, ...] = (),
                 sequential: bool = False) -> list[str]:
    """The command line of the benchmark's register_node subprocess."""
    cmd = [sys.executable, "-m", "cegc_ros.tools.bench_node", "--serve", engine,
           "--ros-args", "--params-file", args.params_file, "-r", f"__ns:={namespace}",
           "-p", "input.reliable:=true", *extra]
    if sequential:
        cmd += ["-p", "input.mode:=sequential"]
    if args.checkpoint:
        cmd += ["-p", f"engine.checkpoint:={Path(args.checkpoint).resolve()}"]
    return cmd


class _Node:
    """A register_node subprocess (``engine``: 'process' as shipped, or 'inline') + client."""

    def __init__(self, args: Any, env: dict[str, str], engine: str = "process",
                 namespace: str = "/bench", extra: tuple[str, ...] = (),
                 sequential: bool = False) -> None:
        cmd = node_command(args, engine, namespace, extra, sequential)
        self.log_path = Path(tempfile.mkdtemp(prefix="bench_node_")) / "register_node.log"
        with self.log_path.open("w") as log:
            self.proc = subprocess.Popen(cmd, env=env, cwd=str(REPO), stdout=log,
                                         stderr=subprocess.STDOUT)
        self.client = None
        try:
            from cegc_ros.paths import fastdds_profile
            with fastdds_profile(args.fastdds_profile):   # the publishing side's profile
                self.client = _Client(namespace, sequential)
            if not self.client.wait_connected(300.0, self.proc):
                raise BenchError(f"register_node did not come up; see {self.log_path}")
        except BaseException:
            self.close()
            raise

    @property
    def engine_pid(self) -> int | None:
        with self.client.cond:
            pid = self.client.diag.get("engine_pid", "")
        return int(pid) if pid.isdigit() else None

    def close(self) -> int | None:
        if self.client is not None:
            self.client.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


def load_engine(checkpoint: str) -> Any:
    """The Registrar with the default settings, warmed up like the node's."""
    from cegc_ros.node.engine_process import load_registrar
    from cegc_ros.node.params import SECTIONS

    reg = load_registrar(SECTIONS["preprocess"](),
                         SECTIONS["engine"](checkpoint=checkpoint))
    cloud = np.random.default_rng(0).uniform(-1.0, 1.0, (512, 3)).astype(np.float32)
    reg.register(cloud, cloud[::-1].copy())
    return reg


def bench_latency(args: Any, env: dict[str, str], pairs: list[Any], report: dict) -> None:
    reg = load_engine(args.checkpoint)
    eng = []
    for p in pairs:
        t0 = time.perf_counter()
        reg.register(p.source, p.target)
        eng.append(time.perf_counter() - t0)
    report["engine"] = {"device": reg.device, "checkpoint": reg.checkpoint_path, **_pct(eng)}
    print("engine", report["engine"], flush=True)
    del reg
    node = _Node(args, env)
    try:
        c = node.client
        report["node_rss_mb_idle"] = round(_rss_mb(node.proc.pid), 1)
        report["engine_process_rss_mb_idle"] = round(_rss_mb(node.engine_pid), 1)
        lat, stamp = [], 1_000 * SEC
        for src, tgt in _messages([(p.source, p.target) for p in pairs]):
            stamp += SEC // 2
            t0 = c.send(src, tgt, stamp=stamp)
            with c.cond:
                if c.cond.wait_for(lambda s=stamp: s in c.poses, 120.0):
                    lat.append(c.poses[stamp] - t0)
        time.sleep(1.5)
        with c.cond:
            diag = dict(c.diag)
        report["end_to_end"] = _pct(lat)
        report["node_engine_p50_ms"] = float(diag.get("engine_p50_ms", "nan"))
        print("end_to_end", report["end_to_end"], "node engine p50",
              report["node_engine_p50_ms"], flush=True)
    finally:
        node.close()


def bench_rate(args: Any, env: dict[str, str], pairs: list[Any], report: dict) -> None:
    node = _Node(args, env)
    try:
        c = node.client
        msgs = _messages([(p.source, p.target) for p in pairs])
        rates, stamp = [], 5_000 * SEC
        for rate in (float(r) for r in args.rates.split(",")):
            time.sleep(1.5)   # let the node go idle and publish fresh diagnostics
            with c.cond:
                dropped0 = int(c.diag.get("pairs_dropped", 0))
            t_start = time.perf_counter()
            sent = []
            for k in range(args.rate_pairs):
                src, tgt = msgs[k % len(msgs)]
                stamp += SEC // 2
                delay = t_start + k / rate - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
                c.send(src, tgt, stamp=stamp)
                sent.append(stamp)
            with c.cond:
                c.cond.wait_for(lambda s=sent[-1]: s in c.poses, 60.0)
            time.sleep(1.5)
            with c.cond:
                dropped = int(c.diag.get("pairs_dropped", 0)) - dropped0
                got = sum(s in c.poses for s in sent)
            rates.append({"rate_hz": rate, "sent": len(sent), "poses": got, "dropped": dropped})
            print("rate", rates[-1], flush=True)
        report["rates"] = rates
        ok = [r["rate_hz"] for r in rates if r["dropped"] == 0 and r["poses"] == r["sent"]]
        report["sustained_rate_hz"] = max(ok) if ok else 0.0
    finally:
        node.close()


def _watch(c: _Client, t0: float, done: Any, timeout: float) -> dict[str, Any]:
    """While the node works (from ``t0`` until ``done()``, called under ``c.cond``, returns
    the time the work ended, or ``timeout`` s): ``describe_parameters`` back to back (0.1 s
    apart) and the /diagnostics messages. The figures of one responsiveness row."""
    answers: list[float | None] = []
    while True:
        with c.cond:
            t_end = done()
        if t_end is not None or time.perf_counter() - t0 > timeout:
            break
        answers.append(c.describe_s(timeout=timeout))
        time.sleep(0.1)
    window_end = t_end if t_end is not None else time.perf_counter()
    with c.cond:
        times = [t for t in c.diag_times if t0 <= t <= window_end]
    answered = [a for a in answers if a is not None]
    return {"done_after_s": None if t_end is None else round(t_end - t0, 2),
            "describe_calls": len(answers), "describe_unanswered": len(answers) - len(answered),
            **{f"describe_{k}": v for k, v in _pct(answered).items()
               if k in ("p50_ms", "max_ms")},
            "diagnostics_received": len(times),
            "diagnostics_max_gap_s": round(float(np.diff([t0, *times, window_end]).max()), 2)}


def bench_responsiveness(args: Any, env: dict[str, str], pairs: list[Any],
                         report: dict) -> None:
    if args.responsiveness_mode == "sequential":
        bench_responsiveness_sequential(args, env, pairs, report)
        return
    sizes = [int(s) for s in args.responsiveness.split(",")]
    rows = []
    for engine in ("process", "inline"):
        node = _Node(args, env, engine, namespace=f"/resp_{engine}",
                     extra=("-p", "diagnostics.period:=0.5"))
        try:
            c = node.client
            for k, n in enumerate(sizes * args.repeats):
                p = pairs[k % len(pairs)]
                (src, tgt), = _messages([(densify(p.source, n, 1), densify(p.target, n, 2))])
                stamp = (20_000 + k) * SEC
                time.sleep(1.0)
                idle = [c.describe_s() for _ in range(3)]
                t0 = c.send(src, tgt, stamp=stamp)
                del src, tgt
                w = _watch(c, t0, lambda s=stamp: c.poses.get(s), args.pair_timeout)
                rows.append({"engine": engine, "points": n,
                             "pose_after_s": w.pop("done_after_s"),
                             "describe_idle_ms": _pct([a for a in idle if a is not None])
                             .get("p50_ms"), **w})
                print("responsiveness", rows[-1], flush=True)
        finally:
            node.close()
    report["responsiveness"] = rows


def sequence_clouds(n: int, frames: int, rate: float, first: int = 0,
                    scene_seed: int = 0) -> list[np.ndarray]:
    """``frames`` clouds of ``n`` points each seen by a robot moving through a generated room
    (:func:`cegc_ros.data.sequences.make_room_sequence`, one cloud per 1/``rate`` s of its
    trajectory, from cloud ``first`` on), each densified with :func:`densify`."""
    from cegc_ros.data.sequences import make_room_sequence

    step = max(1, round(30.0 / rate))          # the trajectory runs at 30 frames/s
    seq = make_room_sequence(scene_seed, frames, frame_step=step, first_frame=first * step,
                             pixel_stride=2)
    return [densify(c, n, first + f) for f, c in enumerate(seq.clouds)]


def _odometry_stages(clouds: list[np.ndarray], stamps: list[int]) -> dict[str, Any]:
    """The clouds, stamped as sent to the node, through KeyframeOdometry in this process: ms
    per stage as 'p50 / max'; warmed up first, as the node's odometry is at start-up."""
    from cegc_ros.sequential import KeyframeOdometry

    odo = KeyframeOdometry()
    odo.warm_start()
    stages: dict[str, list[float]] = {}
    methods = []
    for xyz, stamp in zip(clouds, stamps, strict=True):
        fr = odo.feed(stamp, xyz)
        methods.append(fr.method)
        for k, v in fr.timings.items():
            stages.setdefault(k, []).append(v)
    out: dict[str, Any] = {"methods": methods}
    for k, v in stages.items():
        p = _pct(v)
        out[k] = f"{p['p50_ms']} / {p['max_ms']}"
    return out


def bench_responsiveness_sequential(args: Any, env: dict[str, str], pairs: list[Any],
                                    report: dict) -> None:
    """The responsiveness section for ``--responsiveness-mode sequential`` (module doc)."""
    from std_msgs.msg import Header

    from msg_adapters.point_cloud2 import xyz_to_cloud
    sizes = [int(s) for s in args.responsiveness.split(",")]
    period_ns = int(SEC / args.sequence_rate)
    rows = []
    for k, n in enumerate(sizes * args.repeats):
        clouds = sequence_clouds(n, args.sequence_frames, args.sequence_rate)
        node = _Node(args, env, namespace=f"/resp_sequential_{k}",
                     extra=("-p", "diagnostics.period:=0.5"), sequential=True)
        try:
            c = node.client
            msgs = [xyz_to_cloud(xyz, Header(frame_id="cegc_cloud")) for xyz in clouds]
            time.sleep(1.0)
            idle = [c.describe_s() for _ in range(3)]
            with c.cond:
                dropped0 = int(c.diag.get("pairs_dropped", 0))
                base = int(c.diag.get("pairs_done", 0)) + dropped0
                methods0 = [int(c.diag.get(m, 0)) for m in ("tracked", "recoveries")]
            stamps = [40_000 * SEC + f * period_ns for f in range(len(msgs))]
            sent: list[float] = []

            def publish(msgs: list[Any] = msgs, stamps: list[int] = stamps,
                        sent: list[float] = sent) -> None:
                t_start = time.perf_counter()
                for f, (m, s) in enumerate(zip(msgs, stamps, strict=True)):
                    delay = t_start + f / args.sequence_rate - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                    sent.append(c.send(m, stamp=s))

            def done(base: int = base, stamps: list[int] = stamps,
                     sent: list[float] = sent) -> float | None:
                """The last cloud's pose time; now once the node has taken (done or
                dropped) every cloud without a pose for the last; else None."""
                if len(sent) < len(stamps):
                    return None
                if stamps[-1] in c.poses:
                    return c.poses[stamps[-1]]
                taken = int(c.diag.get("pairs_done", 0)) + int(c.diag.get("pairs_dropped", 0))
                return time.perf_counter() if taken - base >= len(stamps) else None

            pub = threading.Thread(target=publish, daemon=True)
            t0 = time.perf_counter()
            pub.start()
            w = _watch(c, t0, done, args.pair_timeout)
            pub.join()
            del msgs
            time.sleep(0.6)       # the counters of the diagnostics after the last cloud
            with c.cond:
                got = sum(s in c.poses for s in stamps)
                diag = dict(c.diag)
            rows.append({"mode": "sequential", "points": n, "frames": len(stamps),
                         "rate_hz": args.sequence_rate, "poses": got,
                         "last_taken_after_s": w.pop("done_after_s"),
                         "describe_idle_ms": _pct([a for a in idle if a is not None])
                         .get("p50_ms"), **w,
                         "dropped": int(diag.get("pairs_dropped", 0)) - dropped0,
                         **{m: int(diag.get(m, 0)) - m0
                            for m, m0 in zip(("tracked", "recoveries"), methods0, strict=True)},
                         "node_odometry_p50_ms": diag.get("odometry_p50_ms"),
                         "load_avg_1min": round(os.getloadavg()[0], 2)})
            rows[-1]["odometry_stages_ms_p50_max"] = _odometry_stages(clouds, stamps)
            print("responsiveness", rows[-1], flush=True)
        finally:
            node.close()
    report["responsiveness"] = rows


def bench_memory(args: Any, env: dict[str, str], pairs: list[Any], report: dict) -> None:
    sizes = [int(s) for s in args.memory_sizes.split(",")]
    node = _Node(args, env, namespace="/memory")
    try:
        c = node.client
        msgs = []
        for k, n in enumerate(sizes):
            p = pairs[k % len(pairs)]
            msgs += _messages([(densify(p.source, n, 1), densify(p.target, n, 2))])
        samples: list[tuple[float, float, float]] = []   # t, node MB, engine MB
        t_start = time.perf_counter()
        end = t_start + args.memory_minutes * 60.0
        stamp, k, last_sample = 30_000 * SEC, 0, -1.0
        while time.perf_counter() < end:
            now = time.perf_counter() - t_start
            if now - last_sample >= 1.0:
                samples.append((now, _rss_mb(node.proc.pid), _rss_mb(node.engine_pid)))
                last_sample = now
            delay = t_start + k * 1.0 - time.perf_counter()     # one pair per second
            if delay > 0:
                time.sleep(min(delay, 1.0))
                continue
            stamp += SEC
            src, tgt = msgs[k % len(msgs)]
            c.send(src, tgt, stamp=stamp)
            k += 1
        time.sleep(3.0)
        with c.cond:
            diag = dict(c.diag)
        t = np.array([s[0] for s in samples])
        out: dict[str, Any] = {"minutes": args.memory_minutes, "sizes": sizes, "pairs_sent": k,
                               "pairs_out": int(diag.get("pairs_out", -1)),
                               "pairs_dropped": int(diag.get("pairs_dropped", -1)),
                               "pairs_rejected": int(diag.get("pairs_rejected", -1)),
                               "engine_restarts": int(diag.get("engine_restarts", -1)),
                               "latency_p50_ms": diag.get("latency_p50_ms")}
        for j, name in ((1, "node"), (2, "engine")):
            rss = np.array([s[j] for s in samples])
            ok = np.isfinite(rss)
            if not ok.any():
                continue
            half = len(rss) // 2
            tail = ok[half:]
            out[name] = {
                "rss_mb_first": round(float(rss[ok][0]), 1),
                "rss_mb_last": round(float(rss[ok][-1]), 1),
                "rss_mb_max": round(float(rss[ok].max()), 1),
                "rss_mb_median_first_minute": round(float(np.median(rss[ok][t[ok] < 60])), 1),
                "rss_mb_median_last_minute": round(float(np.median(
                    rss[ok][t[ok] > t[ok][-1] - 60])), 1),
                "second_half_slope_mb_per_min": round(float(np.polyfit(
                    t[half:][tail], rss[half:][tail], 1)[0] * 60.0), 2) if tail.sum() > 2
                else None,
                "every_minute": [round(float(v), 1) for v in rss[::60]],
            }
        report["memory"] = out
        print("memory", out, flush=True)
    finally:
        node.close()


def serve(engine: str, argv: list[str]) -> int:
    """Run a register_node for the benchmark: as shipped, or with the engine on a thread."""
    from cegc_ros.node import main as node_main

    factory = None
    if engine == "inline":
        from cegc_ros.node.engine_process import InlineEngine, load_registrar
        factory = lambda pre, eng: InlineEngine(load_registrar(pre, eng))  # noqa: E731
    return node_main(["register_node", *argv], engine_factory=factory)


def parse_args(argv: list[str]) -> Any:
    """The benchmark's options (exits 2 with one line for bad usage)."""
    ap = OneLineParser(prog="bench_node", description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=20)
    ap.add_argument("--checkpoint", default="", help="default: the shipped weights")
    ap.add_argument("--params-file", default=str(REPO / "params" / "register_node.yaml"))
    ap.add_argument("--rates", default="1,2,3,4,6,8", help="pairs/s tried for the rate test")
    ap.add_argument("--rate-pairs", type=int, default=20, help="pairs published per rate")
    ap.add_argument("--skip", default="", help="comma-separated: latency, rate")
    ap.add_argument("--responsiveness", default="",
                    help="comma-separated cloud sizes for the responsiveness section")
    ap.add_argument("--repeats", type=int, default=1,
                    help="responsiveness: pairs per size (the sizes cycle)")
    ap.add_argument("--responsiveness-mode", choices=("pairs", "sequential"), default="pairs",
                    help="responsiveness: huge pairs into pairs-mode nodes, or a stream of "
                         "clouds into a node with input.mode sequential")
    ap.add_argument("--sequence-frames", type=int, default=10,
                    help="responsiveness, sequential: clouds per size")
    ap.add_argument("--sequence-rate", type=float, default=2.0,
                    help="responsiveness, sequential: clouds per second")
    ap.add_argument("--pair-timeout", type=float, default=600.0,
                    help="responsiveness: give up on a pose after this many seconds")
    ap.add_argument("--memory-minutes", type=float, default=0.0,
                    help="length of the memory section (0: skip it)")
    ap.add_argument("--memory-sizes", default="1500,20000,300000")
    ap.add_argument("--replay-seconds", type=float, default=0.0,
                    help="older spelling of --memory-minutes, in seconds")
    ap.add_argument("--fastdds-profile", default="default", metavar="default|none|PATH",
                    help="Fast DDS profiles file of the publishing client (default: "
                         "$FASTRTPS_DEFAULT_PROFILES_FILE if set, else the shipped "
                         "fastdds_large_clouds.xml; none: Fast DDS's defaults)")
    ap.add_argument("--out", help="write the figures as JSON here")
    args = ap.parse_args(argv)
    if args.replay_seconds and not args.memory_minutes:
        args.memory_minutes = args.replay_seconds / 60.0
    return args


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--serve"]:
        return serve(argv[1], argv[2:])
    args = parse_args(argv)
    env = _env()
    skip = {s for s in args.skip.split(",") if s}

    from cegc_ros.data.protocols import make_pairs
    from cegc_ros.paths import FASTDDS_PROFILE_ENV, fastdds_profile
    report: dict[str, Any] = {
        "command": " ".join(["python -m cegc_ros.tools.bench_node", *argv]),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.platform()}, "
                   f"python {platform.python_version()}",
        "load_avg_at_start": os.getloadavg(),
        "node_fastdds_profile": env.get(FASTDDS_PROFILE_ENV),
    }
    try:
        with fastdds_profile(args.fastdds_profile) as profile:
            report["client_fastdds_profile"] = profile
        print("Fast DDS profile: client", profile, "node", report["node_fastdds_profile"],
              flush=True)
        pairs = make_pairs("7scenes", "test", args.pairs)
        report["points_per_cloud"] = int(np.median([len(p.source) for p in pairs]))
        if "latency" not in skip:
            bench_latency(args, env, pairs, report)
        if "rate" not in skip:
            bench_rate(args, env, pairs, report)
        if args.responsiveness:
            bench_responsiveness(args, env, pairs, report)
        if args.memory_minutes > 0:
            bench_memory(args, env, pairs, report)
    except (BenchError, OSError, ValueError) as err:
        print(f"bench_node: {' '.join(str(err).split())}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("bench_node: interrupted", file=sys.stderr)
        return 130
    report["load_avg_at_end"] = os.getloadavg()
    text = json.dumps(report, indent=1)
    if args.out:
        Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
