"""Run-time settings of the engine and the node: the one source of their defaults.

Each dataclass is a section; the node declares one ROS parameter per field, named
``<section>.<field>`` (for example ``preprocess.voxel_size``), with the default, the
description and the range given here. ``params/register_node.yaml`` repeats these values for
users to edit; a test checks that it agrees with this module.

The network's own hyper-parameters live in :mod:`cegc_ros.model.config` and travel inside the
checkpoint, because they must match the weights.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any


def _meta(description: str, lo: float | None = None, hi: float | None = None,
          dynamic: bool = True, choices: tuple[str, ...] | None = None) -> dict[str, Any]:
    return {"description": description, "range": (lo, hi), "dynamic": dynamic, "choices": choices}


@dataclass
class PreprocessConfig:
    """How raw clouds (metres) become bounded clouds and the network's input (cegc_ros/bounding.py)."""

    min_range: float = field(default=0.0, metadata=_meta(
        "Points nearer than this many metres to the cloud frame's origin (the sensor) are "
        "dropped and counted; 0 keeps them. Points at exactly (0, 0, 0) (no return) and "
        "non-finite points are always dropped.", 0.0, 1000.0))
    max_range: float = field(default=0.0, metadata=_meta(
        "Points farther than this many metres from the cloud frame's origin are dropped and "
        "counted; 0 keeps them.", 0.0, 100000.0))
    voxel_size: float = field(default=0.0, metadata=_meta(
        "Voxel-grid size in metres applied to both input clouds; 0 derives it from the clouds: "
        "voxel_ratio x the larger robust extent (cegc_ros/bounding.py).", 0.0, 10.0))
    voxel_ratio: float = field(default=0.01, metadata=_meta(
        "Adaptive voxel grid (when voxel_size is 0), as a fraction of the larger of the two "
        "clouds' robust extents (the largest side of the box holding all but 2% of the points "
        "at each end of each axis, so flying pixels do not inflate it); 0 with voxel_size 0 "
        "switches the grid off.", 0.0, 0.2))
    max_points: int = field(default=20000, metadata=_meta(
        "Most points per cloud after the voxel grid: a cloud above it is re-gridded coarser, "
        "then subsampled. Bounds the time and memory of every later stage (ICP, fitness).",
        100, 1_000_000))
    support_points: int = field(default=1024, metadata=_meta(
        "Points per cloud on which normals and FPFH are computed (seeded subsample of the "
        "bounded cloud); the network's points are drawn from them. 1024 with num_points 512 "
        "was chosen on synthetic validation pairs for speed at equal recall "
        "(docs/pipeline.md).", 64, 20000))
    num_points: int = field(default=512, metadata=_meta(
        "Points per cloud fed to the network (seeded subsample of the support points). The "
        "network's time grows as about the square of this.", 64, 8192))
    points_per_network_point: int = field(default=0, metadata=_meta(
        "Speed for small clouds: at most one network point per this many points of the "
        "smaller bounded cloud (at least 64, at most num_points; the support points scale "
        "alike); clouds of this x num_points points and more are not affected. 4: a "
        "1536-point crop runs 384 network points at about two thirds of the time, at the cost "
        "of some accuracy on noisy and low-overlap small clouds (docs/pipeline.md, measured); "
        "0 (default) always uses num_points.", 0, 1024))
    sampling: str = field(default="grid", metadata=_meta(
        "How the support and network points are drawn: 'grid' (spatially even: one point per "
        "cell of the coarsest grid with enough occupied cells) or 'random' (uniform draw, which "
        "follows the sensor's density). See cegc_ros/geometry.py.", choices=("grid", "random")))
    normals: str = field(default="sensor", metadata=_meta(
        "Which side each normal (and so FPFH and the network's inputs) is turned to: 'sensor' "
        "(towards the cloud frame's origin, the viewpoint of a cloud in its sensor's frame, as a "
        "sensor's PointCloud2 is: both views of a surface then agree) or 'centroid' (towards "
        "each cloud's own centroid: for clouds in a map or world frame, or moved off their "
        "sensor's frame). 'sensor' was chosen on synthetic validation pairs (docs/pipeline.md). "
        "See cegc_ros/geometry.py: normals_and_fpfh.",
        choices=("sensor", "centroid")))
    seed: int = field(default=0, metadata=_meta(
        "Seed of the deterministic subsamples.", 0, 2**31 - 1))


