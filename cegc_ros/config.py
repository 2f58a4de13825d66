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
    device: str = field(default="auto", metadata=_meta(
        "Torch device: 'auto' (CUDA when present), 'cpu', 'cuda' or 'cuda:N'.", dynamic=False))
    refine: str = field(default="none", metadata=_meta(
        "Refinement after the network: 'none' or 'icp' (Open3D point-to-plane on the "
        "voxelized clouds, started from the network's estimate).", choices=("none", "icp")))
    icp_max_distance: float = field(default=0.05, metadata=_meta(
        "ICP correspondence distance, as a fraction of the scene's normalisation scale "
        "(largest bounding-box side).", 1e-4, 1.0))
    icp_max_iterations: int = field(default=30, metadata=_meta(
        "ICP iterations.", 1, 1000))
    threads: int = field(default=0, metadata=_meta(
        "Torch intra-op threads; 0 keeps torch's default.", 0, 256, dynamic=False))


def section_items(obj: Any) -> list[tuple[str, Any, dict[str, Any]]]:
    """(name, default value, metadata) for each field of a config section instance."""
    return [(f.name, getattr(obj, f.name), dict(f.metadata)) for f in fields(obj)]
