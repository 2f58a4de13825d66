"""cegc_ros.bootstrap: environment of the jobs, system-library handling, CLI, stamps."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cegc_ros import bootstrap

REPO = Path(__file__).resolve().parents[1]


def test_bootstrap_imports_only_the_standard_library():
    tree = ast.parse((REPO / "cegc_ros" / "bootstrap.py").read_text())
    modules = {alias.name.split(".")[0] for node in ast.walk(tree)
               if isinstance(node, ast.Import) for alias in node.names}
    modules |= {node.module.split(".")[0] for node in ast.walk(tree)
                if isinstance(node, ast.ImportFrom) and node.module and node.level == 0}
    modules.discard("__future__")
    assert modules <= set(sys.stdlib_module_names), modules - set(sys.stdlib_module_names)


def test_job_environment_keeps_dds_local_and_picks_a_domain(monkeypatch):
    monkeypatch.setattr(bootstrap, "jemalloc_path", lambda: None)
    base = {"PATH": "/usr/bin", "AMENT_PREFIX_PATH": f"/opt/ros/jazzy:{bootstrap.VENV}",
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}
    env = bootstrap.job_environment(base)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert 1 <= int(env["ROS_DOMAIN_ID"]) <= 100
    assert env["AMENT_PREFIX_PATH"] == f"{bootstrap.VENV}:/opt/ros/jazzy"
    assert env["PATH"].split(":")[:2] == [str(bootstrap.VENV / "bin"), "/usr/bin"]
    assert env["CEGC_ROS_BOOTSTRAP"] == "1" and "LD_PRELOAD" not in env
    # A domain the user chose is kept; outside tests their discovery range is too.
    env = bootstrap.job_environment(dict(base, ROS_DOMAIN_ID="42"), localhost=False)
    assert env["ROS_DOMAIN_ID"] == "42" and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"


def test_jemalloc_is_preloaded_once(monkeypatch):
    monkeypatch.setattr(bootstrap, "jemalloc_path", lambda: "/lib/libjemalloc.so.2")
    env = bootstrap.job_environment({"PATH": "/usr/bin", "LD_PRELOAD": "/lib/other.so"})
    assert env["LD_PRELOAD"] == "/lib/libjemalloc.so.2:/lib/other.so"
    assert env["MALLOC_CONF"] == "dirty_decay_ms:-1"
    assert bootstrap.job_environment(env)["LD_PRELOAD"] == env["LD_PRELOAD"]
    assert "LD_PRELOAD" not in bootstrap.job_environment({"PATH": "", "CEGC_NO_JEMALLOC": "1"})


def test_missing_libusb_without_root_stops_with_one_line_naming_the_package(monkeypatch):
    monkeypatch.setattr(bootstrap.ctypes.util, "find_library", lambda name: None)
    monkeypatch.setattr(bootstrap.os, "geteuid", lambda: 1000)
    with pytest.raises(bootstrap.BootstrapError) as err:
        bootstrap.ensure_system_libraries()
    message = str(err.value)
    assert "libusb-1.0-0" in message and "\n" not in message


def test_missing_optional_jemalloc_is_not_an_error(monkeypatch):
    monkeypatch.setattr(bootstrap.ctypes.util, "find_library",
                        lambda name: None if name == "jemalloc" else f"lib{name}.so")
    monkeypatch.setattr(bootstrap.os, "geteuid", lambda: 1000)
    bootstrap.ensure_system_libraries()  # no exception, nothing installed


def test_package_hash_follows_the_package_inputs(tmp_path, monkeypatch):
    for name in ("setup.py", "params/a.yaml", "cegc_ros/x.py", "test/t.py"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(name)
    monkeypatch.setattr(bootstrap, "ROOT", tmp_path)
    first = bootstrap.package_hash()
    (tmp_path / "test/t.py").write_text("changed")  # not installed: no reinstall
    (tmp_path / "cegc_ros/__pycache__").mkdir()
    (tmp_path / "cegc_ros/__pycache__/x.cpython-311.pyc").write_text("cache")
    assert bootstrap.package_hash() == first
    (tmp_path / "params/a.yaml").write_text("changed")
    assert bootstrap.package_hash() != first


@pytest.mark.parametrize("args, code, text", [
    (["--help"], 0, "test [ARGS]"),
    ([], 2, "demo [ARGS]"),
    (["bogus"], 2, "unknown job 'bogus'"),
])
def test_cli_usage(args, code, text):
    proc = subprocess.run([sys.executable, "-m", "cegc_ros.bootstrap", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=60,
                          stdin=subprocess.DEVNULL)
    assert proc.returncode == code
    assert text in proc.stdout + proc.stderr


def test_ci_script_runs_exactly_the_readme_test_command():
    script = REPO / ".ci" / "run"
    assert os.access(script, os.X_OK)
    commands = [line.strip() for line in script.read_text().splitlines()
                if line.strip() and not line.lstrip().startswith("#")]
    assert commands[-1] == "exec python3 -m cegc_ros.bootstrap test"
