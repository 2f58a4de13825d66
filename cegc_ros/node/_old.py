"""register_node: the ROS 2 node that registers two PointCloud2 streams with CEGC.

A thin layer over :class:`cegc_ros.engine.Registrar`: parameters -> pair ``source_cloud`` with
``target_cloud`` by stamp -> ``cloud_to_xyz`` -> engine (on one worker thread) -> messages.

Topics (relative names, so namespaces and remapping work):

  in   source_cloud, target_cloud        sensor_msgs/PointCloud2
  out  ~/pose                            geometry_msgs/PoseStamped (T_target_source, target frame)
       ~/pose_with_covariance            geometry_msgs/PoseWithCovarianceStamped
       ~/source_overlap, ~/target_overlap sensor_msgs/PointCloud2 (x, y, z, overlap), own frames
       ~/markers                         visualization_msgs/MarkerArray (target frame)
       /diagnostics                      diagnostic_msgs/DiagnosticArray

Every output of a pair carries the source cloud's stamp. Bad input is logged (throttled per
kind), counted on /diagnostics and skipped; only a checkpoint that cannot be loaded at start-up
stops the node (exit code 1).
"""

from __future__ import annotations

import dataclasses
import math
import signal
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from cegc_ros.config import (
    DiagnosticsConfig,
    EngineConfig,
    InputConfig,
    MarkersConfig,
    OutputConfig,
    PreprocessConfig,
    SyncConfig,
    section_items,
)

NODE_NAME = "register_node"

#: Parameter sections, in declaration order: ``<section>.<field>`` per dataclass field.
SECTIONS: dict[str, type] = {
    "preprocess": PreprocessConfig,
    "engine": EngineConfig,
    "input": InputConfig,
    "sync": SyncConfig,
    "output": OutputConfig,
    "markers": MarkersConfig,
    "diagnostics": DiagnosticsConfig,
}
#: Sections whose change must reach the Registrar (through ``Registrar.update``).
ENGINE_SECTIONS = ("preprocess", "engine")

#: Why a pair produced no pose: the keys of the ``rejected.*`` diagnostics counters.
REJECT_REASONS = (
    "malformed_cloud",   # missing x/y/z fields, data shorter than the layout, bad field types
    "empty_cloud",       # no finite points at all
    "too_few_points",    # fewer finite points than the engine's minimum
    "missing_frame",     # empty header.frame_id: outputs would have no frame
    "invalid_result",    # the engine judged its result invalid (reason logged)
    "low_fitness",       # fitness < output.min_fitness
    "engine_error",      # the engine raised; logged with the exception
)


