"""cegc-eval: run CEGC and the Open3D baselines on the same pairs and write the paper's table.

Pairs come from one of three sources:

* a pair bag (``cegc-eval BAG``), as written by ``cegc-make-bag`` or recorded by a user;
* real pairs with ground truth (``--real-dir DIR``, layouts in :data:`REAL_LAYOUTS`: SUN3D
  fragments ``../shared/data/real/sun3d``, range scans ``.../bunny``, one LiDAR pair
  ``.../lidar``), scored at 15 deg / 0.3 m unless ``--recall-rot/--recall-trans`` say otherwise;
* the 7Scenes protocol applied to those real fragments (``--real-dir DIR --real-protocol
  7scenes``): same-fragment crops built by :func:`cegc_ros.data.protocols.sample_7scenes_pair`,
  seeded, scored at 5 deg: the real-data proxy of the paper's 7Scenes benchmark.

Methods: ``cegc`` (engine, refine none), ``cegc+icp`` (engine, refine icp: the node's defaults),
``net+icp`` (as cegc+icp with ``engine.ransac_candidate`` off: what the networks alone do),
``icp``, ``fgr``, ``ransac``, ``ransac+icp`` (RANSAC then the engine's ICP;
:mod:`cegc_ros.baselines`). With ``--through-node`` the CEGC methods run inside a
``register_node`` subprocess fed by replaying the bag over DDS; the baselines run offline on the
same pairs. Outputs in ``--out DIR``: ``metrics.json``, ``pairs.csv``, ``report.md``,
``errors.png``. A method that raises or returns an invalid result on a pair scores a recall
failure on it (see :mod:`cegc_ros.metrics` for the definitions); nothing is skipped.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cegc_ros import metrics

ALL_METHODS = ("cegc", "cegc+icp", "net+icp", "icp", "fgr", "ransac", "ransac+icp")
CEGC_METHODS = ("cegc", "cegc+icp", "net+icp")
BASELINE_METHODS = ("icp", "fgr", "ransac", "ransac+icp")
# engine settings of each CEGC method over the parameter file's: (engine.refine, engine.ransac_candidate)
CEGC_SETTINGS = {"cegc": ("none", None), "cegc+icp": ("icp", None), "net+icp": ("icp", False)}

# Table columns: (key in the summary, header, lower is better)
COLUMNS = (
    ("rmse_r", "RMSE(R)", True), ("rmse_t", "RMSE(t)", True),
    ("mae_r", "MAE(R)", True), ("mae_t", "MAE(t)", True),
    ("error_r", "Error(R)", True), ("error_t", "Error(t)", True),
    ("recall", "recall", False), ("median_latency_ms", "median ms", True),
)


REPO_ROOT = Path(__file__).resolve().parents[2]


def default_params_file() -> Path:
    """params/register_node.yaml of the checkout, else the installed copy (ament share dir)."""
    here = REPO_ROOT / "params" / "register_node.yaml"
    if here.is_file():
        return here
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    try:
        return Path(get_package_share_directory("cegc_ros")) / "params" / "register_node.yaml"
    except PackageNotFoundError:
        return here


class EvalError(RuntimeError):
    """The evaluation cannot run (bad input folder, unknown method, missing weights, ...)."""


@dataclass
class EvalPair:
    """One pair to evaluate: clouds (N, 3) / (M, 3) in their own frames, ground truth or None."""

    pair_id: str
    source: np.ndarray
    target: np.ndarray
    T_gt: np.ndarray | None        # (4, 4) T_target_source, None when unknown
    info: dict[str, Any] = field(default_factory=dict)


@dataclass
class Outcome:
    """What one method returned on one pair."""

    method: str
    pair_id: str
    T: np.ndarray | None           # (4, 4) T_target_source estimate; None when it raised
    valid: bool
    raised: bool
    reason: str
    fitness: float
    latency_s: float


# --------------------------------------------------------------------------------------------
# Pair sources
# --------------------------------------------------------------------------------------------

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
    tmp = cache / f".{bag.name}.partial"
    if tmp.exists():
        shutil.rmtree(tmp)
    pairs: Iterable[Any] = iter_pairs(protocol, split, n, seed)
    if progress:
        from tqdm import tqdm
        pairs = tqdm(pairs, total=n, unit="pair", desc=f"bag {bag.name}", file=sys.stderr)
    write_pairs(tmp, pairs, protocol=protocol, seed=seed)
    tmp.rename(bag)
    return bag


# --------------------------------------------------------------------------------------------
# Methods
# --------------------------------------------------------------------------------------------

Runner = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, bool, str, float]]


def parse_methods(text: str) -> list[str]:
    methods = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in methods if m not in ALL_METHODS]
    if unknown or not methods:
        raise EvalError(f"unknown method(s) {', '.join(unknown) or '(none)'}; "
                        f"choose from {','.join(ALL_METHODS)}")
    return list(dict.fromkeys(methods))


def engine_configs(params_file: str | Path | None = None) -> tuple[Any, Any]:
    """(PreprocessConfig, EngineConfig) as register_node would build them from a parameter file.

    Reads the ``preprocess.*`` and ``engine.*`` entries of the file's ``ros__parameters``
    (default ``params/register_node.yaml``), so offline CEGC runs with the node's settings.
    """
    import dataclasses

    import yaml

    from cegc_ros.config import EngineConfig, PreprocessConfig

    path = Path(params_file) if params_file else default_params_file()
    pre, eng = PreprocessConfig(), EngineConfig()
    if not path.is_file():
        if params_file:
            raise EvalError(f"parameter file {path} not found")
        return pre, eng
    try:
        doc = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise EvalError(f"parameter file {path} is not valid YAML: {err}") from err
    values: dict[str, Any] = {}
    for node_block in (doc.values() if isinstance(doc, dict) else []):
        if isinstance(node_block, dict) and isinstance(node_block.get("ros__parameters"), dict):
            values.update(node_block["ros__parameters"])
    for section, obj in (("preprocess", pre), ("engine", eng)):
        names = {f.name: f for f in dataclasses.fields(obj)}
        for key, value in values.items():
            head, _, name = key.partition(".")
            if head == section and name in names:
                setattr(obj, name, type(getattr(obj, name))(value))
    return pre, eng


def make_runners(methods: Sequence[str], checkpoint: str | None = None,
                 baseline_config: Any = None, params_file: str | Path | None = None
                 ) -> dict[str, Runner]:
    """Offline runners ``(source, target) -> (T, valid, reason, fitness)`` per method name.

    CEGC runs with the node's settings from ``params_file`` (default params/register_node.yaml);
    ``checkpoint`` overrides the file's ``engine.checkpoint``.
    """
    runners: dict[str, Runner] = {}
    registrar = None
    if any(m in CEGC_METHODS for m in methods):
        from cegc_ros.engine import Registrar
        pre, eng = engine_configs(params_file)
        registrar = Registrar.from_checkpoint(checkpoint or eng.checkpoint or None,
                                              device=eng.device, preprocess=pre, engine=eng)
        base_engine = registrar.engine

        def cegc_runner(method: str) -> Runner:
            import copy
            eng = copy.deepcopy(base_engine)
            eng.refine, candidate = CEGC_SETTINGS[method]
            if candidate is not None:
                eng.ransac_candidate = candidate

            def run(src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, bool, str, float]:
                registrar.update(engine=eng)
                r = registrar.register(src, tgt)
                return r.T_target_source, r.valid, r.reason, r.fitness
            return run

        for m in methods:
            if m in CEGC_METHODS:
                runners[m] = cegc_runner(m)
    if any(m in BASELINE_METHODS for m in methods):
        from cegc_ros import baselines

        baselines.load_open3d(getattr(baseline_config, "threads", 2))  # import outside the timing
        for m in methods:
            if m in BASELINE_METHODS:
                def run(src: np.ndarray, tgt: np.ndarray, _m: str = m
                        ) -> tuple[np.ndarray, bool, str, float]:
                    r = baselines.register(_m, src, tgt, baseline_config)
                    return r.T_target_source, r.valid, r.reason, r.fitness
                runners[m] = run
    return {m: runners[m] for m in methods if m in runners}


def run_method(method: str, runner: Runner, pair: EvalPair) -> Outcome:
    """One method on one pair; an exception becomes a failed Outcome carrying its message."""
    t0 = time.perf_counter()
    try:
        T, valid, reason, fitness = runner(pair.source, pair.target)
    except Exception as err:  # noqa: BLE001 - any failure of a method is a scored failure
        return Outcome(method, pair.pair_id, None, False, True, f"{type(err).__name__}: {err}",
                       0.0, time.perf_counter() - t0)
    return Outcome(method, pair.pair_id, np.asarray(T, np.float64), bool(valid), False,
                   str(reason), float(fitness), time.perf_counter() - t0)


def run_offline(pairs: Sequence[EvalPair], runners: dict[str, Runner],
                progress: bool = True) -> dict[str, list[Outcome]]:
    """Every runner on every pair (pair-major order, so partial runs cover all methods)."""
    from tqdm import tqdm

    out: dict[str, list[Outcome]] = {m: [] for m in runners}
    with tqdm(total=len(pairs) * len(runners), disable=not progress, unit="run",
              desc="cegc-eval", file=sys.stderr) as bar:
        for pair in pairs:
            for m, runner in runners.items():
                bar.set_postfix_str(f"{pair.pair_id} {m}")
                out[m].append(run_method(m, runner, pair))
                bar.update()
    return out


# --------------------------------------------------------------------------------------------
# Through the node
# --------------------------------------------------------------------------------------------

def dds_environment(env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (default os.environ) with DDS kept on this machine and a ROS domain of its own.

    A non-zero ROS_DOMAIN_ID already chosen by the caller (a test session, a user who wants
    to watch the replay) is kept; otherwise one in 1..100 is derived from the pid, never 0, the
    shared default domain where a user's own nodes would hear the replay.
    """
    import os

    env = dict(os.environ if env is None else env)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_LOCALHOST_ONLY", None)
    if not env.get("ROS_DOMAIN_ID") or env["ROS_DOMAIN_ID"] == "0":
        env["ROS_DOMAIN_ID"] = str(1 + os.getpid() % 100)
    ament = [p for p in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    if sys.prefix not in ament:
        env["AMENT_PREFIX_PATH"] = os.pathsep.join([sys.prefix, *ament])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO_ROOT), env.get("PYTHONPATH", "")) if p)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def run_through_node(bag: str | Path, pairs: Sequence[EvalPair], methods: Sequence[str], *,
                     params_file: str | Path | None = None, checkpoint: str | None = None,
                     progress: bool = True, startup_timeout: float = 180.0,
                     pair_timeout: float = 120.0, log_dir: str | Path | None = None
                     ) -> dict[str, list[Outcome]]:
    """CEGC outcomes from a ``register_node`` subprocess fed by replaying ``bag`` over DDS.

    One node per method (its :data:`CEGC_SETTINGS`), started with ``params_file`` plus
    ``input.reliable:=true`` (replay QoS), replayed in lockstep so no pair is dropped. A pair
    the node answered with no pose (rejected, invalid) is a failure scored with identity.
    Latency is the node's answer time: publishing the pair's later cloud to receiving its pose.
    """
    import os
    import subprocess
    import tempfile
    import threading

    from cegc_ros.tools.replay import replay_bag

    env = dds_environment()
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID",
                                           "AMENT_PREFIX_PATH")})
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    params = Path(params_file) if params_file else default_params_file()
    if not params.is_file():
        raise EvalError(f"register_node parameter file {params} not found")
    logs = Path(log_dir) if log_dir else Path(tempfile.mkdtemp(prefix="cegc_eval_node_"))
    logs.mkdir(parents=True, exist_ok=True)
    out: dict[str, list[Outcome]] = {}
    for method in methods:
        if method not in CEGC_METHODS:
            raise EvalError(f"{method} does not run in register_node")
        refine, candidate = CEGC_SETTINGS[method]
        cmd = [sys.executable, "-m", "cegc_ros.node", "--ros-args", "--params-file", str(params),
               "-p", "input.reliable:=true", "-p", f"engine.refine:={refine}"]
        if candidate is not None:
            cmd += ["-p", f"engine.ransac_candidate:={str(candidate).lower()}"]
        if checkpoint:
            cmd += ["-p", f"engine.checkpoint:={Path(checkpoint).resolve()}"]
        log_path = logs / f"register_node_{method.replace('+', '_')}.log"
        with open(log_path, "w") as log:
            proc = subprocess.Popen(cmd, env=env, cwd=str(REPO_ROOT), stdout=log,
                                    stderr=subprocess.STDOUT)
        box: dict[str, Any] = {}

        def replay() -> None:
            try:
                box["result"] = replay_bag(bag, lockstep=True, connect_timeout=startup_timeout,
                                           pair_timeout=pair_timeout, progress=progress)
            except Exception as err:  # noqa: BLE001 - re-raised in the caller's thread
                box["error"] = err

        worker = threading.Thread(target=replay, daemon=True)
        worker.start()
        try:
            while worker.is_alive():
                worker.join(0.2)
                if proc.poll() is not None and worker.is_alive():
                    tail = log_path.read_text().strip().splitlines()[-1:] or ["(no output)"]
                    raise EvalError(f"register_node exited with code {proc.returncode} before "
                                    f"the replay ended: {tail[0]}")
        finally:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        if "error" in box:
            raise EvalError(f"replay into register_node failed: {box['error']}") from box["error"]
        by_stamp = {r.stamp_ns: r for r in box["result"].records}
        outs = []
        for p in pairs:
            rec = by_stamp.get(int(p.info.get("stamp_ns", -1)))
            if rec is None or rec.T_est is None:
                outs.append(Outcome(method, p.pair_id, None, False, True,
                                    "register_node published no pose (rejected or lost)",
                                    math.nan, math.nan))
            else:
                outs.append(Outcome(method, p.pair_id, np.asarray(rec.T_est, np.float64), True,
                                    False, "", math.nan, float(rec.latency_s)))
        out[method] = outs
    return out


