"""README.md and docs/: short, current, and with the commands a newcomer copies."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
DOCS = REPO / "docs"


def readme_lines() -> list[str]:
    return README.read_text().splitlines()


def test_readme_is_short_and_starts_with_the_two_commands():
    lines = readme_lines()
    assert len(lines) <= 250, f"README.md has {len(lines)} lines; move depth to docs/"
    head = "\n".join(lines[:60])
    assert "python3 -m cegc_ros.bootstrap demo" in head
    assert "python3 -m cegc_ros.bootstrap test" in head


def test_readme_shows_the_cegc_register_usage_as_the_cli_prints_it():
    from cegc_ros.tools.register_files import build_parser

    usage = " ".join(build_parser().format_usage().split())
    text = " ".join(README.read_text().split())
    assert usage in text
    assert "cegc-register /tmp/src.npy /tmp/tgt.npy --json" in text


def test_readme_node_commands_need_no_placeholders():
    text = README.read_text()
    assert 'eval "$(python3 -m cegc_ros.bootstrap env)"' in text
    assert "ros2 run cegc_ros register_node" in text
    assert "colcon build --packages-select cegc_ros" in text
    assert "CEGC_TORCH_INDEX=cpu" in text
    for bad in ("../shared", "cegc_ros_repo", "PLACEHOLDER", "<path", "/path/to"):
        assert bad not in text, bad


def test_readme_parameters_exist_with_the_defaults_shown():
    from cegc_ros.node.params import param_specs

    specs = {s.name: s for s in param_specs()}
    rows = re.findall(r"^\| `([a-z_]+\.[a-z_]+)` \| `([^`]*)` \|", README.read_text(), re.MULTILINE)
    assert len(rows) >= 5
    for name, default in rows:
        assert name in specs, f"README names unknown parameter {name}"
        value = specs[name].default
        shown = repr(value).lower() if isinstance(value, bool) else repr(value)
        assert default == shown, f"README: {name} default {default}, code: {shown}"


def _links(path: Path) -> list[str]:
    return re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", path.read_text())


@pytest.mark.parametrize("page", [README, *sorted(DOCS.glob("*.md"))], ids=lambda p: p.name)
def test_relative_links_point_at_files_that_exist(page):
    for link in _links(page):
        if "://" in link:
            continue
        assert (page.parent / link).exists(), f"{page.name} links to missing {link}"


def test_every_docs_page_is_linked_from_the_readme():
    linked = {Path(link).name for link in _links(README) if link.startswith("docs/")}
    assert {p.name for p in DOCS.glob("*.md")} <= linked


def test_no_unfinished_text_in_the_docs():
    for page in [README, *DOCS.glob("*.md")]:
        text = page.read_text()
        for bad in ("PLACEHOLDER", "TODO", "TBD"):
            assert bad not in text, f"{page.name}: {bad}"


def test_parameters_page_is_generated_and_current():
    from cegc_ros.tools.param_docs import parameters_markdown

    assert (DOCS / "parameters.md").read_text() == parameters_markdown(), (
        "docs/parameters.md is stale: python -m cegc_ros.tools.param_docs > docs/parameters.md")


def test_params_file_is_generated_and_current():
    from cegc_ros.node.params import params_yaml

    assert (DOCS.parent / "params" / "register_node.yaml").read_text() == params_yaml(), (
        "params/register_node.yaml is stale: register_node --print-params > params/register_node.yaml")


def test_msg_adapters_page_names_every_public_function():
    import msg_adapters.markers
    import msg_adapters.point_cloud2
    import msg_adapters.pose

    text = (DOCS / "msg_adapters.md").read_text()
    for module in (msg_adapters.point_cloud2, msg_adapters.pose, msg_adapters.markers):
        short = module.__name__.split(".")[-1]
        for name in module.__all__:
            if callable(getattr(module, name)):
                assert f"`{short}.{name}(" in text, f"docs/msg_adapters.md lacks {short}.{name}"
