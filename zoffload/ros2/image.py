"""sensor_msgs/Image and CompressedImage to BGR ``uint8`` pixels (what zoffload's detectors take).

Raw images are checked before any pixel is touched: the encoding must be known, ``step`` must
hold a row, the data must hold ``height`` rows, and the pixel count must be within the cap.
Encodings as cv_bridge names them (``sensor_msgs/image_encodings.hpp``); Bayer patterns map to
OpenCV's codes as cv_bridge maps them (ROS ``bayer_rggb8`` is OpenCV ``BayerBG``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

MAX_PIXELS = 7680 * 4320  # as wire.Limits.max_pixels

# encoding -> (channels, numpy dtype, OpenCV conversion to BGR or None)
_RAW: dict[str, tuple[int, str, str | None]] = {
    "bgr8": (3, "u1", None), "8UC3": (3, "u1", None),
    "rgb8": (3, "u1", "COLOR_RGB2BGR"),
    "bgra8": (4, "u1", "COLOR_BGRA2BGR"), "8UC4": (4, "u1", "COLOR_BGRA2BGR"),
    "rgba8": (4, "u1", "COLOR_RGBA2BGR"),
    "mono8": (1, "u1", "COLOR_GRAY2BGR"), "8UC1": (1, "u1", "COLOR_GRAY2BGR"),
    "mono16": (1, "u2", "COLOR_GRAY2BGR"), "16UC1": (1, "u2", "COLOR_GRAY2BGR"),
    "bgr16": (3, "u2", None), "rgb16": (3, "u2", "COLOR_RGB2BGR"),
    "bayer_rggb8": (1, "u1", "COLOR_BayerBG2BGR"), "bayer_bggr8": (1, "u1", "COLOR_BayerRG2BGR"),
    "bayer_gbrg8": (1, "u1", "COLOR_BayerGR2BGR"), "bayer_grbg8": (1, "u1", "COLOR_BayerGB2BGR"),
    "yuv422": (2, "u1", "COLOR_YUV2BGR_UYVY"), "uyvy": (2, "u1", "COLOR_YUV2BGR_UYVY"),
    "yuv422_yuy2": (2, "u1", "COLOR_YUV2BGR_YUY2"), "yuyv": (2, "u1", "COLOR_YUV2BGR_YUY2"),
}
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"


class ImageMsgError(ValueError):
    """An image message that cannot be turned into pixels."""


def _cv2() -> Any:
    try:
        import cv2
    except ImportError as exc:
        raise ImportError("ROS 2 images need OpenCV: pip install 'zoffload[robot]'") from exc
    return cv2


def image_from_msg(msg: Any, msgtype: str, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """(H, W, 3) BGR uint8 of an Image or CompressedImage message; ``ImageMsgError`` if it
    cannot be read."""
    if msgtype == COMPRESSED:
        return _compressed(msg, max_pixels)
    if msgtype != IMAGE:
        raise ImageMsgError(f"{msgtype} is not an image type ({IMAGE}, {COMPRESSED})")
    enc = str(msg.encoding)
    spec = _RAW.get(enc)
    if spec is None:
        raise ImageMsgError(f"image encoding {enc!r} is not supported ({', '.join(sorted(_RAW))})")
    channels, kind, conversion = spec
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0 or h * w > max_pixels:
        raise ImageMsgError(f"image of {w}x{h} pixels (1 to {max_pixels})")
    dtype = np.dtype((">" if msg.is_bigendian else "<") + kind)
    row = w * channels * dtype.itemsize
    data = np.frombuffer(msg.data, np.uint8) if not isinstance(msg.data, np.ndarray) else \
        msg.data.view(np.uint8).reshape(-1)
    if step < row or len(data) < (h - 1) * step + row:
        raise ImageMsgError(f"{enc} image {w}x{h}: step {step} and {len(data)} bytes do not hold "
                            f"{h} rows of {row} bytes")
    rows = np.lib.stride_tricks.as_strided(data, shape=(h, row), strides=(step, 1))
    img = np.ascontiguousarray(rows).view(dtype).reshape(h, w, channels)
    if dtype.itemsize == 2:  # 16-bit: keep the high byte
        img = (img.astype(np.uint16) >> 8).astype(np.uint8)
    if conversion is None:
        return np.ascontiguousarray(img)
    cv2 = _cv2()
    src = img[:, :, 0] if channels == 1 else img
    return np.ascontiguousarray(cv2.cvtColor(src, getattr(cv2, conversion)))


def _compressed(msg: Any, max_pixels: int) -> np.ndarray:
    cv2 = _cv2()
    data = np.asarray(msg.data, np.uint8).reshape(-1)
    if data.size == 0:
        raise ImageMsgError("empty CompressedImage")
    # OpenCV reads the header first and refuses images over CV_IO_MAX_IMAGE_PIXELS (2^30)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if img is None:
        raise ImageMsgError(f"CompressedImage ({str(msg.format)[:40]!r}) that OpenCV cannot decode")
    if img.shape[0] * img.shape[1] > max_pixels:
        raise ImageMsgError(f"image of {img.shape[1]}x{img.shape[0]} pixels (at most {max_pixels})")
    return img
