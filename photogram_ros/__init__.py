"""photogram_ros: onboard photogrammetric mapping for drones on ROS 2."""

__version__ = '0.1.0'
