"""Sequential mode: one cloud stream, keyframe odometry, ~/odometry, ~/path and /tf.

With ``input.mode: sequential`` the node reads the one topic ``cloud`` and feeds each
cloud to :class:`cegc_ros.sequential.KeyframeOdometry` (tracking ICP against the current
keyframe; CEGC global registration when tracking fails or after a gap). Where things run:

* the odometry (voxel grid, tracking ICP, keyframe checks) runs on the node's worker thread
  (:class:`OdometryWorker`), on clouds voxelized to ``sequential.voxel_size``;
* its global registration is the engine the pairs mode uses, in the engine process
  (:mod:`cegc_ros.node.engine_process`): the network and its ICP on raw clouds never hold the
  node's GIL. A failed engine call (an error, a crash: restarted) is a rejected registration,
  so the cloud is skipped and the odometry is unchanged.

The mode object holds the odometry, so its state (keyframe, path, velocity) outlives a managed
node's deactivate/activate; cleanup drops the mode.

Outputs per accepted cloud (all stamped with the cloud's stamp):
``~/odometry`` (nav_msgs/Odometry: ``output.odom_frame`` -> the cloud's frame, covariance
chained along the keyframes), ``~/path`` (nav_msgs/Path, the last ``sequential.path_length``
poses), ``~/pose`` / ``~/pose_with_covariance`` (the cloud against its keyframe, in the cloud's
frame, as in pairs mode), ``~/source_overlap`` / ``~/target_overlap`` / ``~/markers`` when the
global registration ran, and ``/tf`` where tf2_msgs is installed and ``sequential.publish_tf``.
Per processed cloud, accepted or rejected: ``~/quality`` (diagnostic_msgs/DiagnosticArray,
stamped and framed as ``~/pose``: published or why not, how the cloud was registered, fitness,
keyframe, the global registration's ambiguity: :func:`cegc_ros.node.stats.odometry_quality_values`).
"""

from __future__ import annotations

import time
import types
from collections import deque
from typing import Any

import numpy as np

from cegc_ros.config import SequentialConfig, SyncConfig
from cegc_ros.node.engine_process import EngineDied, EngineError
from cegc_ros.node.stats import Rejected, odometry_quality_values
from cegc_ros.node.support import Job, Offer, percentiles_ms
from cegc_ros.node.worker import RegistrationWorker
from cegc_ros.sequential import KeyframeOdometry
from msg_adapters.nav import time_to_ns

#: Why a cloud gave no odometry in this mode, beyond the pairs mode's reasons (rejected.*).
SEQUENTIAL_REJECT_REASONS = (
    "unusable_cloud",    # the odometry refused it: too few voxels, a stamp not after the last
    "not_registered",    # neither tracking nor global registration passed sequential.min_fitness
)


def cloud_header(job: Job) -> Any:
    """The header of a cloud's outputs in its own frame (``~/pose``, ``~/quality``): the cloud's
    stamp and frame."""
    from std_msgs.msg import Header

    return Header(stamp=job.source.header.stamp, frame_id=job.source.header.frame_id)


