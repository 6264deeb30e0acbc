"""The detector service on a real Zenoh session with a stand-in detector: sizes checked before any
pixel is decoded, robots beyond admission refused without state, eviction answering what waits."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
import zenoh

from tests.helpers import KEYS, client, listen_on, wait_for, wait_token
from zoffload.detect.detector import Detections
from zoffload.edge.admission import Admission
from zoffload.edge.detection import DetectorService
from zoffload.protocol import wire
from zoffload.runtime.session import open_session

cv2 = pytest.importorskip("cv2")


class StandIn:
    """Detects nothing, after ``gate`` opens; counts what it was given."""

    name = "stand-in"
    last_infer_time = 0.001
    input_hw = (416, 416)  # what the edge announces frames can be shrunk to
    stretch = True

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.gate.set()
        self.images: list[tuple[int, ...]] = []

    def detect(self, img: np.ndarray) -> Detections:
        self.gate.wait(10)
        self.images.append(img.shape)
        return Detections.empty()


def frame(robot: str, seq: int, w: int = 8, h: int = 6, **over: Any) -> bytes:
    fields: dict[str, Any] = dict(robot=robot, seq=seq, send_stamp=float(seq), capture_stamp=0.0,
                                  encoding="bgr8", width=w, height=h, data=np.zeros(w * h * 3, np.uint8))
    fields.update(over)
    return wire.encode(wire.Frame(**fields))


def put(s: zenoh.Session, key: str, payload: bytes) -> None:
    """BLOCK: each frame reaches the edge (put's default, DROP, may drop one of a burst on a busy
    host; CI once waited 10 s for an answer with the tests' two workers busy)."""
    s.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)


class Answers:
    def __init__(self, session: zenoh.Session, robot: str) -> None:
        self.items: list[wire.Detections] = []
        self.sub = session.declare_subscriber(KEYS.detections_to(robot), lambda s: self.items.append(
            wire.decode(s.payload.to_bytes(), expect=wire.Detections)))


@contextmanager
def serving(service: DetectorService, port: int) -> Iterator[zenoh.Session]:
    session = open_session(listen_on(port))
    try:
        service.start(session)
        token = session.liveliness().declare_token(KEYS.edge_alive("edge1"))
        yield session
        token.undeclare()
    finally:
        service.stop()
        session.close()


def test_frames_are_sized_before_decoding_and_strangers_refused(free_port: int) -> None:
    det = StandIn()
    service = DetectorService(det, KEYS, "edge1", admission=Admission(max_robots=1),  # type: ignore[arg-type]
                              limits=wire.Limits(max_pixels=100 * 100))
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        mine, other = Answers(s, "r1"), Answers(s, "r2")
        ok, buf = cv2.imencode(".jpg", np.zeros((6, 8, 3), np.uint8))
        jpeg = np.frombuffer(buf.tobytes(), np.uint8)
        put(s, KEYS.frame("r1"), frame("r1", 0))  # fine
        wait_for(lambda: len(mine.items) == 1, what="the first answer")
        put(s, KEYS.frame("r1"), frame("r1", 1, encoding="jpeg", data=jpeg))  # fine
        put(s, KEYS.frame("r1"), frame("r1", 2, w=200, h=200))  # beyond the pixel cap (and short)
        put(s, KEYS.frame("r1"), frame("r1", 3, w=16, h=12, encoding="jpeg", data=jpeg))  # header says 8x6
        put(s, KEYS.frame("r2"), frame("r2", 0))  # the edge serves one robot
        wait_for(lambda: len(mine.items) == 4 and len(other.items) == 1, what="every answer")
        by_seq = {d.seq: d for d in mine.items}
        assert by_seq[0].status == by_seq[1].status == "ok"
        assert by_seq[2].status == "error" and "pixels" in by_seq[2].detail
        assert by_seq[3].status == "error" and "JPEG header says 8x6" in by_seq[3].detail
        assert other.items[0].status == "error" and other.items[0].detail.startswith("refused")
        assert det.images[1:] == [(6, 8, 3), (6, 8, 3)]  # the warm-up image, then the two good frames
        st = service.status()
        assert st["detector.samples"] == 5 and st["detector.received"] == 4 and st["detector.drops"] == 1
        assert st["detector.errors"] == 2 and "r2" not in service._pubs


def test_eviction_answers_waiting_frames_and_forgets_the_robot(free_port: int) -> None:
    det = StandIn()
    admission = Admission(max_robots=4, idle_timeout=0.1)
    # first in, first out: whenever the thread takes the first frame, the three after it wait (the
    # default, newest first, would answer the frames before the one it took superseded)
    service = DetectorService(det, KEYS, "edge1", queue=5, batch=1, admission=admission,  # type: ignore[arg-type]
                              serve="oldest")
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        answers = Answers(s, "r1")
        det.gate.clear()  # hold the first frame in the detector
        pub = s.declare_publisher(KEYS.frame("r1"), congestion_control=zenoh.CongestionControl.BLOCK)
        for seq in range(4):
            pub.put(frame("r1", seq))
        wait_for(lambda: service.status().get("detector.received") == 4, what="four frames in")
        gone = admission.expire(now=admission._last["r1"] + 1.0)
        assert gone == ["r1"]
        service.evict("r1")
        det.gate.set()
        wait_for(lambda: len(answers.items) == 4, what="an answer for every frame")
        statuses = sorted(d.status for d in answers.items)
        assert statuses.count("dropped") >= 2 and all("evicted" in d.detail for d in answers.items
                                                      if d.status == "dropped")
        assert "r1" not in service._pubs and "r1" not in service._pending