# --------------------------------------------------------------------------------------------
# Scoring and reports
# --------------------------------------------------------------------------------------------

def summarize_outcomes(pairs: Sequence[EvalPair], outcomes: dict[str, list[Outcome]],
                       thresholds: metrics.RecallThresholds) -> dict[str, dict[str, Any]]:
    """Per method: the metrics summary (when every pair has ground truth) plus latency/fitness."""
    has_gt = all(p.T_gt is not None for p in pairs)
    result = {}
    for m, outs in outcomes.items():
        s: dict[str, Any] = {}
        if has_gt and pairs:
            T_est = np.stack([o.T if o.T is not None else np.eye(4) for o in outs])
            s.update(metrics.summarize(np.stack([p.T_gt for p in pairs]), T_est,
                                       valid=[o.valid for o in outs],
                                       raised=[o.raised for o in outs], thresholds=thresholds))
        else:
            s.update(n_pairs=len(outs), n_invalid=sum(1 for o in outs if not o.raised and not o.valid),
                     n_exception=sum(1 for o in outs if o.raised))
        lat = [o.latency_s for o in outs if not o.raised]
        s["median_latency_ms"] = 1000.0 * float(np.median(lat)) if lat else math.nan
        fit = [o.fitness for o in outs if not o.raised]
        s["mean_fitness"] = float(np.mean(fit)) if fit else math.nan
        result[m] = s
    return result


