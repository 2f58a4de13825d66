"""Classical peers of the engine: ICP from identity, FGR, RANSAC and SC2-PCR on Open3D FPFH, and
RANSAC and SC2-PCR refined by the engine's own ICP (``ransac+icp``, ``sc2pcr+icp``: the fair
peers of ``cegc+icp``).

Same style as :class:`cegc_ros.engine.Registrar`: numpy clouds in (metres, own frames),
a small result out whose ``T_target_source`` maps source points into the target frame
(``p_t = R p_s + t``). Nothing here knows about ROS. This module reuses the engine's stages
(:mod:`cegc_ros.bounding`, :mod:`cegc_ros.estimator`, :mod:`cegc_ros.refine`); the engine never
imports it.

Every length is scaled to the data, so one setting serves unit-sized synthetic scenes and
metre-sized real fragments alike::

    extent = the larger of the two clouds' largest bounding-box sides
    voxel  = voxel_ratio * extent          (or voxel_size when > 0)
    normal radius = 2 * voxel (30 nn), FPFH radius = 5 * voxel (100 nn)
    RANSAC: distance 1.5 * voxel, 3-point samples, edge-length (0.9) and distance checkers,
            100k iterations / 0.999 confidence, mutual filter off (see BaselineConfig)
    FGR:    Open3D defaults (64 iterations, division factor 1.4, tuple scale 0.95, 1000
            tuples, tuple test on) with maximum correspondence distance 0.5 * voxel
    SC2-PCR: mutual nearest neighbours in FPFH space (all nearest neighbours when fewer than
            30 are mutual), at most 5000 (a seeded subsample; the 3DMatch setting), then
            cegc_ros.estimator.estimate_compatibility with uniform weights, inlier threshold
            2 * voxel (the paper: 0.10 m with 5 cm voxels) and its 3DMatch settings
    ICP:    point-to-plane from identity, distance icp_distance_ratio * extent, 50 iterations
    +icp:   the engine's refine stage at EngineConfig/PreprocessConfig defaults: the clouds
            bounded as the engine bounds them, then refine.icp (cegc_ros/refine.py)
    fitness = fraction of the voxelized source within 1.5 * voxel of the target after alignment

The defaults were chosen on the real SUN3D pairs and on the 7Scenes protocol applied to real
SUN3D fragments (see /work/notes/baselines_real.md for the sweep and its figures).

Determinism: Open3D runs on ``threads`` OpenMP threads (``open3d.utility.set_max_threads``),
except its RANSAC, which runs on ``ransac_threads`` (1): its threads draw from one shared seeded
generator in whatever order the scheduler gives them and stop early at different iterations,
so a multi-threaded RANSAC does not repeat (isl-org/Open3D#7475). RANSAC and FGR are seeded per
call; SC2-PCR's only random step is the seeded subsample. Every method therefore returns the
same transform for the same input, whatever the load and the thread count.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .geometry import finite_cloud

METHODS = ("icp", "fgr", "ransac", "ransac+icp", "sc2pcr", "sc2pcr+icp")


class BaselineError(RuntimeError):
    """A baseline could not run on its input (too few points, unknown method)."""


@dataclass
class BaselineConfig:
    """Settings of the Open3D baselines; lengths are fractions of the cloud extent or of the voxel."""

    voxel_ratio: float = 0.02       # voxel = ratio * extent (largest bbox side, larger cloud)
    voxel_size: float = 0.0         # absolute voxel in metres; overrides voxel_ratio when > 0
    normal_radius_factor: float = 2.0
    normal_max_nn: int = 30
    fpfh_radius_factor: float = 5.0
    fpfh_max_nn: int = 100
    ransac_distance_factor: float = 1.5
    ransac_max_iterations: int = 100_000
    ransac_confidence: float = 0.999
    ransac_mutual_filter: bool = False
    ransac_edge_length: float = 0.9
    ransac_threads: int = 1          # >1 makes RANSAC's result depend on thread scheduling
    fgr_distance_factor: float = 0.5
    fgr_iterations: int = 64
    fgr_division_factor: float = 1.4
    fgr_tuple_scale: float = 0.95
    fgr_max_tuples: int = 1000
    sc2pcr_inlier_factor: float = 2.0        # inlier threshold = factor * voxel
    sc2pcr_max_correspondences: int = 5000
    sc2pcr_min_mutual: int = 30              # fewer mutual matches: use every nearest neighbour
    icp_distance_ratio: float = 0.1  # of the extent: ICP starts from identity, so it needs reach
    icp_max_iterations: int = 50
    fitness_factor: float = 1.5      # fitness threshold = factor * voxel
    min_points: int = 16
    threads: int = 2
    seed: int = 0
    # Turn each cloud's normals to its frame's origin (its sensor), as the engine's
    # preprocess.normals 'sensor' does; False leaves Open3D's unoriented normals, as its
    # pipeline is usually run (docs/accuracy.md measures both)
    sensor_normals: bool = False

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class BaselineResult:
    """Outcome of one baseline registration."""

    T_target_source: np.ndarray      # (4, 4) float64, maps source points into the target frame
    valid: bool
    reason: str                      # why invalid, "" if valid
    fitness: float                   # in [0, 1], see module docstring
    method: str
    voxel_size: float                # metres actually used
    # seconds: "features", "registration", "total" (+ "refine" for the +icp rows)
    timings: dict[str, float] = field(default_factory=dict)


def load_open3d(threads: int = 2):
    """Import Open3D (heavy: on first use only), quiet its logging and pin its thread count."""
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    if threads > 0:
        o3d.utility.set_max_threads(int(threads))
    return o3d


@contextlib.contextmanager
def open3d_threads(o3d: Any, threads: int) -> Iterator[None]:
    """Run the block on ``threads`` Open3D threads, then restore the previous count."""
    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(int(threads))
    try:
        yield
    finally:
        o3d.utility.set_max_threads(before)


def scale_of(source_xyz: np.ndarray, target_xyz: np.ndarray) -> float:
    """Extent of a pair: the larger of the two clouds' largest bounding-box sides, (N, 3), (M, 3).

    Each cloud is measured in its own frame, so the extent does not depend on the unknown motion.
    """
    return float(max(np.max(c.max(axis=0) - c.min(axis=0)) for c in (source_xyz, target_xyz)))


def voxel_for(extent: float, config: BaselineConfig) -> float:
    """Voxel size for a pair of the given extent (see :func:`scale_of`)."""
    if config.voxel_size > 0:
        return float(config.voxel_size)
    if not extent > 0:
        raise ValueError("clouds have zero extent")
    return config.voxel_ratio * extent


class _Prepared:
    """Voxelized clouds with normals (and FPFH when asked) of one pair."""

    def __init__(self, o3d, source_xyz, target_xyz, config: BaselineConfig, fpfh: bool) -> None:
        self.extent = scale_of(source_xyz, target_xyz)   # of the clouds before the voxel grid
        self.voxel = voxel = voxel_for(self.extent, config)
        reg = o3d.pipelines.registration
        normal = o3d.geometry.KDTreeSearchParamHybrid(
            radius=config.normal_radius_factor * voxel, max_nn=config.normal_max_nn)
        feat = o3d.geometry.KDTreeSearchParamHybrid(
            radius=config.fpfh_radius_factor * voxel, max_nn=config.fpfh_max_nn)
        self.clouds = []
        self.features = []
        for xyz in (source_xyz, target_xyz):
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
            pc = pc.voxel_down_sample(voxel)
            pc.estimate_normals(normal)
            if config.sensor_normals:
                pc.orient_normals_towards_camera_location(np.zeros(3))
            self.clouds.append(pc)
            if fpfh:
                self.features.append(reg.compute_fpfh_feature(pc, feat))
        self.source, self.target = self.clouds
        for name, pc in (("source", self.source), ("target", self.target)):
            if len(pc.points) < config.min_points:
                raise ValueError(f"{name} cloud has {len(pc.points)} points after a {voxel:.4g} voxel "
                                 f"grid, need at least {config.min_points}")


def _finish(o3d, prep: _Prepared, T: np.ndarray, method: str, config: BaselineConfig,
            t0: float, t_feat: float) -> BaselineResult:
    T = np.asarray(T, dtype=np.float64).copy()
    t_reg = time.perf_counter()
    reason = ""
    fitness = 0.0
    if not np.all(np.isfinite(T)):
        reason = "non-finite transform"
    elif abs(np.linalg.det(T[:3, :3]) - 1.0) > 1e-3:
        reason = "transform is not a rotation"
    else:
        ev = o3d.pipelines.registration.evaluate_registration(
            prep.source, prep.target, config.fitness_factor * prep.voxel, T)
        fitness = float(ev.fitness)
        if fitness <= 0.0:
            reason = "no source point near the target after alignment"
    done = time.perf_counter()
    return BaselineResult(
        T_target_source=T, valid=not reason, reason=reason, fitness=fitness, method=method,
        voxel_size=prep.voxel,
        timings={"features": t_feat - t0, "registration": t_reg - t_feat, "total": done - t0},
    )


def _prepare(source_xyz: np.ndarray, target_xyz: np.ndarray, config: BaselineConfig | None,
             fpfh: bool) -> tuple[Any, BaselineConfig, _Prepared, float, float]:
    """Shared start of every baseline: validate, voxelize, normals (+ FPFH); returns
    (open3d, config, prepared pair, start time, time after features)."""
    config = config or BaselineConfig()
    o3d = load_open3d(config.threads)
    src = finite_cloud("source cloud", source_xyz, config.min_points)
    tgt = finite_cloud("target cloud", target_xyz, config.min_points)
    t0 = time.perf_counter()
    prep = _Prepared(o3d, src, tgt, config, fpfh=fpfh)
    return o3d, config, prep, t0, time.perf_counter()


def register_icp(source_xyz: np.ndarray, target_xyz: np.ndarray,
                 config: BaselineConfig | None = None) -> BaselineResult:
    """Open3D point-to-plane ICP started from the identity (source (N, 3), target (M, 3))."""
    o3d, config, prep, t0, t_feat = _prepare(source_xyz, target_xyz, config, fpfh=False)
    reg = o3d.pipelines.registration
    res = reg.registration_icp(
        prep.source, prep.target, config.icp_distance_ratio * prep.extent, np.eye(4),
        reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(max_iteration=config.icp_max_iterations))
    return _finish(o3d, prep, res.transformation, "icp", config, t0, t_feat)


def register_fgr(source_xyz: np.ndarray, target_xyz: np.ndarray,
                 config: BaselineConfig | None = None) -> BaselineResult:
    """Open3D Fast Global Registration on FPFH features (source (N, 3), target (M, 3))."""
    o3d, config, prep, t0, t_feat = _prepare(source_xyz, target_xyz, config, fpfh=True)
    reg = o3d.pipelines.registration
    option = reg.FastGlobalRegistrationOption(
        division_factor=config.fgr_division_factor,
        maximum_correspondence_distance=config.fgr_distance_factor * prep.voxel,
        iteration_number=config.fgr_iterations, tuple_scale=config.fgr_tuple_scale,
        maximum_tuple_count=config.fgr_max_tuples, tuple_test=True)
    o3d.utility.random.seed(config.seed)
    res = reg.registration_fgr_based_on_feature_matching(
        prep.source, prep.target, prep.features[0], prep.features[1], option)
    return _finish(o3d, prep, res.transformation, "fgr", config, t0, t_feat)


def register_ransac(source_xyz: np.ndarray, target_xyz: np.ndarray,
                    config: BaselineConfig | None = None) -> BaselineResult:
    """Open3D RANSAC on FPFH feature matches (source (N, 3), target (M, 3)): seeded and on
    ``ransac_threads`` threads (one by default, so that it repeats)."""
    o3d, config, prep, t0, t_feat = _prepare(source_xyz, target_xyz, config, fpfh=True)
    reg = o3d.pipelines.registration
    distance = config.ransac_distance_factor * prep.voxel
    with open3d_threads(o3d, config.ransac_threads):
        o3d.utility.random.seed(config.seed)
        res = reg.registration_ransac_based_on_feature_matching(
            prep.source, prep.target, prep.features[0], prep.features[1], config.ransac_mutual_filter,
            distance, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(config.ransac_edge_length),
             reg.CorrespondenceCheckerBasedOnDistance(distance)],
            reg.RANSACConvergenceCriteria(config.ransac_max_iterations, config.ransac_confidence))
    return _finish(o3d, prep, res.transformation, "ransac", config, t0, t_feat)


def fpfh_correspondences(desc_source: np.ndarray, desc_target: np.ndarray, max_correspondences: int,
                         min_mutual: int, rng: np.random.Generator) -> np.ndarray:
    """(N, D), (M, D) descriptors -> (K, 2) int64 (source, target) index pairs: the mutual
    nearest neighbours, or every source point's nearest neighbour when fewer than ``min_mutual``
    are mutual; at most ``max_correspondences`` (a seeded subsample), in source order."""
    from scipy.spatial import cKDTree
    _, st = cKDTree(desc_target).query(desc_source, k=1)                  # (N,) source -> target
    _, ts = cKDTree(desc_source).query(desc_target, k=1)                  # (M,) target -> source
    src = np.arange(len(desc_source))
    mutual = ts[st] == src
    keep = src[mutual] if mutual.sum() >= min_mutual else src
    if len(keep) > max_correspondences:
        keep = np.sort(rng.choice(keep, max_correspondences, replace=False))
    return np.stack([keep, st[keep]], axis=1).astype(np.int64)


def register_sc2pcr(source_xyz: np.ndarray, target_xyz: np.ndarray,
                    config: BaselineConfig | None = None) -> BaselineResult:
    """SC2-PCR (Chen et al., CVPR 2022) on Open3D FPFH matches (source (N, 3), target (M, 3)):
    the engine's compatibility estimator with uniform weights (cegc_ros/estimator.py)."""
    from .estimator import CompatibilityConfig, estimate_compatibility

    o3d, config, prep, t0, t_feat = _prepare(source_xyz, target_xyz, config, fpfh=True)
    desc = [np.asarray(f.data, np.float64).T for f in prep.features]     # (N, 33) each
    corr = fpfh_correspondences(desc[0], desc[1], config.sc2pcr_max_correspondences,
                                config.sc2pcr_min_mutual, np.random.default_rng(config.seed))
    src = np.asarray(prep.source.points)[corr[:, 0]]
    tgt = np.asarray(prep.target.points)[corr[:, 1]]
    est = estimate_compatibility(src, tgt, np.ones(len(corr)), config.sc2pcr_inlier_factor * prep.voxel,
                                 CompatibilityConfig())
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = est.R, est.t
    result = _finish(o3d, prep, T, "sc2pcr", config, t0, t_feat)
    if not est.valid:
        result.valid, result.reason = False, est.reason
    return result


