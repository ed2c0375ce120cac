"""Stages: what a node does besides ROS, with plain inputs and outputs.

A stage takes what its node receives (fixes, keyframes, attitudes, pair clouds) through plain methods
and hands out plain results (poses, clouds, JSON documents, diagnostics keys and problems with their
levels) through the sinks it is given; its node subscribes, converts the messages (msgs.py), calls and
publishes. Stages compose core/ (never ROS) and io/ (the map on disk, control and mission files), which
core/ may not import: that is why they are a package of their own. Tests and offline commands drive
them without rclpy.
"""
