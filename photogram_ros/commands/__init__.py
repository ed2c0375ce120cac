"""Subcommands of `photogram-ros` (see photogram_ros/cli.py)."""
