"""``register_lifecycle_node``: register_node as a managed (lifecycle) node.

The node (:class:`cegc_ros.node.lifecycle_node.RegisterLifecycleNode`, named ``register_node``)
starts unconfigured; a lifecycle manager (or ``ros2 lifecycle set /register_node configure``)
drives it. Arguments, parameters and topics are register_node's; docs/node.md, "Managed node".
This module imports no rclpy until the node is built, so ``--help`` is instant.
"""

from __future__ import annotations

from collections.abc import Sequence

from cegc_ros.node.main import main as _main


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of ``register_lifecycle_node``; returns the process exit code."""
    return _main(args, managed=True)


if __name__ == "__main__":
    raise SystemExit(main())
