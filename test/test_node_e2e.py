"""register_node as users run it: a subprocess with the params file, real engine, real DDS.

One node is started for the whole module (start-up takes seconds); the tests publish
generated 7Scenes-style pairs and hostile messages and read the node's outputs and its
/diagnostics counters. Small point counts keep inference fast on a shared 2-core machine.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import ros_helpers as rh

rclpy = pytest.importorskip("rclpy")

from cegc_ros.config import PreprocessConfig
from cegc_ros.engine import default_weights
from cegc_ros.spinning import Spinner

SEC = 10**9
CHECKPOINT = Path(os.environ.get("CEGC_TEST_CHECKPOINT", default_weights()))
NUM_POINTS = 256
NODE_ARGS = ["--ros-args", "--params-file", f"{rh.REPO}/params/register_node.yaml",
             "-p", f"engine.checkpoint:={CHECKPOINT}", "-p", "input.reliable:=true",
             "-p", f"preprocess.num_points:={NUM_POINTS}", "-p", "diagnostics.period:=0.5",
             "-p", "engine.device:=cpu"]

needs_checkpoint = pytest.mark.skipif(not CHECKPOINT.is_file(),
                                      reason=f"no checkpoint {CHECKPOINT}")


def start_node(*extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cegc_ros.node", *NODE_ARGS, *extra],
                            env=rh.ros_env(), cwd=rh.REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


@pytest.fixture(scope="module")
def ros():
    from rclpy.executors import SingleThreadedExecutor

    if not CHECKPOINT.is_file():
        pytest.skip(f"no checkpoint {CHECKPOINT}")
    proc = start_node()
    context = rclpy.Context()
    rclpy.init(context=context)
    probe = rh.make_probe(context=context)
    ex = SingleThreadedExecutor(context=context)
    ex.add_node(probe)
    spinner = Spinner(ex)
    if not rh.wait_for(lambda: probe.connected() or proc.poll() is not None, 90.0):
        proc.kill()
        pytest.fail(f"node did not come up:\n{proc.communicate()[0]}")
    assert proc.poll() is None, proc.communicate()[0]
    assert rh.wait_for(lambda: probe.diagnostics(), 5.0)
    yield proc, probe
    if proc.poll() is None:
        proc.kill()
        proc.communicate()
    spinner.stop()
    probe.destroy_node()
    rclpy.try_shutdown(context=context)


@pytest.fixture(scope="module")
def pairs():
    from cegc_ros.data.protocols import make_pairs

    return make_pairs("7scenes", "test", 4)


def _diag(probe, key: str) -> int:
    return int(probe.diagnostics().get(key, "0"))


def _fresh_diag(probe, timeout: float = 3.0) -> dict[str, str]:
    """Diagnostics published after now (the node publishes every 0.5 s here)."""
    n = len(probe.outputs("diagnostics"))
    assert rh.wait_for(lambda: len(probe.outputs("diagnostics")) > n, timeout)
    return probe.diagnostics()


def test_help_exits_zero_without_ros():
    out = subprocess.run([sys.executable, "-m", "cegc_ros.node", "--help"], env=rh.ros_env(),
                         cwd=rh.REPO, capture_output=True, text=True, timeout=60, check=False)
    assert out.returncode == 0 and out.stdout.startswith("usage: register_node")
    assert "sync.slop = 0.05 [0.0, 60.0]" in out.stdout


@pytest.mark.parametrize("kind", ["missing", "broken"])
def test_bad_checkpoint_is_one_line_and_nonzero(tmp_path, kind):
    path = tmp_path / "cegc.pt"
    if kind == "broken":
        path.write_bytes(b"not a checkpoint" * 10)
    out = subprocess.run([sys.executable, "-m", "cegc_ros.node", *NODE_ARGS, "-p",
                          f"engine.checkpoint:={path}"], env=rh.ros_env(), cwd=rh.REPO,
                         capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 1
    lines = [ln for ln in (out.stdout + out.stderr).splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    assert lines[0].startswith("[FATAL] [register_node]: cannot start: CheckpointError:")
    assert str(path) in lines[0]
    assert ("file not found" if kind == "missing" else "unreadable") in lines[0]


def test_every_pair_yields_outputs_matching_the_offline_engine(ros, pairs):
    from cegc_ros.engine import Registrar
    from cegc_ros.metrics import pair_errors
    from msg_adapters.pose import pose_to_matrix

    _, probe = ros
    stamps = []
    for k, p in enumerate(pairs):
        st = 1_000 * SEC + k * SEC // 2
        stamps.append(st)
        probe.send(rh.cloud(p.source, "cegc_source", st), rh.cloud(p.target, "cegc_target", st))
        assert rh.wait_for(lambda st=st: st in probe.by_stamp("pose"), 30.0), f"no pose {k}"
    names = ("pose_with_covariance", "source_overlap", "target_overlap")
    assert rh.wait_for(lambda: all(set(stamps) <= set(probe.by_stamp(n)) for n in names), 5.0)
    # The markers are the last output of a pair.
    assert rh.wait_for(lambda: set(stamps) <= {rh.stamp_of(m.markers[-1])
                                               for m in probe.outputs("markers")}, 5.0)

    reg = Registrar.from_checkpoint(CHECKPOINT, device="cpu",
                                    preprocess=PreprocessConfig(num_points=NUM_POINTS))
    T_gt = np.array([p.T_target_source for p in pairs])
    T_node = np.array([pose_to_matrix(probe.by_stamp("pose")[s].pose) for s in stamps])
    T_off = np.array([reg.register(p.source, p.target).T_target_source for p in pairs])
    e_node, e_off = pair_errors(T_gt, T_node), pair_errors(T_gt, T_off)
    # Same clouds, same seed: the node reproduces the offline engine.
    np.testing.assert_allclose(e_node.rot_error_deg, e_off.rot_error_deg, atol=0.05)
    np.testing.assert_allclose(e_node.trans_error, e_off.trans_error, atol=1e-3)
    np.testing.assert_allclose(T_node, T_off, atol=1e-3)

    for s in stamps:
        pose = probe.by_stamp("pose")[s]
        assert pose.header.frame_id == "cegc_target"
        cov = probe.by_stamp("pose_with_covariance")[s]
        assert cov.header.frame_id == "cegc_target" and cov.pose.pose == pose.pose
        so, to = probe.by_stamp("source_overlap")[s], probe.by_stamp("target_overlap")[s]
        assert (so.header.frame_id, to.header.frame_id) == ("cegc_source", "cegc_target")
        assert [f.name for f in so.fields] == ["x", "y", "z", "overlap"]
        assert 0 < so.width <= NUM_POINTS and 0 < to.width <= NUM_POINTS
        from msg_adapters.point_cloud2 import cloud_to_xyz
        assert cloud_to_xyz(so).shape == (so.width, 3)
        ma = next(m for m in probe.outputs("markers") if rh.stamp_of(m.markers[-1]) == s)
        lines = ma.markers[-1]
        assert lines.header.frame_id == "cegc_target"
        assert 0 < len(lines.points) <= 2 * 200 and len(lines.points) % 2 == 0


def test_hostile_input_is_counted_and_the_node_keeps_answering(ros, pairs):
    from sensor_msgs.msg import PointCloud2

    proc, probe = ros
    good_s, good_t = pairs[0].source, pairs[0].target
    before = _fresh_diag(probe)
    t = 2_000 * SEC

    def send(src, tgt, wait=False):
        nonlocal t
        done = _diag(probe, "pairs_done")
        probe.send(src, tgt)
        t += SEC
        if wait:  # one at a time: a pair in the mailbox would be replaced by the next one
            assert rh.wait_for(lambda: _diag(probe, "pairs_done") > done, 15.0)

    def c(xyz, frame, st=None):
        return rh.cloud(xyz, frame, t if st is None else st)

    done0 = int(before["pairs_done"])
    send(c(np.zeros((0, 3)), "cegc_source"), c(good_t, "cegc_target"), wait=True)           # empty
    send(c(good_s[:8], "cegc_source"), c(good_t, "cegc_target"), wait=True)                 # too few
    nofield = c(good_s, "cegc_source")
    nofield.fields = [f for f in nofield.fields if f.name != "y"]
    send(nofield, c(good_t, "cegc_target"), wait=True)                                      # missing field
    short = c(good_t, "cegc_target")
    short.data = short.data[: len(short.data) // 3]
    send(c(good_s, "cegc_source"), short, wait=True)                                        # corrupt length
    assert _diag(probe, "pairs_done") == done0 + 4
    # Bytes that are not a PointCloud2 at all, straight onto the wire: the node reads its
    # inputs' serialized bytes itself, so it sees them and counts a take error (not a message).
    raw_pub = probe.create_publisher(PointCloud2, "/source_cloud", 10)
    assert rh.wait_for(lambda: raw_pub.get_subscription_count() > 0, 30.0)
    raw_pub.publish(b"\x00\x01\x00\x00" + b"\xff" * 64)
    # A 5-million-point cloud (60 MB), all but 0.03% of it uniform noise in a 2 m cube:
    # thinned to input.max_points and registered, but no pose can explain it; the engine's
    # verdict (fitness below engine.min_valid_fitness) rejects it instead of publishing a pose
    # that lays a few per cent of the source on the target.
    rng = np.random.default_rng(0)
    big = np.concatenate([good_s, rng.uniform(-1, 1, (5_000_000 - len(good_s), 3))]).astype(
        np.float32)
    big_stamp = t
    rejected = _diag(probe, "rejected.invalid_result")
    send(c(big, "cegc_source"), c(good_t, "cegc_target"))
    del big
    assert rh.wait_for(lambda: _diag(probe, "rejected.invalid_result") > rejected, 60.0)
    assert big_stamp not in probe.by_stamp("pose")
    # A burst of 100 pairs: the one-slot mailbox drops what the engine cannot keep up with.
    burst = []
    src_msg, tgt_msg = c(good_s, "cegc_source"), c(good_t, "cegc_target")
    for _ in range(100):
        for m in (src_msg, tgt_msg):
            m.header.stamp.sec, m.header.stamp.nanosec = t // SEC, t % SEC
        burst.append(t)
        send(src_msg, tgt_msg)
    assert rh.wait_for(lambda: burst[-1] in probe.by_stamp("pose"), 60.0)
    # ...and a plain valid pair afterwards is still answered.
    last = t
    send(c(pairs[1].source, "cegc_source"), c(pairs[1].target, "cegc_target"))
    assert rh.wait_for(lambda: last in probe.by_stamp("pose"), 30.0)
    assert proc.poll() is None

    after = _fresh_diag(probe)
    d = {k: int(after[k]) - int(before[k]) for k in after
         if k.startswith(("rejected.", "pairs_", "thinned", "messages_in", "unpaired",
                          "take_errors"))}
    assert d["rejected.empty_cloud"] == 1
    assert d["rejected.too_few_points"] == 1
    assert d["rejected.malformed_cloud"] == 2
    assert d["thinned_clouds"] == 1
    assert d["rejected.invalid_result"] == 1          # the noise cloud's pose, fitness < 0.05
    assert d["pairs_out"] >= 2                       # last of the burst, final pair
    assert d["pairs_dropped"] >= 1                   # the burst outran the engine
    # Every pair that formed was answered, dropped or rejected; nothing vanished.
    assert d["pairs_in"] == d["pairs_done"] + d["pairs_dropped"]
    assert d["pairs_rejected"] == 5
    burst_poses = [s for s in probe.by_stamp("pose") if burst[0] <= s <= burst[-1]]
    assert len(burst_poses) == d["pairs_out"] - 1
    # 4 bad + 1 big + 100 burst + 1 final sources were sent (plus the garbage bytes); burst
    # messages may be lost in the input queue (KEEP_LAST depth 5), never duplicated.
    assert 7 <= d["messages_in.source"] <= 106
    assert d["take_errors"] == 1


def test_runtime_parameters_over_the_parameter_service(ros, pairs):
    from rcl_interfaces.msg import Parameter as ParamMsg
    from rcl_interfaces.msg import ParameterType, ParameterValue
    from rcl_interfaces.srv import DescribeParameters, SetParameters

    _, probe = ros
    set_cli = probe.create_client(SetParameters, "/register_node/set_parameters")
    desc_cli = probe.create_client(DescribeParameters, "/register_node/describe_parameters")
    assert set_cli.wait_for_service(10.0) and desc_cli.wait_for_service(10.0)

    def call(cli, req):
        fut = cli.call_async(req)
        assert rh.wait_for(fut.done, 10.0)
        return fut.result()

    def set_double(name, value):
        req = SetParameters.Request(parameters=[ParamMsg(name=name, value=ParameterValue(
            type=ParameterType.PARAMETER_DOUBLE, double_value=value))])
        return call(set_cli, req).results[0]

    desc = call(desc_cli, DescribeParameters.Request(names=["output.min_fitness"])).descriptors[0]
    assert desc.floating_point_range[0].to_value == 1.0 and "fitness" in desc.description
    bad = set_double("output.min_fitness", 1.5)
    assert not bad.successful and "output.min_fitness" in bad.reason
    bad = set_double("sync.slop", -1.0)
    assert not bad.successful and "sync.slop" in bad.reason

    # min_fitness 1.0: a pose needs every source point to be an inlier -> rejected, counted.
    before = _fresh_diag(probe)
    assert set_double("output.min_fitness", 1.0).successful
    t = 3_000 * SEC
    p = pairs[2]
    probe.send(rh.cloud(p.source, "cegc_source", t), rh.cloud(p.target, "cegc_target", t))
    assert rh.wait_for(lambda: _diag(probe, "rejected.low_fitness")
                       == int(before["rejected.low_fitness"]) + 1, 30.0)
    assert t not in probe.by_stamp("pose")
    assert set_double("output.min_fitness", 0.0).successful

    # Slop 0.05 -> a pair 0.2 s apart is not matched; raise the slop and it is.
    t += SEC
    probe.send(rh.cloud(p.source, "cegc_source", t), rh.cloud(p.target, "cegc_target",
                                                                t + SEC // 5))
    time.sleep(1.0)
    assert t not in probe.by_stamp("pose")
    assert set_double("sync.slop", 0.3).successful
    t += SEC
    probe.send(rh.cloud(p.source, "cegc_source", t), rh.cloud(p.target, "cegc_target",
                                                                t + SEC // 5))
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 30.0)
    assert set_double("sync.slop", 0.05).successful


def test_replay_records_poses_next_to_ground_truth(ros, pairs, tmp_path):
    from cegc_ros.data.bag import write_pairs
    from cegc_ros.tools.replay import main as replay_main
    from cegc_ros.replay import replay_bag

    bag = tmp_path / "pairs"
    write_pairs(bag, pairs[:3])
    res = replay_bag(bag, lockstep=True, timeout=5.0)
    assert len(res.records) == 3
    for r, p in zip(res.records, pairs):
        assert r.T_est is not None and r.latency_s is not None and r.latency_s > 0
        np.testing.assert_allclose(r.T_gt, p.T_target_source, atol=1e-6)
        # The pair's ~/quality: the engine's fitness; no stream fields (method, keyframe).
        assert r.rejected is None and r.fitness is not None and 0.0 < r.fitness <= 1.0
        assert r.method is None and r.keyframe is None
    out = tmp_path / "replay.csv"
    assert replay_main([str(bag), "--rate", "4", "--out", str(out)]) == 0
    rows = out.read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith("index,loop,stamp_ns,latency_s,est_00")
    assert rows[0].endswith(",fitness,ambiguity,rejected,method,keyframe")
    assert all(row.split(",")[1] == "0" for row in rows[1:])              # one play


def test_sigterm_exits_cleanly(ros):
    proc, _ = ros
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert "shutting down" in out and "Traceback" not in out


@needs_checkpoint
def test_sigint_exits_cleanly():
    proc = start_node()
    try:
        ready = ""
        end = time.monotonic() + 90
        while time.monotonic() < end and "ready (" not in ready:
            line = proc.stdout.readline()
            if not line:
                break
            ready += line
        assert "ready (pairs mode):" in ready and "within slop 0.05 s" in ready, ready
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0, ready + out
        assert "Traceback" not in out
    finally:
        if proc.poll() is None:
            proc.kill()
