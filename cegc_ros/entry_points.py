"""The console scripts of setup.py: each preloads jemalloc (see :mod:`cegc_ros.allocator`),
then runs its tool's ``main``. ``ros2 run cegc_ros register_node`` runs one of these too, so a
node started by ROS gets the same allocator as one started by the bootstrap."""

from __future__ import annotations

import importlib

from cegc_ros.allocator import apply_thread_environment, reexec_with_allocator

#: console script -> module whose ``main()`` it runs (setup.py builds its entry points from this).
SCRIPTS = {
    "register_node": "cegc_ros.node",
    "register_lifecycle_node": "cegc_ros.node.lifecycle_main",
    "cegc-register": "cegc_ros.tools.register_files",
    "cegc-demo": "cegc_ros.tools.demo",
    "cegc-eval": "cegc_ros.tools.evaluate",
    "cegc-eval-seq": "cegc_ros.tools.evaluate_seq",
    "cegc-make-bag": "cegc_ros.tools.make_bag",
    "cegc-make-pairs": "cegc_ros.tools.make_pairs",
    "cegc-replay": "cegc_ros.tools.replay",
    "cegc-train": "cegc_ros.tools.train",
}


def _run(script: str) -> int:
    apply_thread_environment()                # before torch loads OpenMP (also without jemalloc)
    reexec_with_allocator()
    return importlib.import_module(SCRIPTS[script]).main()


def register_node() -> int:
    return _run("register_node")


def register_lifecycle_node() -> int:
    return _run("register_lifecycle_node")


def cegc_register() -> int:
    return _run("cegc-register")


def cegc_demo() -> int:
    return _run("cegc-demo")


def cegc_eval() -> int:
    return _run("cegc-eval")


def cegc_eval_seq() -> int:
    return _run("cegc-eval-seq")


def cegc_make_bag() -> int:
    return _run("cegc-make-bag")


def cegc_make_pairs() -> int:
    return _run("cegc-make-pairs")


def cegc_replay() -> int:
    return _run("cegc-replay")


def cegc_train() -> int:
    return _run("cegc-train")
