"""register_node: the ROS 2 node that registers two PointCloud2 streams with CEGC.

A thin layer over :class:`cegc_ros.engine.Registrar`: parameters -> pair ``source_cloud`` with
``target_cloud`` by stamp -> ``cloud_to_xyz`` -> engine (in a process of its own) -> messages.

With ``input.mode: sequential`` it reads one ``cloud`` stream into keyframe odometry instead
(``sequential_mode``; docs/sequential.md): ``~/odometry``, ``~/path`` and /tf besides the outputs
below, each cloud against its keyframe.

Topics (relative names, so namespaces and remapping work):

  in   source_cloud, target_cloud        sensor_msgs/PointCloud2 (sequential mode: cloud)
  out  ~/pose                            geometry_msgs/PoseStamped (T_target_source, target frame)
       ~/pose_with_covariance            geometry_msgs/PoseWithCovarianceStamped
       ~/source_overlap, ~/target_overlap sensor_msgs/PointCloud2 (x, y, z, overlap), own frames
       ~/markers                         visualization_msgs/MarkerArray (target frame)
       ~/quality                         diagnostic_msgs/DiagnosticArray, one per finished pair
                                         (sequential mode: per cloud), as its pose's header:
                                         published or why not, fitness, ambiguity (sequential:
                                         also how registered, keyframe)
       /diagnostics                      diagnostic_msgs/DiagnosticArray, status
                                         '<node's fully qualified name>: registration'

Every output of a pair carries the source cloud's stamp. Bad input is logged (throttled per
kind), counted on /diagnostics and skipped; a start-up problem (parameter, checkpoint) stops
the node with one ``[FATAL]`` line and exit code 1. docs/node.md has the details.

Modules: ``params`` (parameters from cegc_ros.config), ``support`` (mailbox, throttled log),
``stats`` (counters), ``pairs_mode`` (the pairing mode), ``sequential_mode`` (keyframe
odometry), ``engine_process`` (the engine in a child process), ``worker`` (the thread that
feeds it), ``ros_node`` (rclpy), ``main``; ``lifecycle_node`` and ``lifecycle_main`` (the
managed node, ``register_lifecycle_node``). This package imports no rclpy and no torch until
a node is built, so ``--help`` is instant.
"""

from __future__ import annotations

from typing import Any

from cegc_ros.node.main import main
from cegc_ros.node.params import (
    ENGINE_SECTIONS,
    NODE_NAME,
    SECTIONS,
    ParameterError,
    ParamSpec,
    check_value,
    param_specs,
    params_yaml,
    usage,
)
from cegc_ros.node.stats import REJECT_REASONS, Rejected
from cegc_ros.node.support import Mailbox, ThrottledLog, percentiles_ms, thin

__all__ = ["ENGINE_SECTIONS", "NODE_NAME", "REJECT_REASONS", "SECTIONS", "Mailbox",
           "ParamSpec", "ParameterError", "Rejected", "ThrottledLog", "check_value", "main",
           "node_class", "param_specs", "params_yaml", "percentiles_ms", "thin",
           "usage"]


def node_class() -> Any:
    """The RegisterNode class (imported on first use so that --help needs no rclpy)."""
    from cegc_ros.node.ros_node import RegisterNode
    return RegisterNode
