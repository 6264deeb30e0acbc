"""Scan sources: KITTI .bin folders, PCD/PLY folders, and the built-in simulator."""

from zoffload.sources.base import ScanFrame, ScanSource, ScanSourceError, open_scan_source

__all__ = ["ScanFrame", "ScanSource", "ScanSourceError", "open_scan_source"]
