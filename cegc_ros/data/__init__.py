"""Synthetic registration data: procedural rooms and sensors, pair protocols, the pair cache
and rosbag2 storage (see docs/data.md)."""