@dataclass
class EngineConfig:
    """Which weights run where, and the stages after the network (cegc_ros/engine.py)."""

    checkpoint: str = field(default="", metadata=_meta(
        "Path of a CEGC checkpoint (.pt); empty uses the weights shipped with the package.",
        dynamic=False))
    device: str = field(default="auto", metadata=_meta(
        "Torch device: 'auto' (CUDA when present), 'cpu', 'cuda' or 'cuda:N'.", dynamic=False))
    verification: str = field(default="", metadata=_meta(
        "Path of a learned verification model (.json, python -m cegc_ros.tools.fit_verification) "
        "for verify_score 'learned'; empty uses the one shipped with the package, fitted to the "
        "shipped weights (refit it for other weights). See cegc_ros/verification.py.",
        dynamic=False))
    candidates: str = field(default="both", metadata=_meta(
        "Candidate partners scored by CAMS for each source point: 'learned' (nearest in the "
        "network's feature space), 'fpfh' (nearest in FPFH space), 'both', or 'all' (the "
        "paper: every pair of the top-N overlap sets, argmax per row). See cegc_ros/matching.py.",
        choices=("learned", "fpfh", "both", "all")))
    learned_candidates: int = field(default=3, metadata=_meta(
        "Candidates per source point from the learned feature space.", 1, 64))
    fpfh_candidates: int = field(default=2, metadata=_meta(
        "Candidates per source point from FPFH space.", 1, 64))
    confidence: str = field(default="learned", metadata=_meta(
        "Correspondence weights for the estimator: 'learned' (HOCE overlap x CAMS/CFM pair "
        "confidence) or 'uniform' (all 1: the ablation without the learned confidence).",
        choices=("learned", "uniform")))
    max_correspondences: int = field(default=1500, metadata=_meta(
        "Most correspondences handed to the estimator (the most confident; its cost grows as "
        "the square of this). 1500 with 512 network points was chosen on synthetic validation "
        "pairs (docs/pipeline.md).", 10, 10000))
    estimator: str = field(default="compatibility", metadata=_meta(
        "Pose from the weighted correspondences: 'compatibility' (second-order spatial "
        "compatibility seeded by the confidences, SC2-PCR style) or 'svd' (the paper's "
        "confidence-weighted SVD over all of them). See cegc_ros/estimator.py.",
        choices=("compatibility", "svd")))
    verify_hypotheses: int = field(default=150, metadata=_meta(
        "Distinct pose hypotheses of the compatibility estimator re-ranked by their count x "
        "verify_score (the learned features' agreement, or the geometric fitness: share of the "
        "network's source points that land near a target point); 0 ranks by the count alone, "
        "as SC2-PCR. 150 was chosen on synthetic validation pairs under the learned "
        "verification: more low-overlap pairs than 100 for ~20 ms on the pairs in doubt "
        "(docs/pipeline.md). See cegc_ros/estimator.py.", 0, 1000))
    verify_score: str = field(default="learned", metadata=_meta(
        "What the verification multiplies each hypothesis' count by: 'fitness' (the share of the "
        "network's source points that land near a target point) or 'features' (over those "
        "points, the sum of the cosine between the learned features of the point and of the "
        "target point it lands on: a wrong pose at low overlap explains as many points as the "
        "right one, but of places the network tells apart) or 'learned' ('features', and in the "
        "pass with the free-space check a log-linear score of the count, the agreement, the "
        "fitness and HOCE's confidence of the points each pose lands, fitted on generated "
        "training pairs and shipped as weights/verification.json; its own free-space weight "
        "applies there, engine.free_space 0 turns that pass off). 'learned' was chosen on "
        "synthetic validation pairs (docs/pipeline.md); 'fitness' on the paper's path "
        "(candidates 'all'). See cegc_ros/verification.py.",
        choices=("fitness", "features", "learned")))
    explore_seeds: int = field(default=200, metadata=_meta(
        "Seeds of the compatibility estimator drawn at random (seeded) besides its spectral "
        "ones: at low overlap the spectral seeds gather on a wrong consistent cluster. Chosen "
        "on synthetic validation pairs (docs/pipeline.md). See cegc_ros/estimator.py.", 0, 2000))
    sure_fitness: float = field(default=0.85, metadata=_meta(
        "The estimator's first choice (spectral seeds, count x fitness) is kept when its fitness "
        "is at least this; below it, explore_seeds more seeds are drawn and every hypothesis is "
        "verified again with the free-space check. Above 1: always. 0.85 changes no validation "
        "result against always and spares clean high-overlap pairs the extra ~40 ms "
        "(docs/pipeline.md).", 0.0, 1.01))
    sure_ambiguity: float = field(default=0.3, metadata=_meta(
        "The estimator's first choice is also kept, below sure_fitness, when it is unambiguous: "
        "no distinct alignment among its hypotheses scores above this fraction of its score "
        "(its ambiguity) and its fitness is at least 0.3. Below 0 never. 0.3 changes no "
        "synthetic validation or test-bag result against -1 and spares a fifth of the "
        "validation pairs the exploring pass (docs/pipeline.md). See cegc_ros/estimator.py.",
        -1.0, 1.0))
    redraw_ambiguity: float = field(default=1.0, metadata=_meta(
        "A second draw of the network points (sampling seed preprocess.seed + 7919) when the "
        "estimator's choice needed its exploring pass and its ambiguity is above this: the pair "
        "is registered again and the answer the learned verification scores higher over both "
        "draws is kept. Needs verify_score 'learned'; 1 (default): never. 0.5 registers more "
        "low-overlap pairs (the test bags' pairs under 30% overlap 51% -> 54% and 60% -> 65%, "
        "the weights of 2026-12-07) "
        "and costs those it leaves in doubt a second features, match, "
        "estimate and refine stage (the benchmark's 20k-point pairs 186 -> 286 ms), beyond the "
        "speed targets: off by default, for loop closures and other pairs where a right answer "
        "is worth the time (docs/pipeline.md). See cegc_ros/second_draw.py.", 0.0, 1.0))
    sure_seeds: int = field(default=16, metadata=_meta(
        "The estimator first builds hypotheses from this many of its strongest spectral seeds "
        "and builds the rest only when the choice among those has a fitness below "
        "sure_fitness; 0 builds every seed's at once. 16 changes no synthetic validation result "
        "against 0 and spares a clean crop ~8 ms (docs/pipeline.md). See "
        "cegc_ros/estimator.py.", 0, 2000))
    free_space: float = field(default=10.0, metadata=_meta(
        "Weight of the free-space check in the hypotheses' verification: each one's count x "
        "fitness is multiplied by exp(-free_space x the share of points it puts where the other "
        "cloud's sensor saw through). Assumes each cloud is in its sensor's frame (the origin "
        "is the viewpoint, as a sensor's PointCloud2 is); 0 for clouds in a map or world frame. "
        "Chosen on synthetic validation pairs (docs/pipeline.md). See cegc_ros/visibility.py.",
        0.0, 100.0))
    inlier_factor: float = field(default=2.0, metadata=_meta(
        "Inlier and compatibility distance of the estimator, in multiples of the target "
        "network points' median spacing.", 0.25, 20.0))
    min_valid_fitness: float = field(default=0.05, metadata=_meta(
        "Verdict: a result whose fitness (share of the network's source points within the "
        "inlier distance of a target point after the pose) is below this is invalid (reason "
        "given): such a pose explains almost none of the source and is almost surely wrong. "
        "0 switches the floor off. Chosen on synthetic validation pairs (docs/pipeline.md).",
        0.0, 1.0))
    refine: str = field(default="icp", metadata=_meta(
        "Refinement after the estimator: 'none' or 'icp' (Open3D point-to-plane on the bounded "
        "clouds, at most icp_points each, started from the estimate).", choices=("none", "icp")))
    icp_max_distance: float = field(default=0.02, metadata=_meta(
        "ICP correspondence distance, as a fraction of the normalisation scale (twice the "
        "larger RMS radius of the two clouds).", 1e-4, 1.0))
    icp_max_iterations: int = field(default=30, metadata=_meta(
        "ICP iterations.", 1, 1000))
    icp_points: int = field(default=5000, metadata=_meta(
        "Most points per cloud that ICP uses (seeded subsample of the bounded clouds).",
        100, 1_000_000))
    threads: int = field(default=0, metadata=_meta(
        "Torch intra-op threads; 0 keeps the library's default.", 0, 256, dynamic=False))
    runtime: str = field(default="auto", metadata=_meta(
        "What runs the network on a CPU: 'onnxruntime' (the checkpoint's ONNX export beside it, "
        "e.g. cegc_views.onnx; an error at start-up when it is missing or stale), 'torch', or "
        "'auto' (ONNX Runtime when the export matches the checkpoint, else torch). ONNX Runtime "
        "serves engine.candidates 'both' at the exported learned_candidates; other settings, "
        "CUDA and engine.compile run torch. See cegc_ros/onnx_network.py.", dynamic=False,
        choices=("auto", "torch", "onnxruntime")))
    compile: bool = field(default=False, metadata=_meta(
        "torch.compile the network at start-up for clouds of exactly preprocess.num_points "
        "points (the usual case); other sizes run eagerly. Costs about 40 s at start-up on a "
        "2-core CPU (an empty compile cache; seconds with a warm one). Needs a C++ compiler; "
        "without one the node logs it and runs eagerly.", dynamic=False))