# ---------------------------------------------------------------------------------------------
# Parameters <-> config dataclasses (no rclpy objects are needed to describe them)
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter, derived from a config dataclass field."""

    name: str            # "<section>.<field>"
    section: str
    field: str
    default: Any
    description: str
    range: tuple[float | None, float | None]
    dynamic: bool
    choices: tuple[str, ...] | None


def param_specs() -> list[ParamSpec]:
    """Every parameter of the node, with the defaults of :mod:`cegc_ros.config`."""
    specs = []
    for section, cls in SECTIONS.items():
        for name, default, meta in section_items(cls()):
            specs.append(ParamSpec(f"{section}.{name}", section, name, default,
                                   meta["description"], tuple(meta["range"]), meta["dynamic"],
                                   meta["choices"]))
    return specs


def check_value(spec: ParamSpec, value: Any) -> str | None:
    """Why ``value`` is not acceptable for ``spec`` (type, range, choices), or None if it is."""
    kind = type(spec.default)
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if type(value) is not kind:
        return f"{spec.name} must be a {kind.__name__}, got {type(value).__name__} {value!r}"
    lo, hi = spec.range
    if kind in (int, float):
        if kind is float and not math.isfinite(value):
            return f"{spec.name} must be finite, got {value}"
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            return f"{spec.name} = {value} is out of range [{lo}, {hi}]"
    if spec.choices is not None and value not in spec.choices:
        return f"{spec.name} = {value!r} is not one of {', '.join(spec.choices)}"
    return None


def usage() -> str:
    """The --help text: how to run the node and every parameter with its default."""
    lines = [
        (f"usage: {NODE_NAME} [-h] [--print-params] [--ros-args [--params-file FILE] "
         "[-p NAME:=VALUE] "
         "[-r FROM:=TO] ...]"),
        "",
        "Registers source_cloud onto target_cloud (sensor_msgs/PointCloud2, paired by stamp)",
        "with CEGC and publishes ~/pose, ~/pose_with_covariance, ~/source_overlap,",
        "~/target_overlap, ~/markers and /diagnostics.",
        "--print-params writes the parameter file with every default (YAML) to stdout.",
        "",
        ("example: ros2 run cegc_ros register_node --ros-args --params-file "
         "params/register_node.yaml -r source_cloud:=/scan -r target_cloud:=/map_cloud"),
        "",
        "parameters (name, default, range; * = read-only after start-up):",
    ]
    for s in param_specs():
        lo, hi = s.range
        rng = f" [{lo}, {hi}]" if lo is not None or hi is not None else ""
        if s.choices:
            rng = " {" + ", ".join(s.choices) + "}"
        ro = "" if s.dynamic else " *"
        lines.append(f"  {s.name} = {s.default!r}{rng}{ro}")
        lines.append(f"      {s.description}")
    return "\n".join(lines)


def params_yaml() -> str:
    """The text of ``params/register_node.yaml``: every parameter at its default, described.

    Regenerate the file after changing :mod:`cegc_ros.config` with
    ``register_node --print-params > params/register_node.yaml``.
    """
    import textwrap

    def fmt(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        return f'"{v}"' if isinstance(v, str) else repr(v)

    lines = ["# Parameters of register_node (defaults; the single source is cegc_ros/config.py).",
             "# Load with: register_node --ros-args --params-file params/register_node.yaml",
             "# read-only = fixed at start-up; everything else can be changed at run time and",
             "# applies to the next pair.", "/**:", "  ros__parameters:"]
    section = None
    for s in param_specs():
        if s.section != section:
            if section is not None:
                lines.append("")
            section = s.section
        lo, hi = s.range
        extra = []
        if s.choices:
            extra.append("one of " + ", ".join(s.choices))
        elif lo is not None or hi is not None:
            extra.append(f"range [{lo}, {hi}]")
        if not s.dynamic:
            extra.append("read-only")
        desc = s.description + (" (" + "; ".join(extra) + ")" if extra else "")
        lines += ["    # " + ln for ln in textwrap.wrap(desc, 92, break_on_hyphens=False,
                                                      break_long_words=False)]
        lines.append(f"    {s.name}: {fmt(s.default)}")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# Small helpers used by the node (ROS-free, so they are easy to test)
# ---------------------------------------------------------------------------------------------
class Mailbox:
    """A one-slot hand-over between the executor and the worker: the newest item wins."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: Any = None
        self._closed = False

    def put(self, item: Any) -> Any:
        """Leave ``item`` for the worker; returns the item it replaced (dropped) or None."""
        with self._cond:
            replaced, self._item = self._item, item
            self._cond.notify()
            return replaced

    def get(self, timeout: float | None = None) -> Any:
        """The waiting item (emptying the slot), or None once closed / after ``timeout``."""
        with self._cond:
            self._cond.wait_for(lambda: self._item is not None or self._closed, timeout)
            if self._closed:
                return None
            item, self._item = self._item, None
            return item

    def close(self) -> Any:
        """Wake the worker for good; returns the item that was still waiting, if any."""
        with self._cond:
            self._closed = True
            item, self._item = self._item, None
            self._cond.notify_all()
            return item


