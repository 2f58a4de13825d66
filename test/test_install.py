"""Both install routes of README: pip (what the bootstrap does) and a colcon workspace.

Each route is built from a copy of the package's sources in ``tmp_path``, so the test checks
the checkout as it is now and leaves no build/, install/ or log/ in the repository.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from cegc_ros import bootstrap, entry_points

REPO = Path(__file__).resolve().parents[1]
PY = f"python{sys.version_info.major}.{sys.version_info.minor}"
PARAMS = sorted(p.name for p in (REPO / "params").glob("*.yaml"))
ENTRY_POINTS = sorted(entry_points.SCRIPTS)
WEIGHTS = sorted(p.name for p in (REPO / "cegc_ros" / "weights").glob("*") if p.suffix in (".pt", ".json"))


def copy_sources(dest: Path) -> Path:
    """The files setup.py reads, copied to ``dest`` (no caches, no build leftovers)."""
    dest.mkdir(parents=True)
    for name in bootstrap.PACKAGE_INPUTS:
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=bootstrap._IGNORE)
        elif src.is_file():
            shutil.copy2(src, dest / name)
    return dest


def run(cmd: list[str], timeout: float = 300, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL, **kw)
    assert proc.returncode == 0, (
        f"{' '.join(map(str, cmd))} exited {proc.returncode}\n--- stdout\n{proc.stdout[-4000:]}"
        f"\n--- stderr\n{proc.stderr[-4000:]}")
    return proc


def assert_params_installed(share: Path) -> None:
    assert PARAMS, "the repository ships no params/*.yaml"
    installed = sorted(p.name for p in (share / "params").glob("*.yaml"))
    assert installed == PARAMS
    for name in PARAMS:
        assert (share / "params" / name).read_bytes() == (REPO / "params" / name).read_bytes()
    assert (share / "package.xml").read_bytes() == (REPO / "package.xml").read_bytes()
    assert WEIGHTS, "the repository ships no weights"
    for name in WEIGHTS:
        assert (share / "weights" / name).read_bytes() == (
            REPO / "cegc_ros" / "weights" / name).read_bytes(), name


def share_dir_in(env: dict[str, str]) -> Path:
    """get_package_share_directory('cegc_ros') as a fresh interpreter sees it in ``env``."""
    code = ("from ament_index_python.packages import get_package_share_directory as g; "
            "print(g('cegc_ros'))")
    out = run([sys.executable, "-c", code], timeout=60, env=env, cwd="/").stdout
    return Path(out.strip().splitlines()[-1])


def test_pip_route_installs_share_files_found_by_ament_index(tmp_path):
    """``pip install .`` into a fresh prefix puts the marker, package.xml and params where
    ament_index_python looks once AMENT_PREFIX_PATH names the prefix."""
    src = copy_sources(tmp_path / "src")
    prefix = tmp_path / "prefix"
    # --ignore-installed: without it pip would first uninstall the copy in this venv.
    run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation",
         "--ignore-installed", "--disable-pip-version-check", "--no-input",
         "--prefix", str(prefix), str(src)])
    assert (prefix / "share/ament_index/resource_index/packages/cegc_ros").is_file()
    for name in ENTRY_POINTS:
        assert os.access(prefix / "bin" / name, os.X_OK), name
    env = dict(os.environ, AMENT_PREFIX_PATH=str(prefix))
    share = share_dir_in(env)
    assert share == prefix / "share" / "cegc_ros"
    assert_params_installed(share)
    # The installed package (not the checkout) finds weights that are those of the checkout.
    site = next(prefix.glob("lib/python3*/site-packages"))
    code = ("import cegc_ros.paths as p; print(p.__file__); "
            "print(p.shipped_weights('cegc_views.pt'))")
    out = run([sys.executable, "-c", code], timeout=60, cwd="/",
              env=dict(env, PYTHONPATH=str(site))).stdout.split()
    assert Path(out[-2]).is_relative_to(site)
    assert Path(out[-1]).read_bytes() == (
        REPO / "cegc_ros" / "weights" / "cegc_views.pt").read_bytes()


@pytest.mark.skipif(not os.environ.get("CEGC_ROS_BOOTSTRAP"),
                    reason="checks the bootstrap's install; run via "
                           "`python3 -m cegc_ros.bootstrap test`")
def test_bootstrap_install_is_current_and_found():
    """Under the bootstrap, this interpreter's prefix holds the current share/cegc_ros."""
    share = share_dir_in(dict(os.environ))
    assert share == Path(sys.prefix) / "share" / "cegc_ros"
    assert_params_installed(share)
    assert shutil.which("register_node") == str(Path(sys.prefix) / "bin" / "register_node")


