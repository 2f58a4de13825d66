"""Every method on every pair, offline, and :func:`evaluate`: runs plus scores in one call.

A runner is ``(source (N, 3), target (M, 3)) -> (T_target_source (4, 4), valid, reason,
fitness)``. CEGC rows share one :class:`cegc_ros.engine.Registrar` (one copy of the weights);
each row's runner hands the registrar its own settings before every pair.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cegc_ros import metrics
from cegc_ros.evaluation import EvalPair, Outcome
from cegc_ros.evaluation.methods import (
    BASELINE_METHODS,
    CEGC_METHODS,
    default_params_file,
    describe_row,
    engine_configs,
    row_configs,
)
from cegc_ros.evaluation.report import Evaluation, machine_line, summarize_outcomes

Runner = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, bool, str, float]]


class CegcRunner:
    """One CEGC row: the shared registrar with this row's (PreprocessConfig, EngineConfig)."""

    def __init__(self, method: str, registrar: Any, preprocess: Any, engine: Any) -> None:
        self.method = method
        self.registrar = registrar
        self.preprocess = preprocess
        self.engine = engine
        self.last: Any = None             # the RegistrationResult of the latest pair

    def __call__(self, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, bool, str, float]:
        self.registrar.update(preprocess=self.preprocess, engine=self.engine)
        self.last = r = self.registrar.register(source, target)
        return r.T_target_source, r.valid, r.reason, r.fitness


def make_runners(methods: Sequence[str], checkpoint: str | None = None,
                 baseline_config: Any = None, params_file: str | Path | None = None
                 ) -> dict[str, Runner]:
    """Offline runners per method name, in the order of ``methods``.

    CEGC rows start from the node's settings in ``params_file`` (default the shipped
    params/register_node.yaml) with the row's overrides on top; ``checkpoint`` overrides the
    file's ``engine.checkpoint``.
    """
    runners: dict[str, Runner] = {}
    rows = [m for m in methods if m in CEGC_METHODS]
    if rows:
        from cegc_ros.engine import Registrar
        pre, eng = engine_configs(params_file)
        registrar = Registrar.from_checkpoint(checkpoint or eng.checkpoint or None,
                                              device=eng.device, preprocess=pre, engine=eng)
        for m in rows:
            row_pre, row_eng = row_configs(m, pre, registrar.engine)
            runners[m] = CegcRunner(m, registrar, row_pre, row_eng)
    if any(m in BASELINE_METHODS for m in methods):
        from cegc_ros import baselines

        baselines.load_open3d(getattr(baseline_config, "threads", 2))  # import outside the timing
        for m in methods:
            if m in BASELINE_METHODS:
                def run(src: np.ndarray, tgt: np.ndarray, _m: str = m
                        ) -> tuple[np.ndarray, bool, str, float]:
                    r = baselines.register(_m, src, tgt, baseline_config)
                    return r.T_target_source, r.valid, r.reason, r.fitness
                runners[m] = run
    return {m: runners[m] for m in methods if m in runners}


def run_method(method: str, runner: Runner, pair: EvalPair) -> Outcome:
    """One method on one pair; an exception becomes a failed Outcome carrying its message."""
    t0 = time.perf_counter()
    try:
        T, valid, reason, fitness = runner(pair.source, pair.target)
    except Exception as err:  # noqa: BLE001 - any failure of a method is a scored failure
        return Outcome(method, pair.pair_id, None, False, True, f"{type(err).__name__}: {err}",
                       0.0, time.perf_counter() - t0)
    latency = time.perf_counter() - t0
    last = getattr(runner, "last", None)      # a CegcRunner's RegistrationResult of this pair
    return Outcome(method, pair.pair_id, np.asarray(T, np.float64), bool(valid), False,
                   str(reason), float(fitness), latency,
                   float(last.ambiguity) if last is not None else float("nan"))


def run_offline(pairs: Sequence[EvalPair], runners: dict[str, Runner],
                progress: bool = True) -> dict[str, list[Outcome]]:
    """Every runner on every pair (pair-major order, so partial runs cover all methods)."""
    from tqdm import tqdm

    out: dict[str, list[Outcome]] = {m: [] for m in runners}
    with tqdm(total=len(pairs) * len(runners), disable=not progress, unit="run",
              desc="cegc-eval", file=sys.stderr) as bar:
        for pair in pairs:
            for m, runner in runners.items():
                bar.set_postfix_str(f"{pair.pair_id} {m}")
                out[m].append(run_method(m, runner, pair))
                bar.update()
    return out


def evaluate(pairs: Sequence[EvalPair], methods: Sequence[str], *,
             thresholds: metrics.RecallThresholds = metrics.SEVEN_SCENES_RECALL,
             checkpoint: str | None = None, baseline_config: Any = None,
             node_outcomes: dict[str, list[Outcome]] | None = None, progress: bool = True,
             title: str = "cegc-eval", settings: dict[str, Any] | None = None,
             params_file: str | Path | None = None) -> Evaluation:
    """Score ``methods`` on ``pairs``; methods present in ``node_outcomes`` are taken from there."""
    from cegc_ros import baselines

    pairs = list(pairs)
    node_outcomes = node_outcomes or {}
    offline = [m for m in methods if m not in node_outcomes]
    runners = make_runners(offline, checkpoint, baseline_config, params_file)
    outs = run_offline(pairs, runners, progress=progress)
    outcomes = {m: (node_outcomes[m] if m in node_outcomes else outs[m]) for m in methods}
    st: dict[str, Any] = {"machine": machine_line(), "recall": thresholds.describe()}
    rows = [m for m in methods if m in CEGC_METHODS]
    if rows:
        st["cegc"] = ("through register_node over DDS" if any(m in node_outcomes for m in rows)
                      else "offline through cegc_ros.engine.Registrar")
        st["checkpoint"] = checkpoint or "from the parameter file (empty: shipped weights)"
        st["node parameters"] = str(params_file or default_params_file())
        st["cegc rows"] = [describe_row(m) for m in rows]
    if any(m in BASELINE_METHODS for m in methods):
        st["baselines"] = baselines.describe(baseline_config)
    st.update(settings or {})
    summaries = summarize_outcomes(pairs, outcomes, thresholds)
    return Evaluation(pairs, outcomes, summaries, thresholds, st, title)
