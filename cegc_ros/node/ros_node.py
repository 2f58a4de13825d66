"""RegisterNode: the rclpy side of register_node (parameters, topics, diagnostics).

Everything that is not rclpy lives in sibling modules: the parameters' descriptions
(params.py), the mode that turns messages into jobs (pairs_mode.py), the worker thread
(worker.py) and the engine process (engine_process.py). The node's behaviour is a mixin
(:class:`RegistrationNodeMixin`) whose construction steps a managed (lifecycle) variant can
run from its transitions; :class:`RegisterNode` is the plain node that runs them at once.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
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
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from cegc_ros.node.engine_process import EngineProcess
from cegc_ros.node.pairs_mode import PairsMode
from cegc_ros.node.sequential_mode import SequentialMode
from cegc_ros.node.params import (
    ENGINE_SECTIONS,
    NODE_NAME,
    ParamSpec,
    build_sections,
    check_value,
    check_values,
    coerce,
    param_specs,
)
from cegc_ros.node.stats import NodeStats, Rejected, quality_values
from cegc_ros.node.support import Job, ThrottledLog
from cegc_ros.refine import UNCONSTRAINED_VARIANCE
from msg_adapters.markers import correspondence_markers
from msg_adapters.nav import time_to_ns
from msg_adapters.point_cloud2 import xyz_to_cloud
from msg_adapters.point_cloud2_cdr import CdrError, parse_point_cloud2
from msg_adapters.pose import pose_stamped, pose_with_covariance_stamped

_PTYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
           float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}

#: engine_factory(preprocess, engine) -> an engine (EngineProcess / InlineEngine), not started.
EngineFactory = Callable[[Any, Any], Any]


def pair_header(job: Job) -> Header:
    """The header of a pair's outputs in the target frame (pose, markers, ~/quality): the
    source cloud's stamp, the target cloud's frame."""
    return Header(stamp=job.source.header.stamp, frame_id=job.target.header.frame_id)


def descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """The ROS descriptor of a parameter: type, description, range, read-only."""
    d = ParameterDescriptor(name=spec.name, type=_PTYPES[spec.kind],
                            description=spec.description, read_only=not spec.dynamic)
    lo, hi = spec.range
    if spec.kind is float and (lo is not None or hi is not None):
        d.floating_point_range = [FloatingPointRange(
            from_value=float(-math.inf if lo is None else lo),
            to_value=float(math.inf if hi is None else hi), step=0.0)]
    elif spec.kind is int and (lo is not None or hi is not None):
        d.integer_range = [IntegerRange(from_value=int(-(2**63) if lo is None else lo),
                                        to_value=int(2**63 - 1 if hi is None else hi), step=0)]
    if spec.choices:
        d.additional_constraints = "one of: " + ", ".join(spec.choices)
    return d


class RegistrationNodeMixin:
    """The register_node behaviour for any rclpy Node class (plain or lifecycle).

    Construction steps, in order: :meth:`setup_parameters`, :meth:`start_engine`,
    :meth:`create_mode`, :meth:`create_outputs`, :meth:`create_inputs`, :meth:`start_worker`;
    :meth:`close` undoes the last two and the engine. :class:`RegisterNode` runs them all at once; a managed
    node can run them from its transitions (and override :meth:`create_outputs` to make
    lifecycle publishers).
    """

    # -- construction steps ---------------------------------------------------------------
    def setup_parameters(self) -> None:
        """Declare every parameter (after checking the overrides) and build ``self.cfg``."""
        self._specs = {s.name: s for s in param_specs()}
        overrides = self._parameter_overrides            # rclpy's: params files, -p, kwargs
        given = {name: p.value for name, p in overrides.items() if name in self._specs}
        values = check_values(given)                     # ParameterError naming each bad one
        for name, value in values.items():
            if type(value) is not type(given[name]):     # an integer for a float: store it as one
                overrides[name] = Parameter(name, value=value)
        for spec in self._specs.values():
            self.declare_parameter(spec.name, spec.default, descriptor(spec))
        # rclpy declares its own (use_sim_time, start_type_description_service): a params file
        # dumped from a running node names them, and they are not unknown.
        self.unknown_parameters = sorted(set(overrides) - set(self._parameters))
        if self.unknown_parameters:
            self.get_logger().warning("ignoring unknown parameters: "
                                      + ", ".join(self.unknown_parameters))
        self.cfg: dict[str, Any] = build_sections(
            {name: coerce(spec, self.get_parameter(name).value)
             for name, spec in self._specs.items()})
        self.stats = NodeStats(self.cfg["diagnostics"].window)
        self._log = ThrottledLog(self.get_logger().warning, self.cfg["diagnostics"].log_throttle)
        self.add_pre_set_parameters_callback(self._coerce_parameters)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

    def start_engine(self, engine_factory: EngineFactory | None = None) -> None:
        """Build and start the engine (checkpoint, warm-up); EngineStartError on failure."""
        factory = engine_factory or EngineProcess
        self.engine = factory(self.cfg["preprocess"], self.cfg["engine"])
        info = self.engine.start()
        if info.compiled_s:
            self.get_logger().info(f"engine.compile: network compiled in {info.compiled_s:.1f} s")
        if info.warm_up_error:
            self.get_logger().warning(f"warm-up registration failed: {info.warm_up_error}")

    def create_mode(self) -> None:
        """The mode ``input.mode`` names: pairs (PairsMode) or keyframe odometry
        (SequentialMode); it holds the state that outlives a managed node's deactivation."""
        if self.cfg["input"].mode == "sequential":
            self.mode: Any = SequentialMode(self.cfg["sequential"])
        else:
            self.mode = PairsMode(self.cfg["sync"])

    def create_outputs(self) -> None:
        self.pub_pose = self.create_publisher(PoseStamped, "~/pose", 10)
        self.pub_pose_cov = self.create_publisher(PoseWithCovarianceStamped,
                                                  "~/pose_with_covariance", 10)
        self.pub_src_overlap = self.create_publisher(PointCloud2, "~/source_overlap", 5)
        self.pub_tgt_overlap = self.create_publisher(PointCloud2, "~/target_overlap", 5)
        self.pub_markers = self.create_publisher(MarkerArray, "~/markers", 5)
        self.pub_quality = self.create_publisher(DiagnosticArray, "~/quality", 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._diag_prev = (0, 0)
        self.diag_timer = self.create_timer(self.cfg["diagnostics"].period,
                                            self.publish_diagnostics)
        self.mode.create_outputs(self)

    def create_inputs(self) -> None:
        """The subscriptions of the mode (one per input of the mode).

        They take the serialized bytes (``raw=True``): rclpy building a Python message of a
        5M-point cloud costs the executor ~200 ms, most of it holding the GIL. The executor
        reads only the header and the layout (:meth:`on_serialized_cloud`); the points stay
        in the bytes until the worker converts them.
        """
        inp = self.cfg["input"]
        reliability = (ReliabilityPolicy.RELIABLE if inp.reliable
                       else qos_profile_sensor_data.reliability)
        self.input_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=inp.queue_depth,
                                    reliability=reliability,
                                    durability=qos_profile_sensor_data.durability)
        self.inputs = [self.create_subscription(
            PointCloud2, topic, lambda data, side=side: self.on_serialized_cloud(side, data),
            self.input_qos, raw=True) for side, topic in self.mode.inputs.items()]
        self.create_controls()

    def create_controls(self) -> None:
        """``~/reset`` (std_srvs/srv/Trigger, both modes) and, in sequential mode, the
        ``initialpose`` input (geometry_msgs/PoseWithCovarianceStamped, relative: RViz's
        "2D Pose Estimate" publishes /initialpose). They live and go with the inputs."""
        from std_srvs.srv import Trigger

        self.controls: list[Any] = [self.create_service(Trigger, "~/reset", self.on_reset)]
        if self.mode.name == "sequential":
            self.controls.append(self.create_subscription(
                PoseWithCovarianceStamped, "initialpose", self.on_initial_pose, 10))

    def on_reset(self, request: Any, response: Any) -> Any:
        """Pairs mode: forget the clouds waiting for a partner. Sequential mode: forget the
        odometry, its keyframes and path (the next cloud starts a new frame at the identity).
        Both: the job waiting for the worker is dropped."""
        waiting = self.worker.clear_pending()
        if self.mode.name == "pairs":
            self.mode.reset()                       # executor-side state
            what = "pairing state cleared"
        else:
            self.worker.defer(self.mode.reset)      # worker-side state
            what = "odometry, keyframes and path cleared; the next cloud starts a new frame"
        self.stats.add("resets")
        response.success = True
        response.message = (f"{self.mode.name} mode reset: {what}"
                            + ("; the waiting cloud was dropped" if waiting else ""))
        self.get_logger().info(response.message)
        return response

    def on_initial_pose(self, msg: Any) -> None:
        """Sequential mode: the next cloud starts a new odometry frame at this pose (the pose
        of the cloud in ``output.odom_frame``); a pose in another frame is counted, logged and
        ignored."""
        from msg_adapters.pose import pose_to_matrix

        odom = self.cfg["output"].odom_frame
        if msg.header.frame_id not in (odom, ""):
            self.stats.add("initial_poses_ignored")
            self._log("initial_pose", f"initial pose in frame {msg.header.frame_id!r} ignored: "
                      f"it must be in output.odom_frame {odom!r}")
            return
        try:
            T = pose_to_matrix(msg.pose.pose)
            C = np.asarray(msg.pose.covariance, np.float64).reshape(6, 6)
        except ValueError as err:
            self.stats.add("initial_poses_ignored")
            self._log("initial_pose", f"initial pose ignored: {err}")
            return
        self.worker.clear_pending()
        self.worker.defer(lambda: self.mode.reset(T, C))
        self.stats.add("initial_poses")
        self.get_logger().info(f"initial pose received: the next cloud starts a new odometry "
                               f"frame at x {T[0, 3]:.3f} y {T[1, 3]:.3f} z {T[2, 3]:.3f}")

    def start_worker(self) -> None:
        self.worker = self.mode.make_worker(self)
        self.worker.start()

    def close(self, timeout: float = 10.0) -> bool:
        """Stop the worker (waiting up to ``timeout`` s for the pair in progress) and the
        engine; True if the pair in progress finished."""
        finished = True
        worker = getattr(self, "worker", None)
        if worker is not None:
            finished = worker.stop(timeout)
        engine = getattr(self, "engine", None)
        if engine is not None:
            engine.close()
        if worker is not None and not finished:
            worker.stop(5.0)
        return finished

    # -- parameters -----------------------------------------------------------------------
    def _coerce_parameters(self, params: list[Parameter]) -> list[Parameter]:
        # ros2 param set sync.slop 1 sends an integer: store it as the double it stands for.
        out = []
        for p in params:
            spec = self._specs.get(p.name)
            value = coerce(spec, p.value) if spec is not None else p.value
            out.append(Parameter(p.name, value=value) if value is not p.value else p)
        return out

    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
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

    def _apply_parameters(self, params: list[Parameter]) -> None:
        # Runs on the executor thread after a successful set: the new config objects are
        # swapped in whole, so the worker always sees a consistent section.
        for p in params:
            spec = self._specs.get(p.name)
            if spec is None:
                continue
            cfg = dict(self.cfg)
            cfg[spec.section] = dataclasses.replace(cfg[spec.section],
                                                    **{spec.field: coerce(spec, p.value)})
            self.cfg = cfg
            worker = getattr(self, "worker", None)   # a managed node may have none yet
            if spec.section in ENGINE_SECTIONS and worker is not None:
                worker.engine_settings_changed()
            self.get_logger().info(f"parameter {p.name} = {p.value!r} (applies to the next pair)")
        if getattr(self, "mode", None) is not None:
            self.mode.configure(self.cfg["sync"])
        diag = self.cfg["diagnostics"]
        self._log.period = diag.log_throttle
        self.stats.set_window(diag.window)

    # -- inputs (executor thread) ---------------------------------------------------------
    def on_serialized_cloud(self, side: str, data: bytes) -> None:
        """One cloud as its CDR bytes: header and layout read (a few hundred bytes, whatever
        the size of the cloud), the points left in ``data`` as a view; then :meth:`on_cloud`.
        Bytes that are not a PointCloud2 are a take error, as when rclpy could not
        deserialize a message."""
        try:
            cloud = parse_point_cloud2(data)
        except CdrError as err:
            self.take_error(err)
            return
        stamp = cloud.header.stamp
        cloud.header = Header(stamp=Time(sec=stamp.sec, nanosec=stamp.nanosec),
                              frame_id=cloud.header.frame_id)   # the outputs' header type
        self.on_cloud(side, cloud)

    def on_cloud(self, side: str, msg: Any) -> None:
        """One cloud (a PointCloud2 or a CdrPointCloud2): counted, paired, maybe a job."""
        now = time.monotonic()
        self.stats.add(f"messages_in.{side}")
        offer = self.mode.offer(side, time_to_ns(msg.header.stamp), msg, now)
        for unpaired_side, text in zip(offer.unpaired_sides, offer.unpaired):
            self.stats.add(f"unpaired.{unpaired_side}")
            self._log(f"unpaired.{unpaired_side}", text)
        if offer.job is not None:
            self.worker.submit(offer.job)

    def take_error(self, err: Exception) -> None:
        """A message that could not be taken (input bytes that are not a PointCloud2, an error
        from rclpy's take): counted, logged."""
        self.stats.add("take_errors")
        self._log("take_error", f"could not take a message: {type(err).__name__}: {err}")

    # -- outputs (worker thread) ----------------------------------------------------------
    def publish_result(self, job: Job, result: Any) -> None:
        """Pose, pose with covariance, then the overlap clouds and markers of one result."""
        src, tgt = job.source, job.target
        tgt_header = pair_header(job)
        try:
            pose = pose_stamped(result.T_target_source, tgt_header)
        except ValueError as err:
            raise Rejected("invalid_result", f"engine result unusable: {err}") from err
        try:
            pose_cov = pose_with_covariance_stamped(result.T_target_source, result.covariance,
                                                    tgt_header)
        except ValueError as err:
            # The pose is sound; only its uncertainty is not: publish it as undetermined
            # (every direction UNCONSTRAINED_VARIANCE, which fusion ignores) and count it.
            self.stats.add("covariance_fallbacks")
            self._log("covariance_fallback", f"pose published with the undetermined covariance "
                      f"(diagonal {UNCONSTRAINED_VARIANCE:g}): {err}")
            pose_cov = pose_with_covariance_stamped(
                result.T_target_source, np.diag([UNCONSTRAINED_VARIANCE] * 6), tgt_header)
        self.pub_pose.publish(pose)
        self.stats.pose_out(time.monotonic() - job.received)
        self.pub_pose_cov.publish(pose_cov)
        try:
            self._publish_extras(result, src, tgt, tgt_header)
        except ValueError as err:  # the pose is out; a visual output could not be built
            self.stats.add("output_errors")
            self._log("output_error", f"overlap clouds / markers not published: {err}")

    def publish_quality(self, header: Header, values: dict[str, str],
                        rejected: Rejected | None) -> None:
        """One ``~/quality`` message (both modes), with the ``header`` of the pose it is about
        (published or not): one status named as the node's /diagnostics one, OK with "pose
        published" or WARN with the rejection's line, and the mode's key-``values``. A SLAM
        back-end gates a loop closure (or watches the odometry) on it by stamp; every finished
        job gets one, rejected or not."""
        status = DiagnosticStatus(name=self.status_name, hardware_id=self.engine.info.device)
        status.level = DiagnosticStatus.OK if rejected is None else DiagnosticStatus.WARN
        status.message = "pose published" if rejected is None else f"{rejected.reason}: {rejected}"
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        self.pub_quality.publish(DiagnosticArray(header=header, status=[status]))

    def report_pair(self, job: Job, result: Any, rejected: Rejected | None) -> None:
        """The pairs mode's worker ``report``: ``~/quality`` of one finished pair, stamped and
        framed as its pose (:func:`pair_header`), :func:`~cegc_ros.node.stats.quality_values`."""
        self.publish_quality(pair_header(job), quality_values(result, rejected), rejected)

    def _publish_extras(self, result: Any, src: Any, tgt: Any, tgt_header: Any) -> None:
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

    # -- diagnostics ----------------------------------------------------------------------
    @property
    def status_name(self) -> str:
        """The name of this node's /diagnostics status: '<fully qualified name>: registration'."""
        return f"{self.get_fully_qualified_name()}: registration"

    def diagnostics_values(self) -> dict[str, str]:
        """The /diagnostics key-values (also handy for tests)."""
        info = self.engine.info
        return self.stats.values({"mode": self.mode.name, "device": info.device,
                                  "checkpoint": info.checkpoint,
                                  "engine_pid": info.pid if info.pid is not None else "inline",
                                  **self.mode.diagnostics(self.stats)})

    def publish_diagnostics(self) -> None:
        values = self.diagnostics_values()
        rejected, dropped = int(values["pairs_rejected"]), int(values["pairs_dropped"])
        prev, self._diag_prev = self._diag_prev, (rejected, dropped)
        status = DiagnosticStatus(name=self.status_name, hardware_id=values["device"])
        new_rej, new_drop = rejected - prev[0], dropped - prev[1]
        if new_rej or new_drop:
            status.level = DiagnosticStatus.WARN
            status.message = f"{new_rej} pairs rejected, {new_drop} dropped since the last report"
        else:
            status.level = DiagnosticStatus.OK
            status.message = (f"{values['pairs_out']} poses published"
                              if int(values["pairs_in"]) else "waiting for cloud pairs")
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)


