"""register_node under a busy engine, a crashing engine, huge clouds and several instances.

In-process nodes over real DDS with stand-in engines (fake_engines.py) in the node's engine
process, started exactly as the real engine is. No wall-clock budgets: every wait is a
generous bound on a hang, and the assertions are about order and counts.
"""

from __future__ import annotations


import numpy as np
import pytest
import ros_helpers as rh

rclpy = pytest.importorskip("rclpy")

from rclpy.parameter import Parameter  # noqa: E402

from cegc_ros.node.engine_process import EngineProcess  # noqa: E402
from cegc_ros.spinning import Spinner  # noqa: E402

SEC = 10**9


def _pts(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (n, 3)).astype(np.float32)


class _Stack:
    """Nodes and probes in one context, spun by one executor; torn down in ``close``."""

    def __init__(self) -> None:
        from rclpy.executors import MultiThreadedExecutor

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.executor = MultiThreadedExecutor(num_threads=3, context=self.context)
        self.nodes: list = []
        self.spinner = Spinner(self.executor)

    def node(self, factory: str, namespace: str = "/", **params):
        from cegc_ros.node import node_class

        overrides = [Parameter("input.reliable", value=True),
                     Parameter("input.queue_depth", value=100),
                     Parameter("diagnostics.period", value=0.2)]
        overrides += [Parameter(k.replace("__", "."), value=v) for k, v in params.items()]
        node = node_class()(engine_factory=lambda p, e: EngineProcess(p, e, factory=factory),
                            namespace=namespace, context=self.context,
                            parameter_overrides=overrides)
        probe = rh.make_probe(namespace=namespace, context=self.context)
        for n in (node, probe):
            self.nodes.append(n)
            self.executor.add_node(n)
        assert rh.wait_for(probe.connected, 30.0), "probe never matched the node"
        return node, probe

    def close(self) -> None:
        self.spinner.stop()
        for n in self.nodes:
            n.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def stack():
    s = _Stack()
    yield s
    s.close()


def test_parameters_and_diagnostics_answer_while_the_engine_holds_its_gil(stack):
    """The engine stand-in holds its GIL in one C call per pair (like a long Open3D call):
    with the engine in the node's process nothing else in the node would run meanwhile."""
    from rcl_interfaces.srv import DescribeParameters

    node, probe = stack.node("fake_engines:gil_hog", "/busy",
                             engine__checkpoint=str(10**8))  # ~1 s idle, several s loaded
    client = stack.nodes[-1].create_client(DescribeParameters,
                                           "/busy/register_node/describe_parameters")
    assert client.wait_for_service(30.0)
    t = 1000 * SEC
    probe.send(rh.cloud(_pts(100), "a", t), rh.cloud(_pts(100), "b", t))
    assert rh.wait_for(lambda: node.stats.busy, 30.0, 0.002)
    diag_before = len(probe.outputs("diagnostics"))
    answers = []
    for _ in range(3):
        fut = client.call_async(DescribeParameters.Request(names=["sync.slop"]))
        assert rh.wait_for(fut.done, 60.0)
        answers.append((fut.result().descriptors[0].name, node.stats.count("pairs_done")))
    assert rh.wait_for(lambda: len(probe.outputs("diagnostics")) >= diag_before + 2
                       or node.stats.count("pairs_done") > 0, 60.0)
    # Both happened while the engine was still working on the pair.
    busy_diags = [a for a in probe.outputs("diagnostics")[diag_before:]
                  if any(kv.key == "busy" and kv.value == "true" for kv in a.status[0].values)]
    done_at_answers = [d for _, d in answers]
    assert [n for n, _ in answers] == ["sync.slop"] * 3
    assert done_at_answers == [0, 0, 0]
    assert len(busy_diags) >= 2
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 120.0)


def test_a_crashed_engine_is_counted_restarted_and_the_node_goes_on(stack):
    node, probe = stack.node("fake_engines:echo", "/crash")
    pid = node.engine.info.pid
    t = 2000 * SEC
    probe.send(rh.cloud(_pts(77), "a", t), rh.cloud(_pts(100), "b", t))   # SIGKILLs itself
    assert rh.wait_for(lambda: node.stats.count("pairs_done") == 1, 60.0)
    values = node.diagnostics_values()
    assert values["rejected.engine_error"] == "1" and values["engine_restarts"] == "1"
    assert node.engine.info.pid != pid and node.engine.alive()
    t += SEC
    probe.send(rh.cloud(_pts(100), "a", t), rh.cloud(_pts(100), "b", t))
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 60.0)
    assert node.diagnostics_values()["engine_pid"] == str(node.engine.info.pid)


