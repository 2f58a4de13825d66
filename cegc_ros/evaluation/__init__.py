"""What ``cegc-eval`` is made of, one module per concern; the CLI is cegc_ros/tools/evaluate.py.

    datasets.py     pairs with ground truth: bags, real folders, the 7Scenes protocol on real
                    fragments, cached synthetic bags
    methods.py      the methods compared: CEGC rows (overrides of the node's parameter file:
                    the ablations) and the classical peers of cegc_ros/baselines.py
    runners.py      every method on every pair, offline; :func:`runners.evaluate`
    through_node.py the CEGC rows inside a register_node subprocess fed over DDS
    report.py       scoring, metrics.json, pairs.csv, report.md, errors.png
    suite.py        the documented evaluation (docs/accuracy.md) in one run

The shared vocabulary (an evaluation error, a pair, one method's outcome on one pair) lives here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


class EvalError(RuntimeError):
    """The evaluation cannot run (bad input folder, unknown method, missing weights, ...)."""


@dataclass
class EvalPair:
    """One pair to evaluate: clouds (N, 3) / (M, 3) in their own frames, ground truth or None."""

    pair_id: str
    source: np.ndarray
    target: np.ndarray
    T_gt: np.ndarray | None        # (4, 4) T_target_source, None when unknown
    info: dict[str, Any] = field(default_factory=dict)


@dataclass
class Outcome:
    """What one method returned on one pair."""

    method: str
    pair_id: str
    T: np.ndarray | None           # (4, 4) T_target_source estimate; None when it raised
    valid: bool
    raised: bool
    reason: str
    fitness: float
    latency_s: float
    #: the engine's RegistrationResult.ambiguity (CEGC rows: offline from the result, through
    #: the node from its ~/quality message); NaN for the peers
    ambiguity: float = float("nan")
