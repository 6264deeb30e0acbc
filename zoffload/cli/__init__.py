"""Command line: argument parsing only; flags are built from the settings models."""

from zoffload.cli.main import edge_main, main, robot_main

__all__ = ["edge_main", "main", "robot_main"]
