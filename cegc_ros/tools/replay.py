"""cegc-replay: play a bag into a running register_node and record the poses it returns.

    cegc-replay BAG [--rate R] [--lockstep] [--loop | --loops N] [--out FILE.json|FILE.csv]
                    [--timeout S]
                    [--node-name register_node] [--node-namespace /]
                    [--source-topic T] [--target-topic T] [--pose-topic T]
                    [--remap FROM:=TO ...] [--start-offset S]
                    [--wait S] [--fastdds-profile default|none|PATH]

Any rosbag2 (sqlite3 or mcap) plays, as ``ros2 bag play`` would play it: ``--remap FROM:=TO``
(repeatable) chooses the PointCloud2 topics and where they go; without it, a pair bag's two
topics go to the node's inputs (below) and a sequence bag's ``/cegc/cloud``, or a recording's
one PointCloud2 topic, to ``<namespace>/cloud`` (sequential mode). Other topics (IMU, packets,
tf_static, custom message types) are skipped without reading them. ``--start-offset S`` skips
the bag's first S seconds.

A pair bag's ``/cegc/source`` and ``/cegc/target`` messages are published as they are stored
(serialized CDR, no decoding) onto the node's ``source_cloud`` / ``target_cloud`` with
RELIABLE QoS, paced by the bag's time stamps (``--rate 2`` plays twice as fast). Every
``~/pose`` the node publishes is matched to its pair by header stamp and written next to the
ground truth from ``/cegc/ground_truth``. A cloud stream is answered on ``~/odometry``
(sequential mode): each odometry pose is matched to its cloud, next to a sequence bag's
ground truth relative to the first cloud played. ``--lockstep`` publishes the next pair (or
cloud) only when the node has answered the previous one (a pose, or a rejection seen on
``~/quality`` or /diagnostics), which is what an accuracy evaluation wants: nothing is dropped
because the node was busy. Each record also carries the item's ``~/quality`` (both modes):
fitness, ambiguity, the rejection reason, and for a stream how the cloud was registered
(``method``) and whether it became the ``keyframe``. A node that dies (its input
subscriptions end) or leaves an item unanswered for ``--wait`` seconds (default 30) ends the
replay with one line and exit status 1.
``--loops N`` plays the bag N times and ``--loop`` until Ctrl-C (then the completed plays are
reported and written, exit 0), as ``ros2 bag play --loop``;
before each repeat the node's ``~/reset`` is called, so a sequential-mode node starts a new
odometry instead of refusing the repeated stamps (a node without the service: exit 1).

Start the node with ``input.reliable:=true`` for replay; with the default sensor-data QoS
(best effort) large clouds can be lost on the way. Unless ROS_AUTOMATIC_DISCOVERY_RANGE is
set, replay keeps DDS discovery on this machine (LOCALHOST). Unless FASTRTPS_DEFAULT_PROFILES_FILE
is set, replay publishes with the shipped Fast DDS profile for huge clouds
(``params/fastdds_large_clouds.xml``: reliable writers repair lost fragments after 0.1 s, not
3 s; docs/node.md); ``--fastdds-profile none`` publishes with Fast DDS's defaults.

:func:`cegc_ros.replay.replay_bag` is the reusable part (``cegc-eval --through-node`` calls it).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import NoReturn

from cegc_ros.replay import ReplayError, parse_remap, replay_bag, summary, write_records


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports a usage error on one line (and exits 2), not usage + error."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return value


def _at_least_one(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 1")
    return value


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cegc-replay``: 0 on success, 1 with one line on stderr when the bag or
    the node is the problem, 2 for a usage error."""
    ap = OneLineParser(prog="cegc-replay", description=__doc__.split("\n\n")[0])
    ap.add_argument("bag", help="rosbag2 pair bag (directory)")
    ap.add_argument("--rate", type=_positive, default=1.0,
                    help="playback speed factor (default 1)")
    ap.add_argument("--lockstep", action="store_true",
                    help="publish each pair (or cloud of a stream) only after the node answered "
                         "the previous one: its pose (odometry) or a counted rejection")
    loop = ap.add_mutually_exclusive_group()
    loop.add_argument("--loop", action="store_const", const=0, dest="loops",
                      help="play the bag again and again until interrupted (Ctrl-C), calling "
                           "the node's ~/reset before each repeat")
    loop.add_argument("--loops", type=_at_least_one, metavar="N",
                      help="play the bag N times, with ~/reset before each repeat (default 1)")
    ap.set_defaults(loops=1)
    ap.add_argument("--out", help="write records here (.json or .csv)")
    ap.add_argument("--timeout", type=_positive, default=10.0,
                    help="seconds to wait for outstanding poses after the last pair")
    ap.add_argument("--connect-timeout", type=_positive, default=30.0,
                    help="seconds to wait for the node's topics")
    ap.add_argument("--wait", type=_positive, default=30.0,
                    help="--lockstep: seconds to wait for the node's answer to one pair "
                         "(default 30); past it, or when the node goes away, exit 1")
    ap.add_argument("--node-name", default="register_node")
    ap.add_argument("--node-namespace", default="/")
    ap.add_argument("--source-topic", help="default: <namespace>/source_cloud")
    ap.add_argument("--target-topic", help="default: <namespace>/target_cloud")
    ap.add_argument("--pose-topic", help="default: <namespace>/<node-name>/pose")
    ap.add_argument("--remap", action="append", default=[], metavar="FROM:=TO",
                    help="publish the bag's PointCloud2 topic FROM on TO (repeatable; as ros2 "
                         "bag play --remap). With remaps only they are played; without, a pair "
                         "bag's two topics, or a bag's one cloud topic onto <namespace>/cloud")
    ap.add_argument("--start-offset", type=float, default=0.0, metavar="S",
                    help="skip the bag's first S seconds (default 0)")
    ap.add_argument("--fastdds-profile", default="default", metavar="default|none|PATH",
                    help="Fast DDS profiles file to publish with (default: "
                         "$FASTRTPS_DEFAULT_PROFILES_FILE if set, else the shipped "
                         "fastdds_large_clouds.xml; none: Fast DDS's defaults)")
    args = ap.parse_args(argv)

    from cegc_ros.data.bag import BagError
    try:
        remaps = [parse_remap(r) for r in args.remap]
    except ValueError as err:
        ap.error(str(err))
    if args.start_offset < 0:
        ap.error(f"--start-offset must be >= 0, got {args.start_offset}")
    try:
        result = replay_bag(args.bag, args.rate, lockstep=args.lockstep, timeout=args.timeout,
                            connect_timeout=args.connect_timeout, node_name=args.node_name,
                            node_namespace=args.node_namespace, source_topic=args.source_topic,
                            target_topic=args.target_topic, pose_topic=args.pose_topic,
                            pair_timeout=args.wait, progress=sys.stderr.isatty(),
                            fastdds_profile=args.fastdds_profile, remaps=remaps,
                            start_offset=args.start_offset, loops=args.loops)
        info = summary(result)
        if args.out:
            write_records(result, args.out, {"bag": str(args.bag), "rate": args.rate,
                                             "lockstep": args.lockstep, "loops": args.loops,
                                             "summary": info})
    except (BagError, ReplayError, ValueError, OSError) as err:
        print(f"cegc-replay: {' '.join(str(err).split())}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("cegc-replay: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001  one line, never a traceback (e.g. rclpy errors)
        print(f"cegc-replay: {type(err).__name__}: {' '.join(str(err).split())}",
              file=sys.stderr)
        return 1
    print(json.dumps(info))
    return 0


if __name__ == "__main__":
    sys.exit(main())