def _fmt(key: str, v: Any) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if key == "recall":
        return f"{v:.3f}"
    if key.endswith("_t"):
        return f"{v:.4f}"
    if key == "median_latency_ms":
        return f"{v:.0f}"
    return f"{v:.3f}"


def table_markdown(summaries: dict[str, dict[str, Any]], columns=COLUMNS, bold: bool = True) -> str:
    """The paper's table: one row per method, best value per column in bold."""
    cols = [c for c in columns if any(c[0] in s for s in summaries.values())]
    lines = ["| method | " + " | ".join(h for _, h, _ in cols) + " | failures |",
             "|---|" + "---|" * (len(cols) + 1)]
    best = {}
    for key, _, lower in cols:
        vals = [round(float(s[key]), 12) for s in summaries.values()
                if key in s and s[key] is not None and math.isfinite(float(s[key]))]
        if vals:
            best[key] = min(vals) if lower else max(vals)
    for m, s in summaries.items():
        cells = []
        for key, _, _ in cols:
            text = _fmt(key, s.get(key))
            v = s.get(key)
            if bold and v is not None and key in best and math.isfinite(float(v)) \
                    and round(float(v), 12) == best[key] and len(summaries) > 1:
                text = f"**{text}**"
            cells.append(text)
        fails = s.get("n_invalid", 0) + s.get("n_exception", 0)
        cells.append(f"{fails}/{s.get('n_pairs', 0)}")
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _pose_cells(T: np.ndarray | None) -> list[str]:
    if T is None:
        return ["-"] * 6
    e = metrics.euler_xyz_deg(T[:3, :3])
    return [f"{x:.4f}" for x in T[:3, 3]] + [f"{x:.2f}" for x in e]


