"""Image sources: clips with moving ground truth, folders, video."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from zoffload.sources.images import CocoClipSource, ImageSourceError, open_image_source

cv2 = pytest.importorskip("cv2")


def _still(tmp_path: Path, boxes: list[list[float]], w: int = 640, h: int = 480) -> Path:
    """A synthetic annotated still: white rectangles where the person boxes are."""
    img = np.zeros((h, w, 3), np.uint8)
    for x, y, bw, bh in boxes:
        img[int(y):int(y + bh), int(x):int(x + bw)] = 255
    cv2.imwrite(str(tmp_path / "a.png"), img)
    gt = {"images": [{"id": 1, "file_name": "a.png", "width": w, "height": h}],
          "annotations": [{"image_id": 1, "category_id": 1, "bbox": b} for b in boxes]}
    (tmp_path / "person_gt.json").write_text(json.dumps(gt))
    return tmp_path


def test_clip_boxes_follow_the_pixels(tmp_path: Path) -> None:
    src = CocoClipSource(_still(tmp_path, [[300, 200, 60, 120]]), size=(424, 240), frames_per_image=20)
    first, last = src.read(0), src.read(19)
    for frame in (first, last):
        assert frame.image.shape == (240, 424, 3)
        assert frame.gt_boxes is not None and len(frame.gt_boxes) == 1
        x1, y1, x2, y2 = frame.gt_boxes[0]
        inside = frame.image[int(y1) + 2:int(y2) - 2, int(x1) + 2:int(x2) - 2]
        assert inside.min() > 200  # the box covers the white rectangle ...
        ring = frame.image[int(y1) - 4:int(y2) + 4, int(x2) + 3:int(x2) + 6]
        assert ring.max() < 60  # ... and ends where it ends
    # the camera moved: the box moved and grew (zooming in)
    assert first.gt_boxes is not None and last.gt_boxes is not None
    assert abs(first.gt_boxes[0][0] - last.gt_boxes[0][0]) > 5
    assert (last.gt_boxes[0][2] - last.gt_boxes[0][0]) > (first.gt_boxes[0][2] - first.gt_boxes[0][0])


def test_a_box_mostly_outside_the_crop_is_not_ground_truth(tmp_path: Path) -> None:
    src = CocoClipSource(_still(tmp_path, [[0, 200, 40, 80]]), size=(424, 240), frames_per_image=10,
                         zoom=(0.6, 0.6))
    counts = [len(src.boxes(i)) for i in range(10)]
    assert counts[0] == 1 and counts[-1] == 0  # the pan leaves the box behind


def test_image_folder_and_a_corrupt_image(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "0.png"), np.full((10, 12, 3), 7, np.uint8))
    (tmp_path / "1.png").write_bytes(b"\x89PNG broken")
    src = open_image_source(str(tmp_path))
    assert len(src) == 2 and src.read(0).image.shape == (10, 12, 3)
    with pytest.raises(ImageSourceError, match="not a readable image"):
        src.read(1)
    with pytest.raises(ImageSourceError, match="does not exist"):
        open_image_source(str(tmp_path / "nope"))


def test_video_file_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "v.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 12.0, (64, 48))
    for k in range(5):
        vw.write(np.full((48, 64, 3), 40 * k, np.uint8))
    vw.release()
    src = open_image_source(str(path))
    assert len(src) == 5 and src.rate_hz == pytest.approx(12.0)
    means = [src.read(k).image.mean() for k in range(5)]
    assert means == sorted(means) and means[-1] > 120
    assert src.read(1).image.mean() == pytest.approx(means[1], abs=1)  # seeking back works


@pytest.mark.realdata
def test_shared_coco_clips_have_moving_ground_truth(coco_dir: Path) -> None:
    src = open_image_source(f"coco-clips:{coco_dir}")
    assert isinstance(src, CocoClipSource) and len(src) == 50 * 50
    assert src.read(0).image.shape == (480, 848, 3)
    assert sum(len(src.boxes(i)) for i in range(0, len(src), 50)) >= 60
