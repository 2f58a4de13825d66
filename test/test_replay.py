"""cegc-replay --lockstep against nodes that stop answering: a dead node and a silent one end
the replay with one line and exit status 1, instead of a silent wait per pair and exit 0."""

from __future__ import annotations

import threading
import time

import pytest
import ros_helpers as rh

from cegc_ros.spinning import Spinner

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
        self.spinner = Spinner(self.executor)

    def _on(self, _msg) -> None:
        self.received += 1
        if self.die and not self.dead.is_set():
            self.dead.set()
            threading.Thread(target=self._drop, daemon=True).start()

    def _drop(self) -> None:
        for sub in self.subs:
            self.node.destroy_subscription(sub)

    def close(self) -> None:
        self.spinner.stop()
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


class RejectingNode(SilentNode):
    """Answers every pair with a ~/quality message saying it was rejected as ambiguous
    (fitness 0.25, ambiguity 0.9), never with a pose, as register_node does for such pairs."""

    def __init__(self, namespace: str) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        super().__init__(namespace, die_after_first=False)
        self.quality = self.node.create_publisher(DiagnosticArray,
                                                  f"{namespace}/register_node/quality", 10)
        self.clouds: dict[int, int] = {}

    def _on(self, msg) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        stamp = rh.stamp_of(msg)
        self.clouds[stamp] = self.clouds.get(stamp, 0) + 1
        if self.clouds[stamp] == 2:
            values = {"published": "false", "reason": "ambiguous", "fitness": "0.2500",
                      "ambiguity": "0.9000"}
            status = DiagnosticStatus(level=DiagnosticStatus.WARN, message="ambiguous: test",
                                      values=[KeyValue(key=k, value=v) for k, v in values.items()])
            self.quality.publish(DiagnosticArray(header=msg.header, status=[status]))


def test_a_pair_the_node_rejected_is_recorded_with_its_reason_and_not_waited_for(bag):
    """A rejected pair's ~/quality answers it: the replay records the reason and the engine's
    numbers and does not wait out --wait for a pose that will not come."""
    from cegc_ros.replay import replay_bag

    node = RejectingNode("/rejecting")
    try:
        t0 = time.monotonic()
        result = replay_bag(bag, rate=50.0, timeout=60.0, node_namespace="/rejecting")
        took = time.monotonic() - t0
    finally:
        node.close()
    assert [(r.T_est, r.rejected, r.fitness, r.ambiguity) for r in result.records] == \
        [(None, "ambiguous", 0.25, 0.9)] * 3
    assert all(r.method is None and r.keyframe is None for r in result.records)   # a pair's
    assert took < 30.0        # answered: no 60 s wait for poses
    from cegc_ros.replay import summary
    assert summary(result)["rejected"] == {"ambiguous": 3} and summary(result)["poses"] == 0


@pytest.fixture
def stuck_spinner(monkeypatch):
    """replay_bag's spinner stops, then raises as Spinner.stop does when a callback outlives its
    timeout. Yields (the nodes it spun, the nodes destroyed meanwhile); the spun ones are
    destroyed afterwards."""
    import cegc_ros.spinning
    from rclpy.node import Node

    spun, destroyed = [], []
    destroy = Node.destroy_node

    class StuckSpinner(Spinner):
        def stop(self, timeout: float = 30.0) -> None:
            spun.extend(self.executor.get_nodes())
            super().stop(timeout)
            raise RuntimeError("a callback still runs")

    def recorded_destroy(node):
        destroyed.append(node)
        return destroy(node)

    monkeypatch.setattr(cegc_ros.spinning, "Spinner", StuckSpinner)
    monkeypatch.setattr(Node, "destroy_node", recorded_destroy)
    yield spun, destroyed
    for node in spun:
        destroy(node)


def test_a_failed_replay_raises_its_own_error_when_the_spinner_cannot_stop(bag, stuck_spinner):
    """The replay's error goes on, the stop's as a note; the node a callback may still use is
    left alive."""
    from cegc_ros.replay import ReplayError, replay_bag
    spun, destroyed = stuck_spinner
    with pytest.raises(ReplayError, match="no register_node answered within 0.3 s") as info:
        replay_bag(bag, node_namespace="/nobody", connect_timeout=0.3)
    assert info.value.__notes__ == ["then stopping the spin thread failed: a callback still runs"]
    assert len(spun) == 1 and destroyed == []


