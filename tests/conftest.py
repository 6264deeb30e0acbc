"""Shared fixtures: where the real data lives, and free loopback ports."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

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


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """On two workers (`pytest -n 2`, pytest-xdist; README, Tests, says why not by default), in two
    phases. First the core and daemon tests, handed out one at a time to whichever worker is free;
    then the system tests, one after another on one worker, after the others (overlapping at most
    the last two or three daemon tests still on the other worker): they start daemons, routers,
    detectors and network namespaces, assert on timing and mostly wait, and beside other tests on a
    two-core host some failed (README, Tests). (xdist orders its scopes largest first, which
    started the system tests at once beside the rest; its own `--dist loadgroup` renames node ids
    to group them, which pytest 9.2 no longer lets it do.)"""
    if config.getoption("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    config.option.loadscopereorder = False  # collection order: tests/system comes last

    class SystemTestsLast(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return "tests/system" if nodeid.startswith("tests/system/") else nodeid

    return SystemTestsLast(config, log)


_EXIT = {"status": 0}


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    _EXIT["status"] = int(exitstatus)


def pytest_unconfigure(config: pytest.Config) -> None:
    """A test that leaves a Zenoh session open (say, after a failed assertion) leaves Zenoh's
    callback thread behind, and the interpreter would wait for it for ever: name the threads and
    leave with pytest's own exit status instead of hanging CI."""
    import threading
    import time

    deadline = time.monotonic() + 10
    lingering = [t for t in threading.enumerate() if not t.daemon and t is not threading.main_thread()]
    for t in lingering:
        t.join(max(0.0, deadline - time.monotonic()))
    lingering = [t for t in lingering if t.is_alive()]
    if lingering:
        print(f"\nconftest: {len(lingering)} non-daemon thread(s) still running at exit "
              f"({', '.join(t.name for t in lingering)}): a test left a session open; exiting anyway",
              flush=True)
        os._exit(_EXIT["status"])
