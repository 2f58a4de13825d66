"""register_node's parameters as ROS hands them over: params files, -p, the parameter services.

In-process nodes with the echo stand-in engine (fake_engines.py, in its own process like the
real one); the rcl argument parser is exercised through a context built from the same
arguments a user types after --ros-args.
"""

from __future__ import annotations


import pytest
import ros_helpers as rh
import yaml

rclpy = pytest.importorskip("rclpy")

from rclpy.parameter import Parameter  # noqa: E402

from cegc_ros.node import ParameterError, param_specs  # noqa: E402
from cegc_ros.node.engine_process import EngineProcess  # noqa: E402
from cegc_ros.spinning import Spinner  # noqa: E402


def _echo(pre, eng):
    return EngineProcess(pre, eng, factory="fake_engines:echo")


class _Running:
    """A node in a context of its own, spun on a thread; ``close()`` tears all of it down."""

    def __init__(self, ros_args: list[str], namespace: str = "/", **kwargs) -> None:
        from rclpy.executors import SingleThreadedExecutor

        from cegc_ros.node import node_class

        self.context = rclpy.Context()
        rclpy.init(args=["register_node", "--ros-args", *ros_args], context=self.context)
        self.node = self.executor = self.spinner = None
        try:
            self.node = node_class()(engine_factory=_echo, namespace=namespace,
                                     context=self.context, **kwargs)
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
            self.spinner = Spinner(self.executor)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        if self.spinner is not None:
            self.spinner.stop()
        if self.node is not None:
            self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _write(path, doc) -> str:
    path.write_text(yaml.safe_dump(doc))
    return str(path)


def test_integers_are_taken_for_floats_from_p_and_params_files(tmp_path):
    params = _write(tmp_path / "p.yaml", {"/**": {"ros__parameters": {
        "output.min_fitness": 0, "markers": {"line_width": 1}}}})
    run = _Running(["-p", "sync.slop:=1", "--params-file", params])
    try:
        node = run.node
        for name, value in [("sync.slop", 1.0), ("output.min_fitness", 0.0),
                            ("markers.line_width", 1.0)]:
            p = node.get_parameter(name)
            assert p.type_ == Parameter.Type.DOUBLE and p.value == value, name
        assert node.cfg["sync"].slop == 1.0 and type(node.cfg["sync"].slop) is float
        assert node.mode.pairer.slop_s == 1.0
        assert node.unknown_parameters == []
    finally:
        run.close()


def test_integer_for_a_float_at_run_time_over_the_parameter_service():
    from rcl_interfaces.msg import Parameter as ParamMsg
    from rcl_interfaces.msg import ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    run = _Running([], namespace="/int_set")
    client_node = rclpy.create_node("cegc_param_client", context=run.context)
    run.executor.add_node(client_node)
    try:
        cli = client_node.create_client(SetParameters, "/int_set/register_node/set_parameters")
        assert cli.wait_for_service(30.0)

        def set_int(name: str, value: int):
            req = SetParameters.Request(parameters=[ParamMsg(name=name, value=ParameterValue(
                type=ParameterType.PARAMETER_INTEGER, integer_value=value))])
            fut = cli.call_async(req)
            assert rh.wait_for(fut.done, 30.0)
            return fut.result().results[0]

        res = set_int("sync.slop", 2)               # what `ros2 param set ... sync.slop 2` sends
        assert res.successful, res.reason
        p = run.node.get_parameter("sync.slop")
        assert p.type_ == Parameter.Type.DOUBLE and p.value == 2.0
        assert run.node.mode.pairer.slop_s == 2.0
        res = set_int("sync.slop", 99)              # still range-checked
        assert not res.successful and "sync.slop" in res.reason and "60.0" in res.reason
        res = set_int("sync.buffer_size", 3)        # integers stay integers
        assert res.successful and run.node.get_parameter("sync.buffer_size").value == 3
        # The same through the in-process API.
        assert run.node.set_parameters([Parameter("output.min_fitness", value=1)])[0].successful
        assert run.node.cfg["output"].min_fitness == 1.0
    finally:
        client_node.destroy_node()
        run.close()


