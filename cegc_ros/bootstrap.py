"""Set up ``.venv/`` on first use, then run a job in it: ``python3 -m cegc_ros.bootstrap [-v] JOB``.

Jobs:
    demo [ARGS]      run ``cegc-demo``: generate 10 synthetic 7Scenes-style test pairs, replay
                     them through register_node over DDS, run the Open3D baselines on the same
                     pairs, print one table (report in .cache/demo/report/)
    test [ARGS]      run ``python -m pytest -q test`` (ARGS go to pytest: ``-k pose``,
                     ``test/test_pose.py``)
    setup            only install; print nothing else
    env              print ``export`` lines: ``eval "$(python3 -m cegc_ros.bootstrap env)"``
    run CMD [ARGS]   run any command in the environment (``run register_node --help``)
Options (before the job):
    -v, --verbose    show pip's and apt-get's output (by default it goes to .venv/setup.log)
Environment:
    CEGC_TORCH_INDEX=cpu   install torch's CPU build from download.pytorch.org (or =URL of
                           another index); unset, pip takes torch from its usual indexes
    CEGC_NO_JEMALLOC=1     do not preload jemalloc

Standard library only: this runs on a bare ``python3 >= 3.10`` before anything is installed.

What it does, each step skipped when already done, one progress line per step that runs:
1. System libraries: ``libusb-1.0-0`` (Open3D cannot be imported without it) is installed with
   apt-get when running as root, otherwise the bootstrap stops with one line naming the package.
   ``libjemalloc2`` is installed the same way but optionally; when present it is preloaded into
   the job (``LD_PRELOAD``, ``MALLOC_CONF=dirty_decay_ms:-1``; :mod:`cegc_ros.allocator`, which
   the installed console scripts use too), which roughly halves the time of large torch
   temporaries here. ``CEGC_NO_JEMALLOC=1`` turns that off.
2. ``.venv/``: created with this interpreter; ``pip install -r requirements.txt`` then a regular
   (not editable) ``pip install .`` of this repository, because only a regular install puts
   ``share/cegc_ros`` (ament index marker, package.xml, params, weights) into the prefix where
   ``ament_index_python`` finds it. A stamp in ``.venv/`` records hashes of what each step
   installed: requirements are reinstalled only when ``requirements.txt`` (or
   ``CEGC_TORCH_INDEX``) changes, the package (seconds, ``--no-deps``) whenever its sources,
   params or weights change. Repeat runs with nothing changed do not start pip at all.
3. The job's environment: ``.venv/bin`` first on PATH, the venv prepended to
   ``AMENT_PREFIX_PATH``, DDS kept on this machine (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``)
   and a random ``ROS_DOMAIN_ID`` in 1..100 unless one is set, so parallel runs do not talk to
   each other. ``demo`` and ``test`` print the domain they use.
4. ``tf2_msgs`` (not on any package index), so that sequential mode publishes ``/tf``: generated
   from its one message definition by rosidl's generators (wheels in ``.venv``) and compiled
   with gcc into ``.venv/tf2_msgs`` (``scripts/build_tf2_msgs.sh``; about 5 s, 0.3 MB, once
   per venv); the job gets it on ``PYTHONPATH``, ``LD_LIBRARY_PATH`` and ``AMENT_PREFIX_PATH``.
   Without gcc or when the build fails, one line says so and jobs run without ``/tf``.
"""

from __future__ import annotations

import contextlib
import ctypes.util
import hashlib
import json
import os
import random
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from .allocator import allocator_environment, jemalloc_path

ROOT = Path(__file__).resolve().parents[1]
VENV = ROOT / ".venv"
STAMP = VENV / ".cegc_bootstrap.json"
LOCK = VENV / ".cegc_bootstrap.lock"
#: Output of pip, apt-get and venv of the last set-up run (shown instead with -v).
LOG = VENV / "setup.log"

#: What ``pip install .`` reads: setup.py's inputs. Everything else in the repo is ignored.
PACKAGE_INPUTS = ("setup.py", "setup.cfg", "package.xml", "resource", "params", "cegc_ros",
                  "msg_adapters")
_IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", ".pytest_cache")

REQUIRED_LIBS = {"libusb-1.0-0": "usb-1.0"}  # Debian package -> ctypes.util library name
OPTIONAL_LIBS = {"libjemalloc2": "jemalloc"}

