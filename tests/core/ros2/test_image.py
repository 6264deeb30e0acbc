"""sensor_msgs/Image and CompressedImage to BGR pixels."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")
pytest.importorskip("rosbags")

from zoffload.ros2.image import COMPRESSED, IMAGE, ImageMsgError, image_from_msg  # noqa: E402
from zoffload.ros2.messages import header  # noqa: E402
from zoffload.ros2.typestore import msg_class  # noqa: E402

BGR = np.random.default_rng(0).integers(0, 256, (6, 5, 3), dtype=np.uint8)


def raw(encoding: str, pixels: np.ndarray, pad: int = 0, bigendian: bool = False) -> Any:
    h, w = pixels.shape[:2]
    rows = pixels.reshape(h, -1).view(np.uint8) if pixels.dtype == np.uint8 else \
        pixels.astype(">u2" if bigendian else "<u2").reshape(h, -1).view(np.uint8)
    data = np.zeros((h, rows.shape[1] + pad), np.uint8)
    data[:, : rows.shape[1]] = rows
    return msg_class(IMAGE)(header=header(1.0, "cam"), height=h, width=w, encoding=encoding,
                            is_bigendian=bigendian, step=data.shape[1], data=data.reshape(-1))


def test_raw_encodings() -> None:
    np.testing.assert_array_equal(image_from_msg(raw("bgr8", BGR, pad=3), IMAGE), BGR)
    np.testing.assert_array_equal(image_from_msg(raw("rgb8", BGR[:, :, ::-1].copy()), IMAGE), BGR)
    bgra = np.dstack([BGR, np.full(BGR.shape[:2], 255, np.uint8)])
    np.testing.assert_array_equal(image_from_msg(raw("bgra8", bgra), IMAGE), BGR)
    gray = BGR[:, :, 0].copy()
    as_bgr = np.dstack([gray] * 3)
    np.testing.assert_array_equal(image_from_msg(raw("mono8", gray[:, :, None]), IMAGE), as_bgr)
    deep = (gray.astype(np.uint16) << 8)[:, :, None]
    for be in (False, True):
        np.testing.assert_array_equal(image_from_msg(raw("mono16", deep, bigendian=be), IMAGE),
                                      np.dstack([gray] * 3))


def test_compressed() -> None:
    for ext in (".png", ".jpg"):
        ok, buf = cv2.imencode(ext, BGR)
        msg = msg_class(COMPRESSED)(header=header(1.0, "cam"), format=ext[1:], data=buf.reshape(-1))
        img = image_from_msg(msg, COMPRESSED)
        assert img.shape == BGR.shape
        if ext == ".png":
            np.testing.assert_array_equal(img, BGR)


def test_bad_images_are_clear_errors() -> None:
    with pytest.raises(ImageMsgError, match="not supported"):
        image_from_msg(raw("32FC1", BGR), IMAGE)
    short = raw("bgr8", BGR)
    short.data = short.data[:-1]
    with pytest.raises(ImageMsgError, match="rows"):
        image_from_msg(short, IMAGE)
    huge = raw("bgr8", BGR)
    huge.height, huge.width = 100_000, 100_000
    with pytest.raises(ImageMsgError, match="pixels"):
        image_from_msg(huge, IMAGE)
    junk = msg_class(COMPRESSED)(header=header(1.0, "cam"), format="jpeg", data=np.arange(50, dtype=np.uint8))
    with pytest.raises(ImageMsgError, match="cannot decode"):
        image_from_msg(junk, COMPRESSED)
    with pytest.raises(ImageMsgError):
        image_from_msg(junk, "sensor_msgs/msg/PointCloud2")
