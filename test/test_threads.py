"""The engine's own threading: ``import cegc_ros.engine`` sets OpenMP's wait policy before
torch loads, so a user's script gets what the console scripts get; a user's setting wins.

Each case runs in a fresh interpreter without the bootstrap's OMP_* variables. The effect is
checked by what OpenMP threads do after a parallel region: with PASSIVE they sleep, so the
process uses no CPU while the main thread sleeps; with ACTIVE they spin (the control).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

PROBE = r"""
import json, os, resource, sys, time, warnings
first = sys.argv[1]
if first == "torch":
    import torch
import cegc_ros.engine as engine
import torch
torch.set_num_threads(2)
x = torch.randn(2000, 2000)
for _ in range(3):
    (x @ x).relu_()
time.sleep(0.05)
t0 = resource.getrusage(resource.RUSAGE_SELF)
time.sleep(0.5)
t1 = resource.getrusage(resource.RUSAGE_SELF)
idle_cpu = (t1.ru_utime + t1.ru_stime) - (t0.ru_utime + t0.ru_stime)
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    engine.Registrar.from_checkpoint(device="cpu")
print(json.dumps({"policy": os.environ.get("OMP_WAIT_POLICY"), "idle_cpu": idle_cpu,
                  "warnings": [str(w.message) for w in caught]}))
"""


def _probe(first: str, **env_extra: str) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMP_", "GOMP_", "KMP_"))}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", PROBE, first], env=env, capture_output=True,
                         text=True, timeout=300, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_the_python_api_gets_sleeping_openmp_threads():
    r = _probe("engine")
    assert r["policy"] == "PASSIVE" and r["warnings"] == []
    assert r["idle_cpu"] < 0.1          # no thread spun while the main thread slept 0.5 s


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: no second OpenMP thread to spin")
def test_a_users_own_wait_policy_wins_and_spins():
    r = _probe("engine", OMP_WAIT_POLICY="ACTIVE")
    assert r["policy"] == "ACTIVE" and r["warnings"] == []
    assert r["idle_cpu"] > 0.1          # the control: the probe sees spinning when it happens


def test_torch_imported_first_is_told_what_it_costs():
    r = _probe("torch")
    assert len(r["warnings"]) == 1
    assert "OMP_WAIT_POLICY could not take effect" in r["warnings"][0]


@pytest.mark.parametrize("runtime", ["onnxruntime", "torch"])
def test_the_network_runs_with_subnormals_flushed_and_the_callers_thread_keeps_its_own(runtime, monkeypatch):
    """Subnormals are flushed while the network runs (Intel cores pay a slow path for each one
    attention's softmax makes) and nowhere else; the caller's thread gets its own setting back,
    ONNX Runtime's session creation included; the pose is the one computed without the flush."""
    import numpy as np
    import torch

    from cegc_ros import denormals, matching
    from cegc_ros.config import EngineConfig
    from cegc_ros.engine import Registrar

    if not torch.set_flush_denormal(False):
        pytest.skip("no FTZ/DAZ control on this CPU (not x86)")
    assert not denormals.denormals_flushed()
    assert float(np.float32(1e-40) * np.float32(1.0)) > 0.0      # the probe's premise
    with denormals.flush_denormals():
        assert denormals.denormals_flushed()
        assert float(np.float32(1e-40) * np.float32(1.0)) == 0.0
        with denormals.flush_denormals(on=False):                  # only restores
            assert denormals.denormals_flushed()
        assert denormals.denormals_flushed()
    assert not denormals.denormals_flushed()

    reg = Registrar.from_checkpoint(device="cpu", engine=EngineConfig(runtime=runtime), warm=False)
    assert not denormals.denormals_flushed()                      # session creation undone
    if runtime == "onnxruntime":                                  # and its pool flushes too
        opts = reg._onnx.session.get_session_options()
        assert opts.get_session_config_entry("session.set_denormal_as_zero") == "1"
    seen = []
    real_neighbours = matching.fpfh_neighbours

    def outside(*args, **kwargs):                                 # runs just before the network
        seen.append(("outside", denormals.denormals_flushed()))
        return real_neighbours(*args, **kwargs)

    monkeypatch.setattr(matching, "fpfh_neighbours", outside)
    owner, name = (reg._onnx.session, "run") if runtime == "onnxruntime" else (reg.model, "score_candidates")
    real_network = getattr(owner, name)

    def inside(*args, **kwargs):
        seen.append(("network", denormals.denormals_flushed()))
        return real_network(*args, **kwargs)

    monkeypatch.setattr(owner, name, inside)
    rng = np.random.default_rng(3)
    k = 2000
    src = np.concatenate([np.c_[rng.uniform(0, 3, (k, 2)), np.zeros(k)],
                          np.c_[np.zeros(k), rng.uniform(0, 3, k), rng.uniform(0, 2.5, k)],
                          np.c_[rng.uniform(0, 3, k), np.zeros(k), rng.uniform(0, 2.5, k)]])
    c, s = np.cos(0.3), np.sin(0.3)
    tgt = src @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]).T + [0.2, -0.1, 0.05]
    flushed = reg.register(src, tgt)
    assert flushed.runtime == runtime
    assert seen == [("outside", False), ("network", True)] and not denormals.denormals_flushed()
    monkeypatch.setattr(torch, "set_flush_denormal", lambda on: False)   # a CPU without the control
    plain = reg.register(src, tgt)
    assert seen[2:] == [("outside", False), ("network", False)]
    np.testing.assert_allclose(flushed.T_target_source, plain.T_target_source, atol=1e-9)
    angle = np.degrees(np.arccos((np.trace(flushed.T_target_source[:3, :3]) - 1) / 2))
    assert abs(angle - np.degrees(0.3)) < 0.5
