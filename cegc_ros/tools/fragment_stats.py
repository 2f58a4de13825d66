"""Measure what differs between synthetic and real fragment pairs, on the same statistics.

    python -m cegc_ros.tools.fragment_stats .cache/pairs/val [--pairs 60] \
        [--real-dir ../shared/data/real/sun3d] [--smooth K] [--json runs/gap.json]

For every pair, both clouds on one 2.5 cm grid (the 3DMatch fragments' own voxel), in metres:

- ``points``, ``extent_m`` (largest side of the bounding box), ``spacing_mm`` (median
  nearest-neighbour distance): density and size;
- ``noise_mm``: median over points of the plane-fit RMS of their 16 nearest neighbours (the
  square root of the smallest eigenvalue of the neighbourhood covariance): surface noise, plus
  curvature at that scale;
- ``planar``: share of points whose neighbourhood is a plane (smallest eigenvalue under 1% of
  the sum): floor, walls, table tops;
- ``overlap``: share of source points within 1.5 voxels of a target point after the ground truth
  (``refine.fitness``);
- ``overlap_planar``: the share of those overlapping source points whose neighbourhood is a plane
  (as ``planar``): whether the overlap holds bare floor and walls or furniture and clutter;
- ``fpfh_inlier``: the classical pipelines' feature quality on this pair: on a 5 cm grid, normals
  (radius 10 cm) and FPFH (radius 25 cm, 100 neighbours, Open3D), each source point's nearest
  target descriptor is a true match when that target point lies within 10 cm of the source point
  moved by the ground truth; the share of source points in the overlap whose match is true.

Synthetic pairs are the Kinect different-view pairs of a pair cache (``cegc-make-pairs``), evenly
spaced, summarised by overlap band; real pairs (``--real-dir``, evaluation only) one row each.
``--smooth K`` measures the synthetic clouds after :func:`smooth_surface` (a what-if for a
TSDF-style smoothing in the generator, before changing it).
Choose generator changes on what this shows, report the real numbers, never train on them.
Errors: one line, exit code 1 (2 for usage).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from cegc_ros.bounding import extent
from cegc_ros.refine import fitness
from cegc_ros.tools.replay import OneLineParser

#: The grid every cloud is measured on (metres): the 3DMatch fragments' voxel.
GRID = 0.025
#: Neighbours of the local plane fit.
PLANE_NN = 16
#: A neighbourhood is planar when its smallest covariance eigenvalue is under this share of the sum.
PLANAR_SHARE = 0.01
#: The feature-quality measurement: voxel, normal / FPFH radii, neighbours, true-match distance.
FPFH_VOXEL = 0.05
FPFH_NORMAL_RADIUS = 0.10
FPFH_RADIUS = 0.25
FPFH_MAX_NN = 100
MATCH_DISTANCE = 0.10
#: Overlap bands of the synthetic summary.
BANDS = ((0.0, 0.3), (0.3, 0.5), (0.5, 1.01))


def cloud_stats(points: np.ndarray) -> dict[str, float]:
    """(N, 3) metres, already on the measuring grid -> points, extent_m, spacing_mm, noise_mm, planar."""
    return _measure(points)[0]


def _measure(points: np.ndarray) -> tuple[dict[str, float], np.ndarray]:
    """:func:`cloud_stats` and the (N,) bool mask of the points whose neighbourhood is a plane."""
    from scipy.spatial import cKDTree
    pts = np.asarray(points, np.float64)
    if len(pts) <= PLANE_NN:
        raise ValueError(f"a cloud of {len(pts)} points is too small to measure (needs > {PLANE_NN})")
    d, nn = cKDTree(pts).query(pts, k=PLANE_NN + 1, workers=-1)
    nb = pts[nn]                                                     # (N, k+1, 3), the point itself first
    nb = nb - nb.mean(1, keepdims=True)
    ev = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", nb, nb) / nb.shape[1])   # ascending (N, 3)
    ev = np.clip(ev, 0.0, None)
    planar = ev[:, 0] < PLANAR_SHARE * ev.sum(1)
    return {"points": float(len(pts)),
            "extent_m": extent(pts),
            "spacing_mm": 1e3 * float(np.median(d[:, 1])),
            "noise_mm": 1e3 * float(np.median(np.sqrt(ev[:, 0]))),
            "planar": float(np.mean(planar))}, planar


def smooth_surface(points: np.ndarray, k: int) -> np.ndarray:
    """(N, 3) -> each point projected onto the least-squares plane of its k nearest neighbours
    (itself included): one pass of the moving-least-squares smoothing a TSDF fusion gives a
    surface. ``k`` < 3 returns the points unchanged."""
    from scipy.spatial import cKDTree
    pts = np.asarray(points, np.float64)
    if k < 3 or len(pts) <= k:
        return pts
    _, nn = cKDTree(pts).query(pts, k=k, workers=-1)
    nb = pts[nn]
    centre = nb.mean(1)
    nb = nb - centre[:, None]
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    normal = vec[:, :, 0]                                            # smallest eigenvalue's vector
    return pts - np.einsum("ni,ni->n", pts - centre, normal)[:, None] * normal


def _grid(points: np.ndarray, voxel: float) -> np.ndarray:
    from cegc_ros.geometry import voxel_downsample
    return voxel_downsample(np.asarray(points, np.float64), voxel).astype(np.float64)


def fpfh_inlier_ratio(source: np.ndarray, target: np.ndarray, T: np.ndarray) -> float:
    """Share of the overlapping source points (FPFH_VOXEL grid) whose nearest target FPFH is a
    true match (within MATCH_DISTANCE after T); nan when no source point overlaps."""
    import open3d as o3d
    from scipy.spatial import cKDTree
    reg = o3d.pipelines.registration
    feats, clouds = [], []
    for pts in (source, target):
        p = _grid(pts, FPFH_VOXEL)
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_NORMAL_RADIUS, max_nn=30))
        f = reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(
            radius=FPFH_RADIUS, max_nn=FPFH_MAX_NN))
        feats.append(np.asarray(f.data).T.copy())
        clouds.append(p)
    moved = clouds[0] @ T[:3, :3].T + T[:3, 3]
    near, _ = cKDTree(clouds[1]).query(moved, k=1)
    inside = near <= MATCH_DISTANCE
    if not inside.any():
        return float("nan")
    _, match = cKDTree(feats[1]).query(feats[0][inside], k=1)
    return float(np.mean(np.linalg.norm(clouds[1][match] - moved[inside], axis=1) <= MATCH_DISTANCE))


def pair_stats(source: np.ndarray, target: np.ndarray, T: np.ndarray) -> dict[str, float]:
    """Both clouds' :func:`cloud_stats` (averaged), their overlap and the FPFH inlier ratio."""
    src, tgt = _grid(source, GRID), _grid(target, GRID)
    (a, planar), (b, _) = _measure(src), _measure(tgt)
    out = {k: 0.5 * (a[k] + b[k]) for k in a}
    out["overlap"] = fitness(src, tgt, T, 1.5 * GRID)               # share of source points on the target
    out["overlap_planar"] = overlap_planar(src, tgt, T, planar)
    out["fpfh_inlier"] = fpfh_inlier_ratio(source, target, T)
    return out


