"""The node's parameter file read without ROS: ``ros__parameters`` YAML -> dotted names.

    values = read_params_file("params/register_node.yaml")
    values["preprocess.num_points"]                      # 1024

A ROS 2 parameter file maps node names (``/**``, ``register_node``, ``/ns/register_node``, or
namespaces nested as mappings) to ``ros__parameters``; each parameter is either written with its
dotted name (``preprocess.num_points: 1024``, as params/register_node.yaml does) or nested
(``preprocess: {num_points: 1024}``). Blocks are merged in file order, so tools that take the
node's file (``cegc-register --params``, ``cegc-eval --params``) see what the node would see.
Values are not checked here: :mod:`cegc_ros.node.params` knows the parameters.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any


class ParamsFileError(ValueError):
    """The file is missing, not YAML, or holds no ``ros__parameters``; the message says which."""


def _flatten(prefix: str, value: Any, out: dict[str, Any]) -> None:
    if isinstance(value, dict):
        for key, sub in value.items():
            _flatten(f"{prefix}.{key}" if prefix else str(key), sub, out)
    else:
        out[prefix] = value


def _collect(doc: Any, out: dict[str, Any]) -> int:
    """Merge every ``ros__parameters`` block under ``doc`` into ``out``; how many were found."""
    if not isinstance(doc, dict):
        return 0
    found = 0
    for key, value in doc.items():
        if key == "ros__parameters":
            if not isinstance(value, dict):
                raise ParamsFileError(f"ros__parameters must be a mapping, got "
                                      f"{type(value).__name__}")
            _flatten("", value, out)
            found += 1
        else:
            found += _collect(value, out)
    return found


def read_params_file(path: str | Path) -> dict[str, Any]:
    """Every parameter in a ROS 2 parameter file, by dotted name; ParamsFileError on a bad file."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise ParamsFileError(f"parameter file {path}: cannot read it "
                              f"({err.strerror or type(err).__name__})") from err
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        where = getattr(err, "problem_mark", None)
        line = f" (line {where.line + 1})" if where is not None else ""
        raise ParamsFileError(f"parameter file {path}: not valid YAML{line}") from err
    values: dict[str, Any] = {}
    try:
        found = _collect(doc, values)
    except ParamsFileError as err:
        raise ParamsFileError(f"parameter file {path}: {err}") from err
    if not found:
        raise ParamsFileError(f"parameter file {path}: no ros__parameters block (expected "
                              "'/**:' or 'register_node:' then 'ros__parameters:')")
    return values
