"""The edge detector service's frame decoding: bad frames are errors, never crashes."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.edge.detection import decode_image
from zoffload.protocol import wire

cv2 = pytest.importorskip("cv2")


def test_bad_frames_are_value_errors_not_crashes() -> None:
    def frame(**kw: object) -> wire.Frame:
        base = dict(robot="r", seq=0, send_stamp=0.0, capture_stamp=0.0, encoding="bgr8", width=6, height=4,
                    data=np.zeros(4 * 6 * 3, np.uint8))
        base.update(kw)
        return wire.Frame(**base)  # type: ignore[arg-type]

    with pytest.raises(ValueError, match="expected"):
        decode_image(frame(width=7))
    with pytest.raises(ValueError, match="undecodable JPEG"):
        decode_image(frame(encoding="jpeg", data=np.frombuffer(b"\xff\xd8garbage", np.uint8)))
    with pytest.raises(ValueError, match="unknown encoding"):
        decode_image(frame(encoding="png"))
    ok, buf = cv2.imencode(".jpg", np.zeros((4, 6, 3), np.uint8))
    assert decode_image(frame(encoding="jpeg", data=buf.ravel())).shape == (4, 6, 3)