class ThrottledLog:
    """Logs each kind of message at once, then at most once per ``period`` s with a count."""

    def __init__(self, emit: Callable[[str], None], period: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._emit = emit
        self.period = period
        self._clock = clock
        self._last: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()

    def __call__(self, kind: str, text: str) -> bool:
        """Log ``text`` unless ``kind`` was logged less than ``period`` ago; True if logged."""
        now = self._clock()
        last = self._last.get(kind)
        if last is not None and now - last < self.period:
            self._suppressed[kind] += 1
            return False
        more = self._suppressed.pop(kind, 0)
        self._last[kind] = now
        self._emit(f"{text} ({more} more like this since the last report)" if more else text)
        return True


def percentiles_ms(samples: Sequence[float], qs: Sequence[float] = (50, 90, 99)) -> list[float]:
    """Percentiles (ms) of durations given in seconds; NaN when there are none."""
    if not samples:
        return [float("nan")] * len(qs)
    return [float(v) * 1e3 for v in np.percentile(np.asarray(samples, np.float64), qs)]


def thin(xyz: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` rows of (N, 3) ``xyz`` by a uniform stride (order kept)."""
    n = xyz.shape[0]
    if n <= max_points:
        return xyz
    return xyz[:: math.ceil(n / max_points)]


def stamp_ns(stamp: Any) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclass
class _Job:
    """A matched pair waiting for (or in) the worker."""

    source: Any          # sensor_msgs/PointCloud2
    target: Any
    received: float      # time.monotonic() when the later of the two arrived


class Rejected(Exception):
    """A pair that produces no pose; ``reason`` is one of :data:`REJECT_REASONS`."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


# ---------------------------------------------------------------------------------------------
# The node
# ---------------------------------------------------------------------------------------------
def load_registrar(preprocess: PreprocessConfig, engine: EngineConfig) -> Any:
    """The engine for these settings (raises cegc_ros.engine.CheckpointError)."""
    from cegc_ros.engine import Registrar  # torch is heavy: import it only when running
    return Registrar.from_checkpoint(engine.checkpoint or None, device=engine.device,
                                     preprocess=preprocess, engine=engine)


def _make_node_class():
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from rcl_interfaces.msg import (
        FloatingPointRange,
        IntegerRange,
        ParameterDescriptor,
        ParameterType,
        SetParametersResult,
    )
    from rclpy.node import Node
    from rclpy.qos import (
        HistoryPolicy,
        QoSProfile,
        ReliabilityPolicy,
        qos_profile_sensor_data,
    )
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Header
    from visualization_msgs.msg import MarkerArray

    from cegc_ros.pairing import ApproximatePairer
    from msg_adapters.markers import correspondence_markers
    from msg_adapters.point_cloud2 import cloud_to_xyz, xyz_to_cloud
    from msg_adapters.pose import pose_stamped, pose_with_covariance_stamped

    ptypes = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
              float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}

    def descriptor(spec: ParamSpec) -> ParameterDescriptor:
        d = ParameterDescriptor(name=spec.name, type=ptypes[type(spec.default)],
                                description=spec.description, read_only=not spec.dynamic)
        lo, hi = spec.range
        if isinstance(spec.default, float) and (lo is not None or hi is not None):
            d.floating_point_range = [FloatingPointRange(
                from_value=float(-math.inf if lo is None else lo),
                to_value=float(math.inf if hi is None else hi), step=0.0)]
        elif isinstance(spec.default, int) and not isinstance(spec.default, bool) \
                and (lo is not None or hi is not None):
            d.integer_range = [IntegerRange(from_value=int(-(2**63) if lo is None else lo),
                                            to_value=int(2**63 - 1 if hi is None else hi),
                                            step=0)]
        if spec.choices:
            d.additional_constraints = "one of: " + ", ".join(spec.choices)
        return d

    class RegisterNode(Node):
        """Pairs the two cloud topics, runs the engine on a worker thread, publishes results."""

        def __init__(self, registrar_factory: Callable[..., Any] = load_registrar,
                     **node_kwargs: Any) -> None:
            super().__init__(NODE_NAME, **node_kwargs)
            self._specs = {s.name: s for s in param_specs()}
            self.cfg: dict[str, Any] = self._declare_parameters()
            self._log = ThrottledLog(self.get_logger().warning, self.cfg["diagnostics"].log_throttle)

            # Counters: written by the executor (inputs) and the worker (results).
            self._lock = threading.Lock()
            self.counts: Counter[str] = Counter()
            win = self.cfg["diagnostics"].window
            self._latency: deque[float] = deque(maxlen=win)   # pair complete -> pose out (s)
            self._engine_time: deque[float] = deque(maxlen=win)  # Registrar.register (s)
            self._last_fitness = float("nan")
            self._last_network = "none"
            self._last_pose_from = "none"
            self._last_frames: dict[str, str] = {}
            self._engine_dirty = False

            # Raises CheckpointError (or ValueError for a bad device): main() reports it.
            self.registrar = registrar_factory(self.cfg["preprocess"], self.cfg["engine"])
            self.min_points = int(getattr(self.registrar, "MIN_POINTS", 16))
            self._warm_up()

            sync = self.cfg["sync"]
            self.pairer: ApproximatePairer[Any] = ApproximatePairer(sync.slop, sync.buffer_size)
            inp = self.cfg["input"]
            if inp.reliable:
                qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=inp.queue_depth,
                                 reliability=ReliabilityPolicy.RELIABLE)
            else:
                qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=inp.queue_depth,
                                 reliability=qos_profile_sensor_data.reliability,
                                 durability=qos_profile_sensor_data.durability)
            self.input_qos = qos
            self.create_subscription(PointCloud2, "source_cloud",
                                     lambda m: self._on_cloud("source", m), qos)
            self.create_subscription(PointCloud2, "target_cloud",
                                     lambda m: self._on_cloud("target", m), qos)
            self.pub_pose = self.create_publisher(PoseStamped, "~/pose", 10)
            self.pub_pose_cov = self.create_publisher(PoseWithCovarianceStamped,
                                                      "~/pose_with_covariance", 10)
            self.pub_src_overlap = self.create_publisher(PointCloud2, "~/source_overlap", 5)
            self.pub_tgt_overlap = self.create_publisher(PointCloud2, "~/target_overlap", 5)
            self.pub_markers = self.create_publisher(MarkerArray, "~/markers", 5)
            self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
            self.create_timer(self.cfg["diagnostics"].period, self.publish_diagnostics)

            self.add_on_set_parameters_callback(self._validate_parameters)
            self.add_post_set_parameters_callback(self._apply_parameters)

            self._mailbox = Mailbox()
            self._busy = False
            self._worker = threading.Thread(target=self._work, name="cegc_worker", daemon=True)
            self._worker.start()
            self.get_logger().info(
                f"ready: device {getattr(self.registrar, 'device', '?')}, checkpoint "
                f"{getattr(self.registrar, 'checkpoint_path', '?')}, input QoS "
                f"{'reliable' if inp.reliable else 'sensor-data (best effort)'}, "
                f"slop {sync.slop} s")

        def _warm_up(self) -> None:
            """One throw-away registration, so the first real pair is not slowed by it."""
            rng = np.random.default_rng(0)
            cloud = rng.uniform(-1.0, 1.0, (512, 3)).astype(np.float32)  # (512, 3)
            t0 = time.perf_counter()
            try:
                compiled = self.registrar.warm_up()
                if compiled:
                    self.get_logger().info(f"engine.compile: networks compiled in {compiled:.1f} s")
                self.registrar.register(cloud, cloud[::-1].copy())
            except Exception as err:  # noqa: BLE001  a failed warm-up is not fatal
                self.get_logger().warning(f"warm-up registration failed: {err}")
            self.get_logger().debug(f"warm-up took {time.perf_counter() - t0:.2f} s")

        # -- parameters -------------------------------------------------------------------
        def _declare_parameters(self) -> dict[str, Any]:
            specs = list(self._specs.values())
            for spec in specs:
                self.declare_parameter(spec.name, spec.default, descriptor(spec))
            problems = [p for p in (check_value(s, self.get_parameter(s.name).value)
                                    for s in specs) if p]
            if problems:
                raise ValueError("invalid parameters: " + "; ".join(problems))
            overrides = getattr(self, "_parameter_overrides", {})  # rclpy keeps them here
            unknown = sorted(set(overrides) - set(self._specs)
                             - {"use_sim_time"})
            if unknown:
                self.get_logger().warning(f"ignoring unknown parameters: {', '.join(unknown)}")
            cfg = {}
            for section, cls in SECTIONS.items():
                values = {s.field: self._value(s, self.get_parameter(s.name).value)
                          for s in specs if s.section == section}
                cfg[section] = cls(**values)
            return cfg

        @staticmethod
        def _value(spec: ParamSpec, value: Any) -> Any:
            return float(value) if isinstance(spec.default, float) else value

        def _validate_parameters(self, params: list[Any]) -> SetParametersResult:
            # rclpy has already applied the descriptors (type, range, read-only); this adds
            # the choices and makes the reason name the parameter.
            for p in params:
                spec = self._specs.get(p.name)
                if spec is None:
                    continue
                problem = check_value(spec, p.value)
                if problem:
                    return SetParametersResult(successful=False, reason=problem)
            return SetParametersResult(successful=True)

        def _apply_parameters(self, params: list[Any]) -> None:
            # Runs on the executor thread after a successful set: the new config objects are
            # swapped in whole, so the worker always sees a consistent section.
            for p in params:
                spec = self._specs.get(p.name)
                if spec is None:
                    continue
                old = self.cfg[spec.section]
                self.cfg[spec.section] = dataclasses.replace(
                    old, **{spec.field: self._value(spec, p.value)})
                if spec.section in ENGINE_SECTIONS:
                    self._engine_dirty = True
                self.get_logger().info(f"parameter {p.name} = {p.value!r} (applies to the "
                                       "next pair)")
            sync = self.cfg["sync"]
            self.pairer.slop_s = sync.slop
            self.pairer.buffer_size = sync.buffer_size
            diag = self.cfg["diagnostics"]
            self._log.period = diag.log_throttle
            with self._lock:
                if self._latency.maxlen != diag.window:
                    self._latency = deque(self._latency, maxlen=diag.window)
                    self._engine_time = deque(self._engine_time, maxlen=diag.window)

        # -- inputs (executor thread) -----------------------------------------------------
        def _on_cloud(self, side: str, msg: Any) -> None:
            now = time.monotonic()
            with self._lock:
                self.counts[f"messages_in.{side}"] += 1
            try:
                stamp = stamp_ns(msg.header.stamp)
            except (AttributeError, TypeError, ValueError) as err:  # pragma: no cover
                self._reject_input("malformed_cloud", f"{side} cloud has no usable stamp: {err}")
                return
            result = self.pairer.add(side, stamp, msg)
            for u in result.unpaired:
                with self._lock:
                    self.counts[f"unpaired.{u.side}"] += 1
                self._log(f"unpaired.{u.side}",
                          f"{u.side} cloud at stamp {u.stamp_ns / 1e9:.3f} s found no "
                          f"{'target' if u.side == 'source' else 'source'} cloud within "
                          f"sync.slop = {self.cfg['sync'].slop} s; dropped")
            if result.pair is None:
                return
            job = _Job(result.pair.source.msg, result.pair.target.msg, now)
            with self._lock:
                self.counts["pairs_in"] += 1
            replaced = self._mailbox.put(job)
            if replaced is not None:
                with self._lock:
                    self.counts["pairs_dropped"] += 1
                self._log("dropped", "registration is slower than the input: the waiting "
                          "pair was replaced by a newer one")

        def _reject_input(self, reason: str, detail: str) -> None:
            with self._lock:
                self.counts["pairs_rejected"] += 1
                self.counts[f"rejected.{reason}"] += 1
            self._log(reason, f"pair rejected ({reason}): {detail}")

        # -- work (worker thread) ---------------------------------------------------------
        def _work(self) -> None:
            while True:
                job = self._mailbox.get()
                if job is None:
                    return
                self._busy = True
                try:
                    self._process(job)
                except Rejected as rej:
                    self._reject_input(rej.reason, str(rej))
                except Exception as err:  # noqa: BLE001  the node must outlive any bad pair
                    self._reject_input("engine_error", f"{type(err).__name__}: {err}")
                finally:
                    with self._lock:
                        self.counts["pairs_done"] += 1
                    self._busy = False

        def _xyz(self, side: str, msg: Any) -> np.ndarray:
            """Finite (N, 3) float32 points of one input, or Rejected."""
            frame = msg.header.frame_id
            if not frame:
                raise Rejected("missing_frame", f"{side} cloud has an empty header.frame_id")
            last = self._last_frames.get(side)
            if last is not None and last != frame:
                with self._lock:
                    self.counts[f"frame_changes.{side}"] += 1
                self._log(f"frame_change.{side}", f"{side} cloud frame changed from {last!r} "
                          f"to {frame!r}; following the new frame")
            self._last_frames[side] = frame
            try:
                xyz = cloud_to_xyz(msg)  # (N, 3) float32, finite only
            except ValueError as err:
                raise Rejected("malformed_cloud", f"{side} cloud: {err}") from err
            n_raw = int(msg.width) * int(msg.height)
            if xyz.shape[0] == 0:
                raise Rejected("empty_cloud", f"{side} cloud has no finite points "
                               f"({n_raw} points in the message)")
            if xyz.shape[0] < self.min_points:
                raise Rejected("too_few_points", f"{side} cloud has {xyz.shape[0]} finite "
                               f"points, the engine needs at least {self.min_points}")
            max_points = self.cfg["input"].max_points
            if xyz.shape[0] > max_points:
                with self._lock:
                    self.counts["thinned_clouds"] += 1
                xyz = thin(xyz, max_points)
            return xyz

        def _process(self, job: _Job) -> None:
            if self._engine_dirty:
                self._engine_dirty = False
                self.registrar.update(preprocess=self.cfg["preprocess"],
                                      engine=self.cfg["engine"])
            out = self.cfg["output"]
            src, tgt = job.source, job.target
            src_xyz = self._xyz("source", src)
            tgt_xyz = self._xyz("target", tgt)

            t0 = time.perf_counter()
            try:
                result = self.registrar.register(src_xyz, tgt_xyz)
            except ValueError as err:
                raise Rejected("too_few_points", f"engine refused the pair: {err}") from err
            engine_s = time.perf_counter() - t0
            with self._lock:
                self._engine_time.append(engine_s)
            if not result.valid:
                raise Rejected("invalid_result", f"engine result invalid: {result.reason}")
            self._last_fitness = float(result.fitness)
            self._last_network = result.network
            self._last_pose_from = result.pose_from
            if result.fitness < out.min_fitness:
                raise Rejected("low_fitness", f"fitness {result.fitness:.3f} < "
                               f"output.min_fitness {out.min_fitness:.3f}")

            stamp = src.header.stamp
            tgt_header = Header(stamp=stamp, frame_id=tgt.header.frame_id)
            try:
                pose = pose_stamped(result.T_target_source, tgt_header)
                pose_cov = pose_with_covariance_stamped(result.T_target_source,
                                                        result.covariance, tgt_header)
            except ValueError as err:
                raise Rejected("invalid_result", f"engine result unusable: {err}") from err
            self.pub_pose.publish(pose)
            done = time.monotonic()
            self.pub_pose_cov.publish(pose_cov)
            with self._lock:
                self.counts["pairs_out"] += 1
                self._latency.append(done - job.received)
            try:
                self._publish_extras(result, src, tgt, tgt_header)
            except ValueError as err:  # the pose is out; a visual output could not be built
                with self._lock:
                    self.counts["output_errors"] += 1
                self._log("output_error", f"overlap clouds / markers not published: {err}")

        def _publish_extras(self, result: Any, src: Any, tgt: Any, tgt_header: Any) -> None:
            """The overlap-masked clouds and the correspondence markers of one result."""
            out, mk = self.cfg["output"], self.cfg["markers"]
            stamp = src.header.stamp
            if out.publish_overlap:
                for points, scores, frame, pub in (
                        (result.source_points, result.source_overlap, src.header.frame_id,
                         self.pub_src_overlap),
                        (result.target_points, result.target_overlap, tgt.header.frame_id,
                         self.pub_tgt_overlap)):
                    keep = scores >= out.overlap_threshold  # (N,)
                    pub.publish(xyz_to_cloud(points[keep], Header(stamp=stamp, frame_id=frame),
                                             {"overlap": scores[keep]}))
            if mk.enabled:
                strong = result.weights >= mk.min_weight  # (M,)
                self.pub_markers.publish(correspondence_markers(
                    result.source_points, result.target_points,
                    result.correspondences[strong], result.weights[strong], tgt_header,
                    T_target_source=result.T_target_source,
                    max_lines=mk.max_correspondences, line_width=mk.line_width))

        # -- diagnostics ------------------------------------------------------------------
        def diagnostics_values(self) -> dict[str, str]:
            """The /diagnostics key-values (also handy for tests)."""
            with self._lock:
                counts = Counter(self.counts)
                lat = list(self._latency)
                eng = list(self._engine_time)
            keys = ["messages_in.source", "messages_in.target", "pairs_in", "pairs_out",
                    "pairs_dropped", "pairs_rejected", "pairs_done", "unpaired.source",
                    "unpaired.target", "frame_changes.source", "frame_changes.target",
                    "thinned_clouds", "take_errors", "output_errors"] + [f"rejected.{r}" for r in REJECT_REASONS]
            values = {k: str(counts.get(k, 0)) for k in keys}
            for q, v in zip((50, 90, 99), percentiles_ms(lat)):
                values[f"latency_p{q}_ms"] = f"{v:.1f}"
            values["latency_max_ms"] = f"{max(lat) * 1e3:.1f}" if lat else "nan"
            values["engine_p50_ms"] = f"{percentiles_ms(eng, (50,))[0]:.1f}"
            values["device"] = str(getattr(self.registrar, "device", "?"))
            values["checkpoint"] = str(getattr(self.registrar, "checkpoint_path", "?"))
            values["last_fitness"] = f"{self._last_fitness:.4f}"
            values["last_network"] = self._last_network       # cascade: "first" | "second"
            values["last_pose_from"] = self._last_pose_from   # "network" | "ransac" (engine.ransac_candidate)
            values["busy"] = str(self._busy).lower()
            return values

        def publish_diagnostics(self) -> None:
            values = self.diagnostics_values()
            rejected, dropped = int(values["pairs_rejected"]), int(values["pairs_dropped"])
            prev = getattr(self, "_diag_prev", (0, 0))
            self._diag_prev = (rejected, dropped)
            status = DiagnosticStatus(name=f"{self.get_name()}: registration",
                                      hardware_id=values["device"])
            new_rej, new_drop = rejected - prev[0], dropped - prev[1]
            if new_rej or new_drop:
                status.level = DiagnosticStatus.WARN
                status.message = (f"{new_rej} pairs rejected, {new_drop} dropped since the "
                                  "last report")
            else:
                status.level = DiagnosticStatus.OK
                status.message = (f"{values['pairs_out']} poses published"
                                  if int(values["pairs_in"]) else "waiting for cloud pairs")
            status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
            msg = DiagnosticArray(status=[status])
            msg.header.stamp = self.get_clock().now().to_msg()
            self.pub_diag.publish(msg)

        # -- shutdown ---------------------------------------------------------------------
        def stop_worker(self, timeout: float = 10.0) -> bool:
            """Stop taking pairs and wait for the one in progress; True if the worker ended."""
            self._mailbox.close()
            self._worker.join(timeout)
            return not self._worker.is_alive()

    return RegisterNode


_NODE_CLASS = None


def node_class():
    """The RegisterNode class (built on first use so that --help needs no rclpy)."""
    global _NODE_CLASS
    if _NODE_CLASS is None:
        _NODE_CLASS = _make_node_class()
    return _NODE_CLASS


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of ``register_node``; returns the process exit code."""
    argv = list(sys.argv if args is None else args)
    own = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if "-h" in own or "--help" in own:
        print(usage())
        return 0
    if "--print-params" in own:
        print(params_yaml(), end="")
        return 0

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()

    def request_stop(signum: int, _frame: Any) -> None:
        stop.set()

    previous = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    node = None
    try:
        from cegc_ros.engine import CheckpointError
        try:
            node = node_class()()
        except (CheckpointError, ValueError, RuntimeError, OSError) as err:
            # One line, no traceback: the usual causes are a wrong path or parameter.
            msg = str(err).replace("\n", " ")
            print(f"[FATAL] [{NODE_NAME}]: cannot start: {type(err).__name__}: {msg}",
                  file=sys.stderr, flush=True)
            return 1
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except Exception as err:  # noqa: BLE001  e.g. a message that fails to deserialize
                with node._lock:
                    node.counts["take_errors"] += 1
                node._log("take_error", f"could not take a message: {type(err).__name__}: {err}")
        node.get_logger().info("shutting down")
        if not node.stop_worker():
            node.get_logger().warning("the registration in progress did not finish in time")
        executor.remove_node(node)
        return 0
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        for s, h in previous.items():
            signal.signal(s, h)


if __name__ == "__main__":
    sys.exit(main())