def test_a_replay_that_succeeded_raises_when_the_spinner_cannot_stop(bag, stuck_spinner):
    from cegc_ros.replay import replay_bag
    spun, destroyed = stuck_spinner
    node = SilentNode("/mute", die_after_first=False)
    try:
        with pytest.raises(RuntimeError, match="^a callback still runs$"):
            replay_bag(bag, rate=100.0, timeout=0.2, node_namespace="/mute")
    finally:
        node.close()
    assert node.received == 6                         # the 3 pairs were played
    assert len(spun) == 1 and destroyed == [node.node]  # the silent node's own close only


# --- any rosbag2: topic choice, remaps, skipped topics, start offset ----------------------------

CUSTOM_MSG = "float64 temperature\nstring note\n"


def _recording(path, storage: str = "sqlite3", clouds=("/os_cloud_node/points",), n: int = 4):
    """A sensor recording as drivers write it: cloud topics, an IMU topic and a custom message
    type (whose definition a replaying machine does not have), 0.1 s apart."""
    import numpy as np
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_types_from_msg

    from cegc_ros.data.bag import _header, _typestore, xyz_to_pointcloud2

    ts = _typestore()
    ts.register(get_types_from_msg(CUSTOM_MSG, "vendor_msgs/msg/Status"))
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    with Writer(path, version=9, storage_plugin=plugin) as w:
        cc = {t: w.add_connection(t, "sensor_msgs/msg/PointCloud2", typestore=ts) for t in clouds}
        imu = w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=ts)
        status = w.add_connection("/vendor/status", "vendor_msgs/msg/Status", typestore=ts)
        for k in range(n):
            t = (50 + k) * 10**8
            for topic, conn in cc.items():
                xyz = np.random.default_rng(k).uniform(-5, 5, (300, 3))
                w.write(conn, t, ts.serialize_cdr(xyz_to_pointcloud2(ts, xyz, _header(ts, t, "os")),
                                                  "sensor_msgs/msg/PointCloud2"))
            w.write(imu, t, ts.serialize_cdr(ts.types["sensor_msgs/msg/Imu"](
                header=_header(ts, t, "imu"), orientation=ts.types["geometry_msgs/msg/Quaternion"](
                    x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=np.zeros(9),
                angular_velocity=ts.types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=ts.types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.8),
                linear_acceleration_covariance=np.zeros(9)), "sensor_msgs/msg/Imu"))
            w.write(status, t, ts.serialize_cdr(ts.types["vendor_msgs/msg/Status"](
                temperature=40.0, note="ok"), "vendor_msgs/msg/Status"))
    return path


