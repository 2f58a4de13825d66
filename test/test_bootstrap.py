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


def test_job_environment_keeps_dds_local_and_picks_a_domain(monkeypatch, tmp_path):
    monkeypatch.setattr(bootstrap, "jemalloc_path", lambda: None)
    monkeypatch.setattr(bootstrap, "TF2_PREFIX", tmp_path / "no_tf2_msgs")
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
    assert bootstrap.job_environment(dict(base, ROS_DOMAIN_ID="0"))["ROS_DOMAIN_ID"] != "0"


def test_a_built_tf2_msgs_is_on_the_jobs_paths_and_a_missing_compiler_is_one_line(
        monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(bootstrap, "jemalloc_path", lambda: None)
    prefix = tmp_path / "tf2_msgs"
    site = prefix / "lib" / "python3.11" / "site-packages"
    site.mkdir(parents=True)
    monkeypatch.setattr(bootstrap, "TF2_PREFIX", prefix)
    base = {"PATH": "/usr/bin", "PYTHONPATH": "/mine", "LD_LIBRARY_PATH": "/opt/lib"}
    assert "PYTHONPATH" not in bootstrap.job_environment({"PATH": "/usr/bin"})   # not built
    (prefix / ".built").write_text("1\n")
    env = bootstrap.job_environment(base)
    assert env["PYTHONPATH"] == f"{site}:/mine"
    assert env["LD_LIBRARY_PATH"] == f"{prefix / 'lib'}:{bootstrap.VENV / 'lib'}:/opt/lib"
    assert env["AMENT_PREFIX_PATH"].split(":")[0] == str(prefix)
    assert bootstrap.ensure_tf2_msgs() == prefix                    # built: nothing to do
    (prefix / ".built").unlink()
    monkeypatch.setattr(bootstrap.shutil, "which", lambda name, path=None: None)
    assert bootstrap.ensure_tf2_msgs() is None
    assert capsys.readouterr().err.strip() == (
        "[bootstrap] tf2_msgs not built (needs gcc, g++ and scripts/build_tf2_msgs.sh): no /tf")


def test_env_prints_the_same_domain_every_time_in_one_checkout(monkeypatch, tmp_path):
    monkeypatch.setattr(bootstrap, "jemalloc_path", lambda: None)
    base = {"PATH": "/usr/bin"}
    a = bootstrap.job_environment(base, stable_domain=True)["ROS_DOMAIN_ID"]
    assert a == bootstrap.job_environment(base, stable_domain=True)["ROS_DOMAIN_ID"]
    assert a == str(bootstrap.checkout_domain_id()) and 1 <= int(a) <= 100
    others = {bootstrap.checkout_domain_id(tmp_path / f"clone{i}") for i in range(20)}
    assert len(others) > 5                                 # other clones: other domains
    assert bootstrap.job_environment(dict(base, ROS_DOMAIN_ID="7"), stable_domain=True)["ROS_DOMAIN_ID"] == "7"
    env = {k: v for k, v in os.environ.items() if k != "ROS_DOMAIN_ID"}
    printed = [subprocess.run([sys.executable, "-m", "cegc_ros.bootstrap", "env"], cwd=REPO, env=env,
                              capture_output=True, text=True, timeout=300, check=True).stdout
               for _ in range(2)]
    lines = [[ln for ln in out.splitlines() if ln.startswith("export ROS_DOMAIN_ID=")] for out in printed]
    assert lines[0] == lines[1] == [f"export ROS_DOMAIN_ID={a}"]


def test_tests_run_on_the_domain_the_bootstrap_prints():
    """The bootstrap prints its ROS_DOMAIN_ID before it starts pytest; the node tests use it."""
    code = "import sys; sys.path.insert(0, 'test'); import ros_helpers as r; print(r.DOMAIN_ID)"
    for given, expect in (("57", "57"), ("0", None)):
        proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                              text=True, timeout=120, env=dict(os.environ, ROS_DOMAIN_ID=given))
        assert proc.returncode == 0, proc.stderr
        got = proc.stdout.split()[-1]
        assert got == expect if expect else got != "0"


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


# --- set-up output for people --------------------------------------------------------------


def test_help_says_what_the_demo_does_with_generated_pairs():
    assert "bundled" not in bootstrap.__doc__
    assert "generate 10 synthetic" in bootstrap.USAGE
    assert ".cache/demo/report/" in bootstrap.USAGE


@pytest.mark.parametrize("seconds, text", [(4.24, "4.2 s"), (38.4, "38 s"),
                                           (185.0, "3 min 05 s"), (3600, "60 min 00 s")])
def test_format_elapsed(seconds, text):
    assert bootstrap.format_elapsed(seconds) == text


