"""Shared helpers of the node tests: DDS isolation, cloud messages and an output probe.

Importing this module pins the process to a LOCALHOST-only DDS domain of its own (the one
the caller set, e.g. the bootstrap, else derived from the pid) before anything calls
``rclpy.init``; child processes get the same environment
through :func:`ros_env`.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

# The caller's domain when it chose one (the bootstrap prints the one it chose), else one from
# the pid; domain 0, every ROS install's default, is never used.
_GIVEN = os.environ.get("ROS_DOMAIN_ID", "")
DOMAIN_ID = int(_GIVEN) if _GIVEN.isdigit() and _GIVEN != "0" else 1 + os.getpid() % 100
os.environ["ROS_DOMAIN_ID"] = str(DOMAIN_ID)
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.pop("ROS_LOCALHOST_ONLY", None)
if sys.prefix not in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
    os.environ["AMENT_PREFIX_PATH"] = os.pathsep.join(
        p for p in (sys.prefix, os.environ.get("AMENT_PREFIX_PATH", "")) if p)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def ros_env(**extra: str) -> dict[str, str]:
    """The environment for a child process: same DDS domain, repo importable."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (REPO, env.get("PYTHONPATH", "")) if p)
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra)
    return env


def cloud(xyz: np.ndarray, frame: str, stamp_ns: int) -> Any:
    """A PointCloud2 of float32 x, y, z."""
    from std_msgs.msg import Header

    from msg_adapters.nav import time_from_ns
    from msg_adapters.point_cloud2 import xyz_to_cloud

    header = Header(stamp=time_from_ns(stamp_ns), frame_id=frame)
    return xyz_to_cloud(np.asarray(xyz, np.float32), header)


def stamp_of(msg: Any) -> int:
    """The header stamp of a message, in nanoseconds."""
    from msg_adapters.nav import time_to_ns
    return time_to_ns(msg.header.stamp)


class OutputRecorder:
    """Messages received per output name (callbacks from any thread) and the newest
    diagnostics status of the node under test (``status_name``: "<full name>: registration")."""

    def __init__(self, status_name: str) -> None:
        self.status_name = status_name
        self.lock = threading.Lock()
        self.got: dict[str, list[Any]] = {}

    def keeper(self, name: str) -> Callable[[Any], None]:
        """A subscription callback that records into ``name``."""
        self.got[name] = []

        def cb(msg: Any) -> None:
            with self.lock:
                self.got[name].append(msg)
        return cb

    def outputs(self, name: str) -> list[Any]:
        with self.lock:
            return list(self.got[name])

    def by_stamp(self, name: str) -> dict[int, Any]:
        return {stamp_of(m): m for m in self.outputs(name)}

    def diagnostics(self) -> dict[str, str]:
        """Key-values of the newest diagnostics status of the node under test."""
        for arr in reversed(self.outputs("diagnostics")):
            for st in arr.status:
                if st.name == self.status_name:
                    return {kv.key: kv.value for kv in st.values}
        return {}


def make_probe(node_name: str = "register_node", namespace: str = "/",
               context: Any = None) -> Any:
    """A node that publishes the two inputs and records every output of the node under test."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    base = namespace.rstrip("/")
    status_name = f"{base}/{node_name}: registration"   # the node's fully qualified name

    class Probe(Node, OutputRecorder):
        def __init__(self) -> None:
            Node.__init__(self, "cegc_test_probe", context=context)
            OutputRecorder.__init__(self, status_name)
            qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
            self.pub = {s: self.create_publisher(PointCloud2, f"{base}/{s}_cloud", qos)
                        for s in ("source", "target")}
            outputs = {"pose": PoseStamped, "pose_with_covariance": PoseWithCovarianceStamped,
                       "source_overlap": PointCloud2, "target_overlap": PointCloud2,
                       "markers": MarkerArray, "quality": DiagnosticArray}
            for name, kind in outputs.items():
                self.create_subscription(kind, f"{base}/{node_name}/{name}",
                                         self.keeper(name), 50)
            self.create_subscription(DiagnosticArray, "/diagnostics", self.keeper("diagnostics"),
                                     50)

        def send(self, source: Any, target: Any) -> None:
            self.pub["source"].publish(source)
            self.pub["target"].publish(target)

        def connected(self) -> bool:
            return all(p.get_subscription_count() > 0 for p in self.pub.values()) and \
                self.count_publishers(f"{base}/{node_name}/pose") > 0

    return Probe()


def wait_for(predicate: Callable[[], bool], timeout: float, poll: float = 0.02) -> bool:
    """Poll ``predicate`` until true or ``timeout`` s pass; returns its last value."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(poll)
    return bool(predicate())


def call_idempotent(client: Any, request: Any, timeout: float, attempt: float = 15.0) -> Any:
    """The service's answer to ``request``, sent again every ``attempt`` s until one comes or
    ``timeout`` s pass (None). Only for requests that may be repeated (a query): a request sent
    just after discovery can go unanswered for good when the server has not yet matched the
    client's response reader (seen once in CI on a busy machine: get_state silent for 120 s)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        future = client.call_async(request)
        if wait_for(future.done, min(attempt, max(0.0, end - time.monotonic()))):
            return future.result()
        client.remove_pending_request(future)
    return None
