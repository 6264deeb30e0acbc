"""Previews for viewers: a small JPEG of a detected camera frame with its person boxes.

Outputs: ``<ns>/view/<robot>/preview`` (wire.Preview), a few per second at most and only while a
subscriber matches, so a robot nobody watches spends nothing on it. The camera pipeline offers
each result (``offer``: a flag check and a slot, no image work); one thread of this publisher
downscales, encodes and puts the newest offered frame, off the detection path.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np
import zenoh

from zoffload.protocol import wire
from zoffload.runtime.session import has_subscribers, undeclare

log = logging.getLogger("zoffload.robot.preview")


@dataclass(frozen=True)
class Offer:
    seq: int
    stamp: float  # robot wall clock when the result came
    side: str  # local or edge
    image: np.ndarray  # the frame (BGR), not copied: frames are never written after capture
    boxes: np.ndarray  # person boxes in the frame's pixels
    scores: np.ndarray


def preview_image(image: np.ndarray, boxes: np.ndarray, max_width: int = 424,
                  quality: int = 70) -> tuple[np.ndarray, int, int, np.ndarray]:
    """The JPEG bytes, width and height of ``image`` shrunk to at most ``max_width`` pixels wide,
    and ``boxes`` scaled to it."""
    import cv2

    h, w = image.shape[:2]
    scale = min(1.0, max_width / w)
    small = image if scale == 1.0 else cv2.resize(image, (max(1, round(w * scale)), max(1, round(h * scale))),
                                                   interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding of the preview failed")
    sh, sw = small.shape[:2]
    scaled = (np.asarray(boxes, np.float32).reshape(-1, 4) * np.float32(sw / w)).astype(np.float32)
    return buf.ravel(), sw, sh, scaled


class PreviewPublisher:
    def __init__(self, session: zenoh.Session, key: str, robot: str, period: float = 0.25,
                 max_width: int = 424, quality: int = 70, poll: float = 0.5) -> None:
        self.robot = robot
        self.period = period
        self.max_width = max_width
        self.quality = quality
        self.poll = poll
        self.published = 0
        self.wanted = False  # a subscriber matched at the last poll
        self._pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
        self._slot: Offer | None = None
        self._last = -float("inf")
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="preview", daemon=True)

    def start(self) -> PreviewPublisher:
        self._thread.start()
        return self

    def offer(self, offer: Offer) -> None:
        """A new result: kept (replacing an older one) if someone watches and one is due."""
        if not self.wanted or offer.stamp - self._last < self.period:
            return
        with self._cond:
            self._last = offer.stamp
            self._slot = offer
            self._cond.notify()

    def _run(self) -> None:
        next_poll = 0.0
        while not self._stop.is_set():
            if time.monotonic() >= next_poll:
                self.wanted = has_subscribers(self._pub)
                next_poll = time.monotonic() + self.poll
            with self._cond:
                if self._slot is None:
                    self._cond.wait(min(self.poll, 0.1))
                offer, self._slot = self._slot, None
            if offer is None:
                continue
            try:
                jpeg, w, h, boxes = preview_image(offer.image, offer.boxes, self.max_width, self.quality)
                self._pub.put(wire.encode(wire.Preview(
                    robot=self.robot, seq=offer.seq, stamp=offer.stamp, side=offer.side, width=w, height=h,
                    jpeg=jpeg, boxes=boxes, scores=np.asarray(offer.scores, np.float32))))
                self.published += 1
            except Exception as exc:  # a preview is never worth stopping the camera for
                log.debug("preview of frame %d not published: %s", offer.seq, exc)

    def close(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        undeclare(self._pub)
