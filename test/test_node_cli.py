"""One-line errors of register_node and cegc-replay, as a user sees them (subprocesses).

None of these start an engine: each fails (as it should) before that, in a second or two.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import ros_helpers as rh

pytest.importorskip("rclpy")


def _run(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], env=rh.ros_env(), cwd=rh.REPO,
                          capture_output=True, text=True, timeout=timeout, check=False)


def _lines(out: subprocess.CompletedProcess) -> list[str]:
    return [ln for ln in (out.stdout + out.stderr).splitlines() if ln.strip()]


FATAL = "[FATAL] [register_node]: cannot start: "


@pytest.mark.parametrize("args, expected", [
    (["-p", "preprocess.num_points:=10"],
     "invalid parameter: preprocess.num_points = 10 is out of range: an integer in [64, 8192]"),
    (["-p", "sync.slop:=-1"],
     "invalid parameter: sync.slop = -1.0 is out of range: a float in [0.0, 60.0]"),
    (["-p", "input.reliable:=yes please"],
     "invalid parameter: input.reliable = 'yes please' has the wrong type (string): a bool"),
    (["--params-file", "/nonexistent/params.yaml"],
     "params file /nonexistent/params.yaml: No such file or directory"),
])
def test_start_up_errors_are_one_fatal_line(args, expected):
    out = _run("-m", "cegc_ros.node", "--ros-args", *args)
    assert out.returncode == 1
    assert _lines(out) == [FATAL + expected]


def test_a_bad_value_in_a_params_file_is_one_fatal_line(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("/**:\n  ros__parameters:\n    markers.max_correspondences: -5\n"
                    "    engine.refine: gicp\n")
    out = _run("-m", "cegc_ros.node", "--ros-args", "--params-file", str(path))
    assert out.returncode == 1
    assert _lines(out) == [FATAL + "invalid parameter: engine.refine = 'gicp' is not one of "
                           "none, icp; markers.max_correspondences = -5 is out of range: an "
                           "integer in [0, 100000]"]


def test_unknown_node_argument_is_a_usage_error():
    out = _run("-m", "cegc_ros.node", "--verbose")
    assert out.returncode == 2
    assert _lines(out) == ["register_node: error: unknown argument '--verbose' (ROS arguments "
                           "go after --ros-args; see --help)"]


@pytest.mark.parametrize("args", [["--help"], ["--ros-args", "--help"], ["--ros-args", "-p", "sync.slop:=0.1", "-h"]])
def test_help_is_usage_wherever_it_is_asked_for(args):
    """``--ros-args --help`` used to end in rclpy's UnknownROSArgsError; it is usage too."""
    out = _run("-m", "cegc_ros.node", *args)
    assert out.returncode == 0 and out.stderr == ""
    assert out.stdout.startswith("usage: register_node") and "preprocess.min_range" in out.stdout


def test_replay_without_a_node_is_one_line_every_time(tmp_path):
    from cegc_ros.data.bag import write_pairs
    from cegc_ros.data.protocols import make_pairs

    bag = tmp_path / "pairs"
    write_pairs(bag, make_pairs("7scenes", "test", 2))
    # The abort ("terminate called without an active exception", rc 134) came from a spin
    # thread left inside rcl at exit; it did not happen on every run.
    for _ in range(3):
        out = _run("-m", "cegc_ros.tools.replay", str(bag), "--connect-timeout", "1",
                   "--node-namespace", "/nobody_here")
        assert out.returncode == 1, out.stderr
        assert out.stdout == ""
        assert _lines(out) == ["cegc-replay: no register_node answered within 1.0 s "
                               "(publishing /nobody_here/source_cloud, "
                               "/nobody_here/target_cloud; listening "
                               "/nobody_here/register_node/pose)"]


@pytest.mark.parametrize("args, code, expected", [
    (["/nonexistent/bag"], 1, "cegc-replay: bag /nonexistent/bag does not exist"),
    ([], 2, "cegc-replay: error: the following arguments are required: bag (see --help)"),
    (["bag", "--rate", "0"], 2, "cegc-replay: error: argument --rate: '0' must be > 0 "
                                "(see --help)"),
])
def test_replay_errors_are_one_line(args, code, expected):
    out = _run("-m", "cegc_ros.tools.replay", *args)
    assert out.returncode == code
    assert _lines(out) == [expected]


@pytest.mark.parametrize("module, args, expected", [
    ("cegc_ros.tools.bench_contention", ["--settings", "turbo"],
     "bench_contention: error: unknown setting 'turbo'; known: default, omp1, passive, "
     "omp1_o3d1, passive_o3d1, api, api1, ransac (see --help)"),
    ("cegc_ros.tools.bench_node", ["--pairs", "many"],
     "bench_node: error: argument --pairs: invalid int value: 'many' (see --help)"),
])
def test_benchmark_usage_errors_are_one_line(module, args, expected):
    out = _run("-m", module, *args)
    assert out.returncode == 2
    assert _lines(out) == [expected]
