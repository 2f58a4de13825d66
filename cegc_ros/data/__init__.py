"""Synthetic 7Scenes-style / fragment / object pairs and rosbag2 storage."""