def engine_icp(source_xyz: np.ndarray, target_xyz: np.ndarray, T: np.ndarray) -> np.ndarray:
    """The engine's refine stage at its defaults, started from T (4x4): both clouds bounded as
    the engine bounds them (PreprocessConfig), then refine.icp with EngineConfig's settings."""
    from . import bounding, refine
    from .config import EngineConfig, PreprocessConfig
    from .geometry import normalise_pair

    pre, eng = PreprocessConfig(), EngineConfig()
    bounded = bounding.bound_pair(source_xyz, target_xyz, pre, 3)
    _, _, norm = normalise_pair(bounded.source, bounded.target)
    return refine.icp(bounded.source, bounded.target, T, eng.icp_max_distance * norm.scale,
                      eng.icp_max_iterations, eng.icp_points, pre.seed)


def _then_engine_icp(first: BaselineResult, source_xyz: np.ndarray, target_xyz: np.ndarray,
                     config: BaselineConfig | None) -> BaselineResult:
    """``first`` refined by :func:`engine_icp`; fitness measured as for the other baselines."""
    from . import refine
    from .geometry import voxel_downsample

    method = f"{first.method}+icp"
    if not first.valid:
        return BaselineResult(first.T_target_source, False, first.reason, first.fitness, method,
                              first.voxel_size, dict(first.timings))
    t0 = time.perf_counter()
    T = engine_icp(source_xyz, target_xyz, first.T_target_source)
    timings = dict(first.timings)
    timings["refine"] = time.perf_counter() - t0
    timings["total"] = timings.get("total", 0.0) + timings["refine"]
    v = first.voxel_size
    src = voxel_downsample(finite_cloud("source cloud", source_xyz, 3), v).astype(np.float64)
    tgt = voxel_downsample(finite_cloud("target cloud", target_xyz, 3), v).astype(np.float64)
    fitness = refine.fitness(src, tgt, T, (config or BaselineConfig()).fitness_factor * v)
    return BaselineResult(T, True, "", fitness, method, v, timings)