def test_colcon_route_builds_a_runnable_ament_python_package(tmp_path):
    """``colcon build`` in a workspace, then what ``ros2 run cegc_ros register_node`` does."""
    colcon = Path(sys.prefix) / "bin" / "colcon"
    if not colcon.exists():
        pytest.fail(f"{colcon} missing: colcon-core/colcon-ros are in requirements.txt")
    ws = tmp_path / "ws"
    copy_sources(ws / "src" / "cegc_ros")
    env = dict(os.environ, COLCON_HOME=str(tmp_path / "colcon_home"),
               AMENT_PREFIX_PATH=os.pathsep.join([sys.prefix] + [
                   p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]))
    env.pop("COLCON_DEFAULTS_FILE", None)
    run([str(colcon), "--log-base", str(tmp_path / "log"), "build",
         "--base-paths", str(ws / "src"), "--build-base", str(ws / "build"),
         "--install-base", str(ws / "install"), "--event-handlers", "console_direct-"],
        env=env, cwd=ws)

    prefix = ws / "install" / "cegc_ros"
    executable = prefix / "lib" / "cegc_ros" / "register_node"
    assert executable.is_file() and os.access(executable, os.X_OK)
    assert (prefix / "share/ament_index/resource_index/packages/cegc_ros").is_file()
    assert (prefix / "lib" / PY / "site-packages" / "msg_adapters" / "point_cloud2.py").is_file()
    assert_params_installed(prefix / "share" / "cegc_ros")
    assert not (ws / "src" / "cegc_ros" / "build").exists()  # sources stay clean

    # Source the workspace as a user would, then resolve the package like `ros2 run`.
    probe = (
        "from ament_index_python.packages import get_package_prefix as p; import cegc_ros; "
        "print(p('cegc_ros')); print(cegc_ros.__file__)")
    # The README sources install/setup.bash (colcon-bash; colcon-core alone writes setup.sh).
    assert (ws / "install" / "setup.bash").is_file()
    script = (f'source "{ws}/install/setup.bash" && "{sys.executable}" -c "{probe}"')
    out = run(["bash", "-c", script], timeout=60, cwd=tmp_path, env=env).stdout.split()
    assert Path(out[-2]) == prefix
    assert Path(out[-1]).is_relative_to(prefix / "lib" / PY / "site-packages")

    script = f'source "{ws}/install/setup.bash" && exec "{executable}" --help'
    proc = run(["bash", "-c", script], timeout=120, cwd=tmp_path, env=env)
    assert "register_node" in proc.stdout
    assert "Traceback" not in proc.stderr
    # Every tool the README names is where `ros2 run cegc_ros <tool>` looks, and the network's
    # ONNX export and the learned verification's weights ship beside the weights.
    for tool in ("cegc-make-bag", "cegc-replay", "cegc-register", "cegc-eval"):
        assert os.access(prefix / "lib" / "cegc_ros" / tool, os.X_OK), tool
    assert (prefix / "share" / "cegc_ros" / "weights" / "cegc_views.onnx").is_file()
    assert (prefix / "share" / "cegc_ros" / "weights" / "verification.json").is_file()