class SequentialMode:
    """One ``cloud`` input registered against keyframes into odometry.

    Args:
        config: the ``sequential.*`` settings the odometry starts with.
    """

    name = "sequential"
    inputs = {"cloud": "cloud"}

    def __init__(self, config: SequentialConfig) -> None:
        self.odometry = KeyframeOdometry(config)        # global registration: set by the worker
        self.odometry.warm_start()      # imports at start-up, not on the first cloud
        self._frame_times: deque[float] = deque(maxlen=200)
        self._poses: deque[Any] = deque(maxlen=config.path_length)   # PoseStamped of ~/path
        self.tf_class: Any = None

    # -- the mode protocol (see pairs_mode.py) --------------------------------------------
    def configure(self, sync: SyncConfig) -> None:
        """Nothing to pair; sequential.* reaches the odometry with the next cloud."""

    def offer(self, side: str, stamp_ns: int, msg: Any, now: float) -> Offer:
        """Every cloud is a job (against the keyframe, which the odometry holds)."""
        return Offer(job=Job(msg, None, now))

    def on_result(self, job: Job, result: Any) -> None:
        """The odometry has already taken the cloud."""

    def reset(self, initial_pose: Any = None, initial_covariance: Any = None) -> None:
        """Forget the odometry (keyframes, path, the last stamp): the next cloud starts a new
        odometry frame, at ``initial_pose`` (4, 4) T_odom_cloud when given. Worker thread."""
        self.odometry.reset(initial_pose, initial_covariance)
        self._poses.clear()

    def create_outputs(self, node: Any) -> None:
        """~/odometry, ~/path and (where tf2_msgs is installed) /tf, beside the common ones."""
        from nav_msgs.msg import Odometry, Path

        from msg_adapters.transform import tf_message_class

        self.pub_odometry = node.create_publisher(Odometry, "~/odometry", 10)
        self.pub_path = node.create_publisher(Path, "~/path", 5)
        self.tf_class = tf_message_class() if node.cfg["sequential"].publish_tf else None
        self.pub_tf = (node.create_publisher(self.tf_class, "/tf", 100)
                       if self.tf_class is not None else None)

    def make_worker(self, node: Any) -> OdometryWorker:
        return OdometryWorker(self, node)

    def diagnostics(self, stats: Any) -> dict[str, str]:
        """Odometry key-values for /diagnostics."""
        s = self.odometry.stats
        values = {"keyframes": s.keyframes, "tracked": s.tracked, "recoveries": s.recoveries,
                  "frames_rejected": s.rejected, "frames_invalid": s.invalid,
                  "odometry_p50_ms": f"{percentiles_ms(list(self._frame_times), (50,))[0]:.1f}"}
        for reason in SEQUENTIAL_REJECT_REASONS:
            values[f"rejected.{reason}"] = stats.count(f"rejected.{reason}")
        for key in ("initial_poses", "initial_poses_ignored"):
            values[key] = stats.count(key)
        d = self.odometry.distances          # None until the first cloud after a start or reset
        for key in ("voxel_size", "icp_max_distance", "inlier_distance",
                    "keyframe_max_translation"):
            values[f"sequential.{key}"] = "-" if d is None else f"{getattr(d, key):.4g}"
        return {k: str(v) for k, v in values.items()}

    # -- outputs (worker thread) ----------------------------------------------------------
    def publish(self, node: Any, job: Job, frame: Any) -> None:
        """Odometry, path, TF, then the pose against the keyframe (and, after a global
        registration, the overlap clouds and markers) of one accepted cloud."""
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Path
        from std_msgs.msg import Header

        from msg_adapters.nav import odometry
        from msg_adapters.pose import matrix_to_pose, pose_stamped, pose_with_covariance_stamped
        from msg_adapters.transform import transform_stamped

        cfg: SequentialConfig = node.cfg["sequential"]
        msg = job.source
        frame_id = msg.header.frame_id
        odom_header = Header(stamp=msg.header.stamp, frame_id=node.cfg["output"].odom_frame)
        own_header = cloud_header(job)
        try:
            odom = odometry(frame.T_odom_cloud, frame.covariance, odom_header, frame_id)
            path_pose = PoseStamped(header=odom_header, pose=matrix_to_pose(frame.T_odom_cloud))
            pose = pose_stamped(frame.T_keyframe_cloud, own_header)
            pose_cov = pose_with_covariance_stamped(frame.T_keyframe_cloud,
                                                    frame.keyframe_covariance, own_header)
            tf = (transform_stamped(frame.T_odom_cloud, odom_header, frame_id)
                  if self.pub_tf is not None else None)
        except ValueError as err:
            raise Rejected("invalid_result", f"odometry result unusable: {err}") from err
        self.pub_odometry.publish(odom)
        node.stats.pose_out(time.monotonic() - job.received)
        if self._poses.maxlen != cfg.path_length:
            self._poses = deque(self._poses, maxlen=cfg.path_length)
        self._poses.append(path_pose)
        self.pub_path.publish(Path(header=odom_header, poses=list(self._poses)))
        if tf is not None:
            self.pub_tf.publish(self.tf_class(transforms=[tf]))
        node.pub_pose.publish(pose)
        node.pub_pose_cov.publish(pose_cov)
        reg = frame.registration
        if reg is not None and getattr(reg, "valid", False) and hasattr(reg, "weights"):
            try:   # the global registration's view: this cloud onto the keyframe (same frame)
                node._publish_extras(reg, msg, msg, own_header)
            except ValueError as err:
                node.stats.add("output_errors")
                node._log("output_error", f"overlap clouds / markers not published: {err}")

    def report(self, node: Any, job: Job, frame: Any, rejected: Rejected | None) -> None:
        """The worker's ``report``: ``~/quality`` of one processed cloud, accepted or not, stamped
        and framed as its ``~/pose`` (:func:`cloud_header`); ``frame``: the odometry's
        FrameResult, None when the cloud never reached the odometry."""
        node.publish_quality(cloud_header(job), odometry_quality_values(frame, rejected),
                             rejected)

    def frame_time(self, seconds: float) -> None:
        self._frame_times.append(seconds)


