"""Pairs to evaluate, each with its ground truth (or None): pair bags, folders of real pairs,
the 7Scenes protocol applied to real fragments, and synthetic bags generated once into a cache.

Real folders (:data:`REAL_LAYOUTS`): SUN3D fragments (``pairs.tsv`` with a scene column, the
clouds in ``fragments/<scene>/``), range scans (``scans/``, the Stanford bunny) or one pair
(``source.npy``, ``target.npy``, ``T_target_source.txt``, the LiDAR pair). Units are metres,
except the 7Scenes protocol's normalised units (largest bounding-box side 1).
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from cegc_ros.evaluation import EvalError, EvalPair


def bag_pairs(path: str | Path) -> list[EvalPair]:
    """All pairs of a pair bag (raises cegc_ros.data.bag.BagError on a bad bag)."""
    from cegc_ros.data.bag import read_pairs

    out = []
    for k, p in enumerate(read_pairs(path)):
        pid = str(p.info.get("pair_id", p.info.get("index", k)))
        out.append(EvalPair(pid, p.source, p.target, p.T_target_source,
                            dict(p.info, stamp_ns=int(p.stamp_ns))))
    return out


REAL_LAYOUTS = ("pairs.tsv (pair_id, source, target[, scene]) with gt/<pair_id>.txt and the clouds "
                "in fragments/<scene>/<name>.npy (with a scene column) or scans/<name>.npy; or one "
                "pair as source.npy, target.npy and T_target_source.txt")


def _read_real_table(real_dir: Path) -> list[dict[str, str]]:
    table = real_dir / "pairs.tsv"
    if not table.is_file():
        raise EvalError(f"{table} not found: --real-dir needs {REAL_LAYOUTS}")
    lines = [ln.rstrip("\n").split("\t") for ln in table.read_text().splitlines() if ln.strip()]
    header, rows = lines[0], lines[1:]
    for col in ("pair_id", "source", "target"):
        if col not in header:
            raise EvalError(f"{table} has no column {col!r} (columns: {', '.join(header)})")
    return [dict(zip(header, r)) for r in rows]


def _cloud_path(real_dir: Path, row: dict[str, str], key: str) -> Path:
    """fragments/<scene>/<name>.npy when the table names a scene (SUN3D), else scans/<name>.npy."""
    if row.get("scene"):
        return real_dir / "fragments" / row["scene"] / f"{row[key]}.npy"
    return real_dir / "scans" / f"{row[key]}.npy"


def _load_cloud(path: Path) -> np.ndarray:
    if not path.is_file():
        raise EvalError(f"fragment {path} not found")
    xyz = np.load(path)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise EvalError(f"fragment {path} has shape {xyz.shape}, expected (N, 3)")
    return xyz.astype(np.float32)


def _load_gt(gt_file: Path) -> np.ndarray:
    if not gt_file.is_file():
        raise EvalError(f"ground truth {gt_file} not found")
    T = np.loadtxt(gt_file, dtype=np.float64)
    if T.shape != (4, 4):
        raise EvalError(f"{gt_file} holds shape {T.shape}, expected a 4x4 matrix")
    return T


def _single_pair(real_dir: Path) -> tuple[Path, Path] | None:
    """(source.npy, target.npy) of a one-pair folder (no pairs.tsv, e.g. the LiDAR pair), else None."""
    src, tgt = real_dir / "source.npy", real_dir / "target.npy"
    if not (real_dir / "pairs.tsv").is_file() and src.is_file() and tgt.is_file():
        return src, tgt
    return None


def real_pairs(real_dir: str | Path) -> list[EvalPair]:
    """The real pairs of a folder (see :data:`REAL_LAYOUTS`) with their ground truth (metres)."""
    real_dir = Path(real_dir)
    single = _single_pair(real_dir)
    if single is not None:
        return [EvalPair(real_dir.name, _load_cloud(single[0]), _load_cloud(single[1]),
                         _load_gt(real_dir / "T_target_source.txt"), {"folder": str(real_dir)})]
    out = []
    for row in _read_real_table(real_dir):
        T = _load_gt(real_dir / "gt" / f"{row['pair_id']}.txt")
        info = {k: v for k, v in row.items() if k != "pair_id"}
        out.append(EvalPair(row["pair_id"], _load_cloud(_cloud_path(real_dir, row, "source")),
                            _load_cloud(_cloud_path(real_dir, row, "target")), T, info))
    return out


def real_fragment_files(real_dir: str | Path) -> list[Path]:
    """The distinct fragment files of a real-pairs folder, in a stable order."""
    real_dir = Path(real_dir)
    single = _single_pair(real_dir)
    if single is not None:
        return list(single)
    files = {_cloud_path(real_dir, r, k) for r in _read_real_table(real_dir) for k in ("source", "target")}
    return sorted(files)


def real_7scenes_pairs(real_dir: str | Path, num_pairs: int = 60, num_points: int = 2048,
                       seed: int = 0, subsample: int | None = None,
                       resample_target: bool = False, noise_sigma: float = 0.0) -> list[EvalPair]:
    """The 7Scenes protocol on real fragments: pair i crops fragment ``i mod F``.

    Each pair is ``sample_7scenes_pair(fragment, default_rng([seed, i]), num_points)``: unit
    bounding box, ``num_points`` resampled, two 75% crops, the target moved by <= 45 deg per
    axis and <= 0.5 per axis. With ``subsample`` each cloud is then independently thinned to that
    many points (seeded), so no exact point correspondences remain; with ``resample_target``
    the target crops its own independent draw of the fragment; ``noise_sigma`` adds independent
    Gaussian noise to each cloud (the paper's robustness test uses 0.01). Units: normalised.
    """
    from cegc_ros.data.protocols import sample_7scenes_pair

    files = real_fragment_files(real_dir)
    clouds = [_load_cloud(f) for f in files]
    out = []
    for i in range(num_pairs):
        rng = np.random.default_rng([seed, i])
        p = sample_7scenes_pair(clouds[i % len(clouds)], rng, num_points=num_points,
                                resample_target=resample_target, noise_sigma=noise_sigma)
        src, tgt = p.source, p.target
        if subsample:
            sub = np.random.default_rng([seed, i, 1])
            src = src[np.sort(sub.choice(len(src), min(subsample, len(src)), replace=False))]
            tgt = tgt[np.sort(sub.choice(len(tgt), min(subsample, len(tgt)), replace=False))]
        info = dict(p.info, fragment=str(files[i % len(files)].relative_to(Path(real_dir))))
        out.append(EvalPair(f"7s{i:03d}", src, tgt, p.T_target_source, info))
    return out


def cached_bag(cache: str | Path, protocol: str, split: str, n: int, seed: int = 0,
               progress: bool = True) -> Path:
    """A synthetic pair bag in ``cache``, written once (atomically: a half bag is never reused).

    Pair i is ``cegc_ros.data.protocols.make_pair(protocol, split, i, seed)``. The folder name
    carries a hash of the generator's source, so a bag made by another version of the data code
    is not mistaken for this one.
    """
    import hashlib
    import shutil

    from cegc_ros.data import protocols, scenes
    from cegc_ros.data.bag import write_pairs
    from cegc_ros.data.protocols import iter_pairs

    digest = hashlib.sha256()
    for module in (protocols, scenes):
        digest.update(Path(module.__file__).read_bytes())
    cache = Path(cache)
    bag = cache / f"{protocol}_{split}_seed{seed}_{n}pairs_{digest.hexdigest()[:10]}"
    if (bag / "metadata.yaml").is_file():
        return bag
    cache.mkdir(parents=True, exist_ok=True)
    # Written under a hidden folder, then moved: the bag directory keeps its final name while
    # it is written, because rosbag2 names its storage file after it (bag/bag.db3).
    tmp = cache / f".{bag.name}.partial"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    pairs: Iterable[Any] = iter_pairs(protocol, split, n, seed)
    if progress:
        from tqdm import tqdm
        pairs = tqdm(pairs, total=n, unit="pair", desc=f"bag {bag.name}", file=sys.stderr)
    write_pairs(tmp / bag.name, pairs, protocol=protocol, seed=seed)
    (tmp / bag.name).rename(bag)
    tmp.rmdir()
    return bag
