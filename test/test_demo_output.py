"""What cegc-demo prints: a plain-text table with units and a fitness for every method."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from cegc_ros.tools import demo
from cegc_ros.tools.evaluate import Outcome


def _summary(**kw) -> dict:
    base = {"rmse_r": 0.17, "rmse_t": 0.0006, "mae_r": 0.109, "mae_t": 0.0005, "error_r": 0.21,
            "error_t": 0.0009, "recall": 1.0, "median_latency_ms": 441.2, "mean_fitness": 0.71,
            "n_pairs": 10, "n_invalid": 0, "n_exception": 0}
    base.update(kw)
    return base


def test_table_is_plain_text_with_units_and_aligned_columns():
    table = demo.format_table({
        "cegc+icp": _summary(),
        "icp": _summary(error_r=58.59, recall=0.4, mean_fitness=math.nan, n_invalid=4,
                        median_latency_ms=12.0),
        "ransac": _summary(mean_fitness=None, n_exception=1),
    })
    lines = table.splitlines()
    assert len(lines) == 5
    assert "**" not in table and "|" not in table and "---" not in table
    assert lines[0].split() == ["method", "Error(R)", "Error(t)", "RMSE(R)", "RMSE(t)", "MAE(R)",
                                "MAE(t)", "recall", "fitness", "time", "failures"]
    assert lines[1].split() == ["deg", "scene", "deg", "scene", "deg", "scene", "ms/pair"]
    rows = {ln.split()[0]: ln.split() for ln in lines[2:]}
    assert rows["cegc+icp"] == ["cegc+icp", "0.210", "0.0009", "0.170", "0.0006", "0.109",
                                "0.0005", "1.00", "0.710", "441", "0/10"]
    assert rows["icp"][1] == "58.590" and rows["icp"][8] == "-" and rows["icp"][-1] == "4/10"
    assert rows["ransac"][8] == "-" and rows["ransac"][-1] == "1/10"
    # right-aligned: every value of a column ends where its header does
    for header in ("Error(R)", "fitness", "failures"):
        end = lines[0].index(header) + len(header)
        for ln in lines[2:]:
            assert ln[end - 1] != " " and (end == len(ln) or ln[end] == " ")


def test_notes_name_the_units_and_the_fitness_definition():
    notes = "\n".join(demo.table_notes("Error(R) < 5 deg", through_node=True))
    assert "scene" in notes and "Error(R) < 5 deg" in notes and "1.5 voxels" in notes
    assert "node rows: cloud published -> pose received" in notes
    assert max(len(ln) for ln in notes.splitlines()) <= 100


def _pair():
    rng = np.random.default_rng(0)
    target = rng.uniform(-1, 1, (800, 3))
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T[:3, 3] = [0.3, -0.2, 0.1]
    source = (target - T[:3, 3]) @ T[:3, :3]          # T maps source onto target exactly

    class P:
        pass

    p = P()
    p.source, p.target, p.T = source, target, T
    return p


def test_node_outcomes_get_the_baselines_fitness_of_their_pose():
    p = _pair()
    nan = math.nan
    outs = [Outcome("cegc+icp", "0", p.T, True, False, "", nan, 0.4),
            Outcome("cegc+icp", "1", np.eye(4), True, False, "", nan, 0.4),
            Outcome("cegc+icp", "2", None, False, True, "no pose", nan, nan),
            Outcome("cegc+icp", "3", p.T, True, False, "", 0.25, 0.4)]
    filled = demo.with_fitness([p, p, p, p], outs)
    assert filled[0].fitness == pytest.approx(1.0)
    assert filled[1].fitness < 0.2                   # a wrong pose fits badly
    assert math.isnan(filled[2].fitness)             # no pose: nothing to measure
    assert filled[3].fitness == 0.25                 # a fitness already there is kept


def test_demo_prints_the_table_and_where_the_report_is(tmp_path, capsys):
    """A tiny generated bag, baselines only (no node): the whole terminal output."""
    assert demo.main(["--pairs", "2", "--methods", "icp,fgr", "--cache", str(tmp_path),
                      "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "**" not in out and "|" not in out
    lines = out.strip().splitlines()
    head = next(i for i, ln in enumerate(lines) if ln.startswith("method "))
    assert lines[head + 1].split()[:2] == ["deg", "scene"]
    for row in lines[head + 2:head + 4]:
        cells = row.split()
        assert cells[0] in ("icp", "fgr") and cells[-1].endswith("/2")
        assert re.fullmatch(r"\d\.\d{3}", cells[8])  # fitness
    assert f"full report: {tmp_path / 'report' / 'report.md'}" in out
    assert (tmp_path / "report" / "metrics.json").is_file()
