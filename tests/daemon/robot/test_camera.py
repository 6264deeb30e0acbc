"""The camera pipeline in-process over real Zenoh sessions with a stand-in detector and a stand-in
edge (a session that answers frames): no model files needed."""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
import zenoh

from tests.helpers import KEYS, client, listen_on, wait_for
from zoffload.detect.detector import Detections
from zoffload.policy.offload import make_strategy
from zoffload.protocol import wire
from zoffload.robot.camera import CameraOffloader, CameraOptions
from zoffload.robot.frames import FallbackRules
from zoffload.robot.server import RobotServer
from zoffload.runtime.config import RobotSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.sources.images import ImageFrame


class FakeDetector:
    """Finds one person in the top-left corner after ``delay`` seconds."""

    name = "fake"

    def __init__(self, delay: float = 0.03) -> None:
        self.delay = delay
        self.last_infer_time = 0.0

    def detect(self, bgr: np.ndarray) -> Detections:
        time.sleep(self.delay)
        self.last_infer_time = self.delay
        return Detections(np.array([[0, 0, 10, 10]], np.float32), np.array([0.9], np.float32),
                          np.array([0], np.int32))


class Frames:
    def __init__(self, n: int, fps: float = 25.0) -> None:
        self.n, self.rate_hz, self.name = n, fps, "synthetic"

    def __len__(self) -> int:
        return self.n

    def read(self, index: int) -> ImageFrame:
        return ImageFrame(index, np.full((48, 64, 3), index % 255, np.uint8))


class FakeEdge:
    """Answers every frame of ``robot`` with one person, unless ``silent``; holds an edge token."""

    def __init__(self, session: zenoh.Session, robot: str = "robot1") -> None:
        self.session, self.silent, self.served = session, False, 0
        self._pub = session.declare_publisher(KEYS.detections(robot, "fake"))
        self._sub = session.declare_subscriber(KEYS.frame(robot), self._on_frame)
        self.token: zenoh.LivelinessToken | None = session.liveliness().declare_token(KEYS.edge_alive("fake"))

    def _on_frame(self, sample: zenoh.Sample) -> None:
        f = wire.decode(sample.payload.to_bytes(), expect=wire.Frame)
        assert f.data.size == f.width * f.height * 3
        if self.silent:
            return
        self.served += 1
        self._pub.put(wire.encode(wire.Detections(
            robot=f.robot, seq=f.seq, send_stamp=f.send_stamp, edge="fake", model="fake", status="ok",
            infer_time=0.01, queue_time=0.0, batch=1, boxes=np.array([[1, 1, 5, 5]], np.float32),
            scores=np.array([0.8], np.float32), classes=np.array([0], np.int32))))

    def vanish(self) -> None:
        assert self.token is not None
        self.token.undeclare()
        self.token = None

    def return_(self) -> None:
        self.token = self.session.liveliness().declare_token(KEYS.edge_alive("fake"))


def camera(strategy: str, n: int, stop: StopSignal) -> CameraOffloader:
    rules = FallbackRules(reply_timeout=0.3, fallback_losses=3, probe_period=0.2, resume_after=2)
    return CameraOffloader(Frames(n), FakeDetector(), make_strategy(strategy), rules, KEYS,
                           CameraOptions(robot_id="robot1", fps=25.0, wait_edge=5.0), stop)


def test_both_sides_work_in_parallel_and_every_frame_is_counted(free_port: int) -> None:
    settings = RobotSettings(zenoh=listen_on(free_port), scans="none", wait_edge=5.0)
    with client(free_port) as edge_session:
        edge = FakeEdge(edge_session)
        stop = StopSignal()
        cam = camera("ratio:0.5", 50, stop)
        metrics = RobotServer(settings, [cam], stop).run()["camera"]
    b = metrics["balance"]
    assert metrics["balanced"] and b["frames_in"] == 50 and b["pending"] == 0
    assert b["edge_done"] >= 15 and b["local_done"] >= 10, b
    assert edge.served >= b["edge_done"]
    assert metrics["edge_rtt_ms"] > 0 and metrics["robot_rtt_ms"] > 0


def test_falls_back_when_the_edge_goes_and_resumes_when_it_returns(free_port: int) -> None:
    settings = RobotSettings(zenoh=listen_on(free_port), scans="none", wait_edge=5.0)
    with client(free_port) as edge_session:
        edge = FakeEdge(edge_session)
        stop = StopSignal()
        cam = camera("edge", 200, stop)  # 8 s at 25 FPS
        server = RobotServer(settings, [cam], stop)
        result: dict[str, Any] = {}
        thread = threading.Thread(target=lambda: result.update(server.run()))
        thread.start()
        wait_for(lambda: cam.book.counters["edge_done"] >= 10, what="edge answers")
        edge.silent = True
        edge.vanish()
        gone = time.time()
        wait_for(lambda: cam.book.fallback, timeout=2, what="fallback")
        entered = cam.book.fallback_events[0]["start"] - gone
        wait_for(lambda: cam.book.counters["local_done"] >= 10, what="local work in fallback")
        edge.silent = False
        edge.return_()
        wait_for(lambda: not cam.book.fallback, timeout=5, what="resume")
        done_before = cam.book.counters["edge_done"]
        wait_for(lambda: cam.book.counters["edge_done"] > done_before + 5, what="offloading again")
        stop.set()
        thread.join(20)
    m = result["camera"]
    assert entered < 0.25 and m["balanced"] and len(m["fallbacks"]) == 1
    assert m["balance"]["pending"] == 0


