"""The methods ``cegc-eval`` compares, by name.

CEGC rows are settings of the one engine, never code paths: each is a set of overrides applied
on top of the node's parameter file (``params/register_node.yaml`` or ``--params``), the same
``<section>.<field>`` names the node takes, so a row runs offline and inside ``register_node``
(``-p name:=value``) alike. The rows isolate what each part of the pipeline adds:

    cegc+icp           the node's settings (learned + FPFH candidates, learned confidence,
                       compatibility estimator, ICP)
    cegc               the same without ICP (engine.refine none)
    cegc-uniform       FPFH candidates, uniform weights, verification by fitness: the pipeline
                       without its learned part (the network's answers are ignored; SC2-PCR-style
                       on the network points' FPFH, then ICP)
    cegc-learned-cand  candidates from the learned feature space only
    cegc-fpfh-cand     candidates from FPFH only, learned confidence
    cegc-svd           the paper's confidence-weighted SVD instead of the compatibility estimator
    cegc-paper         paper-faithful matching and estimator (all pairs of the top-N overlap
                       sets, argmax per row, weighted SVD), then ICP

Peers (cegc_ros/baselines.py): icp, fgr, ransac, ransac+icp, sc2pcr, sc2pcr+icp.

``--methods`` takes names and the groups of :data:`GROUPS` (``default``, ``ablation``,
``peers``, ``all``).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

from cegc_ros.baselines import METHODS as PEER_METHODS
from cegc_ros.evaluation import EvalError

#: CEGC row -> overrides of the parameter file's values, by dotted parameter name.
CEGC_ROWS: dict[str, dict[str, Any]] = {
    "cegc+icp": {},
    "cegc": {"engine.refine": "none"},
    "cegc-uniform": {"engine.confidence": "uniform", "engine.candidates": "fpfh", "engine.verify_score": "fitness"},
    "cegc-learned-cand": {"engine.candidates": "learned"},
    "cegc-fpfh-cand": {"engine.candidates": "fpfh"},
    "cegc-svd": {"engine.estimator": "svd"},
    "cegc-paper": {"engine.candidates": "all", "engine.estimator": "svd"},
}
CEGC_METHODS = tuple(CEGC_ROWS)
BASELINE_METHODS = tuple(PEER_METHODS)
ALL_METHODS = CEGC_METHODS + BASELINE_METHODS
#: The node's pipeline beside every peer: what a user comparing methods wants first.
DEFAULT_METHODS = ("cegc+icp", *BASELINE_METHODS)
GROUPS: dict[str, tuple[str, ...]] = {
    "default": DEFAULT_METHODS,
    "ablation": CEGC_METHODS,
    "peers": BASELINE_METHODS,
    "all": ALL_METHODS,
}


def parse_methods(text: str) -> list[str]:
    """Comma-separated method names and group names -> distinct method names, in order."""
    methods: list[str] = []
    unknown: list[str] = []
    for name in (m.strip() for m in text.split(",")):
        if not name:
            continue
        if name in GROUPS:
            methods += GROUPS[name]
        elif name in ALL_METHODS:
            methods.append(name)
        else:
            unknown.append(name)
    if unknown or not methods:
        raise EvalError(f"unknown method(s) {', '.join(unknown) or '(none)'}; choose from "
                        f"{','.join(ALL_METHODS)} or the groups {','.join(GROUPS)}")
    return list(dict.fromkeys(methods))


def describe_row(method: str) -> str:
    """``cegc-svd: engine.estimator=svd`` (``node settings`` for the row without overrides)."""
    over = CEGC_ROWS[method]
    return f"{method}: " + (", ".join(f"{k}={v}" for k, v in over.items()) or "node settings")


def default_params_file() -> Path:
    """The node's shipped parameter file (the checkout's, else the installed copy)."""
    from cegc_ros.paths import ShippedFileError, shipped_params
    try:
        return shipped_params("register_node.yaml")
    except ShippedFileError as err:
        raise EvalError(str(err)) from err


def _checked(values: dict[str, Any], where: str) -> dict[str, Any]:
    """The node's own checks and coercions of ``<section>.<field>`` values; EvalError naming
    ``where`` and the bad value."""
    from cegc_ros.node.params import ParameterError, check_values
    try:
        return check_values(values)
    except ParameterError as err:
        raise EvalError(f"{where}: {err}") from err


def engine_configs(params_file: str | Path | None = None) -> tuple[Any, Any]:
    """(PreprocessConfig, EngineConfig) as register_node builds them from a parameter file
    (default: the shipped params/register_node.yaml)."""
    from cegc_ros.node.params import build_sections
    from cegc_ros.params_file import ParamsFileError, read_params_file

    path = Path(params_file) if params_file else default_params_file()
    try:
        values = read_params_file(path)
    except ParamsFileError as err:
        raise EvalError(str(err)) from err
    sections = build_sections(_checked(values, f"parameter file {path}"))
    return sections["preprocess"], sections["engine"]


def row_configs(method: str, preprocess: Any, engine: Any) -> tuple[Any, Any]:
    """Copies of (PreprocessConfig, EngineConfig) with the CEGC row's overrides applied."""
    if method not in CEGC_ROWS:
        raise EvalError(f"{method} is not a CEGC row (rows: {', '.join(CEGC_ROWS)})")
    pre, eng = copy.deepcopy(preprocess), copy.deepcopy(engine)
    sections = {"preprocess": pre, "engine": eng}
    for name, value in _checked(CEGC_ROWS[method], f"row {method}").items():
        section, field = name.split(".", 1)
        setattr(sections[section], field, value)
    return pre, eng


def node_arguments(method: str) -> list[str]:
    """The row's overrides as register_node ``-p name:=value`` arguments."""
    args: list[str] = []
    for name, value in CEGC_ROWS[method].items():
        text = str(value).lower() if isinstance(value, bool) else str(value)
        args += ["-p", f"{name}:={text}"]
    return args
