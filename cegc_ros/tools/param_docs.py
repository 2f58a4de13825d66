"""docs/parameters.md and params/register_node.yaml, generated from the node's parameter specs
(cegc_ros/config.py).

    python -m cegc_ros.tools.param_docs > docs/parameters.md
    python -m cegc_ros.tools.param_docs --yaml > params/register_node.yaml

Tests compare both files with this output, so neither can drift from the code.
"""

from __future__ import annotations

import json
import sys
import textwrap

HEADER = """\
# register_node parameters

Generated from `cegc_ros/config.py` by `python -m cegc_ros.tools.param_docs > docs/parameters.md`
(a test checks that this page is current). Each parameter is `<section>.<field>`;
`params/register_node.yaml` holds them all at their defaults. "runtime = no": fixed at start-up;
the others can be changed while the node runs and apply to the next pair.

| parameter | default | range / choices | runtime | description |
|---|---|---|---|---|
"""


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def parameters_markdown() -> str:
    """The whole page: a short header and one table row per parameter."""
    from cegc_ros.node.params import param_specs

    rows = []
    for s in param_specs():
        lo, hi = s.range
        if s.choices:
            allowed = ", ".join(s.choices)
        elif lo is not None or hi is not None:
            allowed = f"[{lo}, {hi}]"
        else:
            allowed = ""
        default = repr(s.default).lower() if isinstance(s.default, bool) else repr(s.default)
        rows.append(f"| `{s.name}` | `{default}` | {allowed} | {'yes' if s.dynamic else 'no'} "
                    f"| {_cell(s.description)} |")
    return HEADER + "\n".join(rows) + "\n"


YAML_HEADER = """\
# Parameters of register_node (defaults; the single source is cegc_ros/config.py).
# Load with: register_node --ros-args --params-file params/register_node.yaml
# read-only = fixed at start-up; everything else can be changed at run time and
# applies to the next pair.
/**:
  ros__parameters:
"""


def parameters_yaml() -> str:
    """params/register_node.yaml: every parameter at its default, its description as a comment,
    sections separated by a blank line."""
    from cegc_ros.node.params import param_specs

    lines, section = [], None
    for s in param_specs():
        if section is not None and s.section != section:
            lines.append("")
        section = s.section
        lo, hi = s.range
        notes = []
        if s.choices:
            notes.append("one of " + ", ".join(s.choices))
        elif lo is not None or hi is not None:
            notes.append(f"range [{lo}, {hi}]")
        if not s.dynamic:
            notes.append("read-only")
        text = s.description + (f" ({'; '.join(notes)})" if notes else "")
        lines += textwrap.wrap(text, 98, initial_indent="    # ", subsequent_indent="    # ",
                               break_on_hyphens=False)
        value = json.dumps(s.default) if isinstance(s.default, (bool, str)) else repr(s.default)
        lines.append(f"    {s.name}: {value}")
    return YAML_HEADER + "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = argv if argv is not None else sys.argv[1:]
    if args not in ([], ["--yaml"]):
        print("usage: python -m cegc_ros.tools.param_docs [--yaml] > docs/parameters.md "
              "(or params/register_node.yaml)", file=sys.stderr)
        return 2
    sys.stdout.write(parameters_yaml() if args else parameters_markdown())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