def test_engine_errors_and_refusals_are_counted_by_reason(stack):
    node, probe = stack.node("fake_engines:echo", "/errors")
    t = 3000 * SEC
    for n in (50, 51):      # the stand-in refuses 50 points (ValueError), fails on 51
        done = node.stats.count("pairs_done")
        probe.send(rh.cloud(_pts(n), "a", t), rh.cloud(_pts(100), "b", t))
        assert rh.wait_for(lambda: node.stats.count("pairs_done") > done, 60.0)
        t += SEC
    values = node.diagnostics_values()
    assert (values["rejected.too_few_points"], values["rejected.engine_error"]) == ("1", "1")
    assert values["engine_restarts"] == "0"


def test_huge_clouds_are_thinned_counted_and_logged_once(stack):
    node, probe = stack.node("fake_engines:echo", "/huge", input__max_points=5000,
                             diagnostics__log_throttle=3600.0)
    logged: list[str] = []
    emit = node._log._emit
    node._log._emit = lambda text: (logged.append(text), emit(text))
    sizes: list[tuple[int, int]] = []
    register = node.engine.register

    def spy(src, tgt, update=None):
        sizes.append((len(src), len(tgt)))
        return register(src, tgt, update)

    node.engine.register = spy
    big = _pts(300_000, 1)
    t = 4000 * SEC
    for k in range(3):
        done = node.stats.count("pairs_done")
        probe.send(rh.cloud(big, "a", t + k * SEC), rh.cloud(_pts(100), "b", t + k * SEC))
        assert rh.wait_for(lambda: node.stats.count("pairs_done") > done, 60.0)
    assert node.stats.count("thinned_clouds") == 3 and node.stats.count("pairs_out") == 3
    assert sizes == [(5000, 100)] * 3          # stride 60: rows 0, 60, ..., 299940
    thinned = [ln for ln in logged if "thinned" in ln]
    assert thinned == ["source cloud of 300000 points thinned to input.max_points = 5000 by a "
                       "uniform stride"]


def test_bytes_that_are_not_a_point_cloud2_are_take_errors_and_the_node_goes_on(stack):
    """The node reads its inputs' serialized bytes itself (raw subscriptions): a buffer that
    is not a PointCloud2 is counted as a take error and logged, never paired, never a crash."""
    from rclpy.serialization import serialize_message

    node, probe = stack.node("fake_engines:echo", "/bytes", diagnostics__log_throttle=3600.0)
    logged: list[str] = []
    emit = node._log._emit
    node._log._emit = lambda text: (logged.append(text), emit(text))
    t = 5000 * SEC
    good = serialize_message(rh.cloud(_pts(100), "a", t))
    for raw in (b"\x00\x01\x00\x00" + b"\xff" * 64,   # a frame_id longer than the buffer
                good[: len(good) // 2],                 # cut inside the points
                good[:-1] + b"\x05",                    # is_dense neither 0 nor 1
                b"\x00\x07" + good[2:]):                # XCDR2: not what this node reads
        probe.pub["source"].publish(raw)
    assert rh.wait_for(lambda: node.stats.count("take_errors") == 4, 30.0)
    assert node.stats.count("messages_in.source") == 0
    probe.send(rh.cloud(_pts(100), "a", t), rh.cloud(_pts(100), "b", t))
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 60.0)
    values = node.diagnostics_values()
    assert (values["take_errors"], values["pairs_out"], values["pairs_rejected"]) == \
        ("4", "1", "0")
    takes = [ln for ln in logged if "could not take" in ln]
    assert takes == ["could not take a message: CdrError: serialized PointCloud2 ends inside "
                     "header.frame_id: 4294967295 bytes needed at offset 16, the buffer has 68"]