def pairs_rows(pairs: Sequence[EvalPair], outcomes: dict[str, list[Outcome]]) -> list[dict[str, Any]]:
    """One row per (pair, method): status, errors (when ground truth exists), pose, latency."""
    rows = []
    for m, outs in outcomes.items():
        for p, o in zip(pairs, outs):
            status = "exception" if o.raised else ("ok" if o.valid else "invalid")
            row: dict[str, Any] = {"pair_id": p.pair_id, "method": m, "status": status,
                                   "reason": o.reason, "fitness": round(o.fitness, 6),
                                   "latency_ms": round(1000 * o.latency_s, 3)}
            if p.T_gt is not None:
                e = metrics.pair_errors(p.T_gt, o.T if o.T is not None else np.eye(4))
                d = e.euler_diff_deg[0]
                row.update(rot_error_deg=float(e.rot_error_deg[0]), trans_error=float(e.trans_error[0]),
                           euler_diff_x=float(d[0]), euler_diff_y=float(d[1]), euler_diff_z=float(d[2]))
            else:
                row.update(rot_error_deg="", trans_error="", euler_diff_x="", euler_diff_y="",
                           euler_diff_z="")
            tx, ty, tz, rx, ry, rz = _pose_cells(o.T)
            row.update(tx=tx, ty=ty, tz=tz, euler_x_deg=rx, euler_y_deg=ry, euler_z_deg=rz)
            if "overlap" in p.info:
                row["overlap"] = p.info["overlap"]
            rows.append(row)
    return rows


def write_pairs_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    fields = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)


