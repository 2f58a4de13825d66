"""register_node in sequential mode over real DDS: one `cloud` topic in, odometry out.

A subprocess node (real engine, small config) gets a generated camera sequence through a
room (cegc_ros/data/sequences.py) one cloud at a time (the next after the odometry of the
last arrived, so no cloud is dropped by the node's one-slot mailbox); the test checks the
frames, stamps, covariance and the final pose against ground truth, the bounded path, the
pose against the keyframe, a bad cloud counted and skipped, ~/quality and /diagnostics.
The ~/quality values of accepted and rejected clouds against the odometry's own frames are
checked without DDS (the node's code, the echo stand-in engine inline, recording publishers).
"""

from __future__ import annotations

import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import ros_helpers as rh

rclpy = pytest.importorskip("rclpy")

from cegc_ros.data.sequences import FRAME_ID, make_room_sequence
from cegc_ros.engine import default_weights
from cegc_ros.node.ros_node import RegistrationNodeMixin
from cegc_ros.spinning import Spinner

CHECKPOINT = Path(os.environ.get("CEGC_TEST_CHECKPOINT", default_weights()))
NUM_CLOUDS = 16
PATH_LENGTH = 10
NODE_ARGS = ["--ros-args", "--params-file", f"{rh.REPO}/params/register_node.yaml",
             "-p", f"engine.checkpoint:={CHECKPOINT}", "-p", "input.reliable:=true",
             "-p", "preprocess.num_points:=256", "-p", "diagnostics.period:=0.5",
             "-p", "engine.device:=cpu", "-p", "input.mode:=sequential",
             "-p", f"sequential.path_length:={PATH_LENGTH}"]


def make_seq_probe(context, node: str = "register_node"):
    """Publishes `cloud`; records ~/odometry, ~/path, ~/pose, ~/pose_with_covariance,
    ~/quality, /tf and /diagnostics of the node under test."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry, Path
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from msg_adapters.transform import tf_message_class

    class SeqProbe(Node, rh.OutputRecorder):
        def __init__(self) -> None:
            Node.__init__(self, "cegc_seq_probe", context=context)
            rh.OutputRecorder.__init__(self, f"/{node}: registration")
            qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
            self.pub = self.create_publisher(PointCloud2, "/cloud", qos)
            outputs = {"odometry": Odometry, "path": Path, "pose": PoseStamped,
                       "pose_with_covariance": PoseWithCovarianceStamped,
                       "quality": DiagnosticArray}
            for name, kind in outputs.items():
                self.create_subscription(kind, f"/{node}/{name}", self.keeper(name), 50)
            self.create_subscription(DiagnosticArray, "/diagnostics", self.keeper("diagnostics"),
                                     50)
            tf = tf_message_class()
            if tf is not None:
                self.create_subscription(tf, "/tf", self.keeper("tf"), 50)

    return SeqProbe()


@pytest.fixture(scope="module")
def sequence():
    # 16 clouds at 10 Hz (1.5 s, 0.58 m) of room 3, every 8th Kinect pixel (~4700 points).
    return make_room_sequence(3, NUM_CLOUDS, frame_step=3, pixel_stride=8)


@pytest.fixture(scope="module")
def seq_node():
    from rclpy.executors import SingleThreadedExecutor

    if not CHECKPOINT.is_file():
        pytest.skip(f"no checkpoint {CHECKPOINT}")
    proc = subprocess.Popen([sys.executable, "-m", "cegc_ros.node", *NODE_ARGS],
                            env=rh.ros_env(), cwd=rh.REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    context = rclpy.Context()
    rclpy.init(context=context)
    probe = make_seq_probe(context)
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(probe)
    spinner = Spinner(ex)
    up = rh.wait_for(lambda: (probe.pub.get_subscription_count() > 0
                              and probe.count_publishers("/register_node/odometry") > 0)
                     or proc.poll() is not None, 120.0)
    if not up or proc.poll() is not None:
        proc.kill()
        pytest.fail(f"node did not come up:\n{proc.communicate()[0]}")
    assert rh.wait_for(lambda: probe.diagnostics(), 10.0)
    yield proc, probe
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
    spinner.stop()
    probe.destroy_node()
    rclpy.try_shutdown(context=context)


def _reset(probe) -> None:
    """Call the node's ~/reset: the next cloud starts a new odometry."""
    from std_srvs.srv import Trigger

    client = probe.create_client(Trigger, "/register_node/reset")
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(Trigger.Request())
    assert rh.wait_for(future.done, 10.0) and future.result().success
    probe.destroy_client(client)