def test_phase_is_one_line_with_the_elapsed_time(capsys, monkeypatch):
    monkeypatch.setattr(bootstrap, "VERBOSE", False)
    with bootstrap.phase("installing things"):
        pass
    with pytest.raises(RuntimeError), bootstrap.phase("breaking things"):
        raise RuntimeError("x")
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2
    assert err[0].startswith("[bootstrap] installing things ... done, ") and err[0].endswith(" s")
    assert err[1].startswith("[bootstrap] breaking things ... failed, ")


def test_quiet_commands_write_the_log_not_the_terminal(tmp_path, monkeypatch, capfd):
    monkeypatch.setattr(bootstrap, "VERBOSE", False)
    monkeypatch.setattr(bootstrap, "LOG", tmp_path / "setup.log")
    monkeypatch.setattr(bootstrap, "_log_opened", False)
    code = bootstrap.run_logged(
        ["sh", "-c", "echo Collecting torch; echo 'ERROR: No matching distribution' >&2; exit 3"],
        "pip")
    assert code == 3
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    log = (tmp_path / "setup.log").read_text()
    assert "Collecting torch" in log and "ERROR: No matching distribution" in log
    message = str(bootstrap._failure("pip install of requirements.txt", code))
    assert "\n" not in message
    assert "exit code 3: ERROR: No matching distribution" in message
    assert str(tmp_path / "setup.log") in message and "-v" in message
    # -v: the output reaches the terminal instead
    monkeypatch.setattr(bootstrap, "VERBOSE", True)
    assert bootstrap.run_logged(["sh", "-c", "echo visible"], "echo") == 0
    assert "visible" in capfd.readouterr().out


def test_last_error_line_prefers_the_error():
    text = "$ pip install x\nCollecting x\nERROR: first\nsome context\nERROR: second\nbye\n"
    assert bootstrap.last_error_line(text) == "ERROR: second"
    assert bootstrap.last_error_line("E: Unable to locate package foo\n") == (
        "E: Unable to locate package foo")
    assert bootstrap.last_error_line("just output\n") == "just output"


def test_cli_verbose_flag_goes_before_the_job():
    proc = subprocess.run([sys.executable, "-m", "cegc_ros.bootstrap", "-v", "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert proc.returncode == 0 and "-v, --verbose" in proc.stdout


# --- torch wheel index ---------------------------------------------------------------------


def test_requirements_install_unchanged_without_a_torch_index(tmp_path):
    req = tmp_path / "requirements.txt"
    req.write_text("numpy==2.4.6\ntorch==2.13.0\n")
    assert bootstrap.torch_index({}) is None
    assert bootstrap.requirement_commands(req, None) == [
        ["install", "--progress-bar", "off", "-r", str(req)]]


def test_cpu_torch_index_installs_the_cpu_build_first(tmp_path):
    req = tmp_path / "requirements.txt"
    req.write_text("# pinned\ntorch==2.13.0   # the CPU build\nscipy==1.17.1\n")
    index = bootstrap.torch_index({"CEGC_TORCH_INDEX": "cpu"})
    assert index == "https://download.pytorch.org/whl/cpu"
    cmds = bootstrap.requirement_commands(req, index)
    assert cmds == [
        ["install", "--progress-bar", "off", "--index-url", index, "torch==2.13.0+cpu"],
        ["install", "--progress-bar", "off", "-r", str(req)]]
    # Another index is used as given, with the pinned version as is.
    url = "https://download.pytorch.org/whl/cu126"
    assert bootstrap.requirement_commands(req, bootstrap.torch_index(
        {"CEGC_TORCH_INDEX": url}))[0][-3:] == ["--index-url", url, "torch==2.13.0"]


def test_bad_torch_index_and_missing_pin_are_one_line_errors(tmp_path):
    with pytest.raises(bootstrap.BootstrapError, match="CEGC_TORCH_INDEX='gpu'"):
        bootstrap.torch_index({"CEGC_TORCH_INDEX": "gpu"})
    req = tmp_path / "requirements.txt"
    req.write_text("torchvision==0.29.1\ntorch>=2\n")
    with pytest.raises(bootstrap.BootstrapError, match="pins no torch version"):
        bootstrap.requirement_commands(req, "https://download.pytorch.org/whl/cpu")


def test_torch_index_is_part_of_the_requirements_stamp():
    plain = bootstrap.requirements_hash({})
    assert bootstrap.requirements_hash({"CEGC_TORCH_INDEX": ""}) == plain
    assert bootstrap.requirements_hash({"CEGC_TORCH_INDEX": "cpu"}) != plain


def test_repository_pins_torch():
    assert bootstrap.torch_pin(REPO / "requirements.txt").count(".") == 2