@dataclass
class InputConfig:
    """How the node subscribes to and accepts its PointCloud2 input(s)."""

    mode: str = field(default="pairs", metadata=_meta(
        "'pairs': register source_cloud onto target_cloud, paired by stamp. 'sequential': "
        "register each cloud of the one topic 'cloud' against the current keyframe and publish "
        "odometry (~/odometry, ~/path, TF).", dynamic=False, choices=("pairs", "sequential")))
    reliable: bool = field(default=False, metadata=_meta(
        "Subscribe with RELIABLE QoS (use for bag replay); false uses the sensor-data profile "
        "(BEST_EFFORT, volatile).", dynamic=False))
    queue_depth: int = field(default=5, metadata=_meta(
        "History depth (KEEP_LAST) of each input subscription.", 1, 1000, dynamic=False))
    max_points: int = field(default=1_000_000, metadata=_meta(
        "Clouds with more finite points are thinned by a uniform stride to at most this many "
        "before preprocessing, which bounds latency and memory for huge clouds.",
        1_000, 100_000_000))


@dataclass
class SyncConfig:
    """Approximate-time pairing of source_cloud with target_cloud by header stamp."""

    slop: float = field(default=0.05, metadata=_meta(
        "Largest difference of header stamps, in seconds, for two clouds to form a pair.",
        0.0, 60.0))
    buffer_size: int = field(default=10, metadata=_meta(
        "Unpaired clouds kept per input while they wait for a partner; the oldest stamp is "
        "dropped (and counted) when full.", 1, 1000))