class OdometryWorker(RegistrationWorker):
    """The worker of the sequential mode: cloud -> points -> odometry -> publish.

    The mailbox, thread, counting and engine restarts are the pairs mode's
    (:class:`~cegc_ros.node.worker.RegistrationWorker`); only :meth:`process` differs.
    """

    def __init__(self, mode: SequentialMode, node: Any) -> None:
        super().__init__(node.engine, node.stats, node._log, settings=lambda: node.cfg,
                         publish=lambda job, frame: mode.publish(node, job, frame),
                         info=node.get_logger().info,
                         report=lambda job, frame, rej: mode.report(node, job, frame, rej))
        self.mode = mode
        self._engine_failure = ""
        self._sequential: SequentialConfig | None = None   # the settings last given to it
        mode.odometry.global_registration = self.global_registration

    def global_registration(self, source: np.ndarray, target: np.ndarray) -> Any:
        """The engine (process) registers ``source`` (N, 3) onto the keyframe ``target``
        (M, 3). Raises ValueError for input it refuses; any other failure is an invalid
        result, so the odometry skips the cloud and keeps its state."""
        update = None
        if self._engine_dirty:
            self._engine_dirty = False
            cfg = self._settings()
            update = (cfg["preprocess"], cfg["engine"])
        t0 = time.perf_counter()
        try:
            result = self.engine.register(source, target, update)
        except EngineDied as err:
            if not self._mailbox.closed:
                self._restart(err)
            self._engine_failure = str(err)
            return types.SimpleNamespace(valid=False, reason=f"engine: {err}")
        except EngineError as err:
            self._engine_failure = str(err)
            return types.SimpleNamespace(valid=False, reason=f"engine: {err}")
        self.stats.engine_time(time.perf_counter() - t0)
        return result

    def process(self, job: Job) -> Any:
        """One cloud: the odometry's FrameResult, published; raises Rejected with the reason it
        gives no odometry (and the frame, when the odometry took the cloud)."""
        cfg = self._settings()
        xyz = self.points("cloud", job.source, cfg["input"].max_points, cfg["preprocess"])
        odo = self.mode.odometry
        if cfg["sequential"] is not self._sequential:    # sections are replaced whole on change
            self._sequential = cfg["sequential"]
            odo.update(self._sequential)
        self._engine_failure = ""
        try:
            frame = odo.feed(time_to_ns(job.source.header.stamp), xyz)
        except ValueError as err:
            raise Rejected("unusable_cloud", f"cloud refused by the odometry: {err}") from err
        self.mode.frame_time(frame.timings.get("total", float("nan")))
        if frame.method == "first" and odo.distances is not None:
            self._info(f"odometry started at stamp {frame.stamp_ns} ns: "
                       f"{odo.distances.describe()}")
        if not frame.accepted:
            reason = "engine_error" if self._engine_failure else "not_registered"
            raise Rejected(reason, f"cloud not registered: {frame.reason}", frame)
        self.stats.last_fitness = float(frame.fitness)
        return self.deliver(job, frame)
