"""cegc-eval-seq: sequential mode (keyframe odometry) against ground truth, KISS-ICP beside it.

Runs the odometry core (:class:`cegc_ros.sequential.KeyframeOdometry`) directly on a sequence
of clouds, no DDS, and KISS-ICP (PyPI ``kiss-icp``) on the same clouds in the same run.

Sequences (one of):

* a sequence bag (``cegc-eval-seq BAG``): ``/cegc/cloud`` with ``/cegc/cloud_ground_truth``
  (:func:`cegc_ros.data.bag.write_sequence`);
* ``--scene SEED``: rendered on the fly through a synthetic room
  (:func:`cegc_ros.data.sequences.make_room_sequence`; ``--trajectory robot|handheld``),
  written as a bag with ``--save-bag``;
* ``--bunny DIR``: the Stanford bunny scans as an object sequence (a turntable ring).

``--drop START:COUNT`` removes frames (all methods see the same clouds): a dropped stretch.

Methods: ``cegc`` (keyframe odometry, CEGC global registration when ICP tracking fails),
``icp-only`` (the same without global registration: what CEGC adds) and ``kiss-icp``
(KISS-ICP 1.x ``KissICP.register_frame`` with ``deskew`` off, ``max_range`` from
``sequential.max_range`` (else ``--kiss-max-range``) and the voxel grid our odometry uses
(``sequential.voxel_size`` or the one derived from the first cloud); skipped, with the reason,
when the package is not installed).

Metrics (:mod:`cegc_ros.sequential.metrics`): ATE from the first frame and after SE(3)
alignment, RPE (translation %, deg/m) per ``--rpe-lengths``, consecutive-frame errors,
keyframes, recoveries, rejections, per-frame latency. Outputs in ``--out``: ``report.md``,
``metrics.json``, ``frames.csv``, ``trajectory.png`` and ``settings.json`` (the settings used).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import importlib.util
import json
import os
import platform
import shlex
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

METHODS = ("cegc", "icp-only", "kiss-icp")


class EvalSeqError(RuntimeError):
    """The evaluation cannot run (bad input, unknown setting, ...); the message says why."""


@dataclass
class MethodRun:
    """One method over a sequence.

    poses: (K, 4, 4) T_odom_cloud, NaN where the method gave no pose; latency: (K,) seconds;
    status: per cloud, "first" / "icp" / "global" / "none" (odometry) or "kiss".
    """

    name: str
    poses: np.ndarray
    latency: np.ndarray
    status: list[str]
    counts: dict[str, int] = field(default_factory=dict)
    skipped: str = ""
    distances: str = ""         # the metre-valued settings used (odometry: derived or set)


# --------------------------------------------------------------------------------------------
# Settings
# --------------------------------------------------------------------------------------------

def _parse_value(text: str) -> Any:
    import yaml
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise EvalSeqError(f"--set value {text!r} is not a YAML scalar") from err


def _apply(obj: Any, section: str, values: dict[str, Any]) -> Any:
    """``obj`` (a config dataclass) with ``section.field`` values applied, range-checked."""
    names = {f.name: f for f in dataclasses.fields(obj)}
    changes = {}
    for key, value in values.items():
        sec, _, name = key.partition(".")
        if sec != section:
            continue
        if name not in names:
            raise EvalSeqError(f"unknown setting {key}; {section}.* has {sorted(names)}")
        default, meta = getattr(obj, name), names[name].metadata
        if isinstance(default, bool):
            ok = isinstance(value, bool)
        elif isinstance(default, (int, float)):
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            value = type(default)(value) if ok else value
        else:
            ok, value = True, str(value)
        if not ok:
            raise EvalSeqError(f"{key} must be a {type(default).__name__}, got {value!r}")
        lo, hi = meta.get("range", (None, None))
        if isinstance(value, (int, float)) and not isinstance(value, bool) and (
                (lo is not None and value < lo) or (hi is not None and value > hi)):
            raise EvalSeqError(f"{key} = {value} is outside [{lo}, {hi}]")
        if meta.get("choices") and value not in meta["choices"]:
            raise EvalSeqError(f"{key} must be one of {meta['choices']}, got {value!r}")
        changes[name] = value
    return dataclasses.replace(obj, **changes)


def load_settings(params: Path | None, sets: list[str]) -> dict[str, Any]:
    """preprocess / engine / sequential settings: defaults, then --params, then --set."""
    from cegc_ros.config import EngineConfig, PreprocessConfig, SequentialConfig

    values: dict[str, Any] = {}
    if params is not None:
        from cegc_ros.params_file import read_params_file
        values.update(read_params_file(params))
    for item in sets:
        key, eq, text = item.partition("=")
        if not eq or "." not in key:
            raise EvalSeqError(f"--set expects SECTION.FIELD=VALUE, got {item!r}")
        if key.split(".")[0] not in ("preprocess", "engine", "sequential"):
            raise EvalSeqError(f"--set {key}: only preprocess.*, engine.* and sequential.* "
                               "settings apply here")
        values[key] = _parse_value(text)
    return {"preprocess": _apply(PreprocessConfig(), "preprocess", values),
            "engine": _apply(EngineConfig(), "engine", values),
            "sequential": _apply(SequentialConfig(), "sequential", values)}


# --------------------------------------------------------------------------------------------
# Input
# --------------------------------------------------------------------------------------------

def _parse_drops(items: list[str]) -> list[tuple[int, int]]:
    out = []
    for item in items:
        start, _, count = item.partition(":")
        try:
            s, c = int(start), int(count)
        except ValueError:
            raise EvalSeqError(f"--drop expects START:COUNT (frame indices), got {item!r}") from None
        if s < 1 or c < 1:
            raise EvalSeqError(f"--drop {item}: START must be >= 1 (the first cloud is the "
                               "odometry frame) and COUNT >= 1")
        out.append((s, c))
    return out


def load_sequence(args: argparse.Namespace) -> Any:
    """The sequence the command line names, with --drop applied; EvalSeqError when unusable."""
    from cegc_ros.data import sequences

    drops = _parse_drops(args.drop)

    if args.bag is not None:
        from cegc_ros.data.bag import read_sequence, read_sequence_info
        frames = list(read_sequence(args.bag))
        if not frames:
            raise EvalSeqError(f"{args.bag} holds no clouds")
        if any(f.T_world_cloud is None for f in frames):
            missing = sum(f.T_world_cloud is None for f in frames)
            raise EvalSeqError(f"{args.bag}: {missing} of {len(frames)} clouds have no ground "
                               "truth (/cegc/cloud_ground_truth)")
        seq = sequences.Sequence([f.cloud for f in frames],
                                 np.stack([f.T_world_cloud for f in frames]),
                                 np.array([f.stamp_ns for f in frames], np.int64),
                                 frames[0].frame_id, read_sequence_info(args.bag))
        seq.info["bag"] = str(args.bag)
    elif args.lidar is not None:
        seq = sequences.make_lidar_sequence(args.lidar, args.clouds, scale=args.scale)
    elif args.scene is not None:
        seq = sequences.make_room_sequence(
            args.scene, args.clouds, frame_step=args.frame_step,
            frames_per_cloud=args.frames_per_cloud, pixel_stride=args.pixel_stride,
            trajectory=args.trajectory, noise=not args.no_noise)
    else:
        seq = sequences.load_bunny_sequence(args.bunny)
    if drops:
        gone = {k for s, c in drops for k in range(s, s + c)}
        keep = [k for k in range(len(seq)) if k not in gone]
        if len(keep) < 2:
            raise EvalSeqError(f"--drop leaves {len(keep)} of {len(seq)} clouds")
        seq = seq.subset(keep)
        seq.info["dropped"] = [list(d) for d in drops]
        seq.info["kept_indices"] = keep
    if len(seq) < 2:
        raise EvalSeqError(f"the sequence has {len(seq)} cloud(s); at least 2 are needed")
    return seq


# --------------------------------------------------------------------------------------------
# Methods
# --------------------------------------------------------------------------------------------

def run_odometry(name: str, seq: Any, config: Any, registration: Any = None,
                 progress: bool = False) -> MethodRun:
    """KeyframeOdometry over the sequence, warmed up first as the node does at start-up (so the
    first cloud's latency is not the imports'); unusable clouds count as rejected (no pose)."""
    from cegc_ros.sequential import KeyframeOdometry

    odo = KeyframeOdometry(config, registration)
    odo.warm_start()
    K = len(seq)
    poses = np.full((K, 4, 4), np.nan)
    latency = np.full(K, np.nan)
    status: list[str] = []
    for k in _progress(range(K), progress, name):
        t0 = time.perf_counter()
        try:
            r = odo.feed(int(seq.stamps_ns[k]), seq.clouds[k])
        except ValueError:
            status.append("invalid")
            latency[k] = time.perf_counter() - t0
            continue
        latency[k] = time.perf_counter() - t0
        status.append(r.method)
        if r.accepted:
            poses[k] = r.T_odom_cloud
    st = odo.stats
    return MethodRun(name, poses, latency, status, {
        "keyframes": st.keyframes, "tracked": st.tracked, "recoveries": st.recoveries,
        "rejected": st.rejected, "invalid": st.invalid},
        distances=odo.distances.describe() if odo.distances is not None else "")


def derived_voxel(seq: Any, config: Any) -> float:
    """The voxel grid our odometry uses on ``seq`` (``sequential.voxel_size``, or derived from
    the first cloud as :class:`KeyframeOdometry` derives it): KISS-ICP gets the same one."""
    from cegc_ros.sequential.odometry import distances_for

    return distances_for(config, seq.clouds[0]).voxel_size


def kiss_icp_available() -> bool:
    return importlib.util.find_spec("kiss_icp") is not None


def run_kiss_icp(seq: Any, voxel_size: float, max_range: float,
                 progress: bool = False) -> MethodRun:
    """KISS-ICP on the same clouds: deskew off, the given voxel size and range."""
    K = len(seq)
    if not kiss_icp_available():
        return MethodRun("kiss-icp", np.full((K, 4, 4), np.nan), np.full(K, np.nan),
                         ["none"] * K, skipped="kiss-icp is not installed (pip install "
                         "kiss-icp==1.3.0)")
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    cfg = KISSConfig()
    cfg.data.deskew = False
    cfg.data.max_range = float(max_range)
    cfg.data.min_range = 0.0
    cfg.mapping.voxel_size = float(voxel_size)
    cfg.registration.max_num_threads = 1          # like our odometry: one thread per frame
    odo = KissICP(cfg)
    poses = np.full((K, 4, 4), np.nan)
    latency = np.full(K, np.nan)
    for k in _progress(range(K), progress, "kiss-icp"):
        cloud = np.asarray(seq.clouds[k], np.float64)
        t0 = time.perf_counter()
        odo.register_frame(cloud, np.zeros(len(cloud)))
        latency[k] = time.perf_counter() - t0
        poses[k] = odo.last_pose
    return MethodRun("kiss-icp", poses, latency, ["kiss"] * K,
                     {"keyframes": 0, "tracked": K - 1, "recoveries": 0, "rejected": 0,
                      "invalid": 0},
                     distances=f"voxel {voxel_size:.4g} m, max range {max_range:g} m")


def _progress(it: Iterable[int], on: bool, name: str) -> Iterable[int]:
    if not on:
        return it
    from tqdm import tqdm
    return tqdm(it, desc=name, leave=False, file=sys.stderr)


# --------------------------------------------------------------------------------------------
# Scoring and outputs
# --------------------------------------------------------------------------------------------

def score(gt: np.ndarray, run: MethodRun, lengths: list[float]) -> dict[str, Any]:
    from cegc_ros.sequential import metrics

    lat = run.latency[np.isfinite(run.latency)] * 1000.0
    out: dict[str, Any] = ({"method": run.name, "skipped": run.skipped} | run.counts
                           | {"distances": run.distances})
    if run.skipped:
        return out
    out["ate"] = metrics.ate(gt, run.poses)
    out["rpe"] = metrics.rpe(gt, run.poses, lengths)
    out["step"] = metrics.step_errors(gt, run.poses)
    out["latency_ms"] = {"median": float(np.median(lat)), "p95": float(np.percentile(lat, 95)),
                         "max": float(lat.max())}
    if run.name != "kiss-icp":
        g = [run.latency[k] * 1000.0 for k, s in enumerate(run.status) if s == "global"]
        out["latency_ms"]["global_median"] = float(np.median(g)) if g else float("nan")
    return out


def _fmt(x: Any, digits: int = 3) -> str:
    if isinstance(x, float):
        return "-" if not np.isfinite(x) else f"{x:.{digits}f}"
    return str(x)


def report_markdown(summary: dict[str, Any]) -> str:
    rows = summary["methods"]
    lengths = summary["rpe_lengths"]
    head = ["method", "ATE first (mm)", "ATE aligned (mm)", "max (mm)", "rot err (deg)",
            "coverage"]
    head += [f"RPE {L:g} m (%, deg/m)" for L in lengths]
    head += ["step (mm, deg)", "keyframes", "recoveries", "rejected", "median ms", "p95 ms"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        if r["skipped"]:
            lines.append(f"| {r['method']} | skipped: {r['skipped']} |" + " |" * (len(head) - 2))
            continue
        a, s, lat = r["ate"], r["step"], r["latency_ms"]
        mm = {k: a[k] * 1000.0 for k in ("rmse_first", "rmse_aligned", "max_first")}
        cells = [r["method"], _fmt(mm["rmse_first"], 1), _fmt(mm["rmse_aligned"], 1),
                 _fmt(mm["max_first"], 1), _fmt(a["rot_first"], 2), _fmt(a["coverage"], 2)]
        for L in lengths:
            e = r["rpe"][f"{L:g}"]
            cells.append(f"{_fmt(e['trans_pct'], 1)}, {_fmt(e['rot_deg_per_m'], 2)}")
        cells += [f"{_fmt(s['trans_mean'] * 1000.0, 1)}, {_fmt(s['rot_mean'], 2)}", r["keyframes"],
                  r["recoveries"], r["rejected"], _fmt(lat["median"], 0), _fmt(lat["p95"], 0)]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    info = summary["sequence"]
    text = [f"# cegc-eval-seq: {info['name']}", "",
            (f"{info['clouds']} clouds, ground-truth path {info['path_length_m']:.2f} m; "
              "ATE (RMS position error) 'first' from the first frame, 'aligned' after SE(3) "
             "alignment; rot err: mean rotation error from the first frame; coverage: share "
             "of clouds with a pose."), "",
            *lines, "",
            *[f"- {r['method']}: {r['distances']}" for r in rows if r.get("distances")], "",
            f"Command: `{summary['command']}`", "",
            f"Machine: {summary['machine']}", ""]
    return "\n".join(text)


def plot(path: Path, gt: np.ndarray, runs: list[MethodRun], title: str) -> None:
    """Trajectories projected on the ground truth's principal plane, and error over frames."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = gt[:, :3, 3]
    centre = P.mean(0)
    _, _, Vt = np.linalg.svd(P - centre)
    axes = Vt[:2]                                      # (2, 3) the plane the path spans most
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 5))
    g2 = (P - centre) @ axes.T
    ax.plot(g2[:, 0], g2[:, 1], "k-", lw=2.5, label="ground truth")
    ax.plot(g2[0, 0], g2[0, 1], "ko")
    for run in runs:
        if run.skipped:
            continue
        ok = np.isfinite(run.poses).all(axis=(1, 2))
        e2 = (run.poses[ok, :3, 3] - centre) @ axes.T
        ax.plot(e2[:, 0], e2[:, 1], ".-", ms=3, lw=1, label=run.name)
        err = np.full(len(gt), np.nan)
        err[ok] = np.linalg.norm(run.poses[ok, :3, 3] - P[ok], axis=1)
        line, = bx.plot(np.arange(len(gt)), err, lw=1, label=run.name)
        rec = [k for k, s in enumerate(run.status) if s == "global"]
        if rec:
            bx.plot(rec, err[rec], "o", color=line.get_color(), ms=5, mfc="none")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("m (first principal axis of the path)")
    ax.set_ylabel("m (second)")
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    bx.set_xlabel("cloud")
    bx.set_ylabel("position error from the first frame (m)")
    bx.set_title("error per cloud (circles: CEGC global recoveries)", fontsize=9)
    bx.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def machine_line() -> str:
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    from cegc_ros.evaluation.report import cpu_model
    return (f"{cpu_model()} ({platform.machine()}), {os.cpu_count()} CPUs, {platform.python_implementation()} "
            f"{platform.python_version()}, load average {load[0]:.1f} / {load[1]:.1f} / "
            f"{load[2]:.1f} (1/5/15 min) at the end of the run")


