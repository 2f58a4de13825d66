"""cegc-register: register two point-cloud files with the node's engine, without ROS.

    cegc-register SOURCE TARGET [--params FILE] [--json] [--out FILE]
    cegc-register --pairs LIST [--params FILE] [--json]

SOURCE and TARGET: .npy ((N, 3) or wider: the first three columns are x, y, z) or any point
cloud file Open3D reads (.ply, .pcd, .xyz, .xyzn, .xyzrgb, .pts); units are metres for the
node's default parameters. Prints T_target_source (maps source points into the target frame)
as a 4x4 matrix, the fitness, the ambiguity (how close another alignment came: 0 to 1),
whether the result is valid (and, for a pair drawn twice, ``draws 2``: the second draw of
``engine.redraw_ambiguity``) and the time of each stage; ``--json`` prints the same as one JSON
object instead (keys T_target_source, fitness, ambiguity, draws, valid, reason, timings;
timings in seconds). ``--params`` takes the node's parameter file
(``preprocess.*`` and ``engine.*`` are used); ``--out`` writes the source moved into the target
frame (.npy, or a format Open3D writes: .ply, .pcd, .xyz, .pts).

``--pairs LIST`` registers many pairs in one process (one start-up, one warm engine): LIST is
a text file with one pair per line, ``SOURCE TARGET [OUT]`` (whitespace-separated; relative
paths are relative to LIST's folder; ``#`` starts a comment). Each pair prints as above, headed
by its line, or with ``--json`` one JSON object per line (JSON Lines) that also has ``line``,
``source``, ``target`` and ``wall_s`` (reading, registering and writing that pair). A pair that
fails prints one line on stderr naming its line in LIST and the run goes on with the next.

Exit status: 0 when a result was computed (valid or not: see ``valid``) for every pair, 1 with
one line on stderr per problem when a file or parameter cannot be used or the engine fails, 2
for a usage error.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

PROG = "cegc-register"
OPEN3D_FORMATS = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
WRITE_FORMATS = (".npy", ".ply", ".pcd", ".xyz", ".pts")


class InputError(RuntimeError):
    """A file or parameter cannot be used; the message is the one line shown to the user."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description="Register SOURCE onto TARGET with CEGC (the engine of "
                               "register_node) and print T_target_source.")
    p.add_argument("source", type=Path, nargs="?", help="cloud to move: .npy, .ply, .pcd, .xyz, ...")
    p.add_argument("target", type=Path, nargs="?", help="cloud that stays: .npy, .ply, .pcd, .xyz, ...")
    p.add_argument("--pairs", type=Path, default=None, metavar="LIST",
                   help="a text file of pairs, one 'SOURCE TARGET [OUT]' per line: all of them "
                        "in one process")
    p.add_argument("--params", type=Path, default=None,
                   help="the node's parameter file (ros__parameters YAML); default: the "
                        "node's defaults")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--out", type=Path, default=None,
                   help="write the source moved into the target frame (.npy .ply .pcd .xyz .pts)")
    return p


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silence C-level stderr (Open3D's readers print their own complaints there)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def read_cloud(path: Path) -> np.ndarray:
    """(N, 3) float64 points of a cloud file; InputError naming the file and the problem."""
    suffix = path.suffix.lower()
    if suffix != ".npy" and suffix not in OPEN3D_FORMATS:
        raise InputError(f"{path}: unknown format {suffix or '(no extension)'}; use .npy or "
                         f"one of {' '.join(OPEN3D_FORMATS)}")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    if suffix == ".npy":
        try:
            xyz = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as err:
            why = "not a .npy file" if "pickle" in str(err) else str(err)   # numpy's advice is wrong here
            raise InputError(f"{path}: not a readable .npy array ({why})".splitlines()[0]) from err
        if xyz.ndim != 2 or xyz.shape[1] < 3 or not np.issubdtype(xyz.dtype, np.number):
            raise InputError(f"{path}: expected an (N, 3) numeric array, got shape "
                             f"{xyz.shape} of {xyz.dtype}")
        xyz = xyz[:, :3]
    else:
        import open3d as o3d

        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        with _quiet_stderr():
            cloud = o3d.io.read_point_cloud(str(path))
        xyz = np.asarray(cloud.points)
    if len(xyz) == 0:
        raise InputError(f"{path}: no points (empty, or not a readable {suffix} file)")
    xyz = np.asarray(xyz, dtype=np.float64)
    if not np.isfinite(xyz).all(axis=1).any():
        raise InputError(f"{path}: no finite points (all {len(xyz)} have a NaN or inf coordinate)")
    return xyz


def write_cloud(path: Path, xyz: np.ndarray) -> None:
    """Write (N, 3) points to ``path`` in the format its extension names."""
    suffix = path.suffix.lower()
    if suffix not in WRITE_FORMATS:
        raise InputError(f"--out {path}: unknown format {suffix or '(no extension)'}; use one "
                         f"of {' '.join(WRITE_FORMATS)}")
    try:
        if suffix == ".npy":
            np.save(path, xyz)
            return
        import open3d as o3d

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
        with _quiet_stderr():
            ok = o3d.io.write_point_cloud(str(path), cloud)
    except OSError as err:
        raise InputError(f"--out {path}: cannot write it ({err.strerror})") from err
    if not ok:
        raise InputError(f"--out {path}: Open3D could not write it")


def engine_settings(params_file: Path | None) -> tuple[Any, Any]:
    """(PreprocessConfig, EngineConfig) as register_node builds them from ``params_file``."""
    from cegc_ros.config import EngineConfig, PreprocessConfig

    if params_file is None:
        return PreprocessConfig(), EngineConfig()
    from cegc_ros.node.params import (
        ENGINE_SECTIONS,
        ParameterError,
        build_sections,
        check_values,
        param_specs,
    )
    from cegc_ros.params_file import ParamsFileError, read_params_file

    try:
        values = read_params_file(params_file)
        checked = check_values(values)
    except ParamsFileError as err:
        raise InputError(str(err)) from err
    except ParameterError as err:
        raise InputError(f"parameter file {params_file}: {err}") from err
    known = {s.name for s in param_specs()}
    unknown = sorted(k for k in values
                     if k.split(".", 1)[0] in ENGINE_SECTIONS and k not in known)
    if unknown:
        raise InputError(f"parameter file {params_file}: unknown parameter "
                         f"{', '.join(unknown)}")
    sections = build_sections(checked)
    return sections["preprocess"], sections["engine"]


def result_dict(result: Any) -> dict[str, Any]:
    """The JSON document of one result."""
    return {"T_target_source": np.asarray(result.T_target_source, float).tolist(),
            "fitness": float(result.fitness),
            "ambiguity": float(result.ambiguity),
            "draws": int(getattr(result, "draws", 1)),
            "valid": bool(result.valid),
            "reason": result.reason,
            "timings": {k: float(v) for k, v in result.timings.items()}}


def format_result(result: Any) -> str:
    """The result for people: the matrix, its angle and shift, fitness, ambiguity, validity,
    timings."""
    from cegc_ros.metrics import rotation_error_deg

    T = np.asarray(result.T_target_source, float)
    rows = "\n".join("  " + " ".join(f"{v:10.6f}" for v in row) for row in T)
    angle = float(rotation_error_deg(np.eye(3), T[:3, :3]))
    stages = ", ".join(f"{k} {1000 * v:.1f}" for k, v in result.timings.items() if k != "total")
    total = result.timings.get("total")
    lines = [
        "T_target_source (maps source points into the target frame):",
        rows,
        (f"rotation {angle:.3f} deg, translation {np.linalg.norm(T[:3, 3]):.4f} "
         "(units of the input)"),
        (f"fitness  {result.fitness:.4f} (share of source points within "
         f"{result.inlier_distance:.4g} of a target point after alignment)"),
        (f"ambiguity {result.ambiguity:.3f} (0: no other alignment came near; 1: another one "
         "explains the clouds as well)"),
        "valid    " + ("yes" if result.valid else f"no: {result.reason}"),
        f"timings  ms: {stages}" + (f"; total {1000 * total:.1f}" if total is not None else ""),
    ]
    if getattr(result, "draws", 1) > 1:
        lines.insert(-1, f"draws    {result.draws} (the network points drawn again: engine.redraw_ambiguity)")
    return "\n".join(lines)


def read_pair_list(path: Path) -> list[tuple[int, Path, Path, Path | None]]:
    """(line number, source, target, out or None) of each pair in a ``--pairs`` LIST file."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"--pairs {path}: cannot read it ({err})".splitlines()[0]) from err
    pairs = []
    for number, line in enumerate(text.splitlines(), 1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        if len(words) not in (2, 3):
            raise InputError(f"--pairs {path}:{number}: expected 'SOURCE TARGET [OUT]', got "
                             f"{len(words)} fields")
        paths = [p if p.is_absolute() else path.parent / p for p in map(Path, words)]
        pairs.append((number, paths[0], paths[1], paths[2] if len(paths) == 3 else None))
    if not pairs:
        raise InputError(f"--pairs {path}: no pairs in it")
    return pairs


def _error_line(err: Exception, where: str = "") -> str:
    text = str(err).strip().splitlines()
    name = "" if isinstance(err, InputError) else f"{type(err).__name__}: "
    return f"{PROG}: error: {where}{name}{text[0] if text else type(err).__name__}"


def _register_one(registrar: Any, source: np.ndarray, target: np.ndarray, out: Path | None) -> Any:
    result = registrar.register(source, target)
    if out is not None:
        T = np.asarray(result.T_target_source, float)
        write_cloud(out, source @ T[:3, :3].T + T[:3, 3])
    return result


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)   # exits 2 on a usage error
    if args.pairs is not None and (args.source is not None or args.out is not None):
        parser.error("--pairs LIST replaces SOURCE TARGET and --out (OUT is LIST's third column)")
    if args.pairs is None and (args.source is None or args.target is None):
        parser.error("SOURCE and TARGET are required (or --pairs LIST)")
    try:
        pre, eng = engine_settings(args.params)
        if args.pairs is not None:
            jobs = read_pair_list(args.pairs)
        else:
            jobs = [(0, args.source, args.target, args.out)]
        for _, _, _, out in jobs:
            if out is not None and out.suffix.lower() not in WRITE_FORMATS:
                raise InputError(f"--out {out}: unknown format; use one of {' '.join(WRITE_FORMATS)}")
        # SOURCE TARGET: read before the engine loads, so that a bad file fails at once.
        preloaded = None if args.pairs is not None else (read_cloud(args.source), read_cloud(args.target))
        from cegc_ros.engine import Registrar

        registrar = Registrar.from_checkpoint(eng.checkpoint or None, device=eng.device,
                                              preprocess=pre, engine=eng)
    except Exception as err:  # noqa: BLE001 - CLI boundary: one line, exit 1
        print(_error_line(err), file=sys.stderr)
        return 1
    failed = 0
    for number, src, tgt, out in jobs:
        where = f"--pairs {args.pairs}:{number}: " if args.pairs is not None else ""
        t0 = time.perf_counter()
        try:
            clouds = preloaded or (read_cloud(src), read_cloud(tgt))
            result = _register_one(registrar, *clouds, out)
        except Exception as err:  # noqa: BLE001 - one line per pair, the others go on
            print(_error_line(err, where), file=sys.stderr)
            failed += 1
            continue
        wall = time.perf_counter() - t0
        if args.pairs is None:
            print(json.dumps(result_dict(result)) if args.json else format_result(result))
        elif args.json:
            print(json.dumps({"line": number, "source": str(src), "target": str(tgt),
                              "wall_s": wall, **result_dict(result)}), flush=True)
        else:
            print(f"== {args.pairs}:{number}: {src} -> {tgt} ({1000 * wall:.0f} ms)\n"
                  f"{format_result(result)}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
