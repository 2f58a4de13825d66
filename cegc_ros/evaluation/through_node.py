"""The CEGC rows run inside ``register_node``: a subprocess per row, fed by replaying a pair bag
over DDS in lockstep (``cegc-eval BAG --through-node``); latency is then the node's answer time.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cegc_ros.evaluation import EvalError, EvalPair, Outcome
from cegc_ros.evaluation.methods import (
    CEGC_METHODS,
    default_params_file,
    node_arguments,
)

REPO_ROOT = Path(__file__).resolve().parents[2]


def dds_environment(env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (default os.environ) with DDS kept on this machine and a ROS domain of its own.

    A non-zero ROS_DOMAIN_ID already chosen by the caller (a test session, a user who wants
    to watch the replay) is kept; otherwise one in 1..100 is derived from the pid, never 0, the
    shared default domain where a user's own nodes would hear the replay.
    """
    import os

    env = dict(os.environ if env is None else env)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_LOCALHOST_ONLY", None)
    if not env.get("ROS_DOMAIN_ID") or env["ROS_DOMAIN_ID"] == "0":
        env["ROS_DOMAIN_ID"] = str(1 + os.getpid() % 100)
    ament = [p for p in env.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    if sys.prefix not in ament:
        env["AMENT_PREFIX_PATH"] = os.pathsep.join([sys.prefix, *ament])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO_ROOT), env.get("PYTHONPATH", "")) if p)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def run_through_node(bag: str | Path, pairs: Sequence[EvalPair], methods: Sequence[str], *,
                     params_file: str | Path | None = None, checkpoint: str | None = None,
                     progress: bool = True, startup_timeout: float = 180.0,
                     pair_timeout: float = 120.0, log_dir: str | Path | None = None
                     ) -> dict[str, list[Outcome]]:
    """CEGC outcomes from a ``register_node`` subprocess fed by replaying ``bag`` over DDS.

    One node per CEGC row (its overrides as ``-p`` arguments), started with ``params_file`` plus
    ``input.reliable:=true`` (replay QoS), replayed in lockstep so no pair is dropped. A pair
    the node answered with no pose (rejected, invalid) is a failure scored with identity.
    Latency is the node's answer time: publishing the pair's later cloud to receiving its pose.
    """
    import os
    import subprocess
    import tempfile
    import threading

    from cegc_ros.replay import replay_bag

    env = dds_environment()
    os.environ.update({k: env[k] for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID",
                                           "AMENT_PREFIX_PATH")})
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    params = Path(params_file) if params_file else default_params_file()
    if not params.is_file():
        raise EvalError(f"register_node parameter file {params} not found")
    logs = Path(log_dir) if log_dir else Path(tempfile.mkdtemp(prefix="cegc_eval_node_"))
    logs.mkdir(parents=True, exist_ok=True)
    out: dict[str, list[Outcome]] = {}
    for method in methods:
        if method not in CEGC_METHODS:
            raise EvalError(f"{method} does not run in register_node")
        cmd = [sys.executable, "-m", "cegc_ros.node", "--ros-args", "--params-file", str(params),
               "-p", "input.reliable:=true", *node_arguments(method)]
        if checkpoint:
            cmd += ["-p", f"engine.checkpoint:={Path(checkpoint).resolve()}"]
        log_path = logs / f"register_node_{method.replace('+', '_')}.log"
        with open(log_path, "w") as log:
            proc = subprocess.Popen(cmd, env=env, cwd=str(REPO_ROOT), stdout=log,
                                    stderr=subprocess.STDOUT)
        box: dict[str, Any] = {}

        def replay(box: dict[str, Any] = box) -> None:
            try:
                box["result"] = replay_bag(bag, lockstep=True, connect_timeout=startup_timeout,
                                           pair_timeout=pair_timeout, progress=progress)
            except Exception as err:  # noqa: BLE001 - re-raised in the caller's thread
                box["error"] = err

        worker = threading.Thread(target=replay, daemon=True)
        worker.start()
        try:
            while worker.is_alive():
                worker.join(0.2)
                if proc.poll() is not None and worker.is_alive():
                    tail = log_path.read_text().strip().splitlines()[-1:] or ["(no output)"]
                    raise EvalError(f"register_node exited with code {proc.returncode} before "
                                    f"the replay ended: {tail[0]}")
        finally:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        if "error" in box:
            raise EvalError(f"replay into register_node failed: {box['error']}") from box["error"]
        by_stamp = {r.stamp_ns: r for r in box["result"].records}
        outs = []
        for p in pairs:
            rec = by_stamp.get(int(p.info.get("stamp_ns", -1)))
            fitness = math.nan if rec is None or rec.fitness is None else rec.fitness
            ambiguity = math.nan if rec is None or rec.ambiguity is None else rec.ambiguity
            if rec is None or rec.T_est is None:
                why = (f"register_node rejected the pair ({rec.rejected})" if rec and rec.rejected
                       else "register_node published no pose (lost)")
                outs.append(Outcome(method, p.pair_id, None, False, True, why, fitness, math.nan,
                                    ambiguity))
            else:
                outs.append(Outcome(method, p.pair_id, np.asarray(rec.T_est, np.float64), True,
                                    False, "", fitness, float(rec.latency_s), ambiguity))
        out[method] = outs
    return out
