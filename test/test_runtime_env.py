"""What every cegc_ros process gets however it was started: shipped files, allocator, scripts."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from cegc_ros import allocator, bootstrap, entry_points, paths

REPO = Path(__file__).resolve().parents[1]


# --- shipped files -------------------------------------------------------------------------


def test_shipped_weights_in_a_checkout_are_the_checkouts():
    for name in paths.WEIGHT_NAMES:
        assert paths.shipped_weights(name) == REPO / "cegc_ros" / "weights" / name
    assert paths.shipped_params() == REPO / "params" / "register_node.yaml"


def _install_layout(tmp_path: Path, with_weights: bool) -> tuple[Path, Path]:
    """A copy of cegc_ros/paths.py as an installed package would have it, and a share dir."""
    site = tmp_path / "site-packages" / "cegc_ros"
    site.mkdir(parents=True)
    (site / "__init__.py").write_text("")
    (site / "paths.py").write_text((REPO / "cegc_ros" / "paths.py").read_text())
    prefix = tmp_path / "prefix"
    (prefix / "share/ament_index/resource_index/packages").mkdir(parents=True)
    (prefix / "share/ament_index/resource_index/packages/cegc_ros").write_text("")
    if with_weights:
        (prefix / "share/cegc_ros/weights").mkdir(parents=True)
        (prefix / "share/cegc_ros/weights/cegc_7scenes.pt").write_bytes(b"w")
    return site.parent, prefix


def _probe(site: Path, prefix: Path | None, code: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(site))
    env["AMENT_PREFIX_PATH"] = str(prefix) if prefix else ""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, cwd=site, timeout=60)


def test_installed_package_finds_its_weights_through_the_ament_index(tmp_path):
    site, prefix = _install_layout(tmp_path, with_weights=True)
    proc = _probe(site, prefix, "from cegc_ros.paths import shipped_weights as s; "
                                "print(s('cegc_7scenes.pt'))")
    assert proc.returncode == 0, proc.stderr
    assert Path(proc.stdout.strip()) == prefix / "share/cegc_ros/weights/cegc_7scenes.pt"


@pytest.mark.parametrize("registered", [True, False])
def test_missing_weights_are_one_clear_error(tmp_path, registered):
    site, prefix = _install_layout(tmp_path, with_weights=False)
    code = ("from cegc_ros.paths import shipped_weights as s, ShippedFileError as E\n"
            "try:\n    s('cegc_views.pt')\nexcept E as e:\n"
            "    print(isinstance(e, FileNotFoundError)); print(e)")
    proc = _probe(site, prefix if registered else None, code)
    assert proc.returncode == 0, proc.stderr
    flag, message = proc.stdout.strip().split("\n")
    assert flag == "True"
    assert message.startswith("shipped weights cegc_views.pt not found: looked at ")
    assert str(site / "cegc_ros" / "weights" / "cegc_views.pt") in message
    if registered:
        assert str(prefix / "share/cegc_ros/weights/cegc_views.pt") in message
    else:
        assert "not in the ament index" in message


def test_weight_names_are_file_names():
    with pytest.raises(ValueError, match="file name"):
        paths.shipped_weights("../params/register_node.yaml")


# --- allocator -----------------------------------------------------------------------------


def test_bootstrap_and_console_scripts_build_the_same_allocator_environment(monkeypatch):
    monkeypatch.setattr(bootstrap, "jemalloc_path", lambda: "/lib/libjemalloc.so.2")
    base = {"PATH": "/usr/bin", "LD_PRELOAD": "/lib/other.so"}
    job = bootstrap.job_environment(base)
    script = allocator.allocator_environment(base, "/lib/libjemalloc.so.2")
    for key in ("LD_PRELOAD", "MALLOC_CONF", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        assert job.get(key) == script.get(key), key
    assert job["LD_PRELOAD"] == "/lib/libjemalloc.so.2:/lib/other.so"
    assert allocator.allocator_environment(dict(base, CEGC_NO_JEMALLOC="1"),
                                           "/lib/libjemalloc.so.2") == dict(
        base, CEGC_NO_JEMALLOC="1", **allocator.THREAD_ENV)


def test_allocator_and_bootstrap_use_only_the_standard_library():
    for name in ("allocator.py", "paths.py", "bootstrap.py"):
        tree = ast.parse((REPO / "cegc_ros" / name).read_text())
        mods = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import)
                for a in n.names}
        mods |= {n.module.split(".")[0] for n in ast.walk(tree)
                 if isinstance(n, ast.ImportFrom) and n.module and n.level == 0}
        mods -= {"__future__", "ament_index_python"}   # paths.py: imported when needed
        assert mods <= set(sys.stdlib_module_names), (name, mods)


def _without_allocator() -> dict[str, str]:
    """This environment as a process started without the bootstrap sees it."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("LD_PRELOAD", "MALLOC_CONF", "CEGC_NO_JEMALLOC", "CEGC_ALLOCATOR_REEXEC")}
    env["PYTHONPATH"] = str(REPO)
    return env


