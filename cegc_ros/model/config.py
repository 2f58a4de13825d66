"""Hyper-parameters of the CEGC network: one dataclass, the paper's defaults, stored in checkpoints."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

from ..geometry import FPFH_MAX_NN, FPFH_RADIUS, NORMAL_RADIUS

VARIANTS = ("paper", "ri")
CAMS_CENTRES = ("own", "overlap")


@dataclass
class ModelConfig:
    """Every hyper-parameter of :class:`cegc_ros.model.cegc.CEGC`.

    ``variant`` selects the input encoding:

    - ``"paper"``: the paper as written. AGNN edges are ``[x_i, x_i - x_j]`` and CAMS's
      spatial descriptor is ``[o_x, o_y, ||o_x - o_y||]``, both in raw coordinates.
    - ``"ri"``: rotation-invariant inputs (our default, see ``cegc.py`` for why). AGNN edges are
      point-pair features ``[|d|, n_i.d, n_j.d, n_i.n_j]`` plus a per-point FPFH descriptor;
      CAMS's spatial descriptor uses each point's distance to its cloud's centroid
      (``cams_centre``: "own"), or to the centroid of the points HOCE believes overlap
      ("overlap", see cegc_ros/model/cams.py).
    """

    variant: str = "ri"
    k: int = 12                          # kNN neighbourhood (paper: 12 everywhere)
    # AGNN layers 2 and 3 gather every dilation-th of each point's k x dilation nearest
    # neighbours (layer 1's edges stay the k nearest): a wider receptive field at the same
    # cost. 1: the paper's neighbourhood (and every checkpoint before 2026-12-05).
    dilation: int = 1
    agnn_dims: tuple[int, ...] = (64, 64, 128)   # C1 of the three AGNN layers
    feat_dim: int = 256                  # C2: per-point feature size (paper: 256)
    attn_layers: int = 2                 # interleaved (self, cross) blocks; the shipped weights have 1
    #                                     (a fifth less network time at equal validation recall: docs/model_card.md)
    attn_heads: int = 4
    desc_dim: int = 33                   # per-point invariant descriptor (FPFH) size, "ri" only
    hoce_topk: int = 16                  # sorted similarities per row fed to HOCE's refinement MLP
    overlap_ratio: float = 0.5           # top-N = floor(overlap_ratio * points) (paper: 0.5)
    cams_dim: int = 32                   # C5 = C6: CAMS pair embedding width
    # "ri": where CAMS's spatial descriptor measures each point's distance from: "own" (each
    # cloud's centroid; every checkpoint before arm 19) or "overlap" (the centroid weighted by
    # HOCE's overlap probability to the power cams_centre_power; cegc_ros/model/cams.py)
    cams_centre: str = "own"
    cams_centre_power: float = 16.0
    # training only (the forward pass is the same): whether CAMS's losses reach HOCE's logits
    # through the "overlap" centre (arm 20) or stop there (arm 19 and every checkpoint before)
    cams_centre_gradient: bool = False
    # The self-attention blocks' logits also read each pair's distance within its cloud, on this
    # many log-spaced knots (GeoTransformer's geometric structure embedding, its distance part:
    # features that know where they sit in their cloud, rigid-invariant; features.AttentionBlock;
    # arm 22, issue 25). 0: none (every checkpoint before 2026-12-07). geo_sigma: the knots'
    # log scale in normalised units (0.04: about one network-point spacing at 512 points).
    geo_embedding: int = 0
    geo_sigma: float = 0.04
    chunk_rows: int = 256                # CAMS rows per chunk (bounds memory at large N)
    match_temperature: float = 0.1       # softmax temperature of soft correspondences (training)
    # Input features ("ri"): normal and FPFH neighbourhoods in normalised units (see
    # cegc_ros/geometry.py for the measurement behind the defaults). Part of the model: a
    # checkpoint is only valid with the radii it was trained on.
    normal_radius: float = NORMAL_RADIUS
    fpfh_radius: float = FPFH_RADIUS
    fpfh_max_nn: int = FPFH_MAX_NN

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"ModelConfig.variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.k < 2:
            raise ValueError(f"ModelConfig.k must be >= 2, got {self.k}")
        if self.dilation < 1:
            raise ValueError(f"ModelConfig.dilation must be >= 1, got {self.dilation}")
        if not 0.0 < self.overlap_ratio <= 1.0:
            raise ValueError(f"ModelConfig.overlap_ratio must be in (0, 1], got {self.overlap_ratio}")
        if self.geo_embedding < 0 or self.geo_embedding == 1:
            raise ValueError(f"ModelConfig.geo_embedding must be 0 or >= 2 knots, got {self.geo_embedding}")
        if not self.geo_sigma > 0:
            raise ValueError(f"ModelConfig.geo_sigma must be > 0, got {self.geo_sigma}")
        if self.cams_centre not in CAMS_CENTRES:
            raise ValueError(f"ModelConfig.cams_centre must be one of {CAMS_CENTRES}, got {self.cams_centre!r}")
        if not self.cams_centre_power > 0:
            raise ValueError(f"ModelConfig.cams_centre_power must be > 0, got {self.cams_centre_power}")
        self.agnn_dims = tuple(int(d) for d in self.agnn_dims)
        if len(self.agnn_dims) != 3:
            raise ValueError(f"ModelConfig.agnn_dims needs 3 layer widths, got {self.agnn_dims}")

    def features(self) -> dict[str, Any]:
        """Keyword arguments of :func:`cegc_ros.geometry.prepare_cloud` for this network."""
        return {"with_features": self.variant == "ri", "normal_radius": self.normal_radius,
                "fpfh_radius": self.fpfh_radius, "fpfh_max_nn": self.fpfh_max_nn}

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["agnn_dims"] = list(self.agnn_dims)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown ModelConfig fields: {sorted(unknown)}")
        return cls(**d)
