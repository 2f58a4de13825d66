"""Scoring and the files ``cegc-eval`` writes: metrics.json, pairs.csv, report.md, errors.png.

Metrics are :mod:`cegc_ros.metrics` (RPM-Net/DCP definitions). A method that raised or returned
an invalid result on a pair is a recall failure on it, scored with its estimate (identity when
it raised); nothing is skipped.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cegc_ros import metrics
from cegc_ros.evaluation import EvalPair, Outcome

# Table columns: (key in the summary, header, lower is better)
COLUMNS = (
    ("rmse_r", "RMSE(R)", True), ("rmse_t", "RMSE(t)", True),
    ("mae_r", "MAE(R)", True), ("mae_t", "MAE(t)", True),
    ("error_r", "Error(R)", True), ("error_t", "Error(t)", True),
    ("recall", "recall", False), ("median_latency_ms", "median ms", True),
)


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
                                   "ambiguity": round(o.ambiguity, 6),
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
                  ("RMSE/MAE(R): Euler xyz (extrinsic, scipy 'xyz') degrees, as RPM-Net/DCP; "
                   "RMSE/MAE(t) and Error(t) in the clouds' units; Error(R)/(t): mean isotropic "
                   f"errors; recall: {thresholds.describe()} on a valid result; failures = "
                   "invalid + exception (scored with identity), out of all pairs.")]
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


def cpu_model() -> str:
    """The CPU's model name and widest vector unit ("AMD EPYC, AVX2"), from /proc/cpuinfo;
    the machine's architecture where that is not readable. Numerics and speed differ between
    AVX2 and AVX-512 machines, so every benchmark names it."""
    import platform
    try:
        lines = open("/proc/cpuinfo", encoding="utf-8", errors="replace").read().splitlines()
    except OSError:
        return platform.machine()
    name = next((line.split(":", 1)[1].strip() for line in lines
                 if line.startswith("model name")), platform.machine())
    flags = next((line.split(":", 1)[1].split() for line in lines if line.startswith("flags")), [])
    vector = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else ""
    return f"{name}, {vector}" if vector else name


def host_line() -> str:
    """CPU (model, vector unit, architecture, count), OS and Python of this machine."""
    import os
    import platform
    return (f"{cpu_model()} ({platform.machine()}), {os.cpu_count()} CPU, {platform.system()} "
            f"{platform.release()}, python {platform.python_version()}")


def machine_line() -> str:
    """:func:`host_line` and the load average when the evaluation ran (timings depend on it)."""
    import os
    load = " ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "?"
    return f"{host_line()}, load average {load}"