class CloudRecorder:
    """Records the stamps of the clouds arriving on one topic; advertises the pose and
    odometry topics (a pairs-mode or sequential-mode node), never answers."""

    def __init__(self, namespace: str, topic: str) -> None:
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("register_node", namespace=namespace, context=self.context)
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        self.stamps: list[int] = []
        self.node.create_subscription(PointCloud2, topic, lambda m: self.stamps.append(rh.stamp_of(m)), qos)
        self.node.create_publisher(PoseStamped, f"{namespace}/register_node/pose", 10)
        self.node.create_publisher(Odometry, f"{namespace}/register_node/odometry", 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.spinner = Spinner(self.executor)

    def close(self) -> None:
        self.spinner.stop()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def test_lockstep_on_a_stream_waits_per_cloud_and_ends_after_wait(tmp_path, capsys):
    # A recording's one cloud stream in lockstep: the first cloud goes out, the node never
    # answers it on ~/odometry nor counts it, and the replay ends after --wait with one line.
    bag = _recording(tmp_path / "rec_lock")
    rec = CloudRecorder("/streamlock", "/streamlock/cloud")
    try:
        code, out, err, _ = _replay([str(bag), "--lockstep", "--node-namespace", "/streamlock",
                                     "--wait", "1.0"], capsys)
    finally:
        rec.close()
    assert rec.stamps == [50 * 10**8]
    assert code == 1 and out == ""
    assert err == ["cegc-replay: register_node did not answer cloud 1 of 4 within --wait 1 s "
                   "(0 poses so far)"]


class OldStreamNode(CloudRecorder):
    """A sequential-mode node without ~/quality (as before it had one): answers every cloud on
    ~/odometry (identity) except those at ``reject`` stamps, and counts each cloud in
    ``pairs_done`` on /diagnostics, published after each cloud and every 0.2 s."""

    def __init__(self, namespace: str, reject: set[int]) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        super().__init__(namespace, f"{namespace}/unused")
        self.name = f"{namespace}/register_node: registration"
        self.reject, self.done = reject, 0
        self.odometry = self.node.create_publisher(Odometry, f"{namespace}/register_node/odometry",
                                                   10)
        self.diag = self.node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(PointCloud2, f"{namespace}/cloud", self._on, qos)
        self.node.create_timer(0.2, self._publish_diag)

    def _on(self, msg) -> None:
        from nav_msgs.msg import Odometry

        stamp = rh.stamp_of(msg)
        self.stamps.append(stamp)
        if stamp not in self.reject:
            odom = Odometry(header=msg.header, child_frame_id=msg.header.frame_id)
            odom.pose.pose.orientation.w = 1.0
            self.odometry.publish(odom)
        self.done += 1
        self._publish_diag()

    def _publish_diag(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        status = DiagnosticStatus(name=self.name,
                                  values=[KeyValue(key="pairs_done", value=str(self.done))])
        self.diag.publish(DiagnosticArray(status=[status]))


def test_a_stream_node_without_quality_still_replays_in_lockstep(tmp_path):
    # No ~/quality at all: a cloud without odometry is answered by pairs_done on /diagnostics,
    # and the records carry no quality values (None), as before the replay listened for them.
    from cegc_ros.replay import replay_bag, summary

    bag = _recording(tmp_path / "rec_old", n=4)
    node = OldStreamNode("/oldstream", reject={52 * 10**8})
    try:
        t0 = time.monotonic()
        result = replay_bag(bag, lockstep=True, pair_timeout=60.0, timeout=60.0,
                            node_namespace="/oldstream")
        took = time.monotonic() - t0
    finally:
        node.close()
    assert node.stamps == [(50 + k) * 10**8 for k in range(4)]
    assert [r.T_est is not None for r in result.records] == [True, True, False, True]
    assert all((r.fitness, r.ambiguity, r.rejected, r.method, r.keyframe) == (None,) * 5
               for r in result.records)
    assert took < 30.0                      # moved on after the rejected cloud, no 60 s waits
    info = summary(result)
    assert (info["clouds"], info["poses"]) == (4, 3)
    assert "rejected" not in info and "methods" not in info and "keyframes" not in info


def test_a_repeated_play_needs_the_nodes_reset_service(tmp_path, capsys):
    bag = _recording(tmp_path / "rec_loop", n=2)
    rec = CloudRecorder("/noreset", "/noreset/cloud")
    try:
        code, out, err, _ = _replay([str(bag), "--node-namespace", "/noreset", "--loops", "2",
                                     "--timeout", "0.3", "--rate", "4"], capsys)
    finally:
        rec.close()
    assert rec.stamps == [50 * 10**8, 51 * 10**8]             # the first play went out
    assert code == 1 and out == ""
    assert err == ["cegc-replay: a repeated play needs /noreset/register_node/reset "
                   "(std_srvs/Trigger) to start over; no such service answered within 5 s"]
    with pytest.raises(SystemExit) as exc:
        _replay([str(bag), "--loop", "--loops", "2"], capsys)
    assert exc.value.code == 2


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_sensor_recording_plays_its_cloud_topic_onto_cloud_and_skips_the_rest(tmp_path, capsys, storage):
    bag = _recording(tmp_path / "rec", storage)
    rec = CloudRecorder("/anybag", "/anybag/cloud")
    try:
        code, out, err, _ = _replay([str(bag), "--node-namespace", "/anybag", "--timeout", "0.5",
                                     "--rate", "4"], capsys)
    finally:
        rec.close()
    assert code == 0, err
    assert rec.stamps == [(50 + k) * 10**8 for k in range(4)]     # IMU and vendor status skipped
    assert '"clouds": 4' in out


def test_remap_chooses_the_topic_and_where_it_goes_and_start_offset_skips(tmp_path, capsys):
    bag = _recording(tmp_path / "rec2", clouds=("/front/points", "/rear/points"))
    code, _, err, _ = _replay([str(bag), "--node-namespace", "/remap"], capsys)
    assert code == 1 and err == ["cegc-replay: the bag has 2 PointCloud2 topics (/front/points, "
                                 "/rear/points): choose with --remap FROM:=TO"]
    code, _, err, _ = _replay([str(bag), "--remap", "/imu:=cloud"], capsys)
    assert code == 1 and err == ["cegc-replay: --remap /imu:=cloud: /imu is sensor_msgs/msg/Imu, "
                                 "only PointCloud2 topics are replayed"]
    rec = CloudRecorder("/remap", "/remap/lidar")
    try:
        code, _, err, _ = _replay([str(bag), "--node-namespace", "/remap", "--remap",
                                   "/rear/points:=lidar", "--start-offset", "0.15",
                                   "--timeout", "0.5", "--rate", "4"], capsys)
    finally:
        rec.close()
    assert code == 0, err
    assert rec.stamps == [52 * 10**8, 53 * 10**8]                # 0.2 and 0.3 s in; the rear only
    with pytest.raises(SystemExit) as exc:
        _replay([str(bag), "--remap", "no-separator"], capsys)
    assert exc.value.code == 2


def test_make_bag_writes_your_own_cloud_files_as_a_sequence_bag(tmp_path, capsys):
    import numpy as np

    from cegc_ros.data.bag import read_sequence
    from cegc_ros.tools.make_bag import main as make_bag

    rng = np.random.default_rng(3)
    files = []
    for k in range(3):
        files.append(tmp_path / f"scan_{k}.npy")
        np.save(files[-1], rng.uniform(-20, 20, (500 + k, 4)))     # x y z intensity
    out = tmp_path / "scans_bag"
    assert make_bag(["--clouds", *map(str, files), "--rate", "5", "--frame-id", "os_sensor",
                     "--out", str(out)]) == 0
    assert capsys.readouterr().out.startswith("wrote 3 clouds (5 Hz, frame os_sensor)")
    frames = list(read_sequence(out))
    assert [f.stamp_ns - frames[0].stamp_ns for f in frames] == [0, 2 * 10**8, 4 * 10**8]
    for f, path in zip(frames, files):
        np.testing.assert_allclose(f.cloud, np.load(path)[:, :3].astype(np.float32))
        assert f.frame_id == "os_sensor" and f.T_world_cloud is None
    assert make_bag(["--clouds", str(tmp_path / "nope.npy"), "--out", str(tmp_path / "b2")]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        f"cegc-make-bag: error: {tmp_path / 'nope.npy'}: no such file"]


class ResettingRecorder(CloudRecorder):
    """A CloudRecorder that also offers ~/reset, counting the calls."""

    def __init__(self, namespace: str, topic: str) -> None:
        from std_srvs.srv import Trigger

        super().__init__(namespace, topic)
        self.resets = 0

        def on_reset(_request, response):
            self.resets += 1
            response.success = True
            return response
        self.node.create_service(Trigger, f"{namespace}/register_node/reset", on_reset)


def test_loop_plays_until_ctrl_c_then_reports_the_completed_plays(tmp_path):
    import json
    import signal
    import subprocess
    import sys

    bag = _recording(tmp_path / "rec_forever", n=3)
    out = tmp_path / "loop.json"
    rec = ResettingRecorder("/forever", "/forever/cloud")
    try:
        proc = subprocess.Popen([sys.executable, "-m", "cegc_ros.tools.replay", str(bag), "--loop",
                                 "--node-namespace", "/forever", "--rate", "8", "--timeout", "0.2",
                                 "--out", str(out)], env=rh.ros_env(), cwd=rh.REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert rh.wait_for(lambda: rec.resets >= 2 or proc.poll() is not None, 60.0)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        rec.close()
    assert proc.returncode == 0, stderr
    report = json.loads(out.read_text())
    plays = report["loops"]
    assert plays >= 2 and json.loads(stdout.strip().splitlines()[-1])["loops"] == plays
    assert [r["loop"] for r in report["records"]] == [k for k in range(plays) for _ in range(3)]
    assert rec.stamps[:6] == [(50 + k) * 10**8 for k in range(3)] * 2     # the same bag again
