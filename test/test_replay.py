"""cegc-replay --lockstep against nodes that stop answering: a dead node and a silent one end
the replay with one line and exit status 1, instead of a silent wait per pair and exit 0."""

from __future__ import annotations

import threading
import time

import pytest

rclpy = pytest.importorskip("rclpy")


class SilentNode:
    """Subscribes to a namespace's inputs and advertises its pose topic, never answers; with
    ``die_after_first`` it drops its subscriptions once the first cloud arrived (a crash)."""

    def __init__(self, namespace: str, die_after_first: bool) -> None:
        from geometry_msgs.msg import PoseStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("register_node", namespace=namespace, context=self.context)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.received = 0
        self.subs = [self.node.create_subscription(PointCloud2, f"{namespace}/{t}", self._on, qos)
                     for t in ("source_cloud", "target_cloud")]
        self.node.create_publisher(PoseStamped, f"{namespace}/register_node/pose", 10)
        self.die = die_after_first
        self.dead = threading.Event()
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _on(self, _msg) -> None:
        self.received += 1
        if self.die and not self.dead.is_set():
            self.dead.set()
            threading.Thread(target=self._drop, daemon=True).start()

    def _drop(self) -> None:
        for sub in self.subs:
            self.node.destroy_subscription(sub)

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self.thread.join(5.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    from cegc_ros.data.bag import write_pairs
    from cegc_ros.data.protocols import make_pairs

    path = tmp_path_factory.mktemp("replay") / "pairs"
    write_pairs(path, make_pairs("7scenes", "test", 3))
    return path


def _replay(argv, capsys):
    from cegc_ros.tools.replay import main
    t0 = time.monotonic()
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err.strip().splitlines(), time.monotonic() - t0


def test_a_node_that_dies_ends_the_lockstep_replay_with_one_line(bag, capsys):
    node = SilentNode("/dying", die_after_first=True)
    try:
        code, out, err, wall = _replay([str(bag), "--lockstep", "--node-namespace", "/dying",
                                        "--wait", "120"], capsys)
    finally:
        node.close()
    assert code == 1 and out == "" and len(err) == 1, err
    assert err[0].startswith("cegc-replay: register_node went away (nothing subscribes to "
                             "/dying/source_cloud, /dying/target_cloud any more) after 1 of 3 "
                             "pairs were sent, 0 answered with a pose")
    assert wall < 100                                 # noticed, not the 120 s --wait


def test_a_node_that_never_answers_ends_it_after_wait(bag, capsys):
    node = SilentNode("/silent", die_after_first=False)
    try:
        code, out, err, _ = _replay([str(bag), "--lockstep", "--node-namespace", "/silent",
                                     "--wait", "1.5"], capsys)
    finally:
        node.close()
    assert node.received == 2                         # one pair sent, then the wait ran out
    assert code == 1 and out == ""
    assert err == ["cegc-replay: register_node did not answer pair 1 of 3 within --wait 1.5 s "
                   "(0 poses so far)"]