#: CEGC_TORCH_INDEX shorthands -> package index URL (anything else must be a URL).
TORCH_INDEXES = {"cpu": "https://download.pytorch.org/whl/cpu"}

USAGE = __doc__.split("\n\n")[1]

#: -v: subprocess output goes to the terminal instead of LOG.
VERBOSE = False


class BootstrapError(Exception):
    """A step failed; the message is the one line shown to the user."""


def log(message: str) -> None:
    print(f"[bootstrap] {message}", file=sys.stderr, flush=True)


def format_elapsed(seconds: float) -> str:
    """``4.2 s``, ``38 s``, ``3 min 05 s``."""
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes, sec = divmod(round(seconds), 60)
    return f"{minutes} min {sec:02d} s"


class Phase:
    """What a step's progress line ends with: ``done`` unless the step says otherwise."""

    def __init__(self) -> None:
        self.outcome = "done"


@contextlib.contextmanager
def phase(text: str) -> Iterator[Phase]:
    """One progress line for a set-up step: ``[bootstrap] text ... done, 12 s``."""
    t0 = time.monotonic()
    if VERBOSE:
        log(f"{text} ...")
    else:
        print(f"[bootstrap] {text} ... ", end="", file=sys.stderr, flush=True)
    step = Phase()
    try:
        yield step
    except BaseException:
        step.outcome = "failed"
        raise
    finally:
        took = format_elapsed(time.monotonic() - t0)
        if VERBOSE:
            log(f"{text}: {step.outcome}, {took}")
        else:
            print(f"{step.outcome}, {took}", file=sys.stderr, flush=True)


_log_opened = False


def run_logged(cmd: list[str], what: str, **kwargs) -> int:
    """Run ``cmd``; its output goes to LOG (the terminal with -v). Returns the exit code."""
    global _log_opened
    if VERBOSE:
        log(" ".join(shlex.quote(a) for a in cmd))
        return subprocess.run(cmd, stdin=subprocess.DEVNULL, **kwargs).returncode
    LOG.parent.mkdir(parents=True, exist_ok=True)
    with LOG.open("a" if _log_opened else "w") as fh:   # the log holds this run only
        _log_opened = True
        fh.write(f"\n$ {' '.join(shlex.quote(a) for a in cmd)}   # {what}\n")
        fh.flush()
        return subprocess.run(cmd, stdin=subprocess.DEVNULL, stdout=fh,
                              stderr=subprocess.STDOUT, **kwargs).returncode


def last_error_line(text: str) -> str:
    """The line of a pip / apt-get log that says what went wrong (its last ERROR line)."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith("$ ")]
    errors = [ln for ln in lines if ln.startswith(("ERROR", "E:", "error:"))]
    return (errors or lines or [""])[-1]


def _log_tail() -> str:
    """The log's error line and where the full log is."""
    try:
        line = last_error_line(LOG.read_text(errors="replace"))
    except OSError:
        line = ""
    return (f"{line} " if line else "") + f"(full log: {LOG}; -v shows it)"


def _failure(what: str, code: int) -> BootstrapError:
    detail = "" if VERBOSE else f": {_log_tail()}"
    return BootstrapError(f"{what} failed with exit code {code}{detail}")


# --- system libraries --------------------------------------------------------------------


def _missing(libs: dict[str, str]) -> list[str]:
    return [pkg for pkg, name in libs.items() if ctypes.util.find_library(name) is None]


def _apt_install(packages: list[str]) -> bool:
    """apt-get install ``packages`` when root with apt-get; True when it ran and succeeded."""
    if not packages or os.geteuid() != 0 or shutil.which("apt-get") is None:
        return False
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    with phase(f"installing system packages {' '.join(packages)} (apt-get)") as step:
        for cmd in (["apt-get", "update", "-qq"],
                    ["apt-get", "install", "-y", "-qq", "--no-install-recommends", *packages]):
            if run_logged(cmd, "apt-get", env=env) != 0:
                step.outcome = (f"failed: {_log_tail()}" if not VERBOSE else "failed")
                return False
    return True


def ensure_system_libraries() -> None:
    """Install what is missing; raise BootstrapError naming a required package still missing."""
    required, optional = _missing(REQUIRED_LIBS), _missing(OPTIONAL_LIBS)
    if os.environ.get("CEGC_NO_JEMALLOC"):
        optional = []
    if required or optional:
        # One apt run for both; if the optional one breaks it, retry without it.
        if not _apt_install(required + optional) and optional:
            _apt_install(required)
    still = _missing(REQUIRED_LIBS)
    if still:
        raise BootstrapError(
            f"missing system package {' '.join(still)} (Open3D needs libusb-1.0.so.0): "
            f"install it with `sudo apt-get install {' '.join(still)}` and run again")