def _dump(node) -> dict:
    """What ``ros2 param dump`` writes for a node: every parameter, dotted names nested."""
    out: dict = {}
    for name in node._parameters:
        keys = name.split(".")
        d = out
        for k in keys[:-1]:
            d = d.setdefault(k, {})
        d[keys[-1]] = node.get_parameter(name).value
    return {node.get_fully_qualified_name(): {"ros__parameters": out}}


def test_a_dumped_params_file_loads_without_warnings(tmp_path):
    run = _Running(["-p", "sync.slop:=0.2", "-p", "preprocess.num_points:=128"],
                   namespace="/dumped")
    try:
        doc = _dump(run.node)
        before = {n: run.node.get_parameter(n).value for n in run.node._parameters}
    finally:
        run.close()
    values = doc["/dumped/register_node"]["ros__parameters"]
    # rclpy's own parameters are in the dump, as ros2 param dump writes them.
    assert {"use_sim_time", "start_type_description_service"} <= set(values)
    path = _write(tmp_path / "dump.yaml", doc)
    run = _Running(["--params-file", path], namespace="/dumped")
    try:
        assert run.node.unknown_parameters == []
        after = {n: run.node.get_parameter(n).value for n in run.node._parameters}
        assert after == before
        assert run.node.cfg["sync"].slop == 0.2 and run.node.cfg["preprocess"].num_points == 128
    finally:
        run.close()


def test_unknown_parameters_are_named():
    run = _Running(["-p", "sync.slopp:=0.1"], namespace="/typo")
    try:
        assert run.node.unknown_parameters == ["sync.slopp"]
    finally:
        run.close()


@pytest.mark.parametrize("args, reason", [
    (["-p", "preprocess.num_points:=10"],
     "preprocess.num_points = 10 is out of range: an integer in [64, 8192]"),
    (["-p", "sync.slop:=fast"], "sync.slop = 'fast' has the wrong type (string): a float in "
                                "[0.0, 60.0]"),
    (["-p", "engine.refine:=gicp", "-p", "input.reliable:=1"],
     "engine.refine = 'gicp' is not one of none, icp; input.reliable = 1 has the wrong type "
     "(integer): a bool"),
])
def test_bad_start_up_values_raise_one_error_naming_each(args, reason):
    with pytest.raises(ParameterError) as info:
        _Running(args, namespace="/bad")
    assert str(info.value) == reason


def test_every_float_parameter_takes_an_integer():
    from cegc_ros.node import check_value
    from cegc_ros.node.params import coerce

    floats = [s for s in param_specs() if s.kind is float]
    assert len(floats) >= 8
    for s in floats:
        lo = 0 if s.range[0] is None else s.range[0]
        value = int(lo) if float(int(lo)) == lo and (s.range[1] is None or int(lo) <= s.range[1]) \
            else None
        if value is None:
            continue
        assert check_value(s, value) is None, s.name
        assert type(coerce(s, value)) is float


def test_the_loop_closure_overlay_loads_after_the_defaults():
    """`--params-file params/register_node.yaml --params-file params/loop_closure.yaml` (as
    docs/node.md shows): the later file's engine.redraw_ambiguity wins, everything else is the
    defaults' file, and nothing is unknown."""
    from pathlib import Path
    params = Path(__file__).resolve().parents[1] / "params"
    run = _Running(["--params-file", str(params / "register_node.yaml"),
                    "--params-file", str(params / "loop_closure.yaml")], namespace="/lc")
    try:
        node = run.node
        assert node.get_parameter("engine.redraw_ambiguity").value == 0.5
        assert node.cfg["engine"].redraw_ambiguity == 0.5
        assert node.get_parameter("engine.sure_ambiguity").value == 0.3
        assert node.unknown_parameters == []
    finally:
        run.close()
