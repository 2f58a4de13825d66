"""Plumbing of tools/bench_node.py (a benchmark script): options, the node's command line, the
sequence it publishes and the figures of a responsiveness row. No timing is asserted."""

from __future__ import annotations

import subprocess
import sys
import threading

import numpy as np
import pytest
import yaml

from cegc_ros.node.params import build_sections, check_values
from cegc_ros.tools import bench_node


def _node_params(cmd: list[str]) -> dict:
    """The ``-p name:=value`` overrides of a node command line, as the node's sections."""
    ros = cmd[cmd.index("--ros-args") + 1:]
    values = {}
    for flag, arg in zip(ros, ros[1:]):
        if flag == "-p":
            name, value = arg.split(":=", 1)
            values[name] = yaml.safe_load(value)
    return build_sections(check_values(values))


def test_sequential_mode_reaches_the_node_parameters():
    args = bench_node.parse_args(["--responsiveness", "1000", "--responsiveness-mode",
                                  "sequential", "--sequence-frames", "4",
                                  "--sequence-rate", "5"])
    assert (args.responsiveness_mode, args.sequence_frames, args.sequence_rate) == \
        ("sequential", 4, 5.0)
    cmd = bench_node.node_command(args, "process", "/resp_sequential",
                                  ("-p", "diagnostics.period:=0.5"), sequential=True)
    assert cmd[cmd.index("--serve") + 1] == "process"
    sections = _node_params(cmd)
    assert sections["input"].mode == "sequential"
    assert sections["input"].reliable is True
    assert sections["diagnostics"].period == 0.5


def test_pairs_mode_is_the_default_and_leaves_the_node_in_pairs_mode():
    args = bench_node.parse_args(["--responsiveness", "1000"])
    assert args.responsiveness_mode == "pairs"
    sections = _node_params(bench_node.node_command(args, "inline", "/resp_inline"))
    assert sections["input"].mode == "pairs"


def test_unknown_responsiveness_mode_is_one_usage_line():
    out = subprocess.run([sys.executable, "-m", "cegc_ros.tools.bench_node",
                          "--responsiveness-mode", "slam"], capture_output=True, text=True,
                         timeout=120, check=False)
    assert out.returncode == 2
    assert out.stdout == ""
    assert out.stderr.strip().splitlines() == [
        "bench_node: error: argument --responsiveness-mode: invalid choice: 'slam' "
        "(choose from 'pairs', 'sequential') (see --help)"]


def test_sequence_is_a_moving_room_camera_densified_to_the_size():
    from cegc_ros.data.sequences import make_room_sequence

    clouds = bench_node.sequence_clouds(200_000, 3, rate=2.0, first=1)
    assert [c.shape for c in clouds] == [(200_000, 3)] * 3
    assert all(c.dtype == np.float32 for c in clouds)
    # clouds 1..3 of the room sequence one 0.5 s (15 trajectory frames) apart, every point kept
    seq = make_room_sequence(0, 4, frame_step=15, pixel_stride=2)
    for c, raw in zip(clouds, seq.clouds[1:], strict=True):
        assert len(raw) < 200_000
        np.testing.assert_array_equal(c[:len(raw)], raw)
    moved = np.linalg.norm(seq.poses[2][:3, 3] - seq.poses[1][:3, 3])
    assert 0.05 < moved < 1.0                  # a robot's half second, not a jump
    np.testing.assert_array_equal(bench_node.sequence_clouds(200_000, 3, 2.0, first=1)[2],
                                  clouds[2])  # deterministic


class _FakeClient:
    """What _watch reads from the bench's client: a condition, /diagnostics arrival times and
    describe_parameters answers (given, not measured)."""

    def __init__(self, answers: list[float | None], diag_times: list[float]) -> None:
        self.cond = threading.Condition()
        self.diag_times = diag_times
        self._answers = list(answers)
        self.calls = 0

    def describe_s(self, timeout: float = 60.0) -> float | None:
        self.calls += 1
        return self._answers.pop(0)


def test_watch_row_counts_answers_and_the_largest_diagnostics_gap(monkeypatch):
    monkeypatch.setattr(bench_node.time, "sleep", lambda s: None)
    t0 = 100.0
    c = _FakeClient([0.002, 0.004, None, 0.9], [99.0, 100.5, 101.0, 102.7, 103.2, 105.0])
    row = bench_node._watch(c, t0, lambda: 103.5 if c.calls == 4 else None, timeout=1e9)
    assert row["done_after_s"] == 3.5
    assert (row["describe_calls"], row["describe_unanswered"]) == (4, 1)
    assert row["describe_max_ms"] == 900.0
    assert row["describe_p50_ms"] == 4.0
    assert row["diagnostics_received"] == 4                    # 100.5 .. 103.2
    assert row["diagnostics_max_gap_s"] == pytest.approx(1.7)  # 101.0 -> 102.7