# --- virtual environment -----------------------------------------------------------------


def venv_python() -> Path:
    return VENV / "bin" / "python"


def _sha256_files(paths: list[Path]) -> str:
    digest = hashlib.sha256()
    for path in paths:
        digest.update(str(path.relative_to(ROOT)).encode() + b"\0")
        with path.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
        digest.update(b"\0")
    return digest.hexdigest()


def torch_index(env: dict[str, str] | None = None) -> str | None:
    """The package index torch comes from, from CEGC_TORCH_INDEX (None: pip's usual ones)."""
    value = (os.environ if env is None else env).get("CEGC_TORCH_INDEX", "").strip()
    if not value:
        return None
    url = TORCH_INDEXES.get(value, value)
    if not url.startswith(("https://", "http://", "file:")):
        raise BootstrapError(f"CEGC_TORCH_INDEX={value!r} is neither "
                             f"{' nor '.join(TORCH_INDEXES)} nor an index URL")
    return url


def requirements_hash(env: dict[str, str] | None = None) -> str:
    python = f"{sys.version_info.major}.{sys.version_info.minor}"
    index = torch_index(env)
    return (python + ":" + _sha256_files([ROOT / "requirements.txt"])
            + (f":torch-index={index}" if index else ""))


def torch_pin(requirements: Path) -> str:
    """The version requirements.txt pins torch to (``torch==X``)."""
    for line in requirements.read_text().splitlines():
        m = re.fullmatch(r"\s*torch\s*==\s*([^\s#;]+)\s*(#.*)?", line)
        if m:
            return m.group(1)
    raise BootstrapError(f"{requirements} pins no torch version (a line `torch==X`)")


def requirement_commands(requirements: Path, index: str | None) -> list[list[str]]:
    """The pip argument lists (after ``python -m pip``) that install ``requirements``.

    With a torch index, torch is installed from it first; ``-r requirements.txt`` then finds
    its pin satisfied. The CPU index's wheels carry a ``+cpu`` local version, named explicitly
    so that a CUDA build installed earlier is replaced.
    """
    common = ["install", "--progress-bar", "off"]
    cmds = []
    if index:
        version = torch_pin(requirements)
        if index == TORCH_INDEXES["cpu"] and "+" not in version:
            version += "+cpu"
        cmds.append([*common, "--index-url", index, f"torch=={version}"])
    cmds.append([*common, "-r", str(requirements)])
    return cmds