def _fresh_diag(probe, timeout: float = 10.0) -> dict[str, str]:
    n = len(probe.outputs("diagnostics"))
    assert rh.wait_for(lambda: len(probe.outputs("diagnostics")) > n, timeout)
    return probe.diagnostics()


def test_sequence_gives_odometry_near_ground_truth_and_skips_a_bad_cloud(seq_node, sequence):
    from msg_adapters.nav import odometry_to_matrix, path_to_matrices
    from msg_adapters.pose import pose_to_matrix

    proc, probe = seq_node
    seq = sequence
    gt = seq.relative_poses()
    bad_at = 8                       # an all-NaN cloud between clouds 7 and 8
    for k, (stamp, xyz) in enumerate(zip(seq.stamps_ns, seq.clouds)):
        if k == bad_at:
            bad_stamp = int(stamp) - 50_000_000
            probe.pub.publish(rh.cloud(np.full((100, 3), np.nan), seq.frame_id, bad_stamp))
            assert rh.wait_for(lambda: int(probe.diagnostics().get("rejected.empty_cloud", 0))
                               >= 1, 60.0), probe.diagnostics()
        probe.pub.publish(rh.cloud(xyz, seq.frame_id, int(stamp)))
        # Generous: the first cloud waits for discovery, a slow one for ICP on a busy machine.
        assert rh.wait_for(lambda s=int(stamp): s in probe.by_stamp("odometry"), 120.0), \
            (k, proc.poll(), probe.diagnostics())
    odom = probe.by_stamp("odometry")
    assert sorted(odom) == sorted(int(s) for s in seq.stamps_ns)     # every good cloud, once
    assert len(probe.outputs("odometry")) == NUM_CLOUDS              # none for the bad one

    # Frames: odom -> the cloud's frame, stamped with the cloud.
    for msg in odom.values():
        assert msg.header.frame_id == "odom" and msg.child_frame_id == FRAME_ID
    first_T, first_cov = odometry_to_matrix(odom[int(seq.stamps_ns[0])])
    np.testing.assert_allclose(first_T, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(first_cov, 0.0)

    # Final pose against ground truth (KeyframeOdometry offline: 1.1 cm, 0.4 deg over 0.58 m).
    T, cov = odometry_to_matrix(odom[int(seq.stamps_ns[-1])])
    G = gt[-1]
    assert np.linalg.norm(T[:3, 3] - G[:3, 3]) < 0.05
    R = G[:3, :3].T @ T[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 1.5
    # Covariance propagated along the keyframe chain: positive and larger than one step's.
    second_cov = odometry_to_matrix(odom[int(seq.stamps_ns[1])])[1]
    assert np.all(np.diag(cov) > 0) and np.trace(cov) > np.trace(second_cov)

    # ~/path: bounded, newest last, in odom; its last pose is the last odometry. (Published
    # after ~/odometry: wait for the path of the last cloud.)
    last_stamp = int(seq.stamps_ns[-1])
    assert rh.wait_for(lambda: path_to_matrices(probe.outputs("path")[-1])[-1][0] == last_stamp,
                       10.0)
    path = probe.outputs("path")[-1]
    assert path.header.frame_id == "odom"
    poses = path_to_matrices(path)
    assert len(poses) == PATH_LENGTH
    assert [s for s, _ in poses] == [int(s) for s in seq.stamps_ns[-PATH_LENGTH:]]
    np.testing.assert_allclose(poses[-1][1], T, atol=1e-6)

    # ~/pose: the cloud against its keyframe, in the cloud's frame, one per cloud.
    # (read after the wait: ~/pose comes after ~/odometry, and beside busy processes the last
    # cloud's arrived after a copy taken before it, a KeyError in CI on the Xeon)
    assert rh.wait_for(lambda: len(probe.by_stamp("pose")) == NUM_CLOUDS, 10.0)
    pose = probe.by_stamp("pose")
    last = pose[int(seq.stamps_ns[-1])]
    assert last.header.frame_id == FRAME_ID
    T_kf = pose_to_matrix(last.pose)
    assert np.linalg.norm(T_kf[:3, 3]) <= 0.5 + 1e-6       # sequential.keyframe_max_translation
    assert len(probe.by_stamp("pose_with_covariance")) == NUM_CLOUDS

    # ~/quality: one per cloud, the bad one too, stamped and framed as ~/pose; the methods and
    # keyframes it names add up to the odometry's counters.
    assert rh.wait_for(lambda: len(probe.by_stamp("quality")) == NUM_CLOUDS + 1, 10.0)
    assert len(probe.outputs("quality")) == NUM_CLOUDS + 1
    quality = {s: {kv.key: kv.value for kv in m.status[0].values}
               for s, m in probe.by_stamp("quality").items()}
    assert all(m.header.frame_id == FRAME_ID for m in probe.outputs("quality"))
    bad = quality.pop(bad_stamp)
    assert (bad["published"], bad["reason"], bad["method"]) == ("false", "empty_cloud", "")
    assert all(q["published"] == "true" and q["reason"] == "" for q in quality.values())
    assert quality[int(seq.stamps_ns[0])]["method"] == "first"
    methods = [q["method"] for q in quality.values()]

    d = _fresh_diag(probe)
    assert methods.count("icp") == int(d["tracked"])
    assert methods.count("global") == int(d["recoveries"])
    assert sum(q["keyframe"] == "true" for q in quality.values()) == int(d["keyframes"])
    assert d["mode"] == "sequential"
    assert int(d["rejected.empty_cloud"]) == 1 and int(d["pairs_rejected"]) == 1
    assert int(d["pairs_out"]) == NUM_CLOUDS
    assert int(d["tracked"]) + int(d["recoveries"]) == NUM_CLOUDS - 1
    assert 2 <= int(d["keyframes"]) < NUM_CLOUDS
    assert int(d["frames_rejected"]) == 0 and d["latency_p50_ms"] != "nan"
    assert float(d["odometry_p50_ms"]) > 0
    assert proc.poll() is None


def test_tf_is_published_where_tf2_msgs_is_installed(seq_node, sequence):
    from msg_adapters.transform import tf_message_class

    if tf_message_class() is None:
        pytest.skip("tf2_msgs is not installed (not on PyPI): /tf is not published; "
                    "msg_adapters.transform.transform_stamped is unit-tested in test_nav_tf.py")
    from msg_adapters.nav import odometry_to_matrix, time_to_ns
    from msg_adapters.transform import transform_to_matrix

    _, probe = seq_node
    assert rh.wait_for(lambda: len(probe.outputs("tf")) >= NUM_CLOUDS, 30.0)
    odom = probe.by_stamp("odometry")
    for msg in probe.outputs("tf"):          # one transform per odometry message, the same pose
        (t,) = msg.transforms
        assert t.header.frame_id == "odom" and t.child_frame_id == FRAME_ID
        T_odom = odometry_to_matrix(odom[time_to_ns(t.header.stamp)])[0]
        np.testing.assert_allclose(transform_to_matrix(t.transform), T_odom, atol=1e-9)


def test_a_sequence_bag_replays_in_lockstep_twice_with_a_reset_between(seq_node, sequence,
                                                                       tmp_path):
    # cegc-replay's core on a sequence bag: every cloud is answered on ~/odometry before the
    # next goes out; the second play starts after ~/reset, so the repeated stamps make a new
    # odometry (not "not after the previous cloud") with the same poses as the first.
    import dataclasses

    from cegc_ros.data.bag import write_sequence
    from cegc_ros.metrics import rotation_error_deg
    from cegc_ros.replay import replay_bag, summary

    proc, probe = seq_node
    _reset(probe)                                                  # a new odometry first
    resets = int(_fresh_diag(probe)["resets"])
    later = dataclasses.replace(sequence, stamps_ns=sequence.stamps_ns + 1000 * 10**9)
    bag = tmp_path / "seq_bag"
    write_sequence(bag, later)
    result = replay_bag(bag, lockstep=True, loops=2, pair_timeout=60.0, timeout=10.0)
    assert result.stream and result.loops == 2
    assert [r.loop for r in result.records] == [0] * NUM_CLOUDS + [1] * NUM_CLOUDS
    assert all(r.T_est is not None for r in result.records), summary(result)
    first, second = result.records[:NUM_CLOUDS], result.records[NUM_CLOUDS:]
    np.testing.assert_allclose(first[0].T_est, np.eye(4), atol=1e-9)     # after our reset
    np.testing.assert_allclose(second[0].T_est, np.eye(4), atol=1e-9)    # after the replay's
    for a, b in zip(first, second):
        np.testing.assert_allclose(a.T_est, b.T_est, atol=1e-6)
    T, G = np.asarray(second[-1].T_est), np.asarray(second[-1].T_gt)     # gt from the bag
    assert np.linalg.norm(T[:3, 3] - G[:3, 3]) < 0.05
    assert rotation_error_deg(G[:3, :3], T[:3, :3]) < 1.5
    d = _fresh_diag(probe)
    assert int(d["resets"]) == resets + 1                          # the replay's, between plays
    assert float(d["sequential.voxel_size"]) > 0                   # derived from the first cloud
    assert proc.poll() is None


def test_lockstep_moves_on_after_a_cloud_the_node_rejects(seq_node, sequence, tmp_path):
    # A cloud the node rejects (all NaN: counted, no odometry) is answered by its ~/quality
    # (published false; its counters on /diagnostics too): the lockstep replay goes on to the
    # next cloud instead of waiting --wait, and each record carries the cloud's ~/quality: the
    # odometry's fitness and method of an accepted cloud, the reason of the rejected one.
    import csv
    import dataclasses

    from cegc_ros.data.bag import write_sequence
    from cegc_ros.replay import replay_bag, summary, write_records

    _, probe = seq_node
    _reset(probe)
    rejected = int(_fresh_diag(probe)["rejected.empty_cloud"])
    clouds = list(sequence.clouds[:4])
    clouds[2] = np.full((200, 3), np.nan, np.float32)
    short = dataclasses.replace(sequence, clouds=clouds, poses=sequence.poses[:4],
                                stamps_ns=sequence.stamps_ns[:4] + 2000 * 10**9)
    bag = tmp_path / "with_a_bad_cloud"
    write_sequence(bag, short)
    result = replay_bag(bag, lockstep=True, pair_timeout=60.0, timeout=10.0)
    recs = result.records
    assert [r.T_est is not None for r in recs] == [True, True, False, True]
    assert int(_fresh_diag(probe)["rejected.empty_cloud"]) == rejected + 1
    assert [r.rejected for r in recs] == [None, None, "empty_cloud", None]
    accepted = [recs[0], recs[1], recs[3]]
    assert all(r.fitness is not None and 0.0 < r.fitness <= 1.0 for r in accepted), recs
    assert recs[0].method == "first" and recs[0].keyframe is True
    assert all(r.method in ("icp", "global") for r in accepted[1:]), recs
    # The bad cloud never reached the odometry: no method, no fitness, no keyframe.
    assert (recs[2].method, recs[2].fitness, recs[2].keyframe) == (None, None, False)
    for r in recs:            # the global registration's ambiguity only when it ran
        assert (r.ambiguity is not None) <= (r.method == "global"), r
    info = summary(result)
    assert info["rejected"] == {"empty_cloud": 1}
    assert sum(info["methods"].values()) == 3 and info["methods"]["first"] == 1
    assert info["keyframes"] == sum(bool(r.keyframe) for r in recs) >= 1
    out = tmp_path / "records.csv"
    write_records(result, out, {})
    rows = list(csv.DictReader(out.open()))
    assert [(row["rejected"], row["method"]) for row in rows] == \
        [("", "first"), ("", recs[1].method), ("empty_cloud", ""), ("", recs[3].method)]
    assert rows[0]["keyframe"] == "true" and float(rows[1]["fitness"]) == recs[1].fitness


class _RecordingNode(RegistrationNodeMixin):
    """The node's own code (its outputs, ``publish_quality``, the sequential mode and its
    worker) with the echo stand-in engine inline and no rclpy: publishers record what they
    get (``published[topic]``)."""

    def __init__(self) -> None:
        from cegc_ros.node.engine_process import InlineEngine
        from cegc_ros.node.params import build_sections
        from cegc_ros.node.stats import NodeStats
        from cegc_ros.node.support import ThrottledLog
        from fake_engines import echo

        self.cfg = build_sections({"input.mode": "sequential"})
        self.stats = NodeStats(self.cfg["diagnostics"].window)
        self._log = ThrottledLog(lambda text: None, 1.0)
        self.logger = types.SimpleNamespace(info=lambda text: None, warning=lambda text: None)
        self.engine = InlineEngine(echo(self.cfg["preprocess"], self.cfg["engine"]))
        self.engine.start()
        self.published: dict[str, list] = {}
        self.create_mode()
        self.create_outputs()
        self.start_worker()

    def create_publisher(self, kind, topic, depth):
        return types.SimpleNamespace(publish=self.published.setdefault(topic, []).append)

    def create_timer(self, period, callback):
        return None

    def get_logger(self):
        return self.logger

    def get_fully_qualified_name(self) -> str:
        return "/register_node"


def test_quality_has_one_message_per_cloud_accepted_or_rejected():
    """~/quality in sequential mode, without DDS: each cloud's message is stamped and framed as
    its ~/pose; OK with how it was registered and the odometry frame's fitness for an accepted
    cloud; WARN with the reason for one not registered (the global registration's numbers in)
    and for one the odometry refused (no frame: no numbers)."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from test_sequential import World, pose

    node = _RecordingNode()
    frames = {}                                  # stamp -> the odometry's FrameResult
    feed = node.mode.odometry.feed

    def recording_feed(stamp_ns, cloud):
        frames[stamp_ns] = feed(stamp_ns, cloud)
        return frames[stamp_ns]

    node.mode.odometry.feed = recording_feed
    quality = node.published["~/quality"]
    sec = 10**9
    w = World()
    noise = np.random.default_rng(0).uniform(-3.0, 3.0, (3000, 3))    # nothing like the room
    clouds = [(10 * sec, w.cloud(pose())), (11 * sec, w.cloud(pose(5.0, (0.1, 0.0, 0.0)))),
              (12 * sec, noise), (9 * sec, w.cloud(pose()))]          # the last: going back
    try:
        for k, (stamp, xyz) in enumerate(clouds):
            node.on_cloud("cloud", rh.cloud(xyz, "sensor", stamp))
            assert rh.wait_for(lambda n=k + 1: len(quality) == n, 60.0), k
    finally:
        node.close()
    by_stamp = {rh.stamp_of(m): m for m in quality}
    assert sorted(by_stamp) == sorted(s for s, _ in clouds)        # one per cloud
    poses = {rh.stamp_of(m): m for m in node.published["~/pose"]}
    assert sorted(poses) == [10 * sec, 11 * sec]

    def status(stamp):
        msg = by_stamp[stamp]
        (st,) = msg.status
        assert msg.header.frame_id == "sensor" and st.name == "/register_node: registration"
        return st, {kv.key: kv.value for kv in st.values}

    for stamp, method in ((10 * sec, "first"), (11 * sec, "icp")):
        st, v = status(stamp)
        frame = frames[stamp]
        assert by_stamp[stamp].header == poses[stamp].header
        assert st.level == DiagnosticStatus.OK and st.message == "pose published"
        assert (v["published"], v["reason"], v["method"]) == ("true", "", method)
        assert frame.method == method
        assert v["fitness"] == f"{frame.fitness:.4f}" and v["overlap"] == f"{frame.overlap:.4f}"
        assert v["keyframe"] == str(frame.new_keyframe).lower() and v["detail"] == frame.reason
        # tracking sufficed: no global registration, so none of its numbers
        assert (v["ambiguity"], v["correspondences"], v["engine_ms"], v["draws"]) == ("nan", "", "nan", "")
    assert status(10 * sec)[1]["keyframe"] == "true"

    st, v = status(12 * sec)     # tracking fails, the echo's global answer fails its ICP check
    frame = frames[12 * sec]
    assert not frame.accepted and frame.registration is not None
    assert st.level == DiagnosticStatus.WARN
    assert st.message == f"not_registered: cloud not registered: {frame.reason}"
    assert v == {"published": "false", "reason": "not_registered",
                 "detail": f"cloud not registered: {frame.reason}", "method": "none",
                 "keyframe": "false", "fitness": f"{frame.fitness:.4f}",
                 "overlap": f"{frame.overlap:.4f}", "ambiguity": "0.0000",   # the echo's
                 "correspondences": "32", "engine_ms": "nan", "draws": "1"}

    st, v = status(9 * sec)                      # refused by the odometry: no frame
    assert 9 * sec not in frames
    assert st.level == DiagnosticStatus.WARN and st.message.startswith(
        "unusable_cloud: cloud refused by the odometry: cloud stamp")
    assert (v["published"], v["reason"], v["method"], v["keyframe"], v["fitness"]) == \
        ("false", "unusable_cloud", "", "false", "nan")
    assert v["detail"] == st.message.removeprefix("unusable_cloud: ")
    assert node.stats.count("rejected.not_registered") == 1
    assert node.stats.count("rejected.unusable_cloud") == 1
