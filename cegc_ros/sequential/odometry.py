"""Keyframe odometry: one stream of clouds in, the pose of each cloud in the first one's frame out.

ROS-free; the node holds one :class:`KeyframeOdometry` and converts its :class:`FrameResult`
to messages. Each cloud fed is registered against the current keyframe (the first cloud is the
first keyframe):

1. predict: constant velocity from the last two accepted clouds, over the stamp gap (from
   rest after a global recovery);
2. track: point-to-plane ICP from the prediction on the voxelized clouds, with the prediction
   as a weak prior (:mod:`cegc_ros.sequential.icp`), accepted when its fitness reaches
   ``min_fitness``; when it does not, once more without the prior, from where it stopped;
3. recover (only when tracking is not accepted: fast motion, a kidnapped sensor): first the
   last accepted cloud, when newer, becomes the keyframe and tracking is tried against it (the
   freshest view shares the most with this one); then the injected global registration
   (``Registrar.register`` or any callable with its signature) against the keyframe, refused
   when its ``ambiguity`` is above ``max_ambiguity``, else refined and checked by the same ICP
   and fitness test. After a gap (dropped frames: more than
   ``gap_intervals`` frame intervals since the last accepted cloud) the constant-velocity
   guess is not trusted: global registration comes first, tracking only if it fails;
4. chain: ``T_odom_cloud = T_odom_keyframe @ T_keyframe_cloud``, covariance propagated along the
   keyframe chain (:func:`cegc_ros.sequential.se3.compose_covariance`);
5. keyframe: the cloud becomes the keyframe when fitness or overlap falls below
   ``keyframe_min_overlap`` or it moved more than ``keyframe_max_translation`` /
   ``keyframe_max_rotation`` from the keyframe.

Scale: every distance is derived from the first cloud (after construction or :meth:`reset`)
where its setting is 0, the default (:func:`derive_distances`): a voxel grid of
``voxel_ratio`` x the cloud's robust extent, the ICP correspondence distance 4 voxels, the
inlier distance 1 voxel, the keyframe translation 10 voxels. So the same defaults serve a room
seen by a depth camera (4 cm grid), an object on a turntable (3 mm) and a LiDAR in a hall
(1 m); a setting above 0 is used as given. :attr:`KeyframeOdometry.distances` says what is in
use.

A cloud that neither step 2 nor step 3 can register is rejected: counted, reported, and the
pose, velocity and path are left as they were (the keyframe may have moved on to the last
accepted cloud, itself registered), so the next cloud is tried against that keyframe.
Not thread-safe: feed it from one thread.
"""

from __future__ import annotations

import copy
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..bounding import robust_extent
from ..config import SequentialConfig
from ..geometry import box_corner, finite_cloud
from . import icp as icp_stage
from .se3 import compose_covariance, rotation_angle_deg, scale_motion

#: Fewest finite points, and voxels after the grid, a cloud needs.
MIN_POINTS = 16
#: Fitness gain that lets ICP without the prior replace an answer held to a global
#: registration (``KeyframeOdometry._refine``). Measured on room 3: a right release gained
#: 0.15 (the engine's answer 10 cm off), a wrong one (a 10 cm slide along a wall) 0.02.
PRIOR_RELEASE_FITNESS = 0.05

#: Derived distances (a setting at 0), in voxels of the derived or set grid: the tracking ICP's
#: correspondence distance (the Kinect-room defaults of earlier rounds: 0.2 m on their 5 cm grid),
#: the inlier distance (0.05 m) and the keyframe's translation (0.5 m).
ICP_DISTANCE_VOXELS = 4.0
INLIER_VOXELS = 1.0
KEYFRAME_TRANSLATION_VOXELS = 10.0

#: ``global_registration(source_xyz (N, 3), target_xyz (M, 3)) -> result`` with the fields of
#: :class:`cegc_ros.engine.RegistrationResult` that are read here: ``T_target_source`` (4, 4),
#: ``valid`` (bool), ``reason`` (str). It may raise ValueError for unusable clouds.
GlobalRegistration = Callable[[np.ndarray, np.ndarray], Any]


