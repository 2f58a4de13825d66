"""``register_node``'s entry point: arguments, start-up errors, the spin loop, shutdown."""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Sequence
from typing import Any

from cegc_ros.node.params import NODE_NAME, params_yaml, usage


def fatal(text: str) -> int:
    """Print the one start-up error line and return the exit code 1."""
    text = " ".join(str(text).split())
    print(f"[FATAL] [{NODE_NAME}]: cannot start: {text}", file=sys.stderr, flush=True)
    return 1


def params_file_problem(argv: Sequence[str]) -> str | None:
    """Why a ``--params-file`` of ``argv`` cannot be read, or None.

    rcl would also refuse it, but with a two-line log and a C source location; this names
    the file and the problem on the one [FATAL] line.
    """
    import yaml

    ros = list(argv[argv.index("--ros-args"):]) if "--ros-args" in argv else []
    files = [ros[i + 1] for i, a in enumerate(ros[:-1]) if a == "--params-file"]
    for path in files:
        try:
            with open(path) as f:
                yaml.safe_load(f)
        except OSError as err:
            return f"params file {path}: {err.strerror or err}"
        except yaml.YAMLError as err:
            where = getattr(err, "problem_mark", None)
            line = f" (line {where.line + 1})" if where is not None else ""
            return f"params file {path} is not valid YAML{line}: {getattr(err, 'problem', err)}"
    return None


def main(args: Sequence[str] | None = None, engine_factory: Any = None,
         managed: bool = False) -> int:
    """Entry point of ``register_node`` (``managed``: ``register_lifecycle_node``); returns the
    process exit code.

    Start-up problems (a parameter value, the params file, the checkpoint, the device) end it
    with one ``[FATAL]`` line and exit code 1; arguments it does not know, with exit code 2.
    ``engine_factory`` replaces the engine process (benchmarks compare an in-process engine).
    The managed node starts unconfigured (its start-up problems fail the configure transition)
    and the process ends once it is shut down.
    """
    argv = list(sys.argv if args is None else args)
    own = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if any(a in ("-h", "--help") for a in argv[1:]):   # also after --ros-args (rclpy has no --help)
        if managed:
            print("register_lifecycle_node: register_node as a managed (lifecycle) node; it "
                  "starts unconfigured\n(configure, activate, deactivate, cleanup, shutdown: "
                  "docs/node.md, 'Managed node').\n")
        print(usage())
        return 0
    if "--print-params" in own:
        print(params_yaml(), end="")
        return 0
    if own:
        print(f"{NODE_NAME}: error: unknown argument {own[0]!r} (ROS arguments go after "
              "--ros-args; see --help)", file=sys.stderr)
        return 2

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from cegc_ros.node.engine_process import EngineStartError
    from cegc_ros.node.params import ParameterError

    problem = params_file_problem(argv)
    if problem:
        return fatal(problem)
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as err:  # noqa: BLE001  rcl's errors: a bad --ros-args, params file
        return fatal(f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}")
    stop = threading.Event()

    def request_stop(signum: int, _frame: Any) -> None:
        stop.set()

    previous = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    node = executor = None
    try:
        if managed:
            from cegc_ros.node.lifecycle_node import RegisterLifecycleNode as node_class
        else:
            from cegc_ros.node.ros_node import RegisterNode as node_class
        try:
            node = node_class(engine_factory)
        except ParameterError as err:
            return fatal(f"invalid parameter: {err}")
        except EngineStartError as err:
            return fatal(str(err))
        except Exception as err:  # noqa: BLE001  e.g. rclpy refusing a use_sim_time override
            return fatal(f"{type(err).__name__}: {err}")
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok() and not getattr(node, "finalized", False):
            try:
                executor.spin_once(timeout_sec=0.1)
            except ExternalShutdownException:
                break
            except Exception as err:  # noqa: BLE001  e.g. a message that fails to deserialize
                node.take_error(err)
        node.get_logger().info("shutting down")
        if not node.close(timeout=10.0):
            node.get_logger().warning("the registration in progress did not finish in time")
        return 0
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        for s, h in previous.items():
            signal.signal(s, h)
