"""The engine process of register_node: data through shared memory, errors, crashes, restarts.

Uses the stand-in engines of fake_engines.py (no torch), started the way the node starts the
real one (spawn). No wall-clock budgets: waits are generous and only bound a hang.
"""

from __future__ import annotations

import os
import signal
import threading

import numpy as np
import pytest

from cegc_ros.config import EngineConfig, PreprocessConfig
from cegc_ros.node.engine_process import (
    EngineDied,
    EngineError,
    EngineProcess,
    EngineStartError,
)


def _cloud(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-5, 5, (n, 3)).astype(np.float32)


@pytest.fixture
def echo():
    eng = EngineProcess(PreprocessConfig(), EngineConfig(), factory="fake_engines:echo")
    eng.start()
    yield eng
    eng.close()


def test_clouds_reach_the_engine_intact_and_the_buffer_grows(echo):
    assert echo.info.pid not in (None, os.getpid()) and echo.info.device == "fake"
    for n_src, n_tgt in [(100, 120), (200_000, 150_000), (40, 30)]:   # grow, then reuse
        src, tgt = _cloud(n_src, 1), _cloud(n_tgt, 2)
        res = echo.register(src, tgt)
        assert res.pid == echo.info.pid
        assert res.checksum == pytest.approx(float(src.astype(np.float64).sum()
                                                   + tgt.astype(np.float64).sum()), rel=1e-12)
        np.testing.assert_array_equal(res.source_points, src[:32])
        np.testing.assert_array_equal(res.target_points, tgt[:32])
    assert echo._capacity >= 350_000


def test_settings_travel_with_the_next_pair(echo):
    res = echo.register(_cloud(64, 0), _cloud(64, 1))
    assert res.timings["updates"] == 0 and res.timings["num_points"] == PreprocessConfig().num_points
    res = echo.register(_cloud(64, 0), _cloud(64, 1),
                        update=(PreprocessConfig(num_points=128), EngineConfig()))
    assert res.timings["updates"] == 1 and res.timings["num_points"] == 128


def test_engine_errors_come_back_typed_and_the_engine_keeps_going(echo):
    with pytest.raises(ValueError, match="50 points are refused"):
        echo.register(_cloud(50, 0), _cloud(64, 1))
    with pytest.raises(EngineError, match="RuntimeError: engine failure") as info:
        echo.register(_cloud(51, 0), _cloud(64, 1))
    assert info.value.kind == "RuntimeError" and not isinstance(info.value, EngineDied)
    assert echo.alive()
    assert echo.register(_cloud(64, 0), _cloud(64, 1)).valid


def test_a_crashed_engine_is_reported_and_restarted(echo):
    pid = echo.info.pid
    with pytest.raises(EngineDied, match="ended while registering"):
        echo.register(_cloud(77, 0), _cloud(64, 1))     # the stand-in SIGKILLs itself
    assert not echo.alive()
    with pytest.raises(EngineDied, match="not running"):
        echo.register(_cloud(64, 0), _cloud(64, 1))
    echo.restart()
    assert echo.restarts == 1 and echo.info.pid != pid
    res = echo.register(_cloud(300, 0), _cloud(200, 1))   # a fresh buffer in the new process
    assert res.pid == echo.info.pid and res.checksum == pytest.approx(
        float(_cloud(300, 0).astype(np.float64).sum() + _cloud(200, 1).astype(np.float64).sum()))


def test_sigint_does_not_stop_the_engine(echo):
    # Ctrl-C in a terminal signals the whole process group; the node decides when to stop.
    os.kill(echo.info.pid, signal.SIGINT)
    assert echo.register(_cloud(64, 0), _cloud(64, 1)).valid and echo.alive()


def test_start_failure_names_the_cause():
    eng = EngineProcess(PreprocessConfig(), EngineConfig(checkpoint="/nowhere/x.pt"),
                        factory="fake_engines:broken")
    with pytest.raises(EngineStartError) as info:
        eng.start()
    assert str(info.value) == ("FileNotFoundError: checkpoint /nowhere/x.pt: file not found "
                               "(test)")
    assert not eng.alive()


def test_close_ends_a_registration_in_progress():
    eng = EngineProcess(PreprocessConfig(), EngineConfig(checkpoint=str(10**11)),  # hours
                        factory="fake_engines:gil_hog")
    eng.start()
    outcome: list[BaseException] = []

    def work() -> None:
        try:
            eng.register(_cloud(64, 0), _cloud(64, 1))
        except BaseException as err:  # noqa: BLE001
            outcome.append(err)

    t = threading.Thread(target=work)
    t.start()
    t.join(0.5)
    assert t.is_alive()                   # still summing
    pid = eng.info.pid
    eng.close(timeout=0.5)
    t.join(30.0)
    assert not t.is_alive() and isinstance(outcome[0], EngineDied)
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_thread_environment_defaults_and_the_users_choice_wins(monkeypatch):
    from cegc_ros.node.engine_process import THREAD_ENV

    assert THREAD_ENV == {"OMP_WAIT_POLICY": "PASSIVE"}    # docs/node.md, CPU contention
    for user, expected in ((None, "PASSIVE"), ("ACTIVE", "ACTIVE")):
        if user is None:
            monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
        else:
            monkeypatch.setenv("OMP_WAIT_POLICY", user)
        eng = EngineProcess(PreprocessConfig(), EngineConfig(), factory="fake_engines:echo")
        eng.start()
        try:
            assert eng.register(_cloud(64, 0), _cloud(64, 1)).omp_wait_policy == expected
        finally:
            eng.close()


def test_the_engine_process_does_not_import_a_copy_in_the_working_directory(tmp_path, monkeypatch):
    """A node started from a source checkout runs the cegc_ros it imported; ``python -m`` in the
    child would have put the cwd first and imported the checkout's copy instead."""
    import cegc_ros
    decoy = tmp_path / "cegc_ros"
    decoy.mkdir()
    (decoy / "__init__.py").write_text("raise ImportError('the copy in the working directory')\n")
    monkeypatch.chdir(tmp_path)
    eng = EngineProcess(PreprocessConfig(), EngineConfig(), factory="fake_engines:echo")
    try:
        eng.start()
        assert eng.register(_cloud(64, 0), _cloud(64, 1)).pid == eng.info.pid
    finally:
        eng.close()
    assert cegc_ros.__file__ != str(decoy / "__init__.py")