@dataclass
class OutputConfig:
    """Which results are published."""

    odom_frame: str = field(default="odom", metadata=_meta(
        "frame_id of ~/odometry, ~/path and the parent of the TF (the first cloud's pose).",
        dynamic=False))
    min_fitness: float = field(default=0.0, metadata=_meta(
        "Poses whose fitness (fraction of source points near the target after alignment) is "
        "below this are not published; the rejection is logged and counted.", 0.0, 1.0))
    max_ambiguity: float = field(default=1.0, metadata=_meta(
        "Poses whose ambiguity (how close the best distinct alignment came to the answer in "
        "the estimator's verification: 0 no rival, 1 a tie) is above this are not published; "
        "the rejection is logged and counted. 1 (default) publishes every pose; 0.8 drops half "
        "of the wrong answers and a tenth of the right ones on synthetic different-view "
        "validation pairs (docs/pipeline.md): for loop closures, where a wrong pose costs "
        "more than a missed one.", 0.0, 1.0))
    overlap_threshold: float = field(default=0.5, metadata=_meta(
        "Points whose overlap confidence is at least this are published on ~/source_overlap "
        "and ~/target_overlap.", 0.0, 1.0))
    publish_overlap: bool = field(default=True, metadata=_meta(
        "Publish the overlap-masked clouds ~/source_overlap and ~/target_overlap."))


@dataclass
class MarkersConfig:
    """Correspondence lines on ~/markers (target frame, coloured by confidence)."""

    enabled: bool = field(default=True, metadata=_meta(
        "Publish ~/markers."))
    max_correspondences: int = field(default=200, metadata=_meta(
        "Most correspondence lines drawn (the highest weights are kept).", 0, 100_000))
    min_weight: float = field(default=0.0, metadata=_meta(
        "Correspondences with a smaller confidence weight are not drawn.", 0.0, 1.0))
    line_width: float = field(default=0.005, metadata=_meta(
        "Width of the correspondence lines in metres.", 1e-5, 1.0))


@dataclass
class DiagnosticsConfig:
    """The /diagnostics status and the throttling of warnings."""

    period: float = field(default=1.0, metadata=_meta(
        "Seconds between DiagnosticArray messages on /diagnostics.", 0.05, 3600.0, dynamic=False))
    window: int = field(default=200, metadata=_meta(
        "Number of recent pairs the latency percentiles are computed over.", 1, 100_000))
    log_throttle: float = field(default=5.0, metadata=_meta(
        "Each kind of warning (rejected pair, unpaired cloud, ...) is logged at most once per "
        "this many seconds, with a count of the ones not logged.", 0.0, 3600.0))


