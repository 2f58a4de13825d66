"""Stand-in engines that run inside the node's engine process (spawned: module-level factories).

Each factory takes (PreprocessConfig, EngineConfig) like ``load_registrar``. They need no torch
and start in a fraction of a second. ``engine.checkpoint`` is unused by them, so tests use it to
pass a small instruction (see each factory).
"""

from __future__ import annotations

import os
import signal
import time
from dataclasses import dataclass, field

import numpy as np

T_KNOWN = np.array([[0.0, -1.0, 0.0, 0.5], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, 1.0, 0.1],
                    [0.0, 0.0, 0.0, 1.0]])


@dataclass
class Result:
    T_target_source: np.ndarray
    source_points: np.ndarray
    target_points: np.ndarray
    source_overlap: np.ndarray
    target_overlap: np.ndarray
    correspondences: np.ndarray
    weights: np.ndarray
    covariance: np.ndarray
    fitness: float
    valid: bool
    reason: str = ""
    refined: str = "none"
    ambiguity: float = 0.0
    draws: int = 1
    timings: dict = field(default_factory=dict)
    checksum: float = 0.0         # sum of every coordinate received (data integrity checks)
    pid: int = 0                  # the process that registered
    omp_wait_policy: str = ""     # OMP_WAIT_POLICY in that process's environment


class EchoRegistrar:
    """Answers T_KNOWN with the first 32 points of each cloud; reports what it received.

    Raises ValueError for a source of exactly 50 points (an input the engine refuses),
    RuntimeError for 51 (an engine failure); dies with SIGKILL for 77 (a native crash).
    """

    MIN_POINTS = 16
    device = "fake"

    def __init__(self, preprocess, engine) -> None:
        self.preprocess, self.engine = preprocess, engine
        self.checkpoint_path = engine.checkpoint or "/fake/echo.pt"
        self.updates = 0

    def update(self, preprocess=None, engine=None) -> None:
        self.preprocess = preprocess or self.preprocess
        self.engine = engine or self.engine
        self.updates += 1

    def warm_up(self) -> float:
        return 0.0

    def register(self, src: np.ndarray, tgt: np.ndarray) -> Result:
        if len(src) == 50:
            raise ValueError("50 points are refused (test)")
        if len(src) == 51:
            raise RuntimeError("engine failure (test)")
        if len(src) == 77:
            os.kill(os.getpid(), signal.SIGKILL)
        s, t = np.array(src[:32]), np.array(tgt[:32])
        m = min(len(s), len(t))
        corr = np.stack([np.arange(m), np.arange(m)], 1).astype(np.int64)
        return Result(T_KNOWN, s, t, np.ones(len(s), np.float32), np.ones(len(t), np.float32),
                      corr, np.ones(m, np.float32), np.eye(6) * 1e-4, 1.0, True,
                      timings={"updates": float(self.updates),
                               "num_points": float(self.preprocess.num_points),
                               "source_points_in": float(len(src)),
                               "target_points_in": float(len(tgt))},
                      checksum=float(np.float64(src).sum() + np.float64(tgt).sum()),
                      pid=os.getpid(),
                      omp_wait_policy=os.environ.get("OMP_WAIT_POLICY", "<unset>"))


def echo(preprocess, engine) -> EchoRegistrar:
    return EchoRegistrar(preprocess, engine)


def broken(preprocess, engine):
    """Fails at start-up like a bad checkpoint does."""
    raise FileNotFoundError(f"checkpoint {engine.checkpoint}: file not found (test)")


class GilHogRegistrar(EchoRegistrar):
    """Holds its process's GIL in one C call per pair (like a long Open3D call), then echoes.

    ``engine.checkpoint`` = the number of integers summed by that call (``sum(range(n))``;
    about 0.1 s per 10 million on this machine when idle). The warm-up pair (the first) is
    not slowed.
    """

    calls = 0

    def register(self, src: np.ndarray, tgt: np.ndarray) -> Result:
        self.calls += 1
        n = int(self.engine.checkpoint or 50_000_000) if self.calls > 1 else 0
        t0 = time.perf_counter()
        sum(range(n))                      # one C-level loop: the GIL is never released
        res = super().register(src, tgt)
        res.timings["hog_s"] = time.perf_counter() - t0
        return res


def gil_hog(preprocess, engine) -> GilHogRegistrar:
    return GilHogRegistrar(preprocess, engine)


class BadCovarianceRegistrar(EchoRegistrar):
    """Echoes T_KNOWN with a symmetric covariance that has negative variances (what an inverse
    of a near-singular information matrix once gave): the pose is sound, its uncertainty not."""

    def register(self, src: np.ndarray, tgt: np.ndarray) -> Result:
        res = super().register(src, tgt)
        res.covariance = np.diag([-7.3e13, -8.8e13, 1e-4, 1e-4, 1e-4, 1e-4])
        return res


def bad_covariance(preprocess, engine) -> BadCovarianceRegistrar:
    return BadCovarianceRegistrar(preprocess, engine)
