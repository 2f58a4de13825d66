"""The node's parameters, described from the config dataclasses (no rclpy needed here).

Every field of a section of :mod:`cegc_ros.config` is one parameter ``<section>.<field>``
with that field's default, description, range and choices. This module turns those into
:class:`ParamSpec` rows, checks values against them (:func:`check_value`, used at start-up
and for every run-time change), and writes the ``--help`` text and the params file.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from cegc_ros import config

NODE_NAME = "register_node"

#: Parameter sections, in declaration order: ``<section>.<field>`` per dataclass field.
SECTIONS: dict[str, type] = {
    "preprocess": config.PreprocessConfig,
    "engine": config.EngineConfig,
    "input": config.InputConfig,
    "sync": config.SyncConfig,
    "sequential": config.SequentialConfig,
    "output": config.OutputConfig,
    "markers": config.MarkersConfig,
    "diagnostics": config.DiagnosticsConfig,
}
#: Sections whose change must reach the engine (through ``Registrar.update``).
ENGINE_SECTIONS = ("preprocess", "engine")


class ParameterError(ValueError):
    """One or more parameter values are unacceptable; the message names each one."""


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter, derived from a config dataclass field."""

    name: str            # "<section>.<field>"
    section: str
    field: str
    default: Any
    description: str
    range: tuple[float | None, float | None]
    dynamic: bool
    choices: tuple[str, ...] | None

    @property
    def kind(self) -> type:
        """bool, int, float or str: the parameter's type."""
        return type(self.default)


def param_specs() -> list[ParamSpec]:
    """Every parameter of the node, with the defaults of :mod:`cegc_ros.config`."""
    specs = []
    for section, cls in SECTIONS.items():
        for name, default, meta in config.section_items(cls()):
            specs.append(ParamSpec(f"{section}.{name}", section, name, default,
                                   meta["description"], tuple(meta["range"]), meta["dynamic"],
                                   meta["choices"]))
    return specs


def coerce(spec: ParamSpec, value: Any) -> Any:
    """``value`` as the parameter's type where that loses nothing: an integer for a float.

    ROS parses ``-p sync.slop:=1`` and ``sync.slop: 1`` in a params file as integers; a
    float parameter takes them. Anything else is returned unchanged (and :func:`check_value`
    says what is wrong with it).
    """
    if spec.kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def _type_name(kind: type) -> str:
    return {bool: "bool", int: "integer", float: "float", str: "string"}.get(kind, kind.__name__)


def allowed(spec: ParamSpec) -> str:
    """The allowed values of ``spec`` in words: 'a float in [0.0, 60.0]', 'one of a, b'."""
    if spec.choices:
        return "one of " + ", ".join(spec.choices)
    lo, hi = spec.range
    text = f"a {_type_name(spec.kind)}" if spec.kind is not int else "an integer"
    if lo is not None or hi is not None:
        text += f" in [{lo}, {hi}]"
    return text


def check_value(spec: ParamSpec, value: Any) -> str | None:
    """Why ``value`` is not acceptable for ``spec`` (type, range, choices), or None if it is.

    The reason names the parameter, the value and what is allowed, e.g.
    ``preprocess.num_points = 10 is out of range: an integer in [64, 8192]``.
    """
    value = coerce(spec, value)
    kind = spec.kind
    if type(value) is not kind:
        return (f"{spec.name} = {value!r} has the wrong type ({_type_name(type(value))}): "
                f"{allowed(spec)}")
    lo, hi = spec.range
    if kind in (int, float):
        if kind is float and not math.isfinite(value):
            return f"{spec.name} = {value} is not finite: {allowed(spec)}"
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            return f"{spec.name} = {value!r} is out of range: {allowed(spec)}"
    if spec.choices is not None and value not in spec.choices:
        return f"{spec.name} = {value!r} is not {allowed(spec)}"
    return None