def plot_errors(path: Path, pairs: Sequence[EvalPair], outcomes: dict[str, list[Outcome]],
                thresholds: metrics.RecallThresholds) -> bool:
    """CDF of isotropic rotation and translation errors per method; False without ground truth."""
    if not pairs or any(p.T_gt is None for p in pairs):
        return False
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    T_gt = np.stack([p.T_gt for p in pairs])
    for m, outs in outcomes.items():
        T_est = np.stack([o.T if o.T is not None else np.eye(4) for o in outs])
        e = metrics.pair_errors(T_gt, T_est)
        ok = np.array([o.valid and not o.raised for o in outs])
        # Failed pairs are drawn at infinity: the curve then tops out at the success share.
        # Log axes: errors below a floor (0.01 deg, 1e-4 units) are drawn at the floor.
        for ax, vals, floor in ((axes[0], e.rot_error_deg, 1e-2), (axes[1], e.trans_error, 1e-4)):
            v = np.sort(np.where(ok, np.maximum(vals, floor), np.inf))
            ax.step(v, np.arange(1, len(v) + 1) / len(v), where="post", label=m)
    axes[0].axvline(thresholds.rot_deg, color="grey", ls=":", lw=1)
    if thresholds.trans is not None:
        axes[1].axvline(thresholds.trans, color="grey", ls=":", lw=1)
    axes[0].set(xscale="log", xlabel="rotation error (deg; < 0.01 drawn at 0.01)",
                ylabel="fraction of pairs")
    axes[1].set(xscale="log", xlabel="translation error (< 1e-4 drawn at 1e-4)",
                ylabel="fraction of pairs")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.set_ylim(0, 1.02)
    axes[0].legend(loc="best", fontsize="small")
    fig.suptitle(f"{len(pairs)} pairs; failures (invalid/exception) never reach the curve")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def report_markdown(title: str, pairs: Sequence[EvalPair], outcomes: dict[str, list[Outcome]],
                    summaries: dict[str, dict[str, Any]], thresholds: metrics.RecallThresholds,
                    settings: dict[str, Any]) -> str:
    has_gt = bool(pairs) and all(p.T_gt is not None for p in pairs)
    lines = [f"# {title}", ""]
    lines.append(f"{len(pairs)} pairs; methods: {', '.join(outcomes)}.")
    lines.append("")
    if has_gt:
        lines += [table_markdown(summaries), "",
                  "RMSE/MAE(R): Euler xyz (extrinsic, scipy 'xyz') degrees, as RPM-Net/DCP; "
                  "RMSE/MAE(t) and Error(t) in the clouds' units; Error(R)/(t): mean isotropic "
                  f"errors; recall: {thresholds.describe()} on a valid result; failures = "
                  "invalid + exception (scored with identity), out of all pairs."]
    else:
        cols = (("median_latency_ms", "median ms", True), ("mean_fitness", "mean fitness", False))
        lines += ["No ground truth in this bag: poses and fitness only.", "",
                  table_markdown(summaries, columns=cols), "", "## Poses (T_target_source)", "",
                  "| pair | method | status | tx | ty | tz | euler x | euler y | euler z | fitness |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for row in pairs_rows(pairs, outcomes):
            lines.append(f"| {row['pair_id']} | {row['method']} | {row['status']} | {row['tx']} | "
                         f"{row['ty']} | {row['tz']} | {row['euler_x_deg']} | {row['euler_y_deg']} | "
                         f"{row['euler_z_deg']} | {row['fitness']:.3f} |")
    failures = [(o.pair_id, m, o.reason or "invalid") for m, outs in outcomes.items()
                for o in outs if o.raised or not o.valid]
    if failures:
        lines += ["", "## Failures", ""]
        lines += [f"- {pid} / {m}: {reason}" for pid, m, reason in failures[:50]]
        if len(failures) > 50:
            lines.append(f"- ... and {len(failures) - 50} more (see pairs.csv)")
    lines += ["", "## Settings", ""]
    for k, v in settings.items():
        if isinstance(v, list):
            lines.append(f"- {k}:")
            lines += [f"  - {x}" for x in v]
        else:
            lines.append(f"- {k}: {v}")
    return "\n".join(lines) + "\n"


@dataclass
class Evaluation:
    """Everything one evaluation produced."""

    pairs: list[EvalPair]
    outcomes: dict[str, list[Outcome]]
    summaries: dict[str, dict[str, Any]]
    thresholds: metrics.RecallThresholds
    settings: dict[str, Any]
    title: str


def write_outputs(ev: Evaluation, out_dir: str | Path) -> dict[str, Path]:
    """metrics.json, pairs.csv, report.md and errors.png (with ground truth) into out_dir."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"metrics": out / "metrics.json", "pairs": out / "pairs.csv",
             "report": out / "report.md", "errors": out / "errors.png"}
    has_gt = bool(ev.pairs) and all(p.T_gt is not None for p in ev.pairs)
    doc = {"title": ev.title, "n_pairs": len(ev.pairs), "has_ground_truth": has_gt,
           "recall_definition": ev.thresholds.describe(),
           "methods": {m: {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                           for k, v in s.items()} for m, s in ev.summaries.items()},
           "settings": ev.settings}
    paths["metrics"].write_text(json.dumps(doc, indent=2) + "\n")
    write_pairs_csv(paths["pairs"], pairs_rows(ev.pairs, ev.outcomes))
    paths["report"].write_text(report_markdown(ev.title, ev.pairs, ev.outcomes, ev.summaries,
                                               ev.thresholds, ev.settings))
    if not plot_errors(paths["errors"], ev.pairs, ev.outcomes, ev.thresholds):
        paths.pop("errors")
    return paths


def machine_line() -> str:
    import os
    import platform
    return f"{platform.machine()} {os.cpu_count()} CPU, {platform.system()} {platform.release()}, " \
           f"python {platform.python_version()}"


def evaluate(pairs: Sequence[EvalPair], methods: Sequence[str], *,
             thresholds: metrics.RecallThresholds = metrics.SEVEN_SCENES_RECALL,
             checkpoint: str | None = None, baseline_config: Any = None,
             node_outcomes: dict[str, list[Outcome]] | None = None, progress: bool = True,
             title: str = "cegc-eval", settings: dict[str, Any] | None = None,
             params_file: str | Path | None = None) -> Evaluation:
    """Score ``methods`` on ``pairs``; methods present in ``node_outcomes`` are taken from there."""
    from cegc_ros import baselines

    pairs = list(pairs)
    node_outcomes = node_outcomes or {}
    offline = [m for m in methods if m not in node_outcomes]
    runners = make_runners(offline, checkpoint, baseline_config, params_file)
    outs = run_offline(pairs, runners, progress=progress)
    outcomes = {m: (node_outcomes[m] if m in node_outcomes else outs[m]) for m in methods}
    st: dict[str, Any] = {"machine": machine_line(), "recall": thresholds.describe()}
    if any(m in CEGC_METHODS for m in methods):
        st["cegc"] = ("through register_node over DDS" if any(m in node_outcomes for m in CEGC_METHODS)
                      else "offline through cegc_ros.engine.Registrar")
        st["checkpoint"] = checkpoint or "from the parameter file (empty: shipped weights)"
        st["node parameters"] = str(params_file or default_params_file())
    if any(m in BASELINE_METHODS for m in methods):
        st["baselines"] = baselines.describe(baseline_config)
    st.update(settings or {})
    summaries = summarize_outcomes(pairs, outcomes, thresholds)
    return Evaluation(pairs, outcomes, summaries, thresholds, st, title)


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="cegc-eval", description="Evaluate CEGC and Open3D baselines on the pairs of a bag "
        "or on real fragment pairs; writes metrics.json, pairs.csv, report.md, errors.png.")
    p.add_argument("bag", nargs="?", help="pair bag (rosbag2 directory, sqlite3 or mcap)")
    p.add_argument("--real-dir", help="folder of real pairs with ground truth (instead of a bag): "
                                      + REAL_LAYOUTS)
    p.add_argument("--real-protocol", choices=("pairs", "7scenes"), default="pairs",
                   help="with --real-dir: the listed pairs (default) or the 7Scenes protocol on "
                        "their fragments")
    p.add_argument("--num-pairs", type=int, default=60, help="7scenes protocol: pairs (default 60)")
    p.add_argument("--num-points", type=int, default=2048,
                   help="7scenes protocol: points resampled before the 75%% crops (default 2048)")
    p.add_argument("--subsample", type=int, default=None,
                   help="7scenes protocol: thin each cloud independently to this many points")
    p.add_argument("--resample-target", action="store_true",
                   help="7scenes protocol: the target crops an independent draw of the fragment "
                        "(no shared points)")
    p.add_argument("--noise-sigma", type=float, default=0.0,
                   help="7scenes protocol: Gaussian noise (clipped at 5 sigma) added to each cloud "
                        "independently, normalised units; the paper's robustness test uses 0.01")
    p.add_argument("--seed", type=int, default=0, help="7scenes protocol seed (default 0)")
    p.add_argument("--suite", action="store_true",
                   help="the README evaluation in one run: a 7scenes test bag, a fragments test "
                        "bag (both generated once into --cache), the real pairs of --real-dir and "
                        "the 7Scenes protocol on their fragments; one sub-folder each in --out "
                        "plus summary.md")
    p.add_argument("--suite-pairs", type=int, default=100,
                   help="suite: pairs of the 7scenes test bag (default 100)")
    p.add_argument("--suite-fragment-pairs", type=int, default=50,
                   help="suite: pairs of the fragments test bag (default 50)")
    p.add_argument("--suite-hard-pairs", type=int, default=30,
                   help="suite: pairs of the resampled-target and noisy 7Scenes-protocol sets on the "
                        "real fragments (default 30)")
    p.add_argument("--cache", default=".cache/eval", help="suite: where its bags are kept")
    p.add_argument("--methods", default=",".join(ALL_METHODS),
                   help=f"comma-separated subset of {','.join(ALL_METHODS)}")
    p.add_argument("--through-node", action="store_true",
                   help="run the CEGC methods in a register_node subprocess fed by replaying the bag")
    p.add_argument("--params", default=None,
                   help="register_node parameter file: CEGC's settings offline and in the node "
                        "(default params/register_node.yaml)")
    p.add_argument("--checkpoint", default=None, help="CEGC checkpoint (default: shipped weights)")
    p.add_argument("--voxel-ratio", type=float, default=None,
                   help="baselines: voxel as a fraction of the cloud extent (default "
                        "cegc_ros.baselines.BaselineConfig.voxel_ratio)")
    p.add_argument("--mutual-filter", action="store_true",
                   help="baselines: RANSAC with the mutual nearest-feature filter")
    p.add_argument("--recall-rot", type=float, default=None,
                   help="recall rotation threshold in degrees (default 5; 15 for real pairs)")
    p.add_argument("--recall-trans", type=float, default=None,
                   help="recall translation threshold (default none; 0.3 m for real pairs)")
    p.add_argument("--limit", type=int, default=None, help="evaluate only the first N pairs")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--out", required=True, help="output folder")
    return p


def _thresholds(args: argparse.Namespace, real_fragments: bool) -> metrics.RecallThresholds:
    base = metrics.REAL_FRAGMENT_RECALL if real_fragments else metrics.SEVEN_SCENES_RECALL
    rot = args.recall_rot if args.recall_rot is not None else base.rot_deg
    trans = args.recall_trans if args.recall_trans is not None else base.trans
    return metrics.RecallThresholds(rot, trans)


def run_cli(args: argparse.Namespace, argv: Sequence[str] = ()) -> Evaluation:
    methods = parse_methods(args.methods)
    if (args.bag is None) == (args.real_dir is None):
        raise EvalError("give either a BAG or --real-dir DIR")
    settings: dict[str, Any] = {}
    node_outcomes: dict[str, list[Outcome]] = {}
    if args.bag is not None:
        pairs = bag_pairs(args.bag)
        if args.limit:
            pairs = pairs[: args.limit]
        title = f"cegc-eval: {Path(args.bag).name}"
        settings["source"] = f"bag {args.bag}"
        protocols = {p.info.get("protocol") for p in pairs}
        real_fragments = protocols == {"fragments"}
        if args.through_node:
            node_methods = [m for m in methods if m in CEGC_METHODS]
            if node_methods:
                node_outcomes = run_through_node(
                    args.bag, pairs, node_methods, params_file=args.params,
                    checkpoint=args.checkpoint, progress=not args.no_progress)
    else:
        if args.through_node:
            raise EvalError("--through-node needs a BAG (write one with cegc-make-bag)")
        if args.real_protocol == "pairs":
            pairs = real_pairs(args.real_dir)
            real_fragments = True
            title = f"cegc-eval: real pairs in {args.real_dir}"
            settings["source"] = f"real fragment pairs {args.real_dir} (metres)"
        else:
            if not 0.0 <= args.noise_sigma < 0.5:
                raise EvalError(f"--noise-sigma must be in [0, 0.5), got {args.noise_sigma}")
            pairs = real_7scenes_pairs(args.real_dir, args.num_pairs, args.num_points, args.seed,
                                       args.subsample, args.resample_target, args.noise_sigma)
            real_fragments = False
            title = f"cegc-eval: 7Scenes protocol on the fragments of {args.real_dir}"
            settings["source"] = (f"7Scenes protocol (sample_7scenes_pair) on {args.real_dir}: "
                                  f"{args.num_pairs} pairs, {args.num_points} points resampled, "
                                  f"75% crops, seed {args.seed}"
                                  + (f", each cloud thinned to {args.subsample}" if args.subsample else "")
                                  + (", target an independent resample" if args.resample_target else "")
                                  + (f", Gaussian noise sigma {args.noise_sigma}" if args.noise_sigma else "")
                                  + "; normalised units (largest bbox side 1)")
        if args.limit:
            pairs = pairs[: args.limit]
    if not pairs:
        raise EvalError("no pairs to evaluate")
    thresholds = _thresholds(args, real_fragments)
    settings["command"] = " ".join(["cegc-eval", *argv])
    from cegc_ros.baselines import BaselineConfig
    bcfg = BaselineConfig(ransac_mutual_filter=args.mutual_filter)
    if args.voxel_ratio is not None:
        if not args.voxel_ratio > 0:
            raise EvalError(f"--voxel-ratio must be > 0, got {args.voxel_ratio}")
        bcfg.voxel_ratio = args.voxel_ratio
    return evaluate(pairs, methods, thresholds=thresholds, checkpoint=args.checkpoint,
                    baseline_config=bcfg,
                    node_outcomes=node_outcomes, progress=not args.no_progress, title=title,
                    settings=settings, params_file=args.params)


SUITE_NOISE = 0.01     # the paper's Gaussian-noise test: sigma 0.01, clipped at 0.05
DEFAULT_REAL_DIR = REPO_ROOT.parent / "shared" / "data" / "real" / "sun3d"


def run_suite(args: argparse.Namespace, argv: Sequence[str]) -> Path:
    """Every evaluation of the README table, same methods and settings; returns summary.md."""
    if args.bag is not None or args.through_node:
        raise EvalError("--suite makes its own bags and runs offline: no BAG, no --through-node")
    methods = parse_methods(args.methods)
    out = Path(args.out)
    progress = not args.no_progress
    from cegc_ros.baselines import BaselineConfig
    bcfg = BaselineConfig(ransac_mutual_filter=args.mutual_filter)
    if args.voxel_ratio is not None:
        bcfg.voxel_ratio = args.voxel_ratio
    real_dir = Path(args.real_dir) if args.real_dir else DEFAULT_REAL_DIR
    parts: list[tuple[str, str, Callable[[], list[EvalPair]], metrics.RecallThresholds]] = [
        ("7scenes_test",
         f"synthetic 7Scenes protocol, test split, {args.suite_pairs} pairs (normalised units)",
         lambda: bag_pairs(cached_bag(args.cache, "7scenes", "test", args.suite_pairs, 0, progress)),
         metrics.SEVEN_SCENES_RECALL),
        ("fragments_test",
         f"synthetic fragment pairs, test split, {args.suite_fragment_pairs} pairs (metres)",
         lambda: bag_pairs(cached_bag(args.cache, "fragments", "test", args.suite_fragment_pairs,
                                      0, progress)),
         metrics.REAL_FRAGMENT_RECALL),
    ]
    skipped = []
    if (real_dir / "pairs.tsv").is_file():
        parts += [
            ("real_pairs", f"real fragment pairs of {real_dir} (metres)",
             lambda: real_pairs(real_dir), metrics.REAL_FRAGMENT_RECALL),
            ("real_7scenes", f"7Scenes protocol on the real fragments of {real_dir}, "
                             f"{args.num_pairs} pairs, {args.num_points} points, seed {args.seed}",
             lambda: real_7scenes_pairs(real_dir, args.num_pairs, args.num_points, args.seed,
                                        args.subsample),
             metrics.SEVEN_SCENES_RECALL),
            ("real_7scenes_resample", f"as real_7scenes, the target an independent resample "
                                      f"(no shared points), {args.suite_hard_pairs} pairs, seed 9",
             lambda: real_7scenes_pairs(real_dir, args.suite_hard_pairs, args.num_points, 9,
                                        resample_target=True),
             metrics.SEVEN_SCENES_RECALL),
            ("real_7scenes_noise", f"as real_7scenes, Gaussian noise sigma {SUITE_NOISE} on each "
                                   f"cloud (the paper's noise test), {args.suite_hard_pairs} pairs, seed 9",
             lambda: real_7scenes_pairs(real_dir, args.suite_hard_pairs, args.num_points, 9,
                                        noise_sigma=SUITE_NOISE),
             metrics.SEVEN_SCENES_RECALL),
        ]
    else:
        skipped.append(f"real pairs: {real_dir / 'pairs.tsv'} not found (pass --real-dir)")
    lines = ["# cegc-eval --suite", "", f"Command: `{' '.join(['cegc-eval', *argv])}`", "",
             f"Machine: {machine_line()}", ""]
    combined: dict[str, Any] = {}
    for name, what, load, thresholds in parts:
        pairs = load()
        if args.limit:
            pairs = pairs[: args.limit]
        ev = evaluate(pairs, methods, thresholds=thresholds, checkpoint=args.checkpoint,
                      baseline_config=bcfg, progress=progress, title=f"cegc-eval: {what}",
                      settings={"source": what, "command": " ".join(["cegc-eval", *argv])},
                      params_file=args.params)
        write_outputs(ev, out / name)
        combined[name] = {"source": what, "recall": thresholds.describe(), "methods": ev.summaries}
        lines += [f"## {name}: {what}", "", table_markdown(ev.summaries), "",
                  f"Recall: {thresholds.describe()}. Details: [{name}/report.md]({name}/report.md)", ""]
    for text in skipped:
        lines += [f"Skipped: {text}", ""]
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(combined, indent=2, default=str) + "\n")
    summary = out / "summary.md"
    summary.write_text("\n".join(lines))
    return summary


def main(argv: Iterable[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    try:
        if args.suite:
            summary = run_suite(args, argv)
            print(summary.read_text())
            print(f"wrote {summary.parent}")
            return 0
        ev = run_cli(args, argv)
        paths = write_outputs(ev, args.out)
    except Exception as err:  # noqa: BLE001 - CLI boundary: one line, non-zero exit
        from cegc_ros.data.bag import BagError
        from cegc_ros.engine import CheckpointError
        if isinstance(err, (EvalError, BagError, CheckpointError, FileNotFoundError, ValueError)):
            print(f"cegc-eval: error: {err}", file=sys.stderr)
            return 2
        raise
    print(table_markdown(ev.summaries) if all(p.T_gt is not None for p in ev.pairs)
          else table_markdown(ev.summaries, columns=(("median_latency_ms", "median ms", True),
                                                     ("mean_fitness", "mean fitness", False))))
    print(f"wrote {', '.join(str(p) for p in paths.values())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