_PROBE = ("from cegc_ros.allocator import reexec_with_allocator, jemalloc_loaded; "
          "reexec_with_allocator(); import os; "
          "print(jemalloc_loaded(), os.environ.get('MALLOC_CONF'))")


@pytest.mark.skipif(allocator.jemalloc_path() is None, reason="jemalloc is not installed here")
def test_a_process_started_without_the_bootstrap_gets_jemalloc():
    """What `ros2 run cegc_ros register_node` runs: the console script re-executes itself once
    with jemalloc preloaded, as the bootstrap would have started it."""
    env = _without_allocator()
    proc = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                          env=env, timeout=60, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["True", allocator.MALLOC_CONF]
    proc = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                          env=dict(env, CEGC_NO_JEMALLOC="1"), timeout=60, cwd=REPO)
    assert proc.stdout.split() == ["False", "None"]


_RELEASE_PROBE = (
    "from cegc_ros.allocator import reexec_with_allocator, release_free_memory; "
    "reexec_with_allocator(); import numpy as np; "
    "rss = lambda: int(open('/proc/self/statm').read().split()[1]) * 4096 >> 20; "
    "a = [np.ones(10 ** 7) for _ in range(30)]; del a; before = rss(); "
    "ok = release_free_memory(); print(ok, before, rss())")


@pytest.mark.skipif(allocator.jemalloc_path() is None, reason="jemalloc is not installed here")
def test_release_free_memory_returns_what_jemalloc_keeps():
    """Under the engine's jemalloc settings 2.4 GB freed stay in the process until
    release_free_memory() hands them back; without jemalloc it reports that it did nothing."""
    env = _without_allocator()
    proc = subprocess.run([sys.executable, "-c", _RELEASE_PROBE], capture_output=True, text=True,
                          env=env, timeout=120, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    ok, before, after = proc.stdout.split()
    assert ok == "True" and int(before) > 2000 and int(after) < int(before) - 2000, proc.stdout
    proc = subprocess.run([sys.executable, "-c", _RELEASE_PROBE], capture_output=True, text=True,
                          env=dict(env, CEGC_NO_JEMALLOC="1"), timeout=120, cwd=REPO)
    assert proc.returncode == 0 and proc.stdout.split()[0] == "False", proc.stderr


# --- console scripts -----------------------------------------------------------------------


def test_every_console_script_goes_through_entry_points():
    text = (REPO / "setup.py").read_text()
    declared = dict(re.findall(r'"([\w-]+) = (cegc_ros\.entry_points:\w+)"', text))
    assert sorted(declared) == sorted(entry_points.SCRIPTS)
    assert len(re.findall(r'"[\w-]+ = [\w.]+:\w+"', text)) == len(declared)
    for script, target in declared.items():
        func = getattr(entry_points, target.split(":")[1])
        assert func.__name__ == script.replace("-", "_")
        module = __import__(entry_points.SCRIPTS[script], fromlist=["main"])
        assert callable(module.main)


def test_console_scripts_and_bootstrap_jobs_get_sleeping_openmp_threads():
    """OMP_WAIT_POLICY=PASSIVE under ros2 run / console scripts as under the bootstrap (the
    contention benchmark's choice), and a user's own setting wins."""
    from cegc_ros.allocator import THREAD_ENV, allocator_environment
    assert allocator_environment({}, None)["OMP_WAIT_POLICY"] == "PASSIVE"
    assert allocator_environment({"OMP_WAIT_POLICY": "ACTIVE"}, "/x/libjemalloc.so.2")["OMP_WAIT_POLICY"] == "ACTIVE"
    code = "import os, cegc_ros.entry_points as e; e.reexec_with_allocator = lambda: None; " \
           "e.SCRIPTS['probe'] = 'os'; os.main = lambda: print(os.environ['OMP_WAIT_POLICY']) or 0; e._run('probe')"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == THREAD_ENV["OMP_WAIT_POLICY"]