def register_ransac_icp(source_xyz: np.ndarray, target_xyz: np.ndarray,
                        config: BaselineConfig | None = None) -> BaselineResult:
    """RANSAC on FPFH, then the engine's ICP (:func:`engine_icp`)."""
    return _then_engine_icp(register_ransac(source_xyz, target_xyz, config), source_xyz, target_xyz, config)


def register_sc2pcr_icp(source_xyz: np.ndarray, target_xyz: np.ndarray,
                        config: BaselineConfig | None = None) -> BaselineResult:
    """SC2-PCR on FPFH, then the engine's ICP (:func:`engine_icp`)."""
    return _then_engine_icp(register_sc2pcr(source_xyz, target_xyz, config), source_xyz, target_xyz, config)


_REGISTRY: dict[str, Callable[..., BaselineResult]] = {
    "icp": register_icp, "fgr": register_fgr, "ransac": register_ransac, "ransac+icp": register_ransac_icp,
    "sc2pcr": register_sc2pcr, "sc2pcr+icp": register_sc2pcr_icp}


def register(method: str, source_xyz: np.ndarray, target_xyz: np.ndarray,
             config: BaselineConfig | None = None) -> BaselineResult:
    """Run the baseline named ``method`` (one of :data:`METHODS`)."""
    try:
        fn = _REGISTRY[method]
    except KeyError:
        raise BaselineError(f"unknown baseline {method!r}; expected one of {', '.join(METHODS)}") from None
    return fn(source_xyz, target_xyz, config)


