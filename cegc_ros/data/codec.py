"""The point storage codec of the pair cache: int16 codes per axis around the cloud's centre,
one step in metres per cloud (so storage precision is about 1e-4 of the cloud's size).
Standalone, so that the pair generator (views.py) and the cache (pair_cache.py) share it without
importing each other."""

from __future__ import annotations

import numpy as np

#: Largest code magnitude (int16).
_Q = 32767


def quantise(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(N, 3) points -> (int16 (N, 3) codes, (3,) float64 origin, step in metres)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros((0, 3), np.int16), np.zeros(3), 1.0
    origin = 0.5 * (p.min(0) + p.max(0))
    step = max(float(np.abs(p - origin).max()) / _Q, 1e-7)
    q = np.clip(np.rint((p - origin) / step), -_Q, _Q).astype(np.int16)
    return q, origin, step


def dequantise(q: np.ndarray, origin: np.ndarray, step: float) -> np.ndarray:
    """Codes back to (N, 3) float32 metres (the exact inverse used everywhere)."""
    return (q.astype(np.float64) * step + np.asarray(origin, np.float64)).astype(np.float32)
