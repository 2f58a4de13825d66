"""Test-session setup shared by every test module.

Runs before any test module is imported, so before anything imports rclpy:
- the repository root goes first on ``sys.path`` (tests exercise the checkout, not an older
  installed copy);
- DDS stays on this machine (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) on a ROS domain of
  its own per pytest process (``ROS_DOMAIN_ID`` in 1..100 from the pid), unless the caller
  (e.g. the bootstrap) chose them already; child processes inherit both;
- ``AMENT_PREFIX_PATH`` includes this interpreter's prefix, where the message packages and
  the installed ``share/cegc_ros`` live.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]

if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
_ament = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
if sys.prefix not in _ament:
    os.environ["AMENT_PREFIX_PATH"] = os.pathsep.join([sys.prefix, *_ament])


import pytest  # noqa: E402  (after the environment above, which must come first)


@pytest.fixture(scope="session")
def val_cache(tmp_path_factory):
    """A validation pair cache of one Kinect room: 2 different-view pairs and 1 copy pair
    (tools/select_weights, tools/estimator_study)."""
    from cegc_ros.data import pair_cache as PC
    from cegc_ros.data import splits, views
    cfg = views.ViewConfig(fragments=4, pairs=3, copy_pairs=1, max_points=2000)
    rooms = [views.make_room_pairs(splits.room_seed("val", 2), "kinect", cfg)]
    root = tmp_path_factory.mktemp("val")
    PC.write_shard(root / PC.shard_name(0, 1), rooms, {"split": "val"})
    return root