def write_outputs(out: Path, seq: Any, runs: list[MethodRun], summary: dict[str, Any],
                  settings: dict[str, Any]) -> dict[str, Path]:
    out.mkdir(parents=True, exist_ok=True)
    paths = {"report": out / "report.md", "metrics": out / "metrics.json",
             "frames": out / "frames.csv", "plot": out / "trajectory.png",
             "settings": out / "settings.json"}
    paths["report"].write_text(report_markdown(summary))
    paths["metrics"].write_text(json.dumps(summary, indent=2, default=float))
    paths["settings"].write_text(json.dumps({k: dataclasses.asdict(v) for k, v in
                                             settings.items()}, indent=2))
    gt = seq.relative_poses()
    with paths["frames"].open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["method", "index", "stamp_ns", "status", "x", "y", "z", "gt_x", "gt_y",
                    "gt_z", "error_m", "latency_ms"])
        for run in runs:
            if run.skipped:
                continue
            for k in range(len(seq)):
                t = run.poses[k, :3, 3]
                err = float(np.linalg.norm(t - gt[k, :3, 3]))
                w.writerow([run.name, k, int(seq.stamps_ns[k]), run.status[k],
                            *(f"{v:.5f}" for v in t), *(f"{v:.5f}" for v in gt[k, :3, 3]),
                            f"{err:.5f}", f"{run.latency[k] * 1000:.2f}"])
    plot(paths["plot"], gt, runs, summary["sequence"]["name"])
    return paths


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="cegc-eval-seq",
        description="Evaluate sequential mode (keyframe odometry with CEGC recovery) and "
                    "KISS-ICP on a sequence of clouds with ground-truth poses.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("bag", nargs="?", type=Path, help="sequence bag (/cegc/cloud + ground truth)")
    src.add_argument("--scene", type=int, help="render a sequence through synthetic room SEED")
    src.add_argument("--lidar", type=int, metavar="SEED",
                     help="a LiDAR sequence through synthetic room SEED (one sweep per cloud)")
    src.add_argument("--bunny", type=Path, help="bunny scans folder (../shared/data/real/bunny)")
    p.add_argument("--trajectory", choices=("robot", "handheld"), default="robot",
                   help="camera motion of --scene (default robot)")
    p.add_argument("--clouds", type=int, default=150,
                   help="clouds of --scene or --lidar (default 150)")
    p.add_argument("--scale", type=float, default=1.0,
                   help="--lidar: every length times this (10: a 30-50 m hall; default 1)")
    p.add_argument("--frame-step", type=int, default=3,
                   help="trajectory frames (30 fps) between clouds of --scene (default 3: 10 Hz)")
    p.add_argument("--frames-per-cloud", type=int, default=1,
                   help="depth frames fused per cloud of --scene (default 1)")
    p.add_argument("--pixel-stride", type=int, default=4,
                   help="render every Nth Kinect pixel for --scene (default 4)")
    p.add_argument("--no-noise", action="store_true", help="--scene without sensor noise")
    p.add_argument("--drop", action="append", default=[], metavar="START:COUNT",
                   help="leave out COUNT clouds from index START (repeatable)")
    p.add_argument("--save-bag", type=Path, help="write the evaluated sequence as a bag")
    p.add_argument("--methods", default=",".join(METHODS),
                   help=f"comma-separated, of {', '.join(METHODS)} (default all)")
    p.add_argument("--params", type=Path,
                   help="ROS 2 parameter file: its preprocess.*, engine.*, sequential.* apply")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override one setting, e.g. sequential.voxel_size=0.003 (repeatable)")
    p.add_argument("--device", default=None, help="torch device for CEGC (default engine.device)")
    p.add_argument("--kiss-max-range", type=float, default=100.0,
                   help="KISS-ICP max_range when sequential.max_range is 0 (default 100 m)")
    p.add_argument("--rpe-lengths", default="0.5,1,2",
                   help="RPE segment lengths in metres (default 0.5,1,2)")
    p.add_argument("--out", type=Path, default=Path("runs/eval_seq"), help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def run_cli(args: argparse.Namespace, argv: list[str]) -> tuple[dict[str, Any], dict[str, Path]]:
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise EvalSeqError(f"unknown method(s) {unknown or args.methods!r}; choose from "
                           f"{', '.join(METHODS)}")
    try:
        lengths = [float(x) for x in args.rpe_lengths.split(",") if x.strip()]
    except ValueError:
        raise EvalSeqError(f"--rpe-lengths must be numbers, got {args.rpe_lengths!r}") from None
    if not lengths or min(lengths) <= 0:
        raise EvalSeqError("--rpe-lengths must be positive")
    settings = load_settings(args.params, args.set)
    seq = load_sequence(args)
    if args.save_bag is not None:
        from cegc_ros.data.bag import write_sequence
        write_sequence(args.save_bag, seq)
    gt = seq.relative_poses()
    progress = not args.quiet
    runs: list[MethodRun] = []
    cfg = settings["sequential"]
    for m in methods:
        if m == "cegc":
            from cegc_ros.engine import Registrar
            eng = settings["engine"]
            registrar = Registrar.from_checkpoint(
                None, device=args.device or eng.device, preprocess=settings["preprocess"],
                engine=eng)
            runs.append(run_odometry("cegc", seq, cfg, registrar.register, progress))
        elif m == "icp-only":
            runs.append(run_odometry("icp-only", seq, cfg, None, progress))
        else:
            max_range = cfg.max_range if cfg.max_range > 0 else args.kiss_max_range
            runs.append(run_kiss_icp(seq, derived_voxel(seq, cfg), max_range, progress))
    from cegc_ros.sequential.metrics import path_length
    name = (f"bag {seq.info.get('bag')}" if args.bag is not None else
            f"lidar {args.lidar} (scale {args.scale:g})" if args.lidar is not None else
            f"room {args.scene} ({args.trajectory})" if args.scene is not None else "bunny")
    summary = {
        "sequence": {"name": name, "clouds": len(seq), "path_length_m": path_length(gt),
                     "info": seq.info},
        "rpe_lengths": lengths,
        "methods": [score(gt, r, lengths) for r in runs],
        "command": "cegc-eval-seq " + " ".join(shlex.quote(a) for a in argv),
        "machine": machine_line(),
    }
    paths = write_outputs(args.out, seq, runs, summary, settings)
    return summary, paths


def main(argv: Iterable[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    from cegc_ros.data.bag import BagError
    from cegc_ros.engine import CheckpointError
    try:
        summary, paths = run_cli(args, argv)
    except (EvalSeqError, BagError, CheckpointError, FileNotFoundError, ValueError) as err:
        print(f"cegc-eval-seq: error: {err}", file=sys.stderr)
        return 1
    print(report_markdown(summary))
    print(f"wrote {', '.join(str(p) for p in paths.values())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
