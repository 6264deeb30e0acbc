"""Robot and edge on cores of their own (``experiment detect --edge-apart``): on a 2-core host the
robot's local detections otherwise take CPU from the edge's detector, which a separate edge
computer would not lose. Real processes, pinned by taskset; every thread checked in /proc."""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import pytest

from tests.helpers import wait_for
from zoffload.lab.runner import Spawned, edge_apart_cores
from zoffload.runtime.session import free_tcp_port

pytestmark = pytest.mark.system

CORES = sorted(os.sched_getaffinity(0))
needs_two = pytest.mark.skipif(len(CORES) < 2 or shutil.which("taskset") is None,
                               reason="needs two cores to split and taskset (util-linux)")


def _threads_cores(pid: int) -> dict[int, str]:
    """Each thread of ``pid``: the cores it may run on (``Cpus_allowed_list``)."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            status = (task / "status").read_text()
        except OSError:  # the thread ended meanwhile
            continue
        out[int(task.name)] = next(line.split(":", 1)[1].strip() for line in status.splitlines()
                                   if line.startswith("Cpus_allowed_list"))
    return out


def test_the_edge_gets_the_highest_core_and_the_others_the_rest() -> None:
    assert edge_apart_cores({0, 1}) == {"edge": {1}, "robot": {0}, "link": {0}}
    assert edge_apart_cores({2, 5, 7}) == {"edge": {7}, "robot": {2, 5}, "link": {2, 5}}
    assert edge_apart_cores({3}) == {}  # nothing to split


@needs_two
def test_a_spawned_process_and_every_thread_it_makes_stay_on_its_cores(tmp_path: Path) -> None:
    """An edge (a real zoffload process: Zenoh's runtime threads, made after it started) on the
    highest core: every one of its threads may run there only."""
    last = CORES[-1]
    listen = f"tcp/127.0.0.1:{free_tcp_port()}"
    p = Spawned("edge", ["edge", "--no-multicast-scouting", "--no-shm", "-l", listen, "--no-mapping"],
                tmp_path / "edge.log", {last})
    try:
        wait_for(lambda: len(_threads_cores(p.proc.pid)) > 4, 60, "the edge's threads")
        time.sleep(0.5)
        cores = _threads_cores(p.proc.pid)
        assert len(cores) > 4 and set(cores.values()) == {str(last)}, cores
    finally:
        p.stop()
    free = Spawned("link", ["link", "--help"], tmp_path / "help.log")  # without cores: as before
    assert free.proc.wait(30) == 0 and free.stop() == 0


@needs_two
@pytest.mark.realdata
def test_a_detection_run_with_the_edge_apart_says_so(tmp_path: Path, coco_dir: Path,
                                                      models_dir: Path) -> None:
    """A short run of the detection experiment with ``edge_apart``: every frame in one bucket, the
    cores in its results and its settings (the report keeps such runs in their own rows)."""
    from zoffload.lab.detect_experiment import DetectExperiment, run_detect_experiment
    from zoffload.lab.eval.detect_report import settings_note

    row = run_detect_experiment(DetectExperiment(trace="none", strategy="dispatch", out=str(tmp_path / "run"),
                                                 images=f"coco-clips:{coco_dir}", max_frames=60,
                                                 cpu_quota=None, edge_apart=True))
    saved = json.loads((tmp_path / "run" / "results.json").read_text())
    assert saved["cpus"] == {"edge": [CORES[-1]], "robot": CORES[:-1], "link": CORES[:-1]}
    assert saved["edge_apart"] is True and settings_note(saved) == ""  # the default
    assert settings_note({k: v for k, v in saved.items() if k != "edge_apart"}) == " (edge_apart False)"
    assert row["balanced"] and row["balance"]["frames_in"] >= 50, row.get("balance")