@dataclass
class SequentialConfig:
    """Sequential mode: one cloud stream registered against keyframes into odometry.

    ``input.mode`` chooses between the two-topic pairing and this keyframe odometry
    (cegc_ros/sequential/odometry.py; docs/sequential.md); ``output.odom_frame`` names its frame.
    """

    voxel_size: float = field(default=0.0, metadata=_meta(
        "Voxel grid (metres) of the clouds that tracking ICP and the keyframe checks run on "
        "(global registration gets the raw clouds and uses preprocess.*); 0 derives it: "
        "voxel_ratio x the robust extent of the first cloud after a start or reset "
        "(cegc_ros/sequential/odometry.py, derive_distances).", 0.0, 10.0))
    voxel_ratio: float = field(default=0.02, metadata=_meta(
        "Derived voxel grid (when voxel_size is 0), as a fraction of the first cloud's robust "
        "extent (largest side of its 2%-98% box, as preprocess.voxel_ratio uses): about 4 cm "
        "on a Kinect view of a room, 3 mm on a 14 cm object scan, 0.3 m on a street LiDAR "
        "sweep (chosen on the synthetic room and LiDAR sequences, docs/sequential.md).",
        1e-4, 0.2))
    max_range: float = field(default=0.0, metadata=_meta(
        "Points farther than this (metres) from the sensor (the cloud frame's origin) are left "
        "out of tracking and the keyframe checks; 0 keeps all. Depth noise grows with range "
        "(Kinect-like: quadratically), and far noisy points bias ICP.", 0.0, 10000.0))
    icp_max_distance: float = field(default=0.0, metadata=_meta(
        "Correspondence distance (metres) of the tracking ICP: how far the constant-velocity "
        "prediction may be off and still be pulled in; 0 derives it: 4 voxels.", 0.0, 100.0))
    icp_max_iterations: int = field(default=30, metadata=_meta(
        "Iterations of the tracking ICP.", 1, 1000))
    icp_prior: float = field(default=0.01, metadata=_meta(
        "Weight of the constant-velocity prediction in the tracking ICP, per point (translation "
        "in metres, rotation as angle x the cloud's RMS radius): directions the geometry "
        "constrains less than this (a wall and the floor leave one free) stay near the "
        "prediction instead of sliding on depth noise; 0 is plain point-to-plane ICP.",
        0.0, 1.0))
    inlier_distance: float = field(default=0.0, metadata=_meta(
        "Distance (metres) within which an aligned point counts as on the keyframe, for "
        "fitness, overlap and the covariance; 0 derives it: 1 voxel.", 0.0, 100.0))
    min_fitness: float = field(default=0.5, metadata=_meta(
        "A registration (ICP from the prediction, or the global one) is accepted when at least "
        "this share of the cloud's voxels lies within inlier_distance of the keyframe; below it "
        "ICP hands over to global registration, and a rejected global answer skips the cloud "
        "(counted; the odometry is unchanged).", 0.0, 1.0))
    max_ambiguity: float = field(default=1.0, metadata=_meta(
        "A global registration whose ambiguity (as output.max_ambiguity: how close the best "
        "distinct alignment came to the answer, 0 no rival, 1 a tie) is above this is not "
        "accepted: the cloud is skipped (counted) instead of jumping the odometry to one of two "
        "alignments the geometry cannot tell apart. 1 (default) accepts every answer that "
        "passes min_fitness.", 0.0, 1.0))
    gap_intervals: float = field(default=3.0, metadata=_meta(
        "A cloud arriving more than this many frame intervals (the median of the recent ones) "
        "after the last registered cloud is registered globally first, and tracked only if "
        "that fails: across dropped frames the constant-velocity guess is not trusted. 0 "
        "always tracks first.", 0.0, 1000.0))
    keyframe_min_overlap: float = field(default=0.7, metadata=_meta(
        "A new keyframe is taken when the fitness, or the overlap (share of the keyframe's "
        "voxels within inlier_distance of the aligned cloud), falls below this.", 0.0, 1.0))
    keyframe_max_translation: float = field(default=0.0, metadata=_meta(
        "A new keyframe is taken when the cloud is farther than this (metres) from the "
        "keyframe; 0 derives it: 10 voxels.", 0.0, 1000.0))
    keyframe_max_rotation: float = field(default=20.0, metadata=_meta(
        "A new keyframe is taken when the cloud is rotated more than this (degrees) from the "
        "keyframe.", 0.0, 180.0))
    path_length: int = field(default=1000, metadata=_meta(
        "Poses kept in ~/path (the oldest are dropped).", 1, 1_000_000))
    publish_tf: bool = field(default=True, metadata=_meta(
        "Publish odom_frame -> cloud frame on /tf (where tf2_msgs is importable: a ROS install, or "
        "scripts/build_tf2_msgs.sh, which the bootstrap runs).",
        dynamic=False))


def section_items(obj: Any) -> list[tuple[str, Any, dict[str, Any]]]:
    """(name, default value, metadata) for each field of a config section instance."""
    return [(f.name, getattr(obj, f.name), dict(f.metadata)) for f in fields(obj)]
