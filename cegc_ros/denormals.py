"""Subnormal floats flushed to zero while the network runs, and only there.

Why: attention's softmax puts subnormal weights (below 1.2e-38) into the MatMuls after it, and
Intel cores take a slow microcode path on each one. On a 2-core Xeon (Ice Lake) the network's
ONNX Runtime call took 252 ms with them and 141 ms with the calling thread and ONNX Runtime's
pool flushing them (docs/performance.md; not measured on AMD's cores). The network's outputs
change only where a weight below 1.2e-38 becomes 0.

x86's FTZ / DAZ bits belong to each thread. :func:`flush_denormals` sets them on the calling
thread for a block and gives the thread its own state back; ONNX Runtime's pool threads get them
from the session's ``session.set_denormal_as_zero`` entry (cegc_ros/onnx_network.py), whose
session creation also sets them on the creating thread, so that is wrapped to restore it. Only
the network runs flushed (``matching.match`` wraps its call, whatever the runtime): the rest of
the engine (SciPy's k-d trees among it) sees the caller's setting.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np


def denormals_flushed() -> bool:
    """Whether this thread's floating point unit flushes subnormal floats to zero."""
    return float(np.float32(1e-40) * np.float32(1.0)) == 0.0


@contextlib.contextmanager
def flush_denormals(on: bool = True) -> Iterator[None]:
    """Run the block with subnormals flushed on this thread (``on``; a no-op where the CPU has
    no such control) or as they are (``on=False``: only restore afterwards what the block may
    have changed); either way the thread's own state comes back."""
    import torch
    before = denormals_flushed()
    if on and not before:
        torch.set_flush_denormal(True)
    try:
        yield
    finally:
        if denormals_flushed() != before:
            torch.set_flush_denormal(before)