def overlap_planar(source: np.ndarray, target: np.ndarray, T: np.ndarray,
                   planar: np.ndarray | None = None) -> float:
    """Share of the source's overlapping points (within 1.5 grid voxels of a target point after
    T; both on the measuring grid) whose neighbourhood is a plane: what the overlap holds, bare
    floor and walls (near 1) or furniture and clutter; nan when nothing overlaps. ``planar``:
    the source's mask from :func:`_measure` when the caller has it."""
    from scipy.spatial import cKDTree
    if planar is None:
        planar = _measure(source)[1]
    moved = source @ T[:3, :3].T + T[:3, 3]
    near, _ = cKDTree(target).query(moved, k=1, distance_upper_bound=1.5 * GRID * (1.0 + 1e-9))
    inside = np.isfinite(near)
    if not inside.any():
        return float("nan")
    return float(np.mean(planar[inside]))


COLUMNS = ("points", "extent_m", "spacing_mm", "noise_mm", "planar", "overlap", "overlap_planar", "fpfh_inlier")


def table(rows: list[tuple[str, int, dict[str, float]]]) -> str:
    """Markdown: one line per (name, pairs, statistics)."""
    head = "| pairs | n | " + " | ".join(COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 2)]
    for name, n, st in rows:
        cells = [f"{st[c]:.0f}" if c == "points" else f"{st[c]:.3g}" for c in COLUMNS]
        lines.append(f"| {name} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summarise(stats: list[dict[str, float]]) -> list[tuple[str, int, dict[str, float]]]:
    """Medians of the synthetic pairs in each overlap band (by the measured overlap)."""
    out = []
    for lo, hi in BANDS:
        band = [s for s in stats if lo <= s["overlap"] < hi]
        if band:
            med = {c: float(np.nanmedian([s[c] for s in band])) for c in COLUMNS}
            out.append((f"synthetic, overlap {lo:.0%}-{min(hi, 1.0):.0%}", len(band), med))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = OneLineParser(prog="fragment_stats", description=__doc__.splitlines()[0])
    ap.add_argument("cache", type=Path, help="a pair cache (cegc-make-pairs); its Kinect different-view pairs")
    ap.add_argument("--pairs", type=int, default=60, help="evenly spaced synthetic pairs")
    ap.add_argument("--real-dir", type=Path, default=None,
                    help="real pairs to report beside them (cegc-eval --real-dir layout)")
    ap.add_argument("--smooth", type=int, default=0, metavar="K",
                    help="what-if: project the synthetic clouds onto their K-neighbour planes "
                         "(smooth_surface) before measuring; 0: as generated")
    ap.add_argument("--json", type=Path, default=None, help="write every pair's numbers here")
    args = ap.parse_args(argv)
    if args.pairs < 1:
        ap.error("--pairs must be >= 1")
    try:
        from cegc_ros.data.pair_cache import PairCache, PairCacheError
        try:
            cache = PairCache(args.cache, kinds=("views",), sensors=("kinect",))
        except PairCacheError as err:
            raise ValueError(str(err)) from err
        if len(cache) == 0:
            raise ValueError(f"{args.cache}: no Kinect different-view pairs")
        idx = np.linspace(0, len(cache) - 1, min(args.pairs, len(cache))).astype(int)
        synthetic = []
        for i in idx:
            p = cache[int(i)]
            src, tgt = p.source, p.target
            if args.smooth:
                src, tgt = smooth_surface(src, args.smooth), smooth_surface(tgt, args.smooth)
            synthetic.append(pair_stats(src, tgt, p.T_target_source))
        rows = summarise(synthetic)
        real: list[dict[str, Any]] = []
        if args.real_dir is not None:
            from cegc_ros.evaluation.datasets import real_pairs
            for p in real_pairs(args.real_dir):
                st = pair_stats(p.source, p.target, p.T_gt)
                real.append({"pair": p.pair_id, **st})
                rows.append((f"real {p.pair_id}", 1, st))
    except (OSError, ValueError) as err:
        print(f"fragment_stats: {err}".splitlines()[0], file=sys.stderr)
        return 1
    print(table(rows))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"synthetic": synthetic, "real": real}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
