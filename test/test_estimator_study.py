"""tools/estimator_study and Registrar.match_pair / finish: register() split in two, each half
the same code, so that the later stages can be studied under other settings."""

from __future__ import annotations

import dataclasses
import inspect
import re

import numpy as np
import pytest

from cegc_ros.data import pair_cache as PC
from cegc_ros.tools import estimator_study, select_weights


@pytest.fixture(scope="module")
def registrar():
    from cegc_ros.engine import Registrar
    return Registrar.from_checkpoint(device="cpu")


def test_finish_of_match_pair_is_register(val_cache, registrar):
    """The same pose, inliers, fitness and ambiguity as register(), also when the registrar's
    sampling seed changed in between (ICP draws its points with the seed the pair was matched
    at; 500 ICP points so that it draws), and a Matched finished twice gives the same result
    (finish does not change it). The pose to 1e-9: register() itself differs by ~1e-15 from
    call to call (ICP's threaded sums)."""
    pair = PC.PairCache(val_cache, kinds=("views",), sensors=("kinect",))[0]
    pre, eng = registrar.preprocess, registrar.engine
    try:
        registrar.update(preprocess=dataclasses.replace(pre, seed=3),
                         engine=dataclasses.replace(eng, icp_points=500))
        whole = registrar.register(pair.source, pair.target)
        matched = registrar.match_pair(pair.source, pair.target)
        registrar.update(preprocess=dataclasses.replace(pre, seed=4))
        other = registrar.register(pair.source, pair.target)
        assert np.abs(other.T_target_source - whole.T_target_source).max() > 1e-9   # the seed matters
        for _ in range(2):
            split = registrar.finish(matched)
            np.testing.assert_allclose(split.T_target_source, whole.T_target_source, rtol=0, atol=1e-9)
            np.testing.assert_array_equal(split.inliers, whole.inliers)
            assert (split.fitness, split.ambiguity, split.valid) == (whole.fitness, whole.ambiguity, whole.valid)
            assert set(split.timings) == set(whole.timings)
    finally:
        registrar.update(preprocess=pre, engine=eng)


def test_finish_settings_are_the_ones_finish_reads():
    """Registrar.FINISH_SETTINGS lists exactly the engine settings _finish reads (itself and
    _finish_draw, each draw's estimate, refine and verify): the study tool refuses the others,
    which would silently change nothing there."""
    from cegc_ros.config import EngineConfig
    from cegc_ros.engine import Registrar
    source = inspect.getsource(Registrar._finish) + inspect.getsource(Registrar._finish_draw)
    read = set(re.findall(r"\beng\.(\w+)", source))
    assert read == set(Registrar.FINISH_SETTINGS)
    assert read <= {f.name for f in dataclasses.fields(EngineConfig)}


def test_defaults_reproduce_select_weights_and_variants_change_the_verdicts(val_cache, capsys):
    from cegc_ros.engine import default_weights
    w = str(default_weights())
    assert select_weights.main([str(val_cache), w, "--seeds", "0,1"]) == 0
    reference = capsys.readouterr().out.strip().splitlines()[0]
    recall = reference.split("recall ")[1].split()[0]
    # the pairs' own registrations fail with ICP off and a 1 mm inlier distance: the variant is read
    assert estimator_study.main([str(val_cache), "--seeds", "0,1", "--variant",
                                 "engine.inlier_factor=0.001,engine.refine=none"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith(f"defaults: recall {recall} on 2 pairs x 2 seeds")
    assert lines[1].startswith("engine.inlier_factor=0.001,engine.refine=none: recall 0.000")
    assert float(recall) > 0.0 and ", 0 won / " in lines[1]


def test_only_settings_of_the_later_stages_vary(val_cache, capsys):
    assert estimator_study.main([str(val_cache), "--variant", "engine.max_correspondences=100"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("estimator_study: --variant 'engine.max_correspondences=100'") and len(err.splitlines()) == 1
    assert estimator_study.main([str(val_cache), "--variant", "preprocess.seed=3"]) == 1
    assert "--variant 'preprocess.seed=3'" in capsys.readouterr().err


def test_a_checkpoint_without_its_onnx_export_is_named_on_stderr(val_cache, tmp_path, capsys):
    """As in select_weights: weights copied without their export run under torch and one stderr
    line, naming this tool, says so and how to export; the stdout lines are unchanged."""
    import shutil
    from cegc_ros.engine import default_weights
    copy = tmp_path / "candidate.pt"
    shutil.copy(default_weights(), copy)
    assert estimator_study.main([str(val_cache), str(copy), "--pairs", "1"]) == 0
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"estimator_study: {copy}: the network runs under torch")
    assert err[0].endswith(f"python -m cegc_ros.tools.export_onnx {copy}") and "no ONNX export" in err[0]
    assert captured.out.startswith("defaults: recall ") and len(captured.out.splitlines()) == 1
