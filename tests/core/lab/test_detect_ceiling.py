"""The asynchronous-AP ceiling: every frame detected, scored some frames late."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from zoffload.lab import detect_ceiling
from zoffload.lab.detect_ceiling import late_ap


def test_a_moving_person_found_on_every_frame_scores_less_the_later_it_is_scored() -> None:
    """A box 10 px wide moving 3 px a frame: found exactly, it is perfect on time, still matched
    (IoU 0.54) one frame late, missed from two frames late on (IoU 0.25)."""
    def gt(i: int) -> np.ndarray:
        return np.array([[3.0 * i, 0, 3.0 * i + 10, 10]], np.float32)

    dets = [(gt(i), np.array([0.9], np.float32)) for i in range(20)]
    aps = [late_ap(dets, gt, k) for k in range(3)]
    assert aps[0] == pytest.approx(100.0) and aps[1] == pytest.approx(100.0)
    # two late: only the last two frames (scored against the last frame's truth) still match
    assert aps[2] < 15.0


def test_the_ceiling_table_of_real_clips(coco_dir: Path, models_dir: Path, tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    assert detect_ceiling.main(["--images", f"coco-clips:{coco_dir}@tune", "--frames", "40", "--max-lag", "2",
                                "--models", "nanodet-m", "--cache", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| nanodet-m |"))
    aps = [float(x) for x in row.strip("| \n").split("|")[1:]]
    assert len(aps) == 3 and all(0.0 < a <= 100.0 for a in aps) and aps[0] >= aps[2]
    assert list(tmp_path.glob("*nanodet-m.npz"))  # the detections cached, as the simulation caches them


def _run_dir(path: Path, statuses: list[str], period: float = 0.04) -> Path:
    """A detect run's two files as the robot writes them: frames.csv, detections.npz."""
    box = np.array([[0, 0, 10, 10]], np.float32)
    with open(path / "frames.csv", "w") as f:
        f.write("seq,capture,result,status\n")
        for i, st in enumerate(statuses):
            f.write(f"{i},{(i + 1) * period},{(i + 1) * period + 0.05},{st}\n")
    done = [i for i, st in enumerate(statuses) if st == "edge_done"]
    np.savez(path / "detections.npz", seqs=np.array(done), counts=np.ones(len(done), np.int64),
             boxes=np.repeat(box, len(done), 0), scores=np.full(len(done), 0.9, np.float32), period=period)
    return path


def test_the_frames_the_edge_dropped_detected_later_count_as_processed(tmp_path: Path) -> None:
    """A still person on ten frames; the edge answered eight and dropped two. Had the robot's
    model found it on those two afterwards, every frame would be a hit."""
    from zoffload.lab.detect_ceiling import dropped_detected_later
    from zoffload.lab.eval.detection import detection_metrics

    box = np.array([[0, 0, 10, 10]], np.float32)
    run = _run_dir(tmp_path, ["edge_done"] * 3 + ["edge_dropped"] + ["edge_done"] * 2 + ["edge_dropped"]
                   + ["edge_done"] * 3)
    before = (run / "frames.csv").read_text()
    as_run = detection_metrics(run, lambda i: box, 10)["ap50_async"]
    assert as_run == pytest.approx(100 * 81 * 1.0 / 101, abs=0.5)  # recall 0.8 at precision 1
    local = [(box, np.array([0.8], np.float32))] * 10
    ap, n = dropped_detected_later(run, local, 0.3, lambda i: box, 10)
    assert n == 2 and ap == pytest.approx(100.0)
    missing = [(np.zeros((0, 4), np.float32), np.zeros(0, np.float32))] * 10  # a model that finds nothing
    assert dropped_detected_later(run, missing, 0.3, lambda i: box, 10)[0] == pytest.approx(as_run)
    assert (run / "frames.csv").read_text() == before  # the run itself untouched
