"""The edge detector in a fleet: a frame another edge was asked to detect is counted ``other_edge``
and left alone (no answer, no admission, no decode), every sample is counted once, and the status
says how much room the detector has. Driven by hand with a stand-in detector and session: no
Zenoh, no model files."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import msgpack
import numpy as np
import pytest

from tests.fuzzing import corpus
from zoffload.detect.detector import Detections
from zoffload.edge.admission import Admission
from zoffload.edge.detection import BUSY_WINDOW, DetectorService, frame_edge
from zoffload.protocol import wire
from zoffload.protocol.keys import Keys

KEYS = Keys()
IMG = np.zeros((8, 8, 3), np.uint8)


def frame(robot: str = "r1", seq: int = 0, edge: str = "") -> wire.Frame:
    return wire.Frame(robot=robot, seq=seq, send_stamp=0.0, capture_stamp=0.0, encoding="bgr8", width=8,
                      height=8, data=IMG.reshape(-1), edge=edge)


class StandInDetector:
    name = "stand-in"
    last_infer_time = 0.001
    input_hw = (416, 416)  # what the edge announces frames can be shrunk to
    stretch = True

    def detect(self, bgr: np.ndarray) -> Detections:
        return Detections(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32))


@dataclass
class Payload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class Sample:
    key_expr: str
    payload: Payload


@dataclass
class Session:
    """The stand-in session: what the service publishes, by key."""

    sent: list[tuple[str, bytes]] = field(default_factory=list)

    def declare_publisher(self, key: str, **_: Any) -> Any:
        session = self

        class Pub:
            def put(self, data: bytes) -> None:
                session.sent.append((key, data))

            def undeclare(self) -> None:
                pass

        return Pub()

    def put(self, key: str, data: bytes, **_: Any) -> None:
        self.sent.append((key, data))


def service(edge: str = "edge1", **kw: Any) -> tuple[DetectorService, Session]:
    svc = DetectorService(StandInDetector(), KEYS, edge, **kw)  # type: ignore[arg-type]
    session = Session()
    svc._session = session  # type: ignore[assignment]  # started by hand: no subscriber, no thread
    return svc, session


def put(svc: DetectorService, data: bytes, robot: str = "r1") -> None:
    svc._on_frame(Sample(KEYS.frame(robot), Payload(data)))  # type: ignore[arg-type]


@pytest.mark.parametrize("edge", ["", "edge1", "e" * 31, "e" * 32, "e" * 64])
def test_frame_edge_reads_the_field_without_decoding(edge: str) -> None:
    data = wire.encode(frame(edge=edge))
    assert frame_edge(data) == edge
    assert frame_edge(memoryview(data)) == edge
    # An old (version 1) sender has no field: None, the full decode judges the frame
    obj = msgpack.unpackb(data)
    del obj["edge"]
    obj["v"] = 1
    assert frame_edge(msgpack.packb(obj, use_bin_type=True)) is None
    # The field anywhere in the map, after values of every kind
    obj = {"a": [1, -1, 2**40, -(2**40), 1.5, None, True, {"x": b"\x00" * 70_000}], "b": "s" * 300,
           "edge": edge, "z": 0}
    assert frame_edge(msgpack.packb(obj, use_bin_type=True)) == edge


def test_frame_edge_never_raises_on_hostile_bytes() -> None:
    for data in (b"", b"\x00", b"\x81", b"\x81\xa4edge", b"\x81\xa4edge\xd9\xff", b"\xdf\xff\xff\xff\xff",
                 b"\x81\xa4edge\xa3\xff\xfe\xfd", msgpack.packb({"edge": 5}), msgpack.packb([1, 2])):
        assert frame_edge(data) in (None, "")
    nested = b"\x81\xa1a" + b"\x91" * 10_000 + b"\x00"  # deep nesting: bounded, not a recursion
    assert frame_edge(nested) is None
    for data in corpus(0, 3000, kinds=("frame",)):
        got = frame_edge(data)
        try:
            decoded = wire.decode(data, expect=wire.Frame)
        except wire.WireError:
            continue
        assert got is None or got == decoded.edge  # never a wrong answer for a valid frame


def test_another_edges_frame_is_counted_not_answered_and_leaves_no_state() -> None:
    admission = Admission(max_robots=2)
    svc, session = service(admission=admission)
    put(svc, wire.encode(frame("r9", edge="edge2")), robot="r9")
    assert svc.counters["other_edge"] == 1 and session.sent == []
    assert not admission.is_admitted("r9") and "r9" not in svc._pending
    # A frame whose edge cannot be read is judged by the full decode: malformed
    put(svc, wire.encode(frame("r9", edge="edge2"))[:-3] + b"\xff\xff\xff", robot="r9")
    assert svc.drops.snapshot() == {"malformed": 1} and session.sent == []
    # Ours and any-edge frames are received and queued
    put(svc, wire.encode(frame("r1", 1, edge="edge1")))
    put(svc, wire.encode(frame("r1", 2)))
    assert svc.counters["received"] == 2 and len(svc._pending["r1"]) == 2
    b = svc.balance()
    assert b["samples"] == 4 and b["drops"] == 1 and b["queued"] == 2 and svc.balanced(), b


def test_every_sample_is_counted_once_whatever_happens_to_it() -> None:
    svc, session = service(queue=2, admission=Admission(max_robots=2))
    frames = [wire.encode(replace(frame("r1", s), edge=e)) for s, e in enumerate(["", "edge1", "edge2"] * 4)]
    for data in frames:
        put(svc, data)
    put(svc, wire.encode(frame("r2", 0)), robot="r2")
    put(svc, wire.encode(frame("r3", 0)), robot="r3")  # beyond max_robots: refused
    put(svc, wire.encode(frame("r1", 99)), robot="r2")  # another robot's frame: foreign
    put(svc, b"\x00not msgpack")
    put(svc, wire.encode(replace(frame("r1", 50), width=9)))  # wrong size: an error answer
    svc._on_frame(Sample("zoffload/bad", Payload(b"")))  # type: ignore[arg-type]
    assert svc.balanced(), svc.balance()
    svc.evict("r2")
    for p in svc._take():  # the inference thread's pass, by hand
        svc._serve(p, 1)
    b = svc.balance()
    assert svc.balanced(), b
    assert b["samples"] == 18 and b["other_edge"] == 4 and b["received"] == 10
    # r1's two waiting frames: the newer served, the older superseded (answered dropped)
    assert b["dropped"] == 7 and b["served"] == 1 and b["errors"] == 1 and b["evicted"] == 1
    assert b["drops"] == 4 and b["queued"] == 0 and b["in_pass"] == 0
    answers = [wire.decode(d, expect=wire.Detections) for k, d in session.sent
               if KEYS.answering_edge(k) is not None]
    assert all(a.edge == "edge1" for a in answers)
    assert len(answers) == b["served"] + b["errors"] + b["dropped"] + b["evicted"] + 1  # + r3's refusal


def test_status_says_how_free_the_detector_is() -> None:
    svc, _ = service()
    now = time.monotonic()
    svc._started = now - 100
    assert svc.busy_share(now) == 0.0 and svc.status()["detector.free"] == pytest.approx(1.0, abs=0.01)
    svc._busy.extend([(now - 4.0, now - 3.0), (now - 2.0, now - 1.0), (now - 9.0, now - 8.0)])
    assert svc.busy_share(now) == pytest.approx(2.0 / BUSY_WINDOW)
    svc._busy_since = now - 0.5  # an inference under way counts too
    assert svc.busy_share(now) == pytest.approx(2.5 / BUSY_WINDOW)
    values = svc.status()
    assert 0.4 < values["detector.free"] < 0.6 and values["detector.queued"] == 0


def test_a_pass_serves_each_robots_newest_frame_and_supersedes_the_older() -> None:
    svc, session = service(queue=3, admission=Admission(max_robots=3))
    put(svc, wire.encode(frame("r2", 7)), robot="r2")
    for seq in (1, 2, 3):
        put(svc, wire.encode(frame("r1", seq)))
    put(svc, wire.encode(frame("r3", 5)), robot="r3")
    svc.batch = 2  # two robots a pass: r2 and r1 waited longest, r3 waits for the next
    taken = svc._take()
    assert [(p.frame.robot, p.frame.seq) for p in taken] == [("r2", 7), ("r1", 3)]
    answers = [wire.decode(d, expect=wire.Detections) for k, d in session.sent
               if KEYS.answering_edge(k) is not None]
    assert [(a.seq, a.status) for a in answers] == [(1, "dropped"), (2, "dropped")]
    assert all("superseded" in a.detail for a in answers)
    assert svc.counters["superseded"] == 2 and svc.balanced(), svc.balance()
    for p in taken:
        svc._serve(p, len(taken))
    assert [(p.frame.robot, p.frame.seq) for p in svc._take()] == [("r3", 5)]
    assert svc.balance()["in_pass"] == 1 and svc.balanced()


def test_first_in_first_out_takes_the_oldest_frames_across_robots() -> None:
    svc, session = service(queue=3, admission=Admission(max_robots=2), serve="oldest")
    put(svc, wire.encode(frame("r1", 1)))
    put(svc, wire.encode(frame("r2", 7)), robot="r2")
    put(svc, wire.encode(frame("r1", 2)))
    svc.batch = 2
    assert [(p.frame.robot, p.frame.seq) for p in svc._take()] == [("r1", 1), ("r2", 7)]
    assert session.sent == [] and svc.counters["superseded"] == 0 and svc.balanced()
    with pytest.raises(ValueError, match="serve"):
        service(serve="latest")


def test_the_answer_carries_the_arrival_only_for_a_robot_that_reads_version_4() -> None:
    """A robot that said it reads codec version 4 gets each answer (served or dropped) stamped with
    its frame's arrival on the edge's clock; an older robot's answers go without the field, as
    version 2, which it reads. (The edge's status says it reads 4 or more: edge/server.py, tested
    in tests/daemon/edge/test_server.py.)"""
    svc, session = service(queue=3)
    before = time.monotonic()
    put(svc, wire.encode(replace(frame("r1", 1), reads=4)))
    put(svc, wire.encode(replace(frame("r1", 2), reads=4)))
    put(svc, wire.encode(frame("r1", 3)))  # an older robot's frame (or one to an older edge's robot)
    after = time.monotonic()
    taken = svc._take()
    for p in taken:
        svc._serve(p, len(taken))
    raw = {wire.decode(d, expect=wire.Detections).seq: d for k, d in session.sent
           if KEYS.answering_edge(k) is not None}
    answers = {seq: wire.decode(d, expect=wire.Detections) for seq, d in raw.items()}
    assert {seq: a.status for seq, a in answers.items()} == {1: "dropped", 2: "dropped", 3: "ok"}
    assert before <= answers[1].arrival <= answers[2].arrival <= after
    assert math.isnan(answers[3].arrival)
    assert msgpack.unpackb(raw[3], raw=False)["v"] == 2 and msgpack.unpackb(raw[1], raw=False)["v"] == 4