@dataclass(frozen=True)
class Distances:
    """The metre-valued settings in use: each ``sequential.*`` value, or its derived default
    where the setting is 0 (:func:`derive_distances`). extent: the robust extent (metres) of
    the cloud they were derived from."""

    voxel_size: float
    icp_max_distance: float
    inlier_distance: float
    keyframe_max_translation: float
    extent: float

    def describe(self) -> str:
        return (f"voxel {self.voxel_size:.4g} m, ICP distance {self.icp_max_distance:.4g} m, "
                f"inliers {self.inlier_distance:.4g} m, keyframe translation "
                f"{self.keyframe_max_translation:.4g} m (first cloud's extent {self.extent:.3g} m)")


def derive_distances(config: SequentialConfig, extent: float) -> Distances:
    """The distances for ``config``: a setting above 0 is used as given; at 0 it is derived from
    the voxel grid, itself ``voxel_ratio x extent`` when ``voxel_size`` is 0 (KISS-ICP derives
    its voxel from the range the same way). ``extent``: robust extent of the first cloud."""
    voxel = config.voxel_size if config.voxel_size > 0 else config.voxel_ratio * float(extent)
    if not voxel > 0:
        raise ValueError(f"the first cloud has no extent ({extent:g} m): no voxel grid can be "
                         f"derived; set sequential.voxel_size")

    def pick(value: float, voxels: float) -> float:
        return float(value) if value > 0 else voxels * voxel

    return Distances(float(voxel), pick(config.icp_max_distance, ICP_DISTANCE_VOXELS),
                     pick(config.inlier_distance, INLIER_VOXELS),
                     pick(config.keyframe_max_translation, KEYFRAME_TRANSLATION_VOXELS),
                     float(extent))


def in_range(points: np.ndarray, max_range: float) -> np.ndarray:
    """The points within ``max_range`` (metres) of the sensor, the frame's origin (all at 0)."""
    r = max_range
    return points if r <= 0 else points[(points.astype(np.float64) ** 2).sum(1) <= r * r]


def distances_for(config: SequentialConfig, cloud: np.ndarray) -> Distances:
    """The distances the odometry derives when ``cloud`` (N, 3) is its first: from the robust
    extent of its finite points within ``max_range`` (ValueError when none are left)."""
    points = finite_cloud("cloud", cloud, 1).astype(np.float32)      # as feed() takes it
    return derive_distances(config, robust_extent(in_range(points, config.max_range)))


@dataclass
class FrameResult:
    """What :meth:`KeyframeOdometry.feed` made of one cloud.

    accepted: the cloud was registered and the odometry advanced.
    method: "first" (the first cloud: the odometry frame), "icp" (tracked from the prediction),
        "global" (recovered by global registration) or "none" (rejected).
    T_odom_cloud: (4, 4) pose of the cloud in the odometry frame (the first cloud's), None when
        rejected; covariance: its (6, 6), ROS order x y z roll pitch yaw.
    T_keyframe_cloud: (4, 4) the cloud against the keyframe it was registered to (stamp
        ``keyframe_stamp_ns``); keyframe_covariance: its (6, 6). None when rejected.
    new_keyframe: the cloud is now the current keyframe.
    fitness, overlap: of the accepted (or last tried) registration, 0 when none ran.
    reason: why rejected, or why global registration or a new keyframe was needed ("" if none).
    registration: the global registration's own result when it ran (masked clouds, markers).
    timings: seconds: "prepare", "icp", "global" (when run), "total".
    """

    stamp_ns: int
    accepted: bool
    method: str
    T_odom_cloud: np.ndarray | None
    covariance: np.ndarray | None
    T_keyframe_cloud: np.ndarray | None
    keyframe_covariance: np.ndarray | None
    keyframe_stamp_ns: int
    new_keyframe: bool
    fitness: float = 0.0
    overlap: float = 0.0
    reason: str = ""
    registration: Any = None
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class OdometryStats:
    """Counters since construction or :meth:`KeyframeOdometry.reset` (for /diagnostics).

    frames: clouds fed with usable input; keyframes: keyframes taken (the first cloud is one);
    tracked: accepted by ICP from the prediction; recoveries: accepted by global registration;
    rejected: registered by neither (skipped); invalid: clouds refused as unusable input.
    """

    frames: int = 0
    keyframes: int = 0
    tracked: int = 0
    recoveries: int = 0
    rejected: int = 0
    invalid: int = 0


