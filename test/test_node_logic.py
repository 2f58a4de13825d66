"""register_node in-process over real DDS, with a stand-in engine (fast, no torch).

Covers the node's own logic: parameters and their ranges, pairing, rejection reasons and
counters, outputs' frames and stamps, the one-slot mailbox. The real engine is exercised by
test_node_e2e.py.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
import ros_helpers as rh
import yaml
from fake_engines import T_KNOWN, Result

from cegc_ros.config import InputConfig, OutputConfig, PreprocessConfig, SyncConfig
from cegc_ros.node import (
    Mailbox,
    ThrottledLog,
    check_value,
    param_specs,
    percentiles_ms,
    thin,
    usage,
)
from cegc_ros.node.engine_process import InlineEngine
from cegc_ros.spinning import Spinner

rclpy = pytest.importorskip("rclpy")

SEC = 10**9


class FakeRegistrar:
    """Answers T_KNOWN; fitness = (#source points % 100) / 100, ambiguity = (#target points %
    100) / 100, two draws above ambiguity 0.5 (as engine.redraw_ambiguity); invalid for 99
    source points."""

    MIN_POINTS = 16
    device = "cpu"
    checkpoint_path = "/fake.pt"

    def __init__(self, preprocess, engine) -> None:
        self.preprocess, self.engine = preprocess, engine
        self.delay = 0.0
        self.gate: threading.Event | None = None   # when set, register() waits for it
        self.calls: list[tuple[int, int]] = []
        self.updates = 0

    def update(self, preprocess=None, engine=None) -> None:
        self.preprocess, self.engine = preprocess or self.preprocess, engine or self.engine
        self.updates += 1

    def warm_up(self) -> float:
        return 0.0                                   # nothing to compile

    def register(self, src: np.ndarray, tgt: np.ndarray) -> Result:
        assert src.dtype == np.float32 and src.shape[1] == 3
        self.calls.append((len(src), len(tgt)))
        time.sleep(self.delay)
        if self.gate is not None:
            self.gate.wait(10.0)
        n = self.preprocess.num_points
        s, t = src[:n], tgt[:n]
        so = np.linspace(0, 1, len(s), dtype=np.float32)
        to = np.linspace(1, 0, len(t), dtype=np.float32)
        m = min(len(s), len(t))
        corr = np.stack([np.arange(m), np.arange(m)], 1).astype(np.int64)
        w = np.linspace(0, 1, m, dtype=np.float32)
        return Result(T_KNOWN, s, t, so, to, corr, w, np.eye(6) * 1e-4,
                          (len(src) % 100) / 100, len(src) != 99,
                          "" if len(src) != 99 else "degenerate (test)", ambiguity=(len(tgt) % 100) / 100,
                          draws=1 + int(len(tgt) % 100 > 50))


@pytest.fixture(scope="module")
def ros():
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter

    from cegc_ros.node import node_class

    rclpy.init()
    made = {}

    def factory(pre, eng):
        made["reg"] = FakeRegistrar(pre, eng)
        return InlineEngine(made["reg"])

    node = node_class()(engine_factory=factory, parameter_overrides=[
        Parameter("input.reliable", value=True), Parameter("input.queue_depth", value=100),
        Parameter("diagnostics.period", value=0.2),
        Parameter("preprocess.num_points", value=64), Parameter("sync.slop", value=0.05)])
    probe = rh.make_probe()
    ex = MultiThreadedExecutor(num_threads=2)
    ex.add_node(node)
    ex.add_node(probe)
    spinner = Spinner(ex)
    assert rh.wait_for(probe.connected, 10.0), "probe never matched the node"
    yield node, probe, made["reg"]
    spinner.stop()
    node.destroy_node()
    probe.destroy_node()
    rclpy.try_shutdown()


def _pts(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (n, 3)).astype(np.float32)


def _count(node, key: str) -> int:
    return int(node.diagnostics_values()[key])


def _send_and_wait(node, probe, src, tgt, timeout=5.0) -> None:
    done = _count(node, "pairs_done")
    probe.send(src, tgt)
    assert rh.wait_for(lambda: _count(node, "pairs_done") > done, timeout)


# -- ROS-free parts ---------------------------------------------------------------------------
def test_params_yaml_agrees_with_dataclass_defaults():
    with open(f"{rh.REPO}/params/register_node.yaml") as f:
        doc = yaml.safe_load(f)
    values = doc["/**"]["ros__parameters"]
    specs = {s.name: s for s in param_specs()}
    assert set(values) == set(specs)
    for name, spec in specs.items():
        assert type(values[name]) is type(spec.default), name
        assert values[name] == spec.default, name
    assert specs["sync.slop"].default == SyncConfig().slop == 0.05
    assert specs["input.reliable"].dynamic is False


def test_check_value_reasons():
    specs = {s.name: s for s in param_specs()}
    assert check_value(specs["sync.slop"], 0.2) is None
    assert check_value(specs["sync.slop"], 1) is None  # ints are fine for doubles
    assert check_value(specs["sync.slop"], -0.1) == \
        "sync.slop = -0.1 is out of range: a float in [0.0, 60.0]"
    assert check_value(specs["sync.slop"], math.nan) == \
        "sync.slop = nan is not finite: a float in [0.0, 60.0]"
    assert check_value(specs["preprocess.num_points"], 10) == \
        "preprocess.num_points = 10 is out of range: an integer in [64, 8192]"
    assert check_value(specs["preprocess.num_points"], 1.5) == \
        "preprocess.num_points = 1.5 has the wrong type (float): an integer in [64, 8192]"
    assert check_value(specs["input.reliable"], 1) == \
        "input.reliable = 1 has the wrong type (integer): a bool"
    assert check_value(specs["engine.refine"], "gicp") == \
        "engine.refine = 'gicp' is not one of none, icp"


def test_usage_lists_every_parameter_with_default():
    text = usage()
    for s in param_specs():
        assert f"  {s.name} = {s.default!r}" in text
    assert "output.min_fitness = 0.0 [0.0, 1.0]" in text
    assert "input.reliable = False *" in text


def test_mailbox_keeps_only_the_newest():
    box = Mailbox()
    assert box.put(1) is None
    assert box.put(2) == 1          # 1 dropped
    assert box.get(0.0) == 2
    assert box.get(0.01) is None    # empty: times out
    box.put(3)
    assert box.close() == 3 and box.get() is None


def test_throttled_log_counts_suppressed_messages():
    out, now = [], [0.0]
    log = ThrottledLog(out.append, period=5.0, clock=lambda: now[0])
    assert log("a", "first a") and log("b", "first b")
    assert not log("a", "again") and not log("a", "again")
    now[0] = 5.0
    assert log("a", "later a")
    assert out == ["first a", "first b", "later a (2 more like this since the last report)"]


def test_thin_and_percentiles():
    xyz = np.arange(30, dtype=np.float32).reshape(10, 3)
    assert thin(xyz, 10) is xyz
    assert thin(xyz, 4)[:, 0].tolist() == [0.0, 9.0, 18.0, 27.0]   # stride ceil(10/4) = 3
    assert percentiles_ms([0.001, 0.002, 0.003], (50,)) == [2.0]
    assert all(math.isnan(v) for v in percentiles_ms([]))


# -- the node over DDS -------------------------------------------------------------------------
def test_declared_parameters_have_descriptions_and_ranges(ros):
    node, _, _ = ros
    (d,) = node.describe_parameters(["sync.slop"])
    assert d.description.startswith("Largest difference of header stamps")
    assert (d.floating_point_range[0].from_value, d.floating_point_range[0].to_value) == (0.0, 60.0)
    (d,) = node.describe_parameters(["preprocess.num_points"])
    assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (64, 8192)
    (d,) = node.describe_parameters(["engine.checkpoint"])
    assert d.read_only
    assert node.get_parameter("preprocess.num_points").value == 64   # override applied
    assert node.cfg["input"].reliable is True and node.cfg["output"] == OutputConfig()


def test_pair_yields_pose_overlaps_and_markers_with_frames_and_stamps(ros):
    _, probe, reg = ros
    stamp = 1000 * SEC + 250_000_000
    src, tgt = rh.cloud(_pts(200, 1), "cam_src", stamp), rh.cloud(_pts(300, 2), "cam_tgt",
                                                                   stamp + 10_000_000)
    probe.send(src, tgt)
    names = ("pose", "pose_with_covariance", "source_overlap", "target_overlap", "markers")
    assert rh.wait_for(lambda: all(stamp in probe.by_stamp(n) for n in names if n != "markers")
                       and any(rh.stamp_of(m.markers[0]) == stamp
                               for m in probe.outputs("markers")), 5.0)
    pose = probe.by_stamp("pose")[stamp]
    assert pose.header.frame_id == "cam_tgt"
    from msg_adapters.pose import pose_to_matrix
    np.testing.assert_allclose(pose_to_matrix(pose.pose), T_KNOWN, atol=1e-9)
    cov = probe.by_stamp("pose_with_covariance")[stamp]
    assert cov.header.frame_id == "cam_tgt" and cov.pose.covariance[0] == pytest.approx(1e-4)
    so, to = probe.by_stamp("source_overlap")[stamp], probe.by_stamp("target_overlap")[stamp]
    assert so.header.frame_id == "cam_src" and to.header.frame_id == "cam_tgt"
    assert [f.name for f in so.fields] == ["x", "y", "z", "overlap"]
    # 64 points kept by the fake, scores linspace(0, 1): 32 of them are >= 0.5.
    assert (so.width, to.width) == (32, 32)
    markers = next(m for m in probe.outputs("markers") if rh.stamp_of(m.markers[0]) == stamp)
    lines = markers.markers[1]
    assert lines.header.frame_id == "cam_tgt" and len(lines.points) == 2 * 64
    # Source ends are drawn in the target frame: the strongest line's source end is T p_s.
    p_s = _pts(200, 1)[63]   # the fake keeps the first 64 points; weight 1 on the last
    a = lines.points[0]
    np.testing.assert_allclose([a.x, a.y, a.z], T_KNOWN[:3, :3] @ p_s + T_KNOWN[:3, 3],
                               atol=1e-5)
    assert reg.calls[-1] == (200, 300)


def test_bad_inputs_are_counted_by_reason_and_the_node_keeps_going(ros):
    node, probe, _ = ros
    before = node.diagnostics_values()
    good = _pts(200)
    t = 2000 * SEC
    cases = []
    empty = rh.cloud(np.zeros((0, 3)), "a", t)
    cases.append(("empty_cloud", empty, rh.cloud(good, "b", t)))
    t += SEC
    few = good[:10].copy()
    nan = good.copy()
    nan[5:] = np.nan                          # 5 finite points left
    cases.append(("too_few_points", rh.cloud(nan, "a", t), rh.cloud(good, "b", t)))
    t += SEC
    nofield = rh.cloud(good, "a", t)
    nofield.fields = nofield.fields[:2]       # no z
    cases.append(("malformed_cloud", nofield, rh.cloud(good, "b", t)))
    t += SEC
    short = rh.cloud(good, "a", t)
    short.data = short.data[:100]             # width says 200 points, data holds 8
    cases.append(("malformed_cloud", rh.cloud(good, "a", t), short))
    t += SEC
    cases.append(("missing_frame", rh.cloud(good, "", t), rh.cloud(good, "b", t)))
    t += SEC
    cases.append(("invalid_result", rh.cloud(good[:99], "a", t), rh.cloud(good, "b", t)))
    t += SEC
    cases.append(("too_few_points", rh.cloud(few, "a", t), rh.cloud(good, "b", t)))
    for _, s, g in cases:
        _send_and_wait(node, probe, s, g)
    after = node.diagnostics_values()
    got = {r: int(after[f"rejected.{r}"]) - int(before[f"rejected.{r}"])
           for r in ("empty_cloud", "too_few_points", "malformed_cloud", "missing_frame",
                     "invalid_result")}
    assert got == {"empty_cloud": 1, "too_few_points": 2, "malformed_cloud": 2,
                   "missing_frame": 1, "invalid_result": 1}
    assert int(after["pairs_rejected"]) - int(before["pairs_rejected"]) == 7
    assert int(after["pairs_out"]) == int(before["pairs_out"])
    # ...and a good pair still gets its pose.
    t += SEC
    probe.send(rh.cloud(good, "a", t), rh.cloud(good, "b", t))
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 5.0)
    # The diagnostics topic carries the same counters.
    assert rh.wait_for(lambda: probe.diagnostics().get("rejected.malformed_cloud")
                       == after["rejected.malformed_cloud"], 3.0)


def test_min_fitness_and_runtime_parameters(ros):
    from rclpy.parameter import Parameter

    node, probe, reg = ros
    good = _pts(250)          # fake fitness 0.5
    res = node.set_parameters([Parameter("output.min_fitness", value=0.6)])
    assert res[0].successful
    before = _count(node, "rejected.low_fitness")
    t = 3000 * SEC
    _send_and_wait(node, probe, rh.cloud(good, "a", t), rh.cloud(good, "b", t))
    assert _count(node, "rejected.low_fitness") == before + 1 and t not in probe.by_stamp("pose")
    assert node.set_parameters([Parameter("output.min_fitness", value=0.4)])[0].successful
    # Out of range, wrong type, bad choice, read-only: rejected with the reason, value kept.
    bad = node.set_parameters([Parameter("output.min_fitness", value=1.5)])[0]
    assert not bad.successful and "output.min_fitness" in bad.reason
    bad = node.set_parameters([Parameter("preprocess.num_points", value=10)])[0]
    assert not bad.successful and "10" in bad.reason
    bad = node.set_parameters([Parameter("engine.refine", value="gicp")])[0]
    assert not bad.successful and bad.reason == "engine.refine = 'gicp' is not one of none, icp"
    bad = node.set_parameters([Parameter("input.reliable", value=False)])[0]
    assert not bad.successful and "read-only" in bad.reason
    assert node.get_parameter("output.min_fitness").value == 0.4
    # A dynamic engine setting reaches the Registrar before the next pair.
    updates = reg.updates
    assert node.set_parameters([Parameter("preprocess.num_points", value=128)])[0].successful
    t += SEC
    _send_and_wait(node, probe, rh.cloud(good, "a", t), rh.cloud(good, "b", t))
    assert reg.updates == updates + 1 and reg.preprocess == PreprocessConfig(num_points=128)
    assert rh.wait_for(lambda: t in probe.by_stamp("source_overlap"), 3.0)
    assert probe.by_stamp("source_overlap")[t].width == 64   # 128 scores linspace(0,1) >= 0.5
    node.set_parameters([Parameter("output.min_fitness", value=0.0),
                         Parameter("preprocess.num_points", value=64)])


def test_max_ambiguity_drops_poses_another_alignment_explains_as_well(ros):
    """output.max_ambiguity: a pose whose ambiguity is above it is not published, counted as
    rejected.ambiguous; one at or below it is published; the diagnostics show the last value."""
    from rclpy.parameter import Parameter

    node, probe, _ = ros
    assert node.set_parameters([Parameter("output.max_ambiguity", value=0.4)])[0].successful
    before = _count(node, "rejected.ambiguous")
    t = 3500 * SEC
    _send_and_wait(node, probe, rh.cloud(_pts(200), "a", t), rh.cloud(_pts(260), "b", t))   # 0.6
    assert _count(node, "rejected.ambiguous") == before + 1 and t not in probe.by_stamp("pose")
    t += SEC
    _send_and_wait(node, probe, rh.cloud(_pts(200), "a", t), rh.cloud(_pts(230), "b", t))   # 0.3
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 5.0)
    assert _count(node, "rejected.ambiguous") == before + 1
    assert node.diagnostics_values()["last_ambiguity"] == "0.3000"
    bad = node.set_parameters([Parameter("output.max_ambiguity", value=-0.1)])[0]
    assert not bad.successful and "output.max_ambiguity" in bad.reason
    node.set_parameters([Parameter("output.max_ambiguity", value=1.0)])


def _quality(probe, stamp: int):
    """(the message, its one status, the status's key-values) of the ~/quality message with
    this stamp."""
    assert rh.wait_for(lambda: stamp in probe.by_stamp("quality"), 5.0)
    msg = probe.by_stamp("quality")[stamp]
    (status,) = msg.status
    return msg, status, {kv.key: kv.value for kv in status.values}


def test_every_finished_pair_has_a_quality_message_published_or_rejected(ros):
    """~/quality: one message per pair the worker finishes, with the pose's stamp and frame:
    OK and the engine's numbers for a published pose; WARN, the reason and the numbers for a
    pose a check on the result rejected; WARN with nan for a pair the engine never saw."""
    from diagnostic_msgs.msg import DiagnosticStatus
    from rclpy.parameter import Parameter

    node, probe, _ = ros
    t = 3700 * SEC
    # the fake: fitness 230 % 100 / 100 = 0.30, ambiguity 260 % 100 / 100 = 0.60, 64 pairs
    _send_and_wait(node, probe, rh.cloud(_pts(230), "a", t), rh.cloud(_pts(260), "b", t))
    msg, status, v = _quality(probe, t)
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 5.0)
    assert msg.header.frame_id == "b" == probe.by_stamp("pose")[t].header.frame_id
    assert status.name == probe.status_name and status.level == DiagnosticStatus.OK
    assert status.message == "pose published"
    assert v == {"published": "true", "reason": "", "fitness": "0.3000", "ambiguity": "0.6000",
                 "correspondences": "64", "engine_ms": "nan", "draws": "2"}

    assert node.set_parameters([Parameter("output.max_ambiguity", value=0.4)])[0].successful
    t += SEC
    _send_and_wait(node, probe, rh.cloud(_pts(230), "a", t), rh.cloud(_pts(260), "b", t))
    _, status, v = _quality(probe, t)
    assert t not in probe.by_stamp("pose")
    assert status.level == DiagnosticStatus.WARN
    assert status.message.startswith("ambiguous: ambiguity 0.600 > output.max_ambiguity 0.400")
    assert (v["published"], v["reason"], v["fitness"], v["ambiguity"]) == \
        ("false", "ambiguous", "0.3000", "0.6000")
    node.set_parameters([Parameter("output.max_ambiguity", value=1.0)])

    t += SEC           # 99 source points: the fake's invalid result, fitness 0.99
    _send_and_wait(node, probe, rh.cloud(_pts(99), "a", t), rh.cloud(_pts(230), "b", t))
    _, status, v = _quality(probe, t)
    assert (v["published"], v["reason"], v["fitness"]) == ("false", "invalid_result", "0.9900")
    assert "degenerate (test)" in status.message

    t += SEC           # 5 points: rejected before the engine, so no numbers
    _send_and_wait(node, probe, rh.cloud(_pts(5), "a", t), rh.cloud(_pts(230), "b", t))
    _, status, v = _quality(probe, t)
    assert status.level == DiagnosticStatus.WARN and status.message.startswith("too_few_points: ")
    assert v == {"published": "false", "reason": "too_few_points", "fitness": "nan",
                 "ambiguity": "nan", "correspondences": "", "engine_ms": "nan", "draws": ""}


def test_sync_slop_out_of_order_and_unpaired(ros):
    node, probe, _ = ros
    good = _pts(200)
    base = 4000 * SEC
    unpaired = _count(node, "unpaired.source") + _count(node, "unpaired.target")
    pairs_in = _count(node, "pairs_in")
    # Out of order: sources 3, 1, 2 then targets 2, 3, 1 (5 ms later each): three pairs.
    for k in (3, 1, 2):
        probe.pub["source"].publish(rh.cloud(good, "a", base + k * SEC))
    time.sleep(0.2)
    for k in (2, 3, 1):
        probe.pub["target"].publish(rh.cloud(good, "b", base + k * SEC + 5_000_000))
    assert rh.wait_for(lambda: _count(node, "pairs_in") == pairs_in + 3, 5.0)
    # Outside the slop (60 ms > 50 ms): no pair; the ten later ones push them out as unpaired.
    t = base + 10 * SEC
    probe.pub["source"].publish(rh.cloud(good, "a", t))
    probe.pub["target"].publish(rh.cloud(good, "b", t + 60_000_000))
    for k in range(1, 11):
        probe.pub["source"].publish(rh.cloud(good, "a", t + k * SEC))
    ok = rh.wait_for(lambda: _count(node, "unpaired.source") + _count(node, "unpaired.target")
                     == unpaired + 1, 5.0)
    assert ok, (node.diagnostics_values(), unpaired, node.mode.pairer.pending("source"))
    assert _count(node, "pairs_in") == pairs_in + 3
    # Leave nothing buffered for later tests.
    node.mode.reset()


def test_frame_change_is_counted_and_followed(ros):
    node, probe, _ = ros
    good = _pts(200)
    t = 5000 * SEC
    _send_and_wait(node, probe, rh.cloud(good, "a", t), rh.cloud(good, "b", t))
    before = _count(node, "frame_changes.target")
    t += SEC
    probe.send(rh.cloud(good, "a", t), rh.cloud(good, "b2", t))
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 5.0)
    assert probe.by_stamp("pose")[t].header.frame_id == "b2"
    assert _count(node, "frame_changes.target") == before + 1


def test_busy_engine_drops_the_waiting_pair_not_the_newest(ros):
    node, probe, reg = ros
    good = _pts(200)
    gate = threading.Event()      # the engine holds the first pair until the others are in
    reg.gate = gate
    try:
        dropped = _count(node, "pairs_dropped")
        pairs_in = _count(node, "pairs_in")
        base = 6000 * SEC
        probe.send(rh.cloud(good, "a", base), rh.cloud(good, "b", base))
        assert rh.wait_for(lambda: node.diagnostics_values()["busy"] == "true", 5.0, 0.005)
        for k in range(1, 5):
            probe.send(rh.cloud(good, "a", base + k * SEC), rh.cloud(good, "b", base + k * SEC))
        assert rh.wait_for(lambda: _count(node, "pairs_in") == pairs_in + 5, 5.0)
        reg.gate = None
        gate.set()
        last = base + 4 * SEC
        assert rh.wait_for(lambda: last in probe.by_stamp("pose"), 5.0)
        poses = [s for s in probe.by_stamp("pose") if base <= s <= last]
        # The first pair is in the engine when the others arrive; of those only the newest
        # survives in the one-slot mailbox.
        assert sorted(poses) == [base, last]
        assert _count(node, "pairs_dropped") == dropped + 3
    finally:
        reg.gate = None
        gate.set()


def test_default_input_qos_is_sensor_data():
    from rclpy.qos import ReliabilityPolicy

    from cegc_ros.node import node_class

    node = node_class()(engine_factory=lambda p, e: InlineEngine(FakeRegistrar(p, e)))
    try:
        assert node.input_qos.reliability == ReliabilityPolicy.BEST_EFFORT
        assert node.input_qos.depth == InputConfig().queue_depth
        infos = node.get_subscriptions_info_by_topic("/source_cloud")
        assert any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos)
    finally:
        node.destroy_node()


def test_a_cloud_in_a_map_frame_is_counted_and_warned_of(ros):
    """preprocess.normals 'sensor' and engine.free_space assume sensor frames: a cloud whose
    frame is named like a map frame ("map", "robot1/odom") is counted and the log names the
    settings to change; the pair is still registered."""
    node, probe, _ = ros
    good = _pts(200)
    t = 5100 * SEC
    before = {side: _count(node, f"map_frames.{side}") for side in ("source", "target")}
    _send_and_wait(node, probe, rh.cloud(good, "robot1/map", t), rh.cloud(good, "b", t))
    assert _count(node, "map_frames.source") == before["source"] + 1
    assert _count(node, "map_frames.target") == before["target"]
    # pairs_done counts before the pose crosses DDS to the probe: wait for the pose itself.
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 5.0)
    assert probe.by_stamp("pose")[t].header.frame_id == "b"
    t += SEC
    _send_and_wait(node, probe, rh.cloud(good, "a", t), rh.cloud(good, "a_map", t))   # not a map frame
    assert _count(node, "map_frames.source") == before["source"] + 1
    assert _count(node, "map_frames.target") == before["target"]


def test_the_map_frame_warning_names_the_settings_and_follows_preprocess_normals():
    from types import SimpleNamespace

    from cegc_ros.node.stats import NodeStats
    from cegc_ros.node.worker import RegistrationWorker
    logged = []
    worker = RegistrationWorker(SimpleNamespace(info=SimpleNamespace(min_points=16)), NodeStats(10),
                                lambda kind, text: logged.append((kind, text)), dict, lambda job, r: None)
    msg = rh.cloud(_pts(200), "odom", 1)
    worker.points("source", msg, 10_000, PreprocessConfig())
    assert [k for k, _ in logged] == ["map_frame.source"]
    assert "'odom'" in logged[0][1] and "preprocess.normals to 'centroid'" in logged[0][1]
    assert "engine.free_space to 0" in logged[0][1]
    worker.points("source", msg, 10_000, PreprocessConfig(normals="centroid"))    # set as told: quiet
    assert len(logged) == 1 and worker.stats.count("map_frames.source") == 1
    worker.points("cloud", msg, 10_000, PreprocessConfig())                       # sequential mode's side
    values = worker.stats.values()
    assert values["map_frames.source"] == "1" and values["map_frames.cloud"] == "1"
    assert values["map_frames.target"] == "0"
