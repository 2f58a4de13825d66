"""Conversions between ROS 2 messages and numpy: pure numpy plus message types.

No node, no torch: usable from the node, from bag tools and from tests alike.

- :mod:`msg_adapters.point_cloud2`: ``cloud_to_xyz`` (PointCloud2 -> (N, 3) float32),
  ``xyz_to_cloud`` ((N, 3) + extra float32 fields -> PointCloud2).
- :mod:`msg_adapters.point_cloud2_cdr`: ``parse_point_cloud2`` (a serialized PointCloud2, as a
  ``raw=True`` subscription delivers it -> header, layout and a zero-copy view of the points,
  which ``cloud_to_xyz`` reads); :class:`~msg_adapters.point_cloud2_cdr.CdrError` for bytes
  that are not one. No message import.
- :mod:`msg_adapters.pose`: ``matrix_to_pose``, ``pose_to_matrix``, ``pose_stamped``,
  ``pose_with_covariance_stamped``.
- :mod:`msg_adapters.markers`: correspondence lines and overlap points as a MarkerArray.
- :mod:`msg_adapters.transform`: 4x4 <-> Transform, ``transform_stamped`` for /tf.
- :mod:`msg_adapters.nav`: ``odometry`` (nav_msgs/Odometry), ``path`` (nav_msgs/Path).

Malformed input raises :class:`ValueError` with a message naming the problem.
"""