def describe(config: BaselineConfig | None = None) -> list[str]:
    """One line per baseline stating its settings (for reports)."""
    c = config or BaselineConfig()
    voxel = (f"voxel {c.voxel_size:g} m" if c.voxel_size > 0
             else f"voxel {c.voxel_ratio:g} x extent (largest bbox side)")
    feats = (f"{voxel}; normals r={c.normal_radius_factor:g}v/{c.normal_max_nn}nn"
             f"{' turned to the frame origin' if c.sensor_normals else ''}; "
             f"FPFH r={c.fpfh_radius_factor:g}v/{c.fpfh_max_nn}nn")
    return [
        (f"icp: Open3D point-to-plane ICP from identity; {voxel}; max distance "
         f"{c.icp_distance_ratio:g} x extent; {c.icp_max_iterations} iterations"),
        (f"fgr: Open3D FGR on FPFH; {feats}; max correspondence distance {c.fgr_distance_factor:g}v; "
         f"{c.fgr_iterations} iterations, division factor {c.fgr_division_factor:g}, tuple scale "
         f"{c.fgr_tuple_scale:g}, {c.fgr_max_tuples} tuples, tuple test on; seed {c.seed}"),
        (f"ransac: Open3D RANSAC on FPFH; {feats}; distance {c.ransac_distance_factor:g}v; 3-point "
         f"samples; edge-length {c.ransac_edge_length:g} + distance checkers; "
         f"{c.ransac_max_iterations} iterations / {c.ransac_confidence:g} confidence; mutual filter "
         f"{'on' if c.ransac_mutual_filter else 'off'}; seed {c.seed}, {c.ransac_threads} thread(s)"),
        (f"sc2pcr: SC2-PCR (cegc_ros.estimator.estimate_compatibility, uniform weights, 3DMatch "
         f"settings) on FPFH matches; {feats}; mutual nearest neighbours (all nearest when fewer "
         f"than {c.sc2pcr_min_mutual}), at most {c.sc2pcr_max_correspondences}; inlier threshold "
         f"{c.sc2pcr_inlier_factor:g}v"),
        ("ransac+icp, sc2pcr+icp: the method above, then the engine's point-to-plane ICP "
         "(refine.icp at EngineConfig/PreprocessConfig defaults)"),
        (f"all: {c.threads} Open3D threads (RANSAC: {c.ransac_threads}); fitness within "
         f"{c.fitness_factor:g}v"),
    ]
