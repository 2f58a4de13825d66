"""jemalloc for every cegc_ros process: the bootstrap's jobs and the installed console scripts.

With glibc's allocator, torch's large temporaries are about twice as slow on a small VM
(docs/performance.md), so the bootstrap preloads jemalloc into its jobs. A process started
another way (``ros2 run cegc_ros register_node``, ``register_node`` from a sourced workspace)
gets the same through :func:`reexec_with_allocator`, which every console script calls first:
when jemalloc is installed and not loaded yet, the process re-executes itself once with
``LD_PRELOAD`` set. Both paths build the variables with :func:`allocator_environment`.

Neither path sets thread counts: torch and Open3D keep their defaults unless the node's
``engine.threads`` parameter says otherwise. Both set :data:`THREAD_ENV` (OpenMP threads that
sleep instead of spinning) unless the user's environment sets those variables already, and so
does ``import cegc_ros.engine`` (:func:`apply_thread_environment`), so that a user's own
script gets the same threading as the console scripts.

``CEGC_NO_JEMALLOC=1`` turns jemalloc off. Standard library only.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import subprocess
import sys
from pathlib import Path

JEMALLOC_SONAME = "libjemalloc.so.2"
#: jemalloc keeps freed pages instead of returning them at once (torch reallocates them soon).
MALLOC_CONF = "dirty_decay_ms:-1"
#: Environment every cegc_ros process (console scripts, the node's engine process) starts with
#: unless the user's environment sets the variable already. OpenMP threads that sleep instead
#: of spinning: beside 1-2 CPU-bound processes on 2 cores the engine took 1.8 / 2.5 s per pair
#: with it and 8.3 / 10.4 s without (cegc_ros/tools/bench_contention.py; table in docs/node.md).
THREAD_ENV: dict[str, str] = {"OMP_WAIT_POLICY": "PASSIVE"}
#: Set in the re-executed process, so that a loader that drops LD_PRELOAD cannot cause a loop.
_REEXEC_GUARD = "CEGC_ALLOCATOR_REEXEC"


def jemalloc_path() -> str | None:
    """Full path of libjemalloc.so.2 from the linker cache, or None when it is not installed."""
    if ctypes.util.find_library("jemalloc") is None:
        return None
    try:
        out = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True,
                             check=False).stdout
    except OSError:
        out = ""
    for line in out.splitlines():
        name, _, path = line.strip().partition(" => ")
        if name.startswith(JEMALLOC_SONAME) and Path(path).is_file():
            return path
    return JEMALLOC_SONAME  # the dynamic linker also resolves a bare soname


def allocator_environment(env: dict[str, str], jemalloc: str | None) -> dict[str, str]:
    """``env`` with jemalloc preloaded (``LD_PRELOAD``, ``MALLOC_CONF``) when ``jemalloc`` is a
    library path and ``CEGC_NO_JEMALLOC`` is not set, and :data:`THREAD_ENV` where ``env`` does
    not set those variables; a copy, ``env`` itself is not changed."""
    env = dict(env)
    for key, value in THREAD_ENV.items():
        env.setdefault(key, value)
    if not jemalloc or env.get("CEGC_NO_JEMALLOC"):
        return env
    preload = [p for p in env.get("LD_PRELOAD", "").split(":") if p]
    if jemalloc not in preload:
        env["LD_PRELOAD"] = ":".join([jemalloc, *preload])
        env.setdefault("MALLOC_CONF", MALLOC_CONF)
    return env


#: Libraries that load OpenMP (libgomp reads THREAD_ENV once, when it is loaded).
OPENMP_USERS = ("torch", "open3d")


def apply_thread_environment() -> list[str]:
    """Set the :data:`THREAD_ENV` variables this process's environment lacks (a user's own
    value always wins). Returns those set too late to matter: a library of
    :data:`OPENMP_USERS` was imported already and its OpenMP has read the environment."""
    late = []
    for key, value in THREAD_ENV.items():
        if key in os.environ:
            continue
        os.environ[key] = value
        if any(name in sys.modules for name in OPENMP_USERS):
            late.append(key)
    return late


def jemalloc_loaded() -> bool:
    """Whether this process has jemalloc mapped (Linux: /proc/self/maps)."""
    try:
        return "libjemalloc" in Path("/proc/self/maps").read_text()
    except OSError:
        return False


#: jemalloc's ``mallctl`` index for every arena (MALLCTL_ARENAS_ALL, jemalloc 5).
_ALL_ARENAS = 4096


def release_free_memory() -> bool:
    """Return the pages jemalloc keeps for reuse (:data:`MALLOC_CONF`) to the system, in every
    arena; True when it did, False without jemalloc (nothing kept then). For a process that
    holds many arrays while it registers pair after pair (tools/estimator_study.py): freed
    pages of varied sizes are kept beside the live ones and its memory grew to 3.5-23 GB for
    392 matched pairs that need about 0.8 GB."""
    if not jemalloc_loaded():
        return False
    try:
        mallctl = ctypes.CDLL(None).mallctl
    except (OSError, AttributeError):
        return False
    mallctl.argtypes = [ctypes.c_char_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t]
    mallctl.restype = ctypes.c_int
    return mallctl(f"arena.{_ALL_ARENAS}.purge".encode(), None, None, None, 0) == 0


def reexec_with_allocator() -> None:
    """Re-execute this process with jemalloc preloaded, once, when it is installed and not
    loaded yet; otherwise return. Call it first thing in a console script's main."""
    if os.environ.get(_REEXEC_GUARD) or os.environ.get("CEGC_NO_JEMALLOC") or jemalloc_loaded():
        return
    env = allocator_environment(dict(os.environ), jemalloc_path())
    if env.get("LD_PRELOAD") == os.environ.get("LD_PRELOAD"):
        return
    env[_REEXEC_GUARD] = "1"
    sys.stdout.flush()
    sys.stderr.flush()
    # sys.orig_argv: the interpreter's own arguments too (the script path, or -c CODE / -m MOD).
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)