def check_values(values: Mapping[str, Any]) -> dict[str, Any]:
    """Coerced values of the known parameters in ``values``; ParameterError naming each bad one.

    Names that are not parameters of this node are skipped (the node warns about them); the
    problems are listed in declaration order.
    """
    out, problems = {}, []
    for spec in param_specs():                   # declaration order: a stable message
        if spec.name not in values:
            continue
        name, value = spec.name, values[spec.name]
        problem = check_value(spec, value)
        if problem:
            problems.append(problem)
        else:
            out[name] = coerce(spec, value)
    if problems:
        raise ParameterError("; ".join(problems))
    return out


def build_sections(values: Mapping[str, Any]) -> dict[str, Any]:
    """Section name -> config dataclass instance, from ``<section>.<field>`` values (defaults
    for the ones not given)."""
    out = {}
    for section, cls in SECTIONS.items():
        names = {f.name for f in fields(cls)}
        given = {k.split(".", 1)[1]: v for k, v in values.items()
                 if k.split(".", 1)[0] == section and k.split(".", 1)[1] in names}
        out[section] = cls(**given)
    return out


def usage() -> str:
    """The --help text: how to run the node and every parameter with its default."""
    lines = [
        (f"usage: {NODE_NAME} [-h] [--print-params] [--ros-args [--params-file FILE] "
         "[-p NAME:=VALUE] [-r FROM:=TO] ...]"),
        "",
        "Registers source_cloud onto target_cloud (sensor_msgs/PointCloud2, paired by stamp)",
        "with CEGC and publishes ~/pose, ~/pose_with_covariance, ~/source_overlap,",
        "~/target_overlap, ~/markers and /diagnostics. With -p input.mode:=sequential it",
        "reads the one topic cloud and also publishes odometry: ~/odometry, ~/path (and /tf).",
        "--print-params writes the parameter file with every default (YAML) to stdout.",
        "",
        ("example: ros2 run cegc_ros register_node --ros-args --params-file "
         "params/register_node.yaml -r source_cloud:=/scan -r target_cloud:=/map_cloud"),
        "",
        "parameters (name, default, range; * = read-only after start-up):",
    ]
    for s in param_specs():
        lo, hi = s.range
        rng = f" [{lo}, {hi}]" if lo is not None or hi is not None else ""
        if s.choices:
            rng = " {" + ", ".join(s.choices) + "}"
        ro = "" if s.dynamic else " *"
        lines.append(f"  {s.name} = {s.default!r}{rng}{ro}")
        lines.append(f"      {s.description}")
    return "\n".join(lines)


def params_yaml() -> str:
    """The text of ``params/register_node.yaml``: every parameter at its default, described.

    Regenerate the file after changing :mod:`cegc_ros.config` with
    ``register_node --print-params > params/register_node.yaml``.
    """
    def fmt(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        return f'"{v}"' if isinstance(v, str) else repr(v)

    lines = ["# Parameters of register_node (defaults; the single source is cegc_ros/config.py).",
             "# Load with: register_node --ros-args --params-file params/register_node.yaml",
             "# read-only = fixed at start-up; everything else can be changed at run time and",
             "# applies to the next pair.", "/**:", "  ros__parameters:"]
    section = None
    for s in param_specs():
        if s.section != section:
            if section is not None:
                lines.append("")
            section = s.section
        lo, hi = s.range
        extra = []
        if s.choices:
            extra.append("one of " + ", ".join(s.choices))
        elif lo is not None or hi is not None:
            extra.append(f"range [{lo}, {hi}]")
        if not s.dynamic:
            extra.append("read-only")
        desc = s.description + (" (" + "; ".join(extra) + ")" if extra else "")
        lines += ["    # " + ln for ln in textwrap.wrap(desc, 92, break_on_hyphens=False,
                                                      break_long_words=False)]
        lines.append(f"    {s.name}: {fmt(s.default)}")
    return "\n".join(lines) + "\n"
