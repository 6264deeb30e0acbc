"""Scan sources: folders of .bin (any declared column layout), PCD and PLY scans, ROS 2 topics and
bags, and the built-in simulator."""

from zoffload.sources.base import ScanFrame, ScanSource, ScanSourceError, open_scan_source

__all__ = ["ScanFrame", "ScanSource", "ScanSourceError", "open_scan_source"]
