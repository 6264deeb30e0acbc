"""What one camera frame to the edge costs the robot: CPU time and bytes of the frame sender's work
(``robot/camera.py`` ``frame_message``: shrink, encode, the wire message), whole frames against
frames shrunk to each shipped edge detector's network input (``perception.send_size``), raw and JPEG.

Frames: the COCO clips (848x480) and the KITTI-360 camera (1408x376). CPU: median thread time of
one call over the frames (single-threaded: OpenCV on one thread, as a quarter-core robot runs it).
The detector's input and fit come from the models' graphs, as the edge announces them.

Run: python -m benchmarks.bench_frame_send
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable

import numpy as np

from benchmarks.common import DATA, header, median_ms


def frames() -> dict[str, list[np.ndarray]]:
    from zoffload.sources.images import open_image_source

    out = {}
    clips = open_image_source(f"coco-clips:{DATA / 'coco-person-dev'}")
    out["COCO clips 848x480"] = [clips.read(i).image for i in range(0, 500, 25)]
    kitti = DATA / "kitti360-hdl64" / "image_00"
    if kitti.is_dir():
        src = open_image_source(str(kitti))
        out["KITTI-360 camera 1408x376"] = [src.read(i).image for i in range(min(20, len(src)))]
    return out


def _cycling(images: list[np.ndarray], encoding: str, size: tuple[int, int]) -> Callable[[], bytes]:
    """One frame message per call, over the frames in turn."""
    from zoffload.robot.camera import frame_message

    turn = itertools.cycle(images)
    return lambda: frame_message(next(turn), "r", 0, 0.0, "e", encoding, 80, size)


def main() -> None:
    import cv2

    from zoffload.detect.detector import Detector, shrink_size
    from zoffload.robot.camera import frame_message

    cv2.setNumThreads(1)
    header("frame sender per frame: whole vs shrunk to the edge detector's input")
    models = {name: Detector(name, threads=1) for name in ("picodet-s", "yolox-nano", "nanodet-m")}
    print("| frames | edge detector (input, fit) | sent size | raw: kB, CPU ms | JPEG q80: kB, CPU ms |")
    print("| --- | --- | --- | --- | --- |")
    for label, images in frames().items():
        h, w = images[0].shape[:2]
        rows = [("whole (any)", (w, h))]
        for name, det in models.items():
            net_h, net_w = det.input_hw
            fit = "stretch" if det.stretch else "letterbox"
            rows.append((f"{name} ({net_w}x{net_h}, {fit})", shrink_size(w, h, det.input_hw, det.stretch)))
        for what, size in rows:
            cells = []
            for encoding in ("bgr8", "jpeg"):
                nbytes = [len(frame_message(img, "r", 0, 0.0, "e", encoding, 80, size)) for img in images]
                cpu = median_ms(_cycling(images, encoding, size), repeat=60, warmup=5, clock=time.thread_time)
                cells.append(f"{np.mean(nbytes) / 1e3:.0f} kB, {cpu:.2f} ms")
            print(f"| {label} | {what} | {size[0]}x{size[1]} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
