"""Shared fixtures: where the real data lives, and free loopback ports."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("ZOFFLOAD_DATA", ROOT.parent / "shared" / "data"))
KITTI = DATA / "kitti360-hdl64" / "velodyne"
COCO = DATA / "coco-person-dev"
MODELS = DATA / "models"


@pytest.fixture(scope="session")
def kitti_dir() -> Path:
    if not KITTI.is_dir():
        pytest.skip(f"real KITTI-360 scans not found at {KITTI} (set ZOFFLOAD_DATA)")
    return KITTI


@pytest.fixture
def free_port() -> int:
    from zoffload.runtime.session import free_tcp_port

    return free_tcp_port()


@pytest.fixture(scope="session")
def coco_dir() -> Path:
    if not (COCO / "person_gt.json").is_file():
        pytest.skip(f"COCO person images not found at {COCO} (set ZOFFLOAD_DATA)")
    return COCO


@pytest.fixture(scope="session")
def models_dir() -> Path:
    if not (MODELS / "nanodet_m_320.onnx").is_file():
        pytest.skip(f"detector models not found at {MODELS} (set ZOFFLOAD_DATA)")
    return MODELS
