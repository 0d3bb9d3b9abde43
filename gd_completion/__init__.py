"""Graph-Guided Deformation completion of lidar vehicle scans for ROS 2."""

__version__ = "0.1.0"