def package_hash() -> str:
    files: list[Path] = []
    for name in PACKAGE_INPUTS:
        path = ROOT / name
        if path.is_file():
            files.append(path)
        elif path.is_dir():
            files.extend(p for p in sorted(path.rglob("*"))
                         if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc")
    return _sha256_files(files)


def _read_stamp() -> dict[str, str]:
    try:
        return json.loads(STAMP.read_text())
    except (OSError, ValueError):
        return {}


def _write_stamp(stamp: dict[str, str]) -> None:
    tmp = STAMP.with_suffix(".tmp")
    tmp.write_text(json.dumps(stamp, indent=1) + "\n")
    tmp.replace(STAMP)


@contextlib.contextmanager
def _locked() -> Iterator[None]:
    """Serialise concurrent bootstraps of the same checkout (fcntl lock on a file in .venv)."""
    import fcntl

    LOCK.parent.mkdir(parents=True, exist_ok=True)
    with LOCK.open("w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _pip(*args: str, what: str) -> None:
    cmd = [str(venv_python()), "-m", "pip", "--disable-pip-version-check", "--no-input", *args]
    code = run_logged(cmd, what, cwd=ROOT)
    if code != 0:
        raise _failure(what, code)


def _create_venv() -> None:
    try:
        import ensurepip  # noqa: F401  (Debian ships it in python3-venv)
    except ModuleNotFoundError as err:
        pkg = f"python3.{sys.version_info.minor}-venv"
        if not _apt_install([pkg]):
            raise BootstrapError(f"missing system package {pkg} (needed to create .venv): "
                                 f"install it with `sudo apt-get install {pkg}`") from err
    # The directory may already exist, holding only the lock file: venv fills it in.
    with phase(f"creating .venv with {sys.executable} (Python {sys.version.split()[0]})"):
        code = run_logged([sys.executable, "-m", "venv", str(VENV)], "python -m venv")
        if code != 0:
            raise _failure(f"`{sys.executable} -m venv {VENV}`", code)


def install_package() -> None:
    """``pip install --no-deps .`` from a clean copy of setup.py's inputs.

    Building from a copy keeps build/ and *.egg-info out of the checkout and stops a stale
    build/lib from carrying deleted modules into the install.
    """
    with tempfile.TemporaryDirectory(prefix="cegc_ros-install-") as tmp:
        src = Path(tmp) / "cegc_ros"
        src.mkdir()
        for name in PACKAGE_INPUTS:
            path = ROOT / name
            if path.is_dir():
                shutil.copytree(path, src / name, ignore=_IGNORE)
            elif path.is_file():
                shutil.copy2(path, src / name)
        _pip("install", "--no-deps", "--no-build-isolation", "--force-reinstall",
             "--progress-bar", "off", str(src), what="pip install of cegc_ros")


def ensure_venv() -> None:
    """Create/refresh .venv as needed (see the module docstring)."""
    if sys.version_info < (3, 10):  # noqa: UP036  (this file must run on any python3)
        raise BootstrapError(f"Python >= 3.10 is needed, this is {sys.version.split()[0]}")
    requirements = ROOT / "requirements.txt"
    if not requirements.is_file():
        raise BootstrapError(f"{requirements} is missing: run from a full checkout")
    with _locked():
        if not venv_python().exists():
            _create_venv()
        stamp = _read_stamp()
        req = requirements_hash()
        if stamp.get("requirements") != req:
            index = torch_index()
            note = f", torch from {index}" if index else ""
            with phase(f"installing requirements.txt into .venv (pip{note}; takes minutes the "
                       f"first time)"):
                for args in requirement_commands(requirements, index):
                    _pip(*args, what="pip install of requirements.txt")
            stamp = {"requirements": req}
            _write_stamp(stamp)
        pkg = package_hash()
        marker = VENV / "share" / "ament_index" / "resource_index" / "packages" / "cegc_ros"
        if stamp.get("package") != pkg or not marker.is_file():  # also if uninstalled by hand
            with phase("installing cegc_ros into .venv"):
                install_package()
            stamp["package"] = pkg
            _write_stamp(stamp)


# --- the job's environment ---------------------------------------------------------------


def checkout_domain_id(root: Path | None = None) -> int:
    """A ROS domain in 1..100 fixed for this checkout (from a hash of its path): ``env`` prints
    it, so that a node in one terminal and a replay in another, each after
    ``eval "$(python3 -m cegc_ros.bootstrap env)"``, share a domain."""
    digest = hashlib.sha256(str((root or ROOT).resolve()).encode()).hexdigest()
    return 1 + int(digest, 16) % 100


TF2_PREFIX = VENV / "tf2_msgs"
TF2_SCRIPT = ROOT / "scripts" / "build_tf2_msgs.sh"


def ensure_tf2_msgs() -> Path | None:
    """Build tf2_msgs into TF2_PREFIX once (see the module docstring, step 4); its prefix, or
    None (one logged line) when it cannot be built here."""
    done = TF2_PREFIX / ".built"
    if done.is_file():
        return TF2_PREFIX
    if not TF2_SCRIPT.is_file() or shutil.which("gcc") is None or shutil.which("g++") is None:
        log("tf2_msgs not built (needs gcc, g++ and scripts/build_tf2_msgs.sh): no /tf")
        return None
    log("building tf2_msgs (rosidl + gcc, seconds) -> .venv/tf2_msgs")
    shutil.rmtree(TF2_PREFIX, ignore_errors=True)
    with open(LOG, "a") as out:
        rc = subprocess.call(["bash", str(TF2_SCRIPT), str(venv_python()), str(TF2_PREFIX)],
                             stdout=None if VERBOSE else out, stderr=subprocess.STDOUT)
    if rc != 0:
        log(f"tf2_msgs build failed (exit {rc}; see {LOG}): jobs run without /tf")
        return None
    done.write_text("1\n")
    return TF2_PREFIX


def _prepend(env: dict[str, str], key: str, *paths: str) -> None:
    rest = [p for p in env.get(key, "").split(os.pathsep) if p and p not in paths]
    env[key] = os.pathsep.join([*paths, *rest])


def job_environment(base: dict[str, str] | None = None, *,
                    localhost: bool = True, stable_domain: bool = False) -> dict[str, str]:
    """The environment for a job in .venv (``base`` defaults to os.environ). Without a
    ROS_DOMAIN_ID of the user's, a random one (parallel test runs stay apart), or with
    ``stable_domain`` this checkout's (:func:`checkout_domain_id`)."""
    env = dict(os.environ if base is None else base)
    prefix = str(VENV)
    env["VIRTUAL_ENV"] = prefix
    env.pop("PYTHONHOME", None)
    _prepend(env, "PATH", str(VENV / "bin"))
    _prepend(env, "AMENT_PREFIX_PATH", prefix)
    if localhost:
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    else:
        env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if env.get("ROS_DOMAIN_ID", "0") in ("", "0"):   # 0: every ROS install's default
        env["ROS_DOMAIN_ID"] = str(checkout_domain_id() if stable_domain
                                   else random.SystemRandom().randint(1, 100))
    env["CEGC_ROS_BOOTSTRAP"] = "1"
    tf2 = TF2_PREFIX if (TF2_PREFIX / ".built").is_file() else None
    if tf2 is not None:
        site = sorted(tf2.glob("lib/python3*/site-packages"))
        if site:
            _prepend(env, "PYTHONPATH", str(site[0]))
        _prepend(env, "LD_LIBRARY_PATH", str(tf2 / "lib"), str(VENV / "lib"))
        _prepend(env, "AMENT_PREFIX_PATH", str(tf2))
    return allocator_environment(env, None if env.get("CEGC_NO_JEMALLOC") else jemalloc_path())


def _exec(argv: list[str], env: dict[str, str]) -> None:
    """Replace this process with ``argv`` run from the repo root (exit code passes through)."""
    os.chdir(ROOT)
    executable = argv[0] if os.sep in argv[0] else shutil.which(argv[0], path=env["PATH"])
    if executable is None:
        raise BootstrapError(f"command not found in .venv or PATH: {argv[0]}")
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(executable, argv, env)


def main(argv: list[str] | None = None) -> int:
    global VERBOSE
    args = list(sys.argv[1:] if argv is None else argv)
    while args and args[0] in ("-v", "--verbose"):
        VERBOSE = True
        args.pop(0)
    if not args or args[0] in ("-h", "--help", "help"):
        print(__doc__.split("\n\n")[0] + "\n\n" + USAGE)
        return 0 if args else 2
    job, extra = args[0], args[1:]
    if job not in ("demo", "test", "setup", "env", "run"):
        print(f"unknown job {job!r}\n\n{USAGE}", file=sys.stderr)
        return 2
    if job == "run" and not extra:
        print("run needs a command, e.g. `run register_node --help`", file=sys.stderr)
        return 2
    try:
        ensure_system_libraries()
        ensure_venv()
        ensure_tf2_msgs()
        env = job_environment(localhost=job == "test", stable_domain=job == "env")
        if job == "setup":
            return 0
        if job == "env":
            keys = ("VIRTUAL_ENV", "PATH", "AMENT_PREFIX_PATH", "ROS_AUTOMATIC_DISCOVERY_RANGE",
                    "ROS_DOMAIN_ID", "LD_PRELOAD", "MALLOC_CONF", "PYTHONPATH",
                    "LD_LIBRARY_PATH")
            for key in keys:
                if key in env:
                    print(f"export {key}={shlex.quote(env[key])}")
            return 0
        py = str(venv_python())
        if job in ("test", "demo"):
            log(f"ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']} "
                f"ROS_AUTOMATIC_DISCOVERY_RANGE={env['ROS_AUTOMATIC_DISCOVERY_RANGE']}")
        if job == "test":
            # Given test paths replace the default `test` directory.
            paths = [a for a in extra if not a.startswith("-")
                     and ((ROOT / a.split("::")[0]).exists() or "::" in a)]
            _exec([py, "-m", "pytest", "-q", *([] if paths else ["test"]), *extra], env)
        elif job == "demo":
            _exec([str(VENV / "bin" / "cegc-demo"), *extra], env)
        else:
            _exec(extra, env)
    except BootstrapError as err:
        print(f"cegc_ros bootstrap: {err}", file=sys.stderr)
        return 1
    return 0  # not reached: _exec replaces the process


if __name__ == "__main__":
    sys.exit(main())
