"""cegc_ros: CEGC partial point-cloud registration for ROS 2.

The package root imports nothing heavy, so that ``python3 -m cegc_ros.bootstrap`` runs on a
bare Python before any dependency is installed.
"""

__version__ = "0.1.0"