class RegisterNode(RegistrationNodeMixin, Node):
    """Pairs the two cloud topics, runs the engine in its own process, publishes results.

    Args:
        engine_factory: builds the engine from (preprocess, engine) settings; the default is
            :class:`EngineProcess` with the real Registrar. Tests pass stand-ins.
        node_name: the node's name (``register_node``).
        **node_kwargs: passed to rclpy's Node (``parameter_overrides``, ``context``, ...).

    Raises:
        cegc_ros.node.params.ParameterError: a parameter value is unacceptable.
        cegc_ros.node.engine_process.EngineStartError: the engine did not start.
    """

    def __init__(self, engine_factory: EngineFactory | None = None,
                 node_name: str = NODE_NAME, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self.setup_parameters()
        self.start_engine(engine_factory)
        try:
            self.create_mode()
            self.create_outputs()
            self.create_inputs()
            self.start_worker()
        except BaseException:
            self.engine.close()
            raise
        inp, sync = self.cfg["input"], self.cfg["sync"]
        info = self.engine.info
        inputs = (f"pairs of source_cloud and target_cloud within slop {sync.slop} s"
                  if self.mode.name == "pairs" else "keyframe odometry of cloud")
        self.get_logger().info(
            f"ready ({self.mode.name} mode): device {info.device}, checkpoint {info.checkpoint}, "
            f"engine process {info.pid}, input QoS "
            f"{'reliable' if inp.reliable else 'sensor-data (best effort)'}, {inputs}")

    def destroy_node(self) -> None:
        self.close()
        super().destroy_node()
