"""Sequential mode without ROS: keyframe odometry over one stream of clouds.

- :mod:`cegc_ros.sequential.odometry`: :class:`KeyframeOdometry` (feed stamp + cloud, get a
  :class:`FrameResult`), its counters and path.
- :mod:`cegc_ros.sequential.icp`: point-to-plane ICP on voxelized clouds, fitness, overlap,
  covariance.
- :mod:`cegc_ros.sequential.se3`: constant-velocity prediction and covariance chaining.
"""

from .odometry import FrameResult, GlobalRegistration, KeyframeOdometry, OdometryStats

__all__ = ["FrameResult", "GlobalRegistration", "KeyframeOdometry", "OdometryStats"]