def test_a_silent_edge_with_its_token_still_held_is_detected_by_losses(free_port: int) -> None:
    settings = RobotSettings(zenoh=listen_on(free_port), scans="none", wait_edge=5.0)
    with client(free_port) as edge_session:
        edge = FakeEdge(edge_session)
        stop = StopSignal()
        cam = camera("edge", 100, stop)
        server = RobotServer(settings, [cam], stop)
        thread = threading.Thread(target=server.run)
        thread.start()
        wait_for(lambda: cam.book.counters["edge_done"] >= 5, what="edge answers")
        edge.silent = True  # a hung edge: token present, nothing answered
        wait_for(lambda: cam.book.fallback, timeout=3, what="fallback by losses")
        assert cam.book.counters["edge_lost"] >= 3
        stop.set()
        thread.join(20)
    assert cam.book.balanced()


def test_robot_status_carries_camera_counters(free_port: int) -> None:
    settings = RobotSettings(zenoh=listen_on(free_port), scans="none", wait_edge=5.0, status_period=0.2)
    seen: list[dict[str, float]] = []
    with client(free_port) as s:
        FakeEdge(s)
        sub = s.declare_subscriber(KEYS.robot_status("robot1"), lambda smp: seen.append(
            wire.decode(smp.payload.to_bytes(), expect=wire.Status).values))
        stop = StopSignal()
        RobotServer(settings, [camera("ratio:0.5", 25, stop)], stop).run()
        wait_for(lambda: any(v.get("frames_in") == 25 for v in seen), what="final status")
        sub.undeclare()
    assert all("edges" in v and "local_done" in v for v in seen)




def test_dispatch_uses_both_sides_and_counts_every_frame(free_port: int) -> None:
    """Our default strategy with a slow local detector and an edge that answers at once: the edge
    takes most frames, the local detector was measured, and every frame is in exactly one bucket."""
    settings = RobotSettings(zenoh=listen_on(free_port), scans="none", wait_edge=5.0)
    with client(free_port) as edge_session:
        edge = FakeEdge(edge_session)
        stop = StopSignal()
        cam = camera("dispatch", 75, stop)
        metrics = RobotServer(settings, [cam], stop).run()["camera"]
    b = metrics["balance"]
    assert metrics["balanced"] and b["frames_in"] == 75 and b["pending"] == 0
    assert b["edge_done"] >= 40 and b["local_done"] >= 1, b
    assert edge.served >= b["edge_done"] and metrics["strategy"] == "dispatch"


class Previews:
    def __init__(self, session: zenoh.Session) -> None:
        self.got: list[tuple[float, wire.Preview]] = []
        self.sub = session.declare_subscriber(KEYS.preview("robot1"), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        msg = wire.decode(sample.payload.to_bytes(), expect=wire.Preview)
        assert isinstance(msg, wire.Preview)
        self.got.append((time.monotonic(), msg))


def test_previews_go_out_a_few_times_a_second_only_while_someone_watches(free_port: int) -> None:
    import cv2

    settings = RobotSettings(zenoh=listen_on(free_port), scans="none", wait_edge=5.0)
    with client(free_port) as s:
        FakeEdge(s)
        # nobody watches: nothing is encoded or sent
        stop = StopSignal()
        cam = camera("ratio:0.5", 25, stop)
        RobotServer(settings, [cam], stop).run()
        assert cam.preview is not None and cam.preview.published == 0
        # a viewer: at most one preview per period (0.25 s), local and edge frames alike
        viewer = Previews(s)
        stop = StopSignal()
        cam = camera("ratio:0.5", 75, stop)  # 3 s
        RobotServer(settings, [cam], stop).run()
        wait_for(lambda: len(viewer.got) >= 4, what="previews")
        viewer.sub.undeclare()
    assert len(viewer.got) <= 3 / 0.25 + 2
    stamps = [m.stamp for _, m in viewer.got]
    assert all(b - a >= 0.25 - 1e-6 for a, b in zip(stamps, stamps[1:], strict=False))
    for _, m in viewer.got:
        assert m.robot == "robot1" and m.side in ("local", "edge") and len(m.boxes) == len(m.scores) == 1
        img = cv2.imdecode(m.jpeg, cv2.IMREAD_COLOR)
        assert img is not None and img.shape[:2] == (m.height, m.width) == (48, 64)
    assert {m.side for _, m in viewer.got} == {"local", "edge"}
