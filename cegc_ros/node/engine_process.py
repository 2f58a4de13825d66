"""The registration engine behind a small interface, run in a process of its own.

Why a process: Open3D (KD-trees, ICP, RANSAC) and parts of numpy hold the GIL for whole
calls. With the engine on a thread of the node's process, the executor that answers the
parameter services and publishes /diagnostics waited up to 1.7 s for one call on a 1M-point
pair, and ~40 s on the 5M-point case of issue 15 (docs/node.md, "Responsiveness"). In a child
process the engine can hold its own GIL as long as it likes.

How: the child is a fresh interpreter (``python -m cegc_ros.node.engine_process``: no DDS
threads forked, and unlike multiprocessing's spawn it never re-imports the caller's main
script); it imports torch and the checkpoint, warms up, and then serves requests over a
socket pair.
The two clouds of a request travel through one shared-memory buffer (an anonymous
``memfd``, passed to the child once and replaced only when a larger one is needed); the
result comes back pickled (it is ``preprocess.num_points``-sized). A child that dies (a
crash in a native library, the OOM killer) is noticed at once (the pipe closes) and started
again for the next pair.

:class:`InlineEngine` offers the same interface around a registrar object in the calling
thread (tests, benchmarks, tools that want no second process).
"""

from __future__ import annotations

import dataclasses
import importlib
import mmap
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import types
from collections.abc import Mapping
from multiprocessing import reduction
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

#: The default engine: "module:function" taking (PreprocessConfig, EngineConfig).
ENGINE_FACTORY = "cegc_ros.node.engine_process:load_registrar"

from cegc_ros.allocator import THREAD_ENV  # noqa: E402  (the engine process's thread settings)


