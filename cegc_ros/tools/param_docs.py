"""docs/parameters.md, generated from the node's parameter specs (cegc_ros/config.py).

    python -m cegc_ros.tools.param_docs > docs/parameters.md

A test compares the file with this output, so the page cannot drift from the code.
"""

from __future__ import annotations

import sys

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


def main(argv: list[str] | None = None) -> int:
    if argv if argv is not None else sys.argv[1:]:
        print("usage: python -m cegc_ros.tools.param_docs > docs/parameters.md", file=sys.stderr)
        return 2
    sys.stdout.write(parameters_markdown())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
