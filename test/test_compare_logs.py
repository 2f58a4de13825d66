"""compare_logs: two training logs compared on the steps both hold."""

from __future__ import annotations

import csv
import math

import pytest

from cegc_ros.tools import compare_logs


def write_log(path, rows, fields=("step", "match_acc", "l_desc")):
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(fields))
        w.writeheader()
        w.writerows(rows)
    return path


def test_paired_differences_use_only_the_common_steps_and_carry_a_standard_error(tmp_path):
    # B's per-pair figures swing widely from step to step; A is B + 0.01 plus a small wobble,
    # and A logged steps B did not (ignored)
    b_acc = [0.05, 0.6, 0.2, 0.4, 0.1, 0.5]
    wobble = [0.002, -0.002, 0.002, -0.002, 0.002, -0.002]
    a = write_log(tmp_path / "a.csv", [{"step": 20 * (i + 1), "match_acc": x + 0.01 + w, "l_desc": 3.0}
                                       for i, (x, w) in enumerate(zip(b_acc, wobble))]
                  + [{"step": 999, "match_acc": 9.0, "l_desc": 9.0}])
    b = write_log(tmp_path / "b.csv", [{"step": 20 * (i + 1), "match_acc": x, "l_desc": 3.5}
                                       for i, x in enumerate(b_acc)])
    acc, desc = compare_logs.paired(compare_logs.read_log(a), compare_logs.read_log(b), ("match_acc", "l_desc"))
    assert acc.steps == 6 and acc.diff == pytest.approx(0.01)
    # sample std of the wobble 0.002 * sqrt(6 / 5), over sqrt(6)
    assert acc.se == pytest.approx(0.002 * math.sqrt(6 / 5) / math.sqrt(6))
    assert acc.mean_b == pytest.approx(sum(b_acc) / 6)
    assert desc.diff == pytest.approx(-0.5) and desc.se == pytest.approx(0.0)
    # a step range keeps [lo, hi)
    (part,) = compare_logs.paired(compare_logs.read_log(a), compare_logs.read_log(b), ("match_acc",), 40, 80)
    assert part.steps == 2 and part.mean_b == pytest.approx((0.6 + 0.2) / 2)


def test_logs_that_cannot_be_compared_fail_with_one_line(tmp_path, capsys):
    a = write_log(tmp_path / "a.csv", [{"step": 1, "match_acc": 0.1, "l_desc": 3.0}])
    b = write_log(tmp_path / "b.csv", [{"step": 2, "match_acc": 0.1, "l_desc": 3.0}])
    assert compare_logs.main([str(a), str(b)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("compare_logs: no step in [0, end)") and "\n" not in err
    assert compare_logs.main([str(a), str(tmp_path / "missing.csv")]) == 1
    assert "cannot read" in capsys.readouterr().err
    assert compare_logs.main([str(a), str(a), "--columns", "nope"]) == 1
    assert "'nope'" in capsys.readouterr().err
    assert compare_logs.main([str(a), str(a), "--columns", "match_acc,l_desc"]) == 0
    out = capsys.readouterr().out
    assert "match_acc" in out and "+0.0000" in out
