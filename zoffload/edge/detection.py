"""The edge's object-detector service: every robot's camera frames, one heavier ONNX model.

Inputs:  ``<ns>/data/*/frame`` (wire.Frame).
Outputs: ``<ns>/data/<robot>/detections`` (wire.Detections, one per frame: also for frames it
         could not decode or had to drop, so no robot waits for an answer that will not come).

The Zenoh callback only decodes and queues; one inference thread serves all robots. When frames
queue up it takes up to ``batch`` of them in one pass, oldest first across robots, and serves them
back to back (the three shipped models have a fixed batch dimension of 1, so a pass is a loop, not
one tensor); every answer says how many frames shared its pass. Each robot keeps at most ``queue``
waiting frames; the oldest is answered ``dropped`` when a newer one comes.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np
import zenoh

from zoffload.detect.detector import Detections, Detector
from zoffload.protocol import wire
from zoffload.protocol.intake import decode_from_robot
from zoffload.protocol.keys import Keys

log = logging.getLogger("zoffload.edge.detection")


@dataclass
class _Pending:
    frame: wire.Frame
    arrival: float


def decode_image(frame: wire.Frame) -> np.ndarray:
    """The frame's BGR pixels; ValueError for a wrong size or an undecodable JPEG."""
    import cv2

    if frame.width <= 0 or frame.height <= 0:
        raise ValueError(f"bad frame size {frame.width}x{frame.height}")
    if frame.encoding == "bgr8":
        want = frame.width * frame.height * 3
        if frame.data.size != want:
            raise ValueError(f"bgr8 frame of {frame.data.size} bytes, {frame.width}x{frame.height}x3 = "
                             f"{want} expected")
        return frame.data.reshape(frame.height, frame.width, 3)
    if frame.encoding == "jpeg":
        img = cv2.imdecode(frame.data, cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError("undecodable JPEG")
        if img.shape[:2] != (frame.height, frame.width):
            raise ValueError(f"JPEG of {img.shape[1]}x{img.shape[0]}, header says "
                             f"{frame.width}x{frame.height}")
        return img
    raise ValueError(f"unknown encoding {frame.encoding!r} (bgr8, jpeg)")


class DetectorService:
    name = "detector"

    def __init__(self, detector: Detector, keys: Keys, edge_id: str, queue: int = 2,
                 batch: int = 4) -> None:
        self.detector = detector
        self.keys = keys
        self.edge_id = edge_id
        self.queue_len = queue
        self.batch = batch
        self.counters: Counter[str] = Counter()
        self.infer_times: deque[float] = deque(maxlen=100)
        self._pending: dict[str, deque[_Pending]] = {}
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._work, name="detector", daemon=True)
        self._session: zenoh.Session | None = None
        self._sub: zenoh.Subscriber[None] | None = None

    def start(self, session: zenoh.Session) -> None:
        self.detector.detect(np.zeros((64, 64, 3), np.uint8))  # first-run allocation, not on a frame
        self._session = session
        self._sub = session.declare_subscriber(self.keys.all_frames(), self._on_frame)
        self._thread.start()
        log.info("detector %s serving %s", self.detector.name, self.keys.all_frames())

    def stop(self) -> None:
        # No new frames: one queued after the thread stops would never be answered
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=5)

    def _pub(self, robot: str) -> zenoh.Publisher:
        pub = self._pubs.get(robot)
        if pub is None:
            assert self._session is not None, "frames arrive only after start()"
            pub = self._session.declare_publisher(self.keys.detections(robot), express=True,
                                                  congestion_control=zenoh.CongestionControl.DROP)
            self._pubs[robot] = pub
        return pub

    # Zenoh callback: decode, check, queue
    def _on_frame(self, sample: zenoh.Sample) -> None:
        arrival = time.monotonic()
        frame = decode_from_robot(sample, wire.Frame, self.keys, self.counters, log, "frame")
        if frame is None:
            return
        self.counters["received"] += 1
        dropped = None
        with self._cond:
            q = self._pending.setdefault(frame.robot, deque())
            q.append(_Pending(frame, arrival))
            if len(q) > self.queue_len:
                dropped = q.popleft()
            self._cond.notify()
        if dropped is not None:
            self.counters["dropped"] += 1
            self._reply(dropped, "dropped", detail="edge detector overloaded")

    def _take(self) -> list[_Pending]:
        """Up to ``batch`` queued frames, oldest first across robots."""
        with self._cond:
            while not self._stop.is_set() and not any(self._pending.values()):
                self._cond.wait(0.2)
            items = [p for q in self._pending.values() for p in q]
            items.sort(key=lambda p: p.arrival)
            taken = items[: self.batch]
            for p in taken:
                self._pending[p.frame.robot].remove(p)
            return taken

    def _work(self) -> None:
        while not self._stop.is_set():
            items = self._take()
            for p in items:
                self._serve(p, len(items))

    def _serve(self, p: _Pending, batch: int) -> None:
        start = time.monotonic()
        try:
            img = decode_image(p.frame)
            det = self.detector.detect(img)
        except Exception as exc:  # a bad frame is answered and counted, the service carries on
            self.counters["errors"] += 1
            log.warning("robot %s frame %d: %s", p.frame.robot, p.frame.seq, exc)
            self._reply(p, "error", detail=str(exc)[:200], queue_time=start - p.arrival)
            return
        self.counters["served"] += 1
        self.infer_times.append(self.detector.last_infer_time)
        self._reply(p, "ok", queue_time=start - p.arrival, infer_time=time.monotonic() - start,
                    batch=batch, det=det)

    def _reply(self, p: _Pending, status: str, detail: str = "", queue_time: float = float("nan"),
               infer_time: float = float("nan"), batch: int = 0, det: Detections | None = None) -> None:
        msg = wire.Detections(
            robot=p.frame.robot, seq=p.frame.seq, send_stamp=p.frame.send_stamp, edge=self.edge_id,
            model=self.detector.name, status=status, infer_time=infer_time, queue_time=queue_time,
            batch=batch, detail=detail,
            boxes=det.boxes if det is not None else np.zeros((0, 4), np.float32),
            scores=det.scores if det is not None else np.zeros(0, np.float32),
            classes=det.classes if det is not None else np.zeros(0, np.int32),
        )
        try:
            self._pub(p.frame.robot).put(wire.encode(msg))
        except Exception as exc:  # session closing
            log.debug("detections not published: %s", exc)

    def status(self) -> dict[str, float]:
        values = {f"detector.{k}": float(v) for k, v in self.counters.items()}
        if self.infer_times:
            values["detector.infer_ms"] = float(np.mean(self.infer_times) * 1e3)
        return values
