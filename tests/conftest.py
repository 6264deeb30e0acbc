"""Shared fixtures: where the real data lives, and free loopback ports."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("ZOFFLOAD_DATA", ROOT.parent / "shared" / "data"))
KITTI = DATA / "kitti360-hdl64" / "velodyne"


@pytest.fixture(scope="session")
def kitti_dir() -> Path:
    if not KITTI.is_dir():
        pytest.skip(f"real KITTI-360 scans not found at {KITTI} (set ZOFFLOAD_DATA)")
    return KITTI


@pytest.fixture
def free_port() -> int:
    from zoffload.net import free_tcp_port

    return free_tcp_port()
