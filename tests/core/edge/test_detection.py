"""The edge detector service's frame checks and decoding: bad frames are errors, never crashes,
and no pixel is decoded before the sizes are known to fit."""

from __future__ import annotations

import numpy as np
import pytest

from zoffload.edge.detection import check_frame, decode_image, jpeg_size
from zoffload.protocol import wire

cv2 = pytest.importorskip("cv2")


def frame(**kw: object) -> wire.Frame:
    base = dict(robot="r", seq=0, send_stamp=0.0, capture_stamp=0.0, encoding="bgr8", width=6, height=4,
                data=np.zeros(4 * 6 * 3, np.uint8))
    base.update(kw)
    return wire.Frame(**base)  # type: ignore[arg-type]


def jpeg(width: int, height: int, progressive: bool = False) -> bytes:
    img = np.random.default_rng(0).integers(0, 255, (height, width, 3), np.uint8)
    params = [cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if progressive else []
    ok, buf = cv2.imencode(".jpg", img, params)
    assert ok
    return buf.tobytes()


def claiming(data: bytes, width: int, height: int) -> bytes:
    """The JPEG with its frame header rewritten to claim another size (the data stays small)."""
    b = bytearray(data)
    i = b.index(b"\xff\xc0") if b"\xff\xc0" in b else b.index(b"\xff\xc2")
    b[i + 5:i + 7] = height.to_bytes(2, "big")
    b[i + 7:i + 9] = width.to_bytes(2, "big")
    return bytes(b)


def test_bad_frames_are_value_errors_not_crashes() -> None:
    with pytest.raises(ValueError, match="expected"):
        decode_image(frame(width=7))
    with pytest.raises(ValueError, match="corrupt JPEG"):
        decode_image(frame(encoding="jpeg", data=np.frombuffer(b"\xff\xd8garbage", np.uint8)))
    with pytest.raises(ValueError, match="unknown encoding"):
        decode_image(frame(encoding="png"))
    ok, buf = cv2.imencode(".jpg", np.zeros((4, 6, 3), np.uint8))
    assert decode_image(frame(encoding="jpeg", data=buf.ravel())).shape == (4, 6, 3)
    # A valid header with broken image data after it: the decoder says no, nothing raises further
    broken = jpeg(6, 4)[:-40] + b"\x00" * 40
    try:
        decode_image(frame(encoding="jpeg", data=np.frombuffer(broken, np.uint8)))
    except ValueError:
        pass


@pytest.mark.parametrize("size", [(6, 4), (640, 480), (1, 1), (1920, 1080)])
def test_jpeg_size_reads_the_frame_header(size: tuple[int, int]) -> None:
    assert jpeg_size(jpeg(*size)) == size
    assert jpeg_size(jpeg(*size, progressive=True)) == size


def test_jpeg_size_refuses_what_is_not_a_jpeg_header() -> None:
    for bad in (b"", b"\xff", b"\x89PNG\r\n", b"\xff\xd8", b"\xff\xd8\xff\xd9", b"\xff\xd8\xff\xda\x00\x08",
                b"\xff\xd8\xff\xe0\x00\x01", b"\xff\xd8\xff\xc0\x00\x11\x08"):
        with pytest.raises(ValueError):
            jpeg_size(bad)
    # Fill bytes and segments beyond the bound: refused without walking the whole payload
    with pytest.raises(ValueError, match="frame header"):
        jpeg_size(b"\xff\xd8" + b"\xff" * 1_000_000)
    with pytest.raises(ValueError, match="frame header"):
        jpeg_size(b"\xff\xd8" + b"\xff\xe1\x00\x02" * 20_000 + b"\xff\xc0\x00\x11\x08\x00\x10\x00\x10")


def test_a_small_jpeg_claiming_a_huge_image_never_reaches_the_decoder(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The audit's 829-byte frame: a tiny JPEG whose header claims 65,500 x 65,500 pixels."""
    small = jpeg(8, 8)
    huge = claiming(small, 65_500, 65_500)
    assert len(huge) < 1000 and jpeg_size(huge) == (65_500, 65_500)
    decoded: list[int] = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a: decoded.append(1))
    data = np.frombuffer(huge, np.uint8)
    # Declared small: the header disagrees
    with pytest.raises(ValueError, match="JPEG header says 65500x65500"):
        decode_image(frame(encoding="jpeg", width=8, height=8, data=data))
    # Declared as huge as it claims: beyond the pixel cap
    with pytest.raises(wire.WireError, match="pixels"):
        decode_image(frame(encoding="jpeg", width=65_500, height=65_500, data=data))
    # Within the cap by default, but not within the edge's configured one
    mid = claiming(small, 4000, 3000)
    check_frame(frame(encoding="jpeg", width=4000, height=3000, data=np.frombuffer(mid, np.uint8)))
    with pytest.raises(wire.WireError, match="pixels"):
        check_frame(frame(encoding="jpeg", width=4000, height=3000, data=np.frombuffer(mid, np.uint8)),
                    wire.Limits(max_pixels=3840 * 2160))
    assert decoded == []


def test_boxes_of_a_shrunk_frame_come_back_in_the_camera_pixels() -> None:
    from zoffload.detect.detector import Detections
    from zoffload.edge.detection import to_camera

    det = Detections(np.array([[10, 20, 208, 416], [0, 0, 416, 416]], np.float32),
                     np.array([0.9, 0.5], np.float32), np.array([0, 0], np.int32))
    shrunk = frame(width=416, height=416, data=np.zeros(416 * 416 * 3, np.uint8), camera_width=848,
                   camera_height=480)
    back = to_camera(det, shrunk)
    np.testing.assert_allclose(back.boxes, [[10 * 848 / 416, 20 * 480 / 416, 424, 480], [0, 0, 848, 480]],
                               rtol=1e-6)
    assert back.scores.tolist() == det.scores.tolist()
    whole = frame(width=416, height=416, data=np.zeros(416 * 416 * 3, np.uint8))
    assert to_camera(det, whole) is det  # not shrunk: the frame's pixels are the camera's
