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
    """How raw clouds (metres) become the network's input."""

    voxel_size: float = field(default=0.0, metadata=_meta(
        "Voxel-grid size in metres applied to each input cloud before subsampling; 0 disables it.",
        0.0, 10.0))
    num_points: int = field(default=1024, metadata=_meta(
        "Points per cloud fed to the network after voxelization (seeded random subsample).",
        64, 8192))
    seed: int = field(default=0, metadata=_meta(
        "Seed of the deterministic subsample.", 0, 2**31 - 1))


@dataclass
class EngineConfig:
    """Which weights run where, and what follows the network."""

    checkpoint: str = field(default="", metadata=_meta(
        "Path of a CEGC checkpoint (.pt); empty uses the weights shipped with the package.",
        dynamic=False))
    second_checkpoint: str = field(default="", metadata=_meta(
        "Second network of the cascade, for clouds that share no exact points (independent "
        "scans, noise, resampling): empty uses the shipped cegc_7scenes_noise.pt, 'none' runs "
        "the first network only. See cascade_min_coincident.", dynamic=False))
    cascade_min_coincident: float = field(default=0.1, metadata=_meta(
        "The first network's answer is kept when at least this share of the source lands within "
        "1e-3 of the normalisation scale of a target point (clouds cut from one point set, as "
        "in the 7Scenes protocol); otherwise the second network runs and its answer is used.",
        0.0, 1.0))
    # On by default because it won on the real pairs (README, "Accuracy"): real SUN3D fragment
    # pairs 1/3 -> 3/3, resampled 7Scenes-protocol pairs 0.93 -> 1.00, noisy ones unchanged.
    ransac_candidate: bool = field(default=True, metadata=_meta(
        "When the second network answers (clouds that share no exact points: independent scans), "
        "also run Open3D RANSAC on FPFH (refined like the network's answer) and return whichever "
        "of the two answers puts more of both clouds on each other (RegistrationResult.pose_from). "
        "Adds the RANSAC time (0.1-1 s) to those pairs only; see cegc_ros/engine.py."))
    device: str = field(default="auto", metadata=_meta(
        "Torch device: 'auto' (CUDA when present), 'cpu', 'cuda' or 'cuda:N'.", dynamic=False))
    solver: str = field(default="robust", metadata=_meta(
        "Pose from the network's correspondences: 'svd' (the paper's confidence-weighted SVD over "
        "all argmax matches) or 'robust' (confidence-guided hypothesis testing, then weighted SVD "
        "on the explained matches; see cegc_ros/solver.py).", choices=("svd", "robust")))
    robust_inlier_factor: float = field(default=2.0, metadata=_meta(
        "Inlier residual of the robust solver, in multiples of the target's median point spacing.",
        0.5, 20.0))
    robust_hypotheses: int = field(default=5000, metadata=_meta(
        "Hypotheses per round of the robust solver.", 10, 100000))
    robust_max_hypotheses: int = field(default=50000, metadata=_meta(
        "Budget of the robust solver: rounds continue until the RANSAC stopping rule (99.9%) holds "
        "for the best hypothesis so far or this many were drawn (one round when <= "
        "robust_hypotheses). Easy pairs stop after one round.", 0, 1000000))
    # ICP is the default because it won on the real pairs (README, "Accuracy"): 7Scenes protocol
    # on real SUN3D fragments, with and without shared points.
    refine: str = field(default="icp", metadata=_meta(
        "Refinement after the network: 'none' or 'icp' (Open3D point-to-plane on the "
        "voxelized clouds, started from the network's estimate).", choices=("none", "icp")))
    icp_max_distance: float = field(default=0.02, metadata=_meta(
        "ICP correspondence distance, as a fraction of the normalisation scale (twice the "
        "larger RMS radius of the two clouds).", 1e-4, 1.0))
    icp_max_iterations: int = field(default=30, metadata=_meta(
        "ICP iterations.", 1, 1000))
    threads: int = field(default=0, metadata=_meta(
        "Torch intra-op threads, and Open3D's for the RANSAC candidate; 0 keeps the libraries' "
        "defaults.", 0, 256, dynamic=False))
    compile: bool = field(default=False, metadata=_meta(
        "torch.compile the networks at start-up for clouds of exactly preprocess.num_points "
        "points (the usual case); other sizes run eagerly. Costs about 40 s at start-up on a "
        "2-core CPU (an empty compile cache; seconds with a warm one) and cuts the latency per "
        "pair by about 20% (README, Performance). Needs a C++ compiler; without one the node "
        "logs it and runs eagerly.", dynamic=False))


@dataclass
class InputConfig:
    """How the node subscribes to and accepts its two PointCloud2 inputs."""

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

    min_fitness: float = field(default=0.0, metadata=_meta(
        "Poses whose fitness (fraction of source points near the target after alignment) is "
        "below this are not published; the rejection is logged and counted.", 0.0, 1.0))
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


def section_items(obj: Any) -> list[tuple[str, Any, dict[str, Any]]]:
    """(name, default value, metadata) for each field of a config section instance."""
    return [(f.name, getattr(obj, f.name), dict(f.metadata)) for f in fields(obj)]
