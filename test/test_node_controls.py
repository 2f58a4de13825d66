"""~/reset (std_srvs/Trigger) in both modes and the initialpose input of sequential mode, over
real DDS: in-process nodes with the echo stand-in engine, a client node in the same context."""

from __future__ import annotations


import numpy as np
import pytest
import ros_helpers as rh

rclpy = pytest.importorskip("rclpy")

from rclpy.parameter import Parameter  # noqa: E402

from cegc_ros.node.engine_process import EngineProcess  # noqa: E402
from cegc_ros.spinning import Spinner  # noqa: E402
from test_sequential import World, pose  # noqa: E402

SEC = 10**9


class Rig:
    """One node under test and a client node spun together; torn down in close()."""

    def __init__(self, namespace: str, mode: str) -> None:
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from nav_msgs.msg import Odometry
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        from std_srvs.srv import Trigger

        from cegc_ros.node import node_class

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        overrides = [Parameter("input.reliable", value=True), Parameter("input.mode", value=mode),
                     Parameter("input.queue_depth", value=50),
                     Parameter("diagnostics.period", value=0.2)]
        self.node = node_class()(engine_factory=lambda p, e: EngineProcess(p, e, factory="fake_engines:echo"),
                                 namespace=namespace, context=self.context,
                                 parameter_overrides=overrides)
        self.client_node = rclpy.create_node("controls_client", context=self.context)
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        c = self.client_node
        self.pub = {name: c.create_publisher(PointCloud2, f"{namespace}/{name}", qos)
                    for name in ("cloud", "source_cloud", "target_cloud")}
        self.initial = c.create_publisher(PoseWithCovarianceStamped, f"{namespace}/initialpose", 10)
        self.reset_client = c.create_client(Trigger, f"{namespace}/register_node/reset")
        self.odometry: list = []
        c.create_subscription(Odometry, f"{namespace}/register_node/odometry",
                              self.odometry.append, 50)
        self.executor = MultiThreadedExecutor(num_threads=3, context=self.context)
        for n in (self.node, self.client_node):
            self.executor.add_node(n)
        self.spinner = Spinner(self.executor)
        assert self.reset_client.wait_for_service(30.0)

    def reset(self) -> str:
        from std_srvs.srv import Trigger
        fut = self.reset_client.call_async(Trigger.Request())
        assert rh.wait_for(fut.done, 30.0)
        assert fut.result().success
        return fut.result().message

    def odometry_at(self, stamp: int):
        return next((m for m in self.odometry if rh.stamp_of(m) == stamp), None)

    def close(self) -> None:
        self.spinner.stop()
        for n in (self.node, self.client_node):
            n.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _matrix(odom) -> np.ndarray:
    from msg_adapters.pose import pose_to_matrix
    return pose_to_matrix(odom.pose.pose)


def test_reset_starts_a_new_odometry_frame_and_an_initial_pose_places_it():
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from msg_adapters.nav import time_from_ns
    from msg_adapters.pose import matrix_to_pose

    rig = Rig("/seqctl", "sequential")
    try:
        w = World()
        T1 = pose(5.0, (0.1, 0.0, 0.0))
        for k, T in enumerate((pose(), T1)):
            stamp = (10 + k) * SEC
            rig.pub["cloud"].publish(rh.cloud(w.cloud(T), "sensor", stamp))
            assert rh.wait_for(lambda: rig.odometry_at(stamp) is not None, 60.0)
        moved = _matrix(rig.odometry_at(11 * SEC))
        assert np.linalg.norm(moved[:3, 3]) > 0.03                      # the frame moved on
        # The same clouds again from an earlier stamp: refused before the reset...
        rig.pub["cloud"].publish(rh.cloud(w.cloud(T1), "sensor", 4 * SEC))
        assert rh.wait_for(lambda: rig.node.stats.count("rejected.unusable_cloud") == 1, 60.0)
        assert rig.odometry_at(4 * SEC) is None
        msg = rig.reset()
        assert msg.startswith("sequential mode reset: odometry, keyframes and path cleared")
        rig.pub["cloud"].publish(rh.cloud(w.cloud(T1), "sensor", 5 * SEC))
        assert rh.wait_for(lambda: rig.odometry_at(5 * SEC) is not None, 60.0)
        np.testing.assert_allclose(_matrix(rig.odometry_at(5 * SEC)), np.eye(4), atol=1e-9)
        # ...and an initial pose puts the next cloud where it says.
        T0 = pose(30.0, (2.0, -1.0, 0.5))
        init = PoseWithCovarianceStamped()
        init.header.frame_id, init.header.stamp = "odom", time_from_ns(6 * SEC)
        init.pose.pose = matrix_to_pose(T0)
        rig.initial.publish(init)
        assert rh.wait_for(lambda: rig.node.stats.count("initial_poses") == 1, 30.0)
        bad = PoseWithCovarianceStamped()
        bad.header.frame_id = "map"                                     # not output.odom_frame
        rig.initial.publish(bad)
        assert rh.wait_for(lambda: rig.node.stats.count("initial_poses_ignored") == 1, 30.0)
        rig.pub["cloud"].publish(rh.cloud(w.cloud(T1), "sensor", 7 * SEC))
        assert rh.wait_for(lambda: rig.odometry_at(7 * SEC) is not None, 60.0)
        np.testing.assert_allclose(_matrix(rig.odometry_at(7 * SEC)), T0, atol=1e-6)
        values = rig.node.diagnostics_values()
        assert values["resets"] == "1" and values["initial_poses"] == "1"
    finally:
        rig.close()


def test_reset_in_pairs_mode_forgets_the_cloud_waiting_for_its_partner():
    rig = Rig("/pairsctl", "pairs")
    try:
        pts = np.random.default_rng(0).uniform(-1, 1, (200, 3)).astype(np.float32)
        t = 100 * SEC
        rig.pub["source_cloud"].publish(rh.cloud(pts, "a", t))
        assert rh.wait_for(lambda: rig.node.stats.count("messages_in.source") == 1, 30.0)
        assert rig.reset() == "pairs mode reset: pairing state cleared"
        rig.pub["target_cloud"].publish(rh.cloud(pts, "b", t))           # its partner, too late
        assert rh.wait_for(lambda: rig.node.stats.count("messages_in.target") == 1, 30.0)
        assert rig.node.stats.count("pairs_in") == 0
        t2 = 101 * SEC                                                    # pairing still works
        rig.pub["source_cloud"].publish(rh.cloud(pts, "a", t2))
        rig.pub["target_cloud"].publish(rh.cloud(pts, "b", t2))
        assert rh.wait_for(lambda: rig.node.stats.count("pairs_out") == 1, 60.0)
        assert rig.node.diagnostics_values()["resets"] == "1"
    finally:
        rig.close()
