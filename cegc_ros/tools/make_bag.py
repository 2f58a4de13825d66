"""cegc-make-bag: write synthetic registration pairs into a rosbag2 (sqlite3 or mcap).

    cegc-make-bag --protocol 7scenes --split test --pairs 100 --seed 0 --out bags/7scenes_test
    cegc-make-bag --protocol views --split test --pairs 100 --out bags/views_test
    cegc-make-bag --clouds scan_000.npy scan_001.pcd ... --rate 10 --out bags/my_scans

Pair i depends only on (protocol, split, seed, i). 7scenes / fragments / modelnet: see
cegc_ros.data.protocols.make_pair. views / views-lidar: different-view Kinect / LiDAR fragment
pairs of the rich rooms (cegc_ros.data.views.iter_view_pairs), rooms SEED * 10000, +1, ... of
the split, every room scanned with that sensor (a pair cache of the split holds the same pairs
for its rooms of that sensor).

``--clouds FILE ...``: your own clouds (.npy (N, 3+), or .ply / .pcd / .xyz ... through Open3D,
as cegc-register reads them) into a sequence bag, one cloud per file in the given order,
``--rate`` Hz apart, frame ``--frame-id``: ``cegc-replay`` plays it onto the node's ``cloud``
(sequential mode) and ``cegc-eval-seq`` can read it (without ground truth it reports none).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

PROTOCOLS = ("7scenes", "fragments", "modelnet", "views", "views-lidar")
VIEW_PROTOCOLS = {"views": "kinect", "views-lidar": "lidar"}
ROOMS_PER_SEED = 10_000


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="cegc-make-bag",
        description="Generate synthetic registration pairs (with ground truth) into a rosbag2.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--protocol", choices=PROTOCOLS,
                   help="7scenes (RIENet/FMR crops of a fragment), fragments (two fragments of "
                        "a scene, metres), modelnet (RPM-Net crops of primitive objects), "
                        "views / views-lidar (different-view Kinect / LiDAR fragment pairs of "
                        "the rich rooms, metres, overlap 0.1-0.9)")
    src.add_argument("--clouds", nargs="+", type=Path, metavar="FILE",
                     help="your own cloud files, one message each in this order, into a "
                          "sequence bag (/cegc/cloud) instead of generated pairs")
    p.add_argument("--rate", type=float, default=10.0,
                   help="--clouds: messages per second of the bag's stamps (default 10)")
    p.add_argument("--frame-id", default="sensor",
                   help="--clouds: header frame_id of the clouds (default sensor)")
    p.add_argument("--split", choices=("train", "val", "test"),
                   help="scene/object/room seed range (disjoint); val exists for the views "
                        "protocols only")
    p.add_argument("--pairs", type=int, help="number of pairs (>= 1)")
    p.add_argument("--seed", type=int, default=0, help="dataset seed, 0..999999 (default 0)")
    p.add_argument("--out", required=True, type=Path,
                   help="bag directory to create (must not exist, unless --overwrite)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out when it is a rosbag2 bag already (a directory with "
                        "metadata.yaml); anything else there is never removed")
    p.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3",
                   help="rosbag2 storage plugin (default sqlite3)")
    p.add_argument("--noise", type=float, default=0.0,
                   help="modelnet only: Gaussian noise sigma (clipped to 0.05), e.g. 0.01")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.clouds is None and (args.split is None or args.pairs is None):
        parser.error("--protocol needs --split and --pairs")
    if args.clouds is not None and (args.split or args.pairs or args.noise):
        parser.error("--clouds takes no --split, --pairs or --noise")
    if not args.rate > 0:
        parser.error(f"--rate must be > 0, got {args.rate}")
    if args.clouds is None and args.pairs < 1:
        parser.error(f"--pairs must be >= 1, got {args.pairs}")
    if not 0 <= args.seed <= 999_999:
        parser.error(f"--seed must be in 0..999999, got {args.seed}")
    if args.out.exists():
        if not args.overwrite:
            parser.error(f"--out {args.out} exists already; choose a new directory or add "
                         f"--overwrite")
        if not (args.out.is_dir() and (args.out / "metadata.yaml").is_file()):
            parser.error(f"--out {args.out} exists and is not a rosbag2 bag (no metadata.yaml): "
                         f"not replaced")
    parent = next((d for d in args.out.parents if d.exists()), None)
    if parent is not None and not parent.is_dir():
        parser.error(f"--out {args.out}: {parent} is a file, not a directory")
    if args.clouds is not None:
        return _write_clouds(args)
    if args.noise and args.protocol != "modelnet":
        parser.error("--noise applies to --protocol modelnet only")
    if not 0.0 <= args.noise <= 0.05:
        parser.error(f"--noise must be in [0, 0.05], got {args.noise}")
    if args.split == "val" and args.protocol not in VIEW_PROTOCOLS:
        parser.error(f"--split val exists for --protocol views / views-lidar only, not "
                     f"{args.protocol}")
    if args.protocol in VIEW_PROTOCOLS:
        from cegc_ros.data.splits import num_rooms
        max_seed = num_rooms(args.split) // ROOMS_PER_SEED - 1
        if args.seed > max_seed:
            parser.error(f"--seed for --protocol {args.protocol} must be in 0..{max_seed} "
                         f"(rooms seed * {ROOMS_PER_SEED} onwards of split {args.split})")

    from tqdm import tqdm

    from cegc_ros.data.bag import BagError, write_pairs

    if args.protocol in VIEW_PROTOCOLS:
        from cegc_ros.data.views import iter_view_pairs
        pairs = iter_view_pairs(args.split, args.pairs, VIEW_PROTOCOLS[args.protocol],
                                first_room=args.seed * ROOMS_PER_SEED)
    else:
        from cegc_ros.data.protocols import iter_pairs
        kwargs = {"noise_sigma": args.noise} if args.noise else {}
        pairs = iter_pairs(args.protocol, args.split, args.pairs, args.seed, **kwargs)
    bar = tqdm(pairs, total=args.pairs, unit="pair", desc=f"{args.protocol}/{args.split}",
               disable=args.no_progress)
    _clear_out(args.out)
    try:
        n = write_pairs(args.out, bar, storage=args.storage, protocol=args.protocol,
                        seed=args.seed)
    except BagError as err:
        print(f"cegc-make-bag: error: {err}", file=sys.stderr)
        return 1
    finally:
        bar.close()
    print(f"wrote {n} {args.protocol}/{args.split} pairs (seed {args.seed}) to {args.out} "
          f"[{args.storage}]")
    return 0


def _clear_out(out: Path) -> None:
    """Remove ``out`` before writing: an existing bag that --overwrite may replace (main
    checked that); create its missing parent directories (as ``ros2 bag record -o a/b/bag``
    does), so that the docs' ``--out .cache/bags/NAME`` works in a fresh clone."""
    if out.exists():
        import shutil
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)


def _write_clouds(args: argparse.Namespace) -> int:
    """--clouds: the files, in order, as a sequence bag without ground truth."""
    import numpy as np

    from cegc_ros.data.bag import BagError, write_sequence
    from cegc_ros.data.sequences import Sequence
    from cegc_ros.tools.register_files import InputError, read_cloud

    try:
        clouds = [read_cloud(path).astype(np.float32) for path in args.clouds]
    except InputError as err:
        print(f"cegc-make-bag: error: {err}", file=sys.stderr)
        return 1
    start_ns = 1_700_000_000 * 10**9
    stamps = start_ns + np.round(np.arange(len(clouds)) * 1e9 / args.rate).astype(np.int64)
    seq = Sequence(clouds, None, stamps, args.frame_id,
                   {"source": "files", "files": [str(p) for p in args.clouds]})
    _clear_out(args.out)
    try:
        n = write_sequence(args.out, seq, storage=args.storage)
    except BagError as err:
        print(f"cegc-make-bag: error: {err}", file=sys.stderr)
        return 1
    print(f"wrote {n} clouds ({args.rate:g} Hz, frame {args.frame_id}) to {args.out} "
          f"[{args.storage}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