class EngineError(RuntimeError):
    """The engine raised ``kind`` (an exception type name) with ``message``."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(f"{kind}: {message}")
        self.kind = kind


class EngineDied(EngineError):
    """The engine process ended while it worked on a pair (a crash, a kill)."""


class EngineStartError(RuntimeError):
    """The engine could not be started (a bad checkpoint, device or setting)."""


@dataclasses.dataclass
class EngineInfo:
    """What the node reports about its engine."""

    device: str = "?"
    checkpoint: str = "?"
    min_points: int = 16
    compiled_s: float = 0.0       # torch.compile at start-up (0: not compiled)
    warm_up_s: float = 0.0
    warm_up_error: str = ""       # a failed warm-up is reported, not fatal
    pid: int | None = None        # the engine process (None: in the caller's process)


def load_registrar(preprocess: Any, engine: Any) -> Any:
    """The engine for these settings (raises cegc_ros.engine.CheckpointError, ValueError)."""
    from cegc_ros.engine import Registrar  # torch is heavy: imported only where it runs
    return Registrar.from_checkpoint(engine.checkpoint or None, device=engine.device,
                                     preprocess=preprocess, engine=engine)


def _resolve(factory: str) -> Any:
    module, _, attr = factory.partition(":")
    return getattr(importlib.import_module(module), attr)


def _one_line(err: BaseException) -> str:
    text = str(err).strip().replace("\n", " ")
    return text or type(err).__name__


def _warm_up(registrar: Any) -> EngineInfo:
    """Compile (with engine.compile) and run one throw-away pair, so the first real pair is
    not slowed by either."""
    info = EngineInfo(device=str(getattr(registrar, "device", "?")),
                      checkpoint=str(getattr(registrar, "checkpoint_path", "?")),
                      min_points=int(getattr(registrar, "MIN_POINTS", 16)))
    cloud = np.random.default_rng(0).uniform(-1.0, 1.0, (512, 3)).astype(np.float32)  # (512, 3)
    t0 = time.perf_counter()
    try:
        info.compiled_s = float(registrar.warm_up() or 0.0)
        registrar.register(cloud, cloud[::-1].copy())
    except Exception as err:  # noqa: BLE001  a failed warm-up is not fatal
        info.warm_up_error = f"{type(err).__name__}: {_one_line(err)}"
    info.warm_up_s = time.perf_counter() - t0
    return info


def _plain(result: Any) -> dict[str, Any]:
    """A result object as a dict of its fields (pickles without the engine's classes)."""
    if dataclasses.is_dataclass(result):
        return {f.name: getattr(result, f.name) for f in dataclasses.fields(result)}
    return dict(vars(result))


class InlineEngine:
    """A registrar called in the caller's thread, behind the interface of EngineProcess."""

    def __init__(self, registrar: Any) -> None:
        self.registrar = registrar
        self.info = EngineInfo()
        self.restarts = 0

    def start(self) -> EngineInfo:
        self.info = _warm_up(self.registrar)
        return self.info

    def register(self, source: np.ndarray, target: np.ndarray, update: tuple[Any, Any] | None
                 = None) -> Any:
        """Register (N, 3) source onto (M, 3) target; ``update`` = new (preprocess, engine)
        settings applied first. Raises what the registrar raises."""
        if update is not None:
            self.registrar.update(preprocess=update[0], engine=update[1])
        return self.registrar.register(source, target)

    def close(self, timeout: float = 5.0) -> None:
        pass


class EngineProcess:
    """The engine in a child process; one request at a time (the node's worker thread).

    Args:
        preprocess, engine: the settings the engine starts with.
        factory: "module:function" building the registrar from (preprocess, engine) in the
            child. Tests pass a stand-in; it must be importable there (spawn).
        env: environment defaults for the child (``THREAD_ENV`` by default): a variable the
            user's environment sets already is left alone.
    """

    def __init__(self, preprocess: Any, engine: Any, factory: str = ENGINE_FACTORY,
                 env: Mapping[str, str] | None = None) -> None:
        self.settings = (preprocess, engine)
        self.factory = factory
        self.env = dict(THREAD_ENV if env is None else env)
        self.info = EngineInfo()
        self.restarts = 0
        self._lock = threading.Lock()      # start / close against each other
        self._proc: subprocess.Popen | None = None
        self._conn: Connection | None = None
        self._buffer: mmap.mmap | None = None
        self._capacity = 0                 # points (rows of 3 float32) the buffer holds
        self._closed = False

    # -- life cycle -----------------------------------------------------------------------
    def _child_env(self) -> dict[str, str]:
        env = dict(os.environ)
        for key, value in self.env.items():
            env.setdefault(key, value)         # read by torch / OpenMP when they load
        # The child imports this very copy of cegc_ros (a checkout may shadow an install).
        root = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
        return env

    def start(self) -> EngineInfo:
        """Start the child and wait until it is warmed up; EngineStartError with the reason."""
        with self._lock:
            if self._closed:
                raise EngineStartError("the engine was closed")
            ours, theirs = socket.socketpair()
            try:
                proc = subprocess.Popen(
                    [sys.executable, "-c", _CHILD_BOOT, str(theirs.fileno())],
                    pass_fds=(theirs.fileno(),), env=self._child_env(), stdin=subprocess.DEVNULL)
            except OSError as err:
                ours.close()
                raise EngineStartError(f"cannot start the engine process: {err}") from err
            finally:
                theirs.close()
            conn = Connection(ours.detach())
            self._proc, self._conn = proc, conn
            self._buffer, self._capacity = None, 0
        try:
            conn.send(("start", self.factory, *self.settings, list(sys.path)))
            while not conn.poll(0.2):
                if proc.poll() is not None and not conn.poll(0):   # gone, and said nothing
                    raise EOFError
            reply = conn.recv()
        except (EOFError, OSError) as err:
            self._stop_child(0.0)
            raise EngineStartError(f"the engine process exited with code {proc.poll()} while "
                                   "starting") from err
        if reply[0] == "error":
            self._stop_child(5.0)
            raise EngineStartError(f"{reply[1]}: {reply[2]}")
        self.info = reply[1]
        self.info.pid = proc.pid
        return self.info

    def alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def restart(self) -> EngineInfo:
        """Start a new child after one died (the settings of the last request carry over)."""
        self._stop_child(0.0)
        self.restarts += 1
        return self.start()

    def close(self, timeout: float = 5.0) -> None:
        """Stop the child: asked politely, then terminated after ``timeout`` s, then killed.

        Safe from another thread while a request is in flight: that request ends with
        EngineDied.
        """
        with self._lock:
            self._closed = True
        self._stop_child(timeout)

    def _stop_child(self, timeout: float) -> None:
        with self._lock:
            proc, conn = self._proc, self._conn
            self._proc = self._conn = None
        if proc is None or conn is None:
            return
        if timeout > 0 and proc.poll() is None:
            try:
                conn.send(("stop",))
                proc.wait(timeout)
            except (OSError, ValueError, subprocess.TimeoutExpired):
                pass
        for end in (proc.terminate, proc.kill):
            if proc.poll() is None:
                end()
                try:
                    proc.wait(2.0)
                except subprocess.TimeoutExpired:
                    pass
        conn.close()

    # -- work -----------------------------------------------------------------------------
    def register(self, source: np.ndarray, target: np.ndarray, update: tuple[Any, Any] | None
                 = None) -> Any:
        """Register (N, 3) source onto (M, 3) target in the child.

        ``update``: new (preprocess, engine) settings, applied in the child before this pair.
        Returns the result's fields as attributes (a SimpleNamespace). Raises ValueError when
        the engine refused the input, EngineError when it raised anything else, EngineDied
        when the child ended (start it again with :meth:`restart`).
        """
        if update is not None:
            self.settings = update
        proc, conn = self._proc, self._conn
        if proc is None or conn is None or proc.poll() is not None:
            raise EngineDied("EngineDied", "the engine process is not running")
        n_src, n_tgt = len(source), len(target)
        try:
            self._ensure_capacity(conn, proc.pid, n_src + n_tgt)
            rows = np.ndarray((n_src + n_tgt, 3), np.float32, buffer=self._buffer)  # (N+M, 3)
            rows[:n_src] = source
            rows[n_src:] = target
            del rows
            conn.send(("register", n_src, n_tgt, update))
            reply = conn.recv()
        except (EOFError, OSError) as err:
            try:
                code = proc.wait(1.0)
            except subprocess.TimeoutExpired:
                code = None
            raise EngineDied("EngineDied", "the engine process ended while registering"
                             + (f" (exit code {code})" if code is not None else "")) from err
        if reply[0] == "ok":
            return types.SimpleNamespace(**reply[1])
        _, kind, message, refused = reply
        if refused:
            raise ValueError(message)
        raise EngineError(kind, message)

    def _ensure_capacity(self, conn: Any, pid: int, points: int) -> None:
        if self._buffer is not None and points <= self._capacity:
            return
        capacity = max(points, int(self._capacity * 1.5), 65536)
        size = capacity * 12                              # float32 x, y, z
        fd = os.memfd_create("cegc_clouds", os.MFD_CLOEXEC)
        try:
            os.ftruncate(fd, size)
            buffer = mmap.mmap(fd, size)
            conn.send(("buffer", size))
            reduction.send_handle(conn, fd, pid)
        finally:
            os.close(fd)
        self._buffer, self._capacity = buffer, capacity


def _child_main(conn: Connection) -> None:
    """The engine process: build the registrar, warm up, then answer requests until EOF."""
    # Ctrl-C in a terminal reaches the whole process group; the node decides when the engine
    # stops (it closes the socket), so the child ignores SIGINT instead of dying mid-pair.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        _, factory, preprocess, engine, path = conn.recv()
    except (EOFError, OSError):
        return
    try:
        sys.path[:] = [p for p in path if p not in sys.path] + sys.path   # the caller's modules
        registrar = _resolve(factory)(preprocess, engine)
        info = _warm_up(registrar)
    except BaseException as err:  # noqa: BLE001  reported to the node, which exits with it
        conn.send(("error", type(err).__name__, _one_line(err)))
        return
    conn.send(("ready", info))
    buffer = None
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg[0] == "stop":
            return
        if msg[0] == "buffer":
            fd = reduction.recv_handle(conn)
            buffer = mmap.mmap(fd, msg[1])
            os.close(fd)
            continue
        _, n_src, n_tgt, update = msg
        try:
            if update is not None:
                registrar.update(preprocess=update[0], engine=update[1])
            rows = np.ndarray((n_src + n_tgt, 3), np.float32, buffer=buffer)  # (N+M, 3)
            result = registrar.register(rows[:n_src], rows[n_src:])
            del rows
            reply: tuple[Any, ...] = ("ok", _plain(result))
        except Exception as err:  # noqa: BLE001  one bad pair must not end the engine
            reply = ("error", type(err).__name__, _one_line(err), isinstance(err, ValueError))
        try:
            conn.send(reply)
        except (OSError, ValueError):
            return


#: How the child starts: ``python -c`` with the working directory taken off sys.path first, so
#: that a node started from a source checkout runs the engine it imported itself (the
#: installed one), not the checkout's copy that ``python -m`` would find in the cwd.
_CHILD_BOOT = ("import sys; sys.path.pop(0); from multiprocessing.connection import Connection; "
               "from cegc_ros.node.engine_process import _child_main; "
               "_child_main(Connection(int(sys.argv[1])))")


if __name__ == "__main__":
    # Run the module's real copy (not this __main__ one), so that what the child pickles
    # (EngineInfo) names cegc_ros.node.engine_process, which the node can unpickle.
    from cegc_ros.node.engine_process import _child_main as child_main
    child_main(Connection(int(sys.argv[1])))
