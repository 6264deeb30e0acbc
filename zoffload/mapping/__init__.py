"""Mapping algorithms: the voxel grid, the KISS-ICP mapper (edge, and robot when alone), map export."""
