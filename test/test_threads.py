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