def test_namespaced_nodes_have_their_own_status_and_replay_finds_its_node(stack, tmp_path):
    from cegc_ros.data.bag import write_pairs
    from cegc_ros.data.protocols import make_pairs
    from cegc_ros.replay import replay_bag

    node1, probe1 = stack.node("fake_engines:echo", "/robot1")
    node2, probe2 = stack.node("fake_engines:echo", "/robot2")
    assert rh.wait_for(lambda: probe1.diagnostics() and probe2.diagnostics(), 30.0)
    names = {st.name for arr in probe1.outputs("diagnostics") for st in arr.status}
    assert {"/robot1/register_node: registration",
            "/robot2/register_node: registration"} <= names
    bag = tmp_path / "pairs"
    write_pairs(bag, make_pairs("7scenes", "test", 3))
    res = replay_bag(bag, lockstep=True, node_namespace="/robot1", timeout=30.0,
                     connect_timeout=30.0)
    assert [r.T_est is not None for r in res.records] == [True] * 3
    # The diagnostics the replay followed are robot1's: three pairs done there, none on robot2.
    assert res.diagnostics["pairs_done"] == "3"
    assert node1.stats.count("pairs_done") == 3 and node2.stats.count("pairs_done") == 0


def test_a_pose_whose_only_defect_is_its_covariance_is_published_as_undetermined(stack):
    from cegc_ros.refine import UNCONSTRAINED_VARIANCE
    from fake_engines import T_KNOWN

    node, probe = stack.node("fake_engines:bad_covariance", "/badcov")
    t = 4000 * SEC
    probe.send(rh.cloud(_pts(100), "a", t), rh.cloud(_pts(100), "b", t))
    assert rh.wait_for(lambda: t in probe.by_stamp("pose_with_covariance"), 60.0)
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 5.0)   # topics arrive in any order
    msg = probe.by_stamp("pose_with_covariance")[t]
    C = np.asarray(msg.pose.covariance).reshape(6, 6)
    assert np.array_equal(C, np.diag([UNCONSTRAINED_VARIANCE] * 6))
    p = msg.pose.pose.position
    assert (p.x, p.y, p.z) == pytest.approx(tuple(T_KNOWN[:3, 3]))
    values = node.diagnostics_values()
    assert values["covariance_fallbacks"] == "1" and values["pairs_out"] == "1"
    assert values["rejected.invalid_result"] == "0"


def test_sensor_defects_are_dropped_and_counted_per_cloud(stack):
    """An organized 64 x 32 cloud (an OS1-style sweep, rows of the image) with NaN holes,
    (0, 0, 0) no-returns and returns beyond preprocess.max_range: the engine gets only the
    usable points, /diagnostics counts each kind per cloud."""
    node, probe = stack.node("fake_engines:echo", "/defects", preprocess__max_range=20.0)
    rng = np.random.default_rng(3)
    sweep = rng.uniform(-10, 10, (64 * 32, 3)).astype(np.float32)    # all within 17.4 m
    sweep[::7] = 0.0                                                    # 293 no returns
    holes = rng.choice(np.flatnonzero(sweep.any(1)), 100, replace=False)
    sweep[holes] = np.nan
    r = np.linalg.norm(sweep, axis=1)
    far = rng.choice(np.flatnonzero(np.isfinite(r) & (r > 7.0)), 40, replace=False)
    sweep[far] *= 3.0                                                   # 21-52 m out
    msg = rh.cloud(sweep, "os_sensor", 5000 * SEC)
    msg.height, msg.width, msg.row_step = 64, 32, 32 * msg.point_step   # organized
    seen: list[np.ndarray] = []
    register = node.engine.register

    def spy(src, tgt, update=None):
        seen.append(np.array(src))
        return register(src, tgt, update)

    node.engine.register = spy
    t = 5000 * SEC
    probe.send(msg, rh.cloud(_pts(500), "b", t))
    assert rh.wait_for(lambda: t in probe.by_stamp("pose"), 60.0)
    values = node.diagnostics_values()
    n_zero = len(range(0, 64 * 32, 7))
    (src,) = seen
    assert len(src) == 64 * 32 - n_zero - 100 - 40
    assert np.isfinite(src).all() and src.any(1).all() and (np.linalg.norm(src, axis=1) <= 20.0).all()
    assert (values["dropped.no_return.source"], values["dropped.non_finite.source"],
            values["dropped.out_of_range.source"]) == (str(n_zero), "100", "40")
    assert values["dropped.no_return.target"] == values["dropped.non_finite.target"] == "0"
