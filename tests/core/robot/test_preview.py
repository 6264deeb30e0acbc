"""The viewer preview: a small JPEG with the person boxes scaled to it."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.robot.preview import preview_image

cv2 = pytest.importorskip("cv2")


def test_a_frame_is_shrunk_to_at_most_424_pixels_wide_and_its_boxes_with_it() -> None:
    img = np.zeros((480, 848, 3), np.uint8)
    img[100:300, 200:400] = 255  # a white "person"
    boxes = np.array([[200, 100, 400, 300]], np.float32)
    jpeg, w, h, scaled = preview_image(img, boxes, max_width=424, quality=70)
    assert (w, h) == (424, 240) and jpeg.dtype == np.uint8 and len(jpeg) < 20_000
    small = cv2.imdecode(jpeg, cv2.IMREAD_COLOR)
    assert small.shape == (240, 424, 3)
    assert scaled.dtype == np.float32 and scaled == pytest.approx(np.array([[100, 50, 200, 150]]))
    x1, y1, x2, y2 = scaled[0].astype(int)
    assert small[y1 + 3:y2 - 3, x1 + 3:x2 - 3].min() > 200 and small[y2 + 5:, :].max() < 60
    # a frame already small enough is not enlarged; no boxes is fine
    jpeg, w, h, scaled = preview_image(img[:48, :64], np.zeros((0, 4), np.float32))
    assert (w, h) == (64, 48) and scaled.shape == (0, 4)
