"""cegc-make-pairs: render different-view pairs of procedural rooms into an on-disk pair cache.

    cegc-make-pairs --split train --rooms 2000 --out .cache/pairs/train [--workers 2]
    cegc-make-pairs --stats --out .cache/pairs/train

Rooms 0 .. N-1 of the split (seeds from cegc_ros.data.splits) are rendered in shards of
``--rooms-per-shard`` rooms; a shard that exists is skipped, so the same command resumes an
interrupted run, and a larger ``--rooms`` appends. The settings are kept in ``cache.json``;
resuming with different settings is refused. ``--workers N`` renders N shards side by side
in spawned processes (a room's pairs depend on its seed alone, so the cache is the same).
Read the cache with
``cegc_ros.data.pair_cache.PairCache``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="cegc-make-pairs",
        description="Render different-view fragment pairs of procedural rooms into a pair "
                    "cache (resumable, appendable).")
    p.add_argument("--out", required=True, type=Path, help="cache directory (created if needed)")
    p.add_argument("--split", choices=("train", "val", "test"),
                   help="room-seed range (train / val / test never share a room)")
    p.add_argument("--rooms", type=int, help="make rooms 0 .. ROOMS-1 of the split (>= 1)")
    p.add_argument("--first-room", type=int, default=0,
                   help="make only rooms FIRST_ROOM .. ROOMS-1 this time (default 0; a multiple "
                        "of --rooms-per-shard): a cache grown in pieces, e.g. new rooms first for "
                        "a network that trained on the first ones (a training run takes the "
                        "shards in as they are written, train.refresh_steps)")
    p.add_argument("--rooms-per-shard", type=int, default=8,
                   help="rooms per shard file (default 8; fixed for a cache)")
    p.add_argument("--lidar-fraction", type=float, default=0.1,
                   help="fraction of rooms scanned with the LiDAR model instead of the Kinect "
                        "one, chosen by room seed (default 0.1)")
    p.add_argument("--fragments", type=int, default=7, help="fragments per room (default 7)")
    p.add_argument("--pairs", type=int, default=7,
                   help="at most this many different-view pairs per room (default 7)")
    p.add_argument("--copy-pairs", type=int, default=1,
                   help="copy-protocol pairs per room (default 1)")
    p.add_argument("--max-points", type=int, default=20000,
                   help="cap on the points of a fragment (default 20000)")
    p.add_argument("--wall-views", type=float, default=0.0,
                   help="share of a Kinect room's focuses put on a wall (default 0: as the "
                        "caches before it; docs/data.md)")
    p.add_argument("--stats", action="store_true",
                   help="print what the cache at --out holds (pairs, overlap histogram, "
                        "throughput) and exit")
    p.add_argument("--workers", type=int, default=1,
                   help="processes rendering shards side by side (default 1; a room's pairs "
                        "depend on its seed alone, so any count writes the same pairs; one "
                        "process keeps about one core busy)")
    p.add_argument("--quiet", action="store_true", help="no per-shard progress lines")
    return p


def _generator_digest() -> str:
    """Hash of the data-generating sources (recorded per shard)."""
    from cegc_ros.data import rooms, scenes, sensors, views
    h = hashlib.sha256()
    for m in (rooms, scenes, sensors, views):
        h.update(Path(m.__file__).read_bytes())
    return h.hexdigest()[:12]


def _settings(args: argparse.Namespace) -> dict[str, Any]:
    return {"split": args.split, "rooms_per_shard": args.rooms_per_shard,
            "lidar_fraction": args.lidar_fraction, "fragments": args.fragments,
            "pairs": args.pairs, "copy_pairs": args.copy_pairs, "max_points": args.max_points,
            "overlap_range": [0.1, 0.9], "wall_views": args.wall_views}


#: What a setting was before cache.json recorded it (the caches made before it had these).
_SETTING_BEFORE = {"wall_views": 0.0}


def _usage_errors(args: argparse.Namespace) -> str | None:
    if args.stats:
        return None
    if args.split is None or args.rooms is None:
        return "--split and --rooms are required (or --stats)"
    checks = [(args.rooms >= 1, f"--rooms must be >= 1, got {args.rooms}"),
              (args.rooms_per_shard >= 1, "--rooms-per-shard must be >= 1"),
              (0 <= args.first_room < args.rooms, f"--first-room must be in [0, --rooms), got "
                                                   f"{args.first_room}"),
              (args.rooms_per_shard < 1 or args.first_room % args.rooms_per_shard == 0,
               f"--first-room must be a multiple of --rooms-per-shard ({args.rooms_per_shard}), "
               f"got {args.first_room}"),
              (0.0 <= args.lidar_fraction <= 1.0, "--lidar-fraction must be in [0, 1]"),
              (args.fragments >= 2, "--fragments must be >= 2"),
              (args.pairs >= 0 and args.copy_pairs >= 0, "--pairs/--copy-pairs must be >= 0"),
              (args.max_points >= 100, "--max-points must be >= 100"),
              (0.0 <= args.wall_views <= 1.0, "--wall-views must be in [0, 1]"),
              (args.workers >= 1, f"--workers must be >= 1, got {args.workers}")]
    return next((msg for ok, msg in checks if not ok), None)


def make_shard(out: Path, split: str, k0: int, rooms_per_shard: int, lidar_fraction: float,
               config: Any, settings: dict[str, Any], digest: str) -> tuple[int, int, float, float]:
    """Render rooms k0 .. k0 + rooms_per_shard - 1 of ``split`` and write their shard into
    ``out`` -> (k0, pairs written, wall seconds, load average at the end). Module level so that
    ``--workers`` processes can run it."""
    from cegc_ros.data import splits
    from cegc_ros.data.pair_cache import shard_name, write_shard
    from cegc_ros.data.views import make_room_pairs, sensor_for_room

    t0, c0 = time.time(), time.process_time()
    rooms = []
    for k in range(k0, k0 + rooms_per_shard):
        seed = splits.room_seed(split, k)
        rooms.append(make_room_pairs(seed, sensor_for_room(seed, lidar_fraction), config))
    seconds = time.time() - t0
    load = round(os.getloadavg()[0], 2)
    meta = dict(settings, first_room=k0, end_room=k0 + rooms_per_shard, generator=digest,
                seconds=round(seconds, 2), cpu_seconds=round(time.process_time() - c0, 2),
                load_avg=load)
    n = write_shard(out / shard_name(k0, k0 + rooms_per_shard), rooms, meta)
    return k0, n, seconds, load


def _shards_made(todo: list[int], workers: int, make: Any) -> Any:
    """Yield ``make(k0)``'s results for every k0 of ``todo``: in turn in this process for one
    worker, else from ``workers`` spawned processes in the order they finish (spawned, not
    forked: the parent may hold torch's or OpenMP's threads). ``make`` must pickle (a
    functools.partial of :func:`make_shard`)."""
    if workers <= 1 or len(todo) <= 1:
        for k0 in todo:
            yield make(k0)
        return
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    with ProcessPoolExecutor(max_workers=min(workers, len(todo)),
                             mp_context=multiprocessing.get_context("spawn")) as pool:
        pending = {pool.submit(make, k0) for k0 in todo}
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    yield f.result()
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise


def generate(args: argparse.Namespace) -> int:
    import functools

    from cegc_ros.data import splits
    from cegc_ros.data.pair_cache import MANIFEST, read_manifest, shard_name
    from cegc_ros.data.views import ViewConfig

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    settings = _settings(args)
    manifest = read_manifest(out)
    if manifest:
        old = {k: manifest.get(k, _SETTING_BEFORE.get(k)) for k in settings}
        if old != settings:
            diff = {k: (old[k], settings[k]) for k in settings if old[k] != settings[k]}
            print(f"cegc-make-pairs: error: {out} was made with other settings "
                  f"(cache.json vs now: {diff}); use a new --out", file=sys.stderr)
            return 1
    else:
        (out / MANIFEST).write_text(json.dumps(dict(settings, format=1), indent=1) + "\n")
    R = args.rooms_per_shard
    n_rooms = min(args.rooms, splits.num_rooms(args.split))
    config = ViewConfig(fragments=args.fragments, pairs=args.pairs, copy_pairs=args.copy_pairs,
                        max_points=args.max_points, wall_views=args.wall_views)
    digest = _generator_digest()
    wanted = range(args.first_room, n_rooms, R)
    todo = [k0 for k0 in wanted if not (out / shard_name(k0, k0 + R)).exists()]
    if not args.quiet:
        side_by_side = min(args.workers, len(todo))
        workers = f" by {side_by_side} processes" if side_by_side > 1 else ""
        print(f"[cegc-make-pairs] {args.split}: rooms {args.first_room}-{n_rooms - 1} in "
              f"{len(wanted)} shards, {len(wanted) - len(todo)} done, {len(todo)} to make{workers} "
              f"-> {out}", flush=True)
    make = functools.partial(make_shard, out, args.split, rooms_per_shard=R,
                             lidar_fraction=args.lidar_fraction, config=config,
                             settings=settings, digest=digest)
    total_pairs, t_start = 0, time.time()
    for i, (k0, n, seconds, load) in enumerate(_shards_made(todo, args.workers, make)):
        total_pairs += n
        if not args.quiet:
            rate = total_pairs / (time.time() - t_start)
            print(f"[cegc-make-pairs] rooms {k0}-{k0 + R - 1}: {n} pairs in {seconds:.1f} s; "
                  f"{i + 1}/{len(todo)} shards, {total_pairs} pairs, {rate:.2f} pairs/s "
                  f"(load {load})", flush=True)
    if not args.quiet:
        print(f"[cegc-make-pairs] done: {total_pairs} new pairs in "
              f"{time.time() - t_start:.0f} s", flush=True)
    return 0


def stats(root: Path) -> dict[str, Any]:
    """Summary of a cache: counts, overlap histogram, motion, throughput from shard metas."""
    import numpy as np

    from cegc_ros.data.pair_cache import PairCache, list_shards

    cache = PairCache(root)
    infos = cache.infos
    by: dict[str, int] = {}
    for info in infos:
        key = f"{info['kind']}/{info['sensor']}"
        by[key] = by.get(key, 0) + 1
    views = [i for i in infos if i["kind"] == "views"]
    ov = np.array([i["overlap"] for i in views])
    hist, edges = np.histogram(ov, bins=8, range=(0.1, 0.9))
    seconds = pairs = 0.0
    for path in list_shards(root):
        with np.load(path) as z:
            meta = json.loads(str(z["meta"]))
        seconds += meta.get("seconds", 0.0)
        pairs += meta.get("pairs", 0)
    size = sum(p.stat().st_size for p in list_shards(root))
    rot = np.array([i["rotation_deg"] for i in views])
    return {"path": str(root), "split": cache.split, "pairs": len(infos),
            "rooms": len(cache.room_seeds), "by_kind_sensor": by,
            "views_overlap_hist": {f"{edges[k]:.1f}-{edges[k + 1]:.1f}": int(hist[k])
                                   for k in range(len(hist))},
            "views_overlap_mean": float(ov.mean()) if len(ov) else None,
            "views_rotation_deg_median": float(np.median(rot)) if len(rot) else None,
            "views_rotation_deg_p90": float(np.percentile(rot, 90)) if len(rot) else None,
            "bytes": int(size), "bytes_per_pair": int(size / max(1, len(infos))),
            "render_seconds": round(seconds, 1),
            "pairs_per_second": round(pairs / seconds, 3) if seconds else None}


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    err = _usage_errors(args)
    if err:
        parser.error(err)
    if args.stats:
        from cegc_ros.data.pair_cache import PairCacheError
        try:
            print(json.dumps(stats(args.out), indent=1))
        except PairCacheError as e:
            print(f"cegc-make-pairs: error: {e}", file=sys.stderr)
            return 1
        return 0
    if args.out.exists() and not args.out.is_dir():
        print(f"cegc-make-pairs: error: --out {args.out} is not a directory", file=sys.stderr)
        return 1
    try:
        return generate(args)
    except KeyboardInterrupt:
        print("cegc-make-pairs: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