@dataclass
class Keyframe:
    """A registered cloud: the keyframe the next ones are registered against, or the last
    accepted cloud (which becomes the keyframe when tracking against the keyframe fails)."""

    stamp_ns: int
    T_odom_keyframe: np.ndarray          # (4, 4)
    covariance: np.ndarray               # (6, 6) of T_odom_keyframe
    cloud: np.ndarray                    # (N, 3) float32 finite raw points, for global registration
    prepared: icp_stage.PreparedCloud    # voxelized, for ICP


@dataclass
class _Registration:
    """One accepted-or-not attempt against the keyframe (internal)."""

    method: str
    icp: icp_stage.IcpResult | None
    registration: Any = None
    reason: str = ""


class KeyframeOdometry:
    """Keyframe odometry over one cloud stream; see the module docstring for the steps.

    Args:
        config: the ``sequential.*`` settings.
        global_registration: ``callable(source_xyz, target_xyz) -> RegistrationResult``, e.g.
            ``Registrar.from_checkpoint().register``; None disables recovery (a cloud ICP
            cannot track is rejected).
    """

    def __init__(self, config: SequentialConfig | None = None,
                 global_registration: GlobalRegistration | None = None) -> None:
        self.config = copy.deepcopy(config) if config is not None else SequentialConfig()
        self.global_registration = global_registration
        self.reset()

    # ----------------------------------------------------------------------------------------
    # State
    # ----------------------------------------------------------------------------------------

    def reset(self, initial_pose: np.ndarray | None = None,
              initial_covariance: np.ndarray | None = None) -> None:
        """Forget everything: the next cloud starts a new odometry frame, at ``initial_pose``
        ((4, 4) T_odom_cloud, e.g. from a localization or RViz's initial pose) with
        ``initial_covariance`` ((6, 6)), or at the identity with zero covariance."""
        T0 = np.eye(4) if initial_pose is None else np.asarray(initial_pose, np.float64).copy()
        C0 = (np.zeros((6, 6)) if initial_covariance is None
              else np.asarray(initial_covariance, np.float64).copy())
        if T0.shape != (4, 4) or C0.shape != (6, 6) or not (np.isfinite(T0).all() and np.isfinite(C0).all()):
            raise ValueError("initial pose must be a finite (4, 4) and its covariance a finite (6, 6)")
        self._initial = (T0, C0)
        self.distances: Distances | None = None     # derived at the next first cloud
        self.stats = OdometryStats()
        self.keyframe: Keyframe | None = None
        self._last: Keyframe | None = None                               # last accepted cloud
        self._accepted: deque[tuple[int, np.ndarray]] = deque(maxlen=2)   # (stamp, T_odom_cloud)
        self._last_stamp: int | None = None
        self._intervals: deque[int] = deque(maxlen=16)     # stamp steps between usable clouds
        self._path: deque[tuple[int, np.ndarray]] = deque(maxlen=self.config.path_length)

    def warm_start(self) -> float:
        """Prepare and track a tiny synthetic cloud (three faces of a box corner, 900 points)
        without touching the odometry's state: Open3D and SciPy get imported and set up, so
        that the first real cloud does not pay for it (the real LiDAR pair's first cloud: 0.59 s
        cold, most of it those imports, against 0.03-0.06 s for the clouds after it;
        docs/sequential.md). The node calls it at start-up. Returns the seconds spent."""
        t0 = time.perf_counter()
        corner = box_corner(300)
        robust_extent(corner)
        prepared = icp_stage.prepare_cloud(corner, 0.05)
        icp_stage.icp(prepared, prepared, np.eye(4), 0.2, 0.1, max_iterations=2)
        return time.perf_counter() - t0

    def update(self, config: SequentialConfig) -> None:
        """New settings, from the next cloud on; the keyframe and the path are kept."""
        old = self.config
        self.config = copy.deepcopy(config)
        if config.path_length != old.path_length:
            self._path = deque(self._path, maxlen=config.path_length)
        if self.distances is None:
            return
        before = self.distances
        self.distances = derive_distances(config, before.extent)
        if (self.distances.voxel_size, config.max_range) != (before.voxel_size, old.max_range):
            for cloud in {id(c): c for c in (self.keyframe, self._last) if c}.values():
                cloud.prepared = icp_stage.prepare_cloud(self._in_range(cloud.cloud),
                                                         self.distances.voxel_size)

    @property
    def pose(self) -> np.ndarray | None:
        """(4, 4) T_odom_cloud of the last accepted cloud, None before the first."""
        return self._accepted[-1][1].copy() if self._accepted else None

    @property
    def path(self) -> list[tuple[int, np.ndarray]]:
        """(stamp_ns, T_odom_cloud (4, 4)) of the accepted clouds, oldest first; at most
        ``path_length``."""
        return [(s, T.copy()) for s, T in self._path]

    # ----------------------------------------------------------------------------------------
    # One cloud
    # ----------------------------------------------------------------------------------------

    def feed(self, stamp_ns: int, cloud: np.ndarray) -> FrameResult:
        """Register one cloud (N, 3) metres, stamped ``stamp_ns``, into the odometry.

        Raises:
            ValueError: unusable input (shape, fewer than MIN_POINTS finite points or voxels, a
                stamp not after the previous cloud's); counted in ``stats.invalid``, state kept.
        """
        t0 = time.perf_counter()
        cfg = self.config
        try:
            stamp_ns = int(stamp_ns)
            if self._last_stamp is not None and stamp_ns <= self._last_stamp:
                raise ValueError(f"cloud stamp {stamp_ns} ns is not after the previous cloud's "
                                 f"({self._last_stamp} ns); reset() to start over")
            points = finite_cloud("cloud", cloud, MIN_POINTS).astype(np.float32)
            near = self._in_range(points)
            if len(near) < MIN_POINTS:
                raise ValueError(f"cloud has {len(near)} points within sequential.max_range "
                                 f"{cfg.max_range:g} m, at least {MIN_POINTS} are needed")
            distances = self.distances or derive_distances(cfg, robust_extent(near))
            prepared = icp_stage.prepare_cloud(near, distances.voxel_size)
            if len(prepared) < MIN_POINTS:
                raise ValueError(f"cloud has {len(prepared)} voxels of "
                                 f"{distances.voxel_size:.4g} m, at least {MIN_POINTS} are "
                                 f"needed")
        except ValueError:
            self.stats.invalid += 1
            raise
        timings = {"prepare": time.perf_counter() - t0}
        gap = self._gap(stamp_ns)
        if self._last_stamp is not None:
            self._intervals.append(stamp_ns - self._last_stamp)
        self._last_stamp = stamp_ns
        self.stats.frames += 1

        if self.keyframe is None:
            self.distances = distances
            T0, cov0 = (a.copy() for a in self._initial)
            self._advance(Keyframe(stamp_ns, T0, cov0, points, prepared))
            self._take_keyframe()
            timings["total"] = time.perf_counter() - t0
            return FrameResult(stamp_ns, True, "first", T0.copy(), cov0.copy(), np.eye(4),
                               np.zeros((6, 6)), stamp_ns, True, 1.0, 1.0, "first cloud",
                               timings=timings)

        attempt = self._register(stamp_ns, points, prepared, gap, timings)
        kf = self.keyframe                      # the one registered against (maybe promoted)
        assert kf is not None
        if attempt.method == "none":
            self.stats.rejected += 1
            timings["total"] = time.perf_counter() - t0
            fit = attempt.icp.fitness if attempt.icp is not None else 0.0
            ovl = attempt.icp.overlap if attempt.icp is not None else 0.0
            return FrameResult(stamp_ns, False, "none", None, None, None, None, kf.stamp_ns,
                               False, fit, ovl, attempt.reason, attempt.registration, timings)

        res = attempt.icp
        assert res is not None                  # accepted attempts always carry their ICP
        if attempt.method == "icp":
            self.stats.tracked += 1
        else:
            self.stats.recoveries += 1
        T_kf_cloud = res.T_target_source
        T_odom_cloud = kf.T_odom_keyframe @ T_kf_cloud
        cov = compose_covariance(kf.T_odom_keyframe, kf.covariance, T_kf_cloud, res.covariance)
        why_keyframe = self._keyframe_reason(res)
        if attempt.method == "global":
            # A recovery follows a gap or a jump: the motion across it says nothing about the
            # velocity now, so the next prediction starts from rest.
            self._accepted.clear()
        self._advance(Keyframe(stamp_ns, T_odom_cloud, cov, points, prepared))
        if why_keyframe:
            self._take_keyframe()
        timings["total"] = time.perf_counter() - t0
        reason = "; ".join(r for r in (attempt.reason, why_keyframe) if r)
        return FrameResult(stamp_ns, True, attempt.method, T_odom_cloud, cov, T_kf_cloud.copy(),
                           res.covariance, kf.stamp_ns, bool(why_keyframe), res.fitness,
                           res.overlap, reason, attempt.registration, timings)

    # ----------------------------------------------------------------------------------------
    # Stages
    # ----------------------------------------------------------------------------------------

    def predict(self, stamp_ns: int) -> np.ndarray:
        """(4, 4) T_odom_cloud expected at ``stamp_ns``: the last accepted pose moved on at the
        velocity between the last two accepted clouds (no motion with fewer than two)."""
        if not self._accepted:
            return np.eye(4)
        s1, T1 = self._accepted[-1]
        if len(self._accepted) < 2:
            return T1.copy()
        s0, T0 = self._accepted[0]
        ratio = (stamp_ns - s1) / max(s1 - s0, 1)
        return T1 @ scale_motion(np.linalg.inv(T0) @ T1, ratio)

    def _gap(self, stamp_ns: int) -> str:
        """Why ``stamp_ns`` comes after a gap ("" when it does not): more than ``gap_intervals``
        frame intervals (the median of the recent ones) since the last accepted cloud."""
        factor = self.config.gap_intervals
        if factor <= 0 or self._last is None or not self._intervals:
            return ""
        interval = float(np.median(self._intervals))
        since = stamp_ns - self._last.stamp_ns
        if since <= factor * interval:
            return ""
        return (f"gap of {since / 1e9:.2f} s since the last registered cloud "
                f"(> {factor:g} x {interval / 1e9:.3f} s)")

    def _register(self, stamp_ns: int, points: np.ndarray, prepared: icp_stage.PreparedCloud,
                  gap: str, timings: dict[str, float]) -> _Registration:
        """Track from the prediction, then (tracking failed) against the last accepted cloud
        made the keyframe, then recover globally; after a gap, global registration first."""
        cfg = self.config
        notes: list[str] = []
        if gap and self.global_registration is not None:
            notes.append(gap)
            self._promote(notes)
            found = self._recover(points, prepared, notes, timings)
            if found.method != "none":
                return found
        t0 = time.perf_counter()
        tracked = self._track(stamp_ns, prepared)
        if tracked.fitness < cfg.min_fitness and self._last is not self.keyframe:
            notes.append(f"tracking fitness {tracked.fitness:.2f} < {cfg.min_fitness:.2f}")
            self._promote(notes)
            tracked = self._track(stamp_ns, prepared)
        timings["icp"] = time.perf_counter() - t0
        if tracked.fitness >= cfg.min_fitness:
            return _Registration("icp", tracked, reason="; ".join(notes))
        notes.append(f"tracking fitness {tracked.fitness:.2f} < {cfg.min_fitness:.2f}")
        if gap and self.global_registration is not None:     # global already tried, first
            return _Registration("none", tracked, reason="; ".join(notes))
        return self._recover(points, prepared, notes, timings, tracked)

    def _promote(self, notes: list[str]) -> None:
        """The last accepted cloud, when newer than the keyframe, becomes the keyframe: the
        freshest registered view shares the most with the next cloud (a gap, a fast turn)."""
        if self._last is not self.keyframe:
            self._take_keyframe()
            notes.append("the last registered cloud became the keyframe")

    def _recover(self, points: np.ndarray, prepared: icp_stage.PreparedCloud, notes: list[str],
                 timings: dict[str, float],
                 tracked: icp_stage.IcpResult | None = None) -> _Registration:
        """Global registration against the keyframe, refined and checked by ICP."""
        cfg, kf = self.config, self.keyframe
        assert kf is not None
        if self.global_registration is None:
            return _Registration("none", tracked,
                                 reason="; ".join([*notes, "no global registration"]))
        t1 = time.perf_counter()
        try:
            result = self.global_registration(points, kf.cloud)
        except ValueError as err:
            timings["global"] = time.perf_counter() - t1
            notes.append(f"global registration: {err}")
            return _Registration("none", tracked, reason="; ".join(notes))
        ambiguity = float(getattr(result, "ambiguity", 0.0))
        refusal = ""
        if not getattr(result, "valid", False):
            refusal = f"global registration invalid: {result.reason}"
        elif ambiguity > cfg.max_ambiguity:
            refusal = (f"global registration ambiguous: {ambiguity:.2f} > "
                       f"sequential.max_ambiguity {cfg.max_ambiguity:.2f}")
        if refusal:
            timings["global"] = time.perf_counter() - t1
            notes.append(refusal)
            return _Registration("none", tracked, result, "; ".join(notes))
        # The engine's answer anchors the ICP as the prediction does when tracking: directions
        # the geometry leaves free keep the engine's (feature-based) value instead of sliding
        # (measured: a 10 cm slide after a right answer); a clearly better fit releases it.
        recovered = self._refine(prepared, np.asarray(result.T_target_source, np.float64),
                                 release=True)
        timings["global"] = time.perf_counter() - t1
        if recovered.fitness >= cfg.min_fitness:
            return _Registration("global", recovered, result, "; ".join(notes))
        notes.append(f"global fitness {recovered.fitness:.2f} < {cfg.min_fitness:.2f}")
        return _Registration("none", recovered, result, "; ".join(notes))

    def _track(self, stamp_ns: int, prepared: icp_stage.PreparedCloud) -> icp_stage.IcpResult:
        """ICP against the keyframe from the constant-velocity prediction."""
        kf = self.keyframe
        assert kf is not None
        return self._refine(prepared, np.linalg.inv(kf.T_odom_keyframe) @ self.predict(stamp_ns))

    def _refine(self, prepared: icp_stage.PreparedCloud, T_guess: np.ndarray,
                release: bool = False) -> icp_stage.IcpResult:
        """ICP against the keyframe from ``T_guess``, held to it by ``icp_prior``.

        ICP without the prior then continues from that answer when the held one fails the
        fitness test (the guess was off along a direction the data do constrain, if weakly),
        or, with ``release`` (the guess is a global registration, good to the engine's
        accuracy, not a motion prediction), when it puts :data:`PRIOR_RELEASE_FITNESS` more
        of the cloud on the keyframe. Tracking does not release on a gain alone: on a view of
        a wall and the floor, a slide along both gained more than that (docs/sequential.md).
        """
        held = self._icp(prepared, T_guess)
        if self.config.icp_prior <= 0:
            return held
        if held.fitness >= self.config.min_fitness and not release:
            return held
        free = self._icp(prepared, held.T_target_source, prior=0.0)
        if held.fitness < self.config.min_fitness:
            return free
        return free if free.fitness >= held.fitness + PRIOR_RELEASE_FITNESS else held

    def _in_range(self, points: np.ndarray) -> np.ndarray:
        return in_range(points, self.config.max_range)

    def _icp(self, prepared: icp_stage.PreparedCloud, T_guess: np.ndarray,
             prior: float | None = None) -> icp_stage.IcpResult:
        cfg, kf, d = self.config, self.keyframe, self.distances
        assert kf is not None and d is not None
        return icp_stage.icp(prepared, kf.prepared, T_guess, d.icp_max_distance,
                             d.inlier_distance, cfg.icp_max_iterations,
                             cfg.icp_prior if prior is None else prior)

    def _keyframe_reason(self, res: icp_stage.IcpResult) -> str:
        """Why the registered cloud should become the keyframe ("" when it should not)."""
        cfg, d = self.config, self.distances
        assert d is not None
        T = res.T_target_source
        dist, angle = float(np.linalg.norm(T[:3, 3])), rotation_angle_deg(T)
        if res.fitness < cfg.keyframe_min_overlap:
            return f"keyframe: fitness {res.fitness:.2f} < {cfg.keyframe_min_overlap:.2f}"
        if res.overlap < cfg.keyframe_min_overlap:
            return f"keyframe: overlap {res.overlap:.2f} < {cfg.keyframe_min_overlap:.2f}"
        if dist > d.keyframe_max_translation:
            return (f"keyframe: moved {dist:.3g} m > {d.keyframe_max_translation:.3g} m")
        if angle > cfg.keyframe_max_rotation:
            return f"keyframe: turned {angle:.1f} deg > {cfg.keyframe_max_rotation:.1f} deg"
        return ""

    def _take_keyframe(self) -> None:
        """The last accepted cloud becomes the keyframe."""
        self.keyframe = self._last
        self.stats.keyframes += 1

    def _advance(self, cloud: Keyframe) -> None:
        """Record an accepted cloud: last cloud, velocity history, path."""
        self._last = cloud
        self._accepted.append((cloud.stamp_ns, cloud.T_odom_keyframe.copy()))
        self._path.append((cloud.stamp_ns, cloud.T_odom_keyframe.copy()))
