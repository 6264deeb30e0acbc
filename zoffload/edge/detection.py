"""The edge's object-detector service: every admitted robot's camera frames, one heavier ONNX model.

Inputs:  ``<ns>/data/*/frame`` (wire.Frame).
Outputs: ``<ns>/data/<robot>/detections/<edge>`` (wire.Detections, one per frame: also for frames it
         could not decode or had to drop, so no robot waits for an answer that will not come;
         robots not admitted get an ``error`` answer saying so, rate-limited); status values
         (``status()``): the counters below, ``detector.free`` (the share of the last
         ``BUSY_WINDOW`` seconds the inference thread was idle: robots pick edges with room by it,
         robot/edgechoice.py), ``detector.queued``, ``detector.infer_ms``.

In a fleet every edge's detector hears every frame (the router fans them out). A frame names the
edge asked to detect it (``Frame.edge``; "" = any edge that hears it): a frame for another edge
is not ours, counted ``other_edge`` (not a drop: no answer, no admission, no per-robot state).
That is decided first, from the field read out of the msgpack bytes (``frame_edge``: the pixels
stepped over, no array built), before admission and before the frame is decoded.

Counters: every sample is counted once as ``samples`` and ends in exactly one of a drop
(``detector.drops``: bad key, refused, malformed, foreign, a callback exception), ``other_edge`` or
``received``; every received frame ends in exactly one of ``served``, ``errors``, ``dropped``
(superseded by a newer frame of its robot, or its queue overflowed), ``evicted`` (its robot
evicted), or is still ``queued`` / in a pass (``balance()``). Frames still queued when the
service stops are not answered.

The Zenoh callback only decodes, checks sizes and queues; one inference thread serves all robots.
Sizes are checked before any pixel is decoded: the declared width x height against the pixel cap,
a raw frame's byte count, and a JPEG's own frame header (read from its SOF marker) against the
declared size, so a small JPEG claiming a huge image never reaches the decoder. Each robot keeps
at most ``queue`` waiting frames; the oldest is answered ``dropped`` when a newer one comes.

A pass takes up to ``batch`` robots' frames, the robot waiting longest first, and serves them back
to back (the three shipped models have a fixed batch dimension of 1, so a pass is a loop, not one
tensor); every answer says how many frames shared its pass. ``serve="newest"`` (the default)
takes each robot's *newest* waiting frame and answers its older ones ``dropped`` at once
(``superseded``): their results would reach the robot after the newer frame's, stale on arrival,
and serving the older first delays the newer by a whole inference. A detector behind its camera
so serves the freshest frame it has instead of the one that waited longest. ``serve="oldest"`` is
first in, first out: up to ``batch`` frames oldest first across robots, two of one robot's in one
pass (the thesis' edge, and this one before).
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
from zoffload.edge.admission import Admission
from zoffload.protocol import wire
from zoffload.protocol.intake import robot_in_key
from zoffload.protocol.keys import Keys, check_id
from zoffload.runtime.drops import Drops
from zoffload.runtime.session import undeclare

log = logging.getLogger("zoffload.edge.detection")

BUSY_WINDOW = 5.0  # seconds over which the inference thread's busy share is measured

# Start-of-frame markers (baseline, extended, progressive, lossless; Huffman and arithmetic)
_SOF = frozenset((0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF))
_MAX_MARKERS = 10_000  # segments and fill bytes read before the frame header must have come


def jpeg_size(data: bytes | memoryview) -> tuple[int, int]:
    """(width, height) from a JPEG's frame header, read without decoding; ValueError if there is
    no well-formed header before the image data."""
    b = memoryview(data)
    n = len(b)
    if n < 4 or b[0] != 0xFF or b[1] != 0xD8:
        raise ValueError("not a JPEG (no start-of-image marker)")
    i = 2
    for _ in range(_MAX_MARKERS):
        if i + 4 > n:
            break
        if b[i] != 0xFF:
            raise ValueError(f"corrupt JPEG: no marker at byte {i}")
        marker = b[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
            i += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no frame header came first
            break
        length = (b[i + 2] << 8) | b[i + 3]
        if length < 2:
            raise ValueError(f"corrupt JPEG: segment length {length} at byte {i}")
        if marker in _SOF:
            if i + 9 > n or length < 8:
                break
            height = (b[i + 5] << 8) | b[i + 6]
            width = (b[i + 7] << 8) | b[i + 8]
            return width, height
        i += 2 + length
    raise ValueError("JPEG without a frame header")


def check_frame(frame: wire.Frame, limits: wire.Limits = wire.DEFAULT_LIMITS) -> None:
    """ValueError unless the frame's pixels can be decoded within ``limits`` as declared."""
    frame.check_size(limits)  # declared size within the pixel cap; raw: exactly that many bytes
    if frame.encoding == "jpeg":
        width, height = jpeg_size(frame.data.data)
        if (width, height) != (frame.width, frame.height):
            raise ValueError(f"JPEG header says {width}x{height}, the frame {frame.width}x{frame.height}")


def decode_image(frame: wire.Frame, limits: wire.Limits = wire.DEFAULT_LIMITS) -> np.ndarray:
    """The frame's BGR pixels; ValueError for a wrong size or an undecodable JPEG."""
    import cv2

    if frame.encoding not in ("bgr8", "jpeg"):
        raise ValueError(f"unknown encoding {frame.encoding!r} (bgr8, jpeg)")
    check_frame(frame, limits)
    if frame.encoding == "bgr8":
        return frame.data.reshape(frame.height, frame.width, 3)
    img = cv2.imdecode(frame.data, cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError("undecodable JPEG")
    if img.shape[:2] != (frame.height, frame.width):
        raise ValueError(f"JPEG of {img.shape[1]}x{img.shape[0]}, header says {frame.width}x{frame.height}")
    return img


def to_camera(det: Detections, frame: wire.Frame) -> Detections:
    """``det`` (in the frame's pixels) in the camera's: scaled up when the robot shrank the frame
    to this edge's detector input on the way (``Frame.camera_size``)."""
    cam_w, cam_h = frame.camera_size()
    if (cam_w, cam_h) == (frame.width, frame.height) or not len(det):
        return det
    scale = np.array([cam_w / frame.width, cam_h / frame.height] * 2, np.float32)
    boxes = np.clip(det.boxes * scale, 0, np.array([cam_w, cam_h, cam_w, cam_h], np.float32))
    return Detections(boxes.astype(np.float32), det.scores, det.classes)


def frame_edge(data: bytes | memoryview) -> str | None:
    """The ``edge`` field of an encoded frame, read without decoding the rest (``wire.peek_fields``:
    the pixels are stepped over, never built); None when the field is absent (a version-1 sender),
    not a string, or the bytes are not a well-formed frame map (the full decode judges those)."""
    got = wire.peek_fields(data, wire.Frame.TYPE, ("edge",))
    edge = got.get("edge") if got is not None else None
    return edge if isinstance(edge, str) else None


@dataclass
class _Pending:
    frame: wire.Frame
    arrival: float


class DetectorService:
    name = "detector"

    def __init__(self, detector: Detector, keys: Keys, edge_id: str, queue: int = 2, batch: int = 4,
                 admission: Admission | None = None, limits: wire.Limits = wire.DEFAULT_LIMITS,
                 serve: str = "newest") -> None:
        if serve not in ("newest", "oldest"):
            raise ValueError(f"serve must be 'newest' or 'oldest', not {serve!r}")
        self.detector = detector
        self.keys = keys
        self.edge_id = check_id(edge_id, "edge id")  # its answers go under it
        self.queue_len = queue
        self.batch = batch
        self.serve = serve
        self.admission = admission or Admission()
        self.limits = limits
        self.counters: Counter[str] = Counter()
        self.drops = Drops(log)
        self.infer_times: deque[float] = deque(maxlen=100)
        self._pending: dict[str, deque[_Pending]] = {}
        self._in_pass = 0  # frames taken by the inference thread, not yet answered
        # (start, end) of the inference thread's recent work, monotonic; bounded by the window
        # (a pass is at least one inference) and by maxlen whatever the clock does
        self._busy: deque[tuple[float, float]] = deque(maxlen=10_000)
        self._busy_since: float | None = None  # the current inference's start
        self._started = time.monotonic()
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._cond = threading.Condition()  # pending, publishers and counters
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._work, name="detector", daemon=True)
        self._session: zenoh.Session | None = None
        self._sub: zenoh.Subscriber[None] | None = None

    def start(self, session: zenoh.Session) -> None:
        self.detector.detect(np.zeros((64, 64, 3), np.uint8))  # first-run allocation, not on a frame
        self._session = session
        self._sub = session.declare_subscriber(self.keys.all_frames(),
                                               self.drops.guard(self._on_frame, "frame"))
        self._thread.start()
        log.info("detector %s serving %s", self.detector.name, self.keys.all_frames())

    def stop(self) -> None:
        # No new frames: one queued after the thread stops would never be answered
        undeclare(self._sub)
        self._sub = None
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=5)
        log.info("detector stopped: %s, drops %s", self.balance(), self.drops.snapshot())

    def _pub(self, robot: str) -> zenoh.Publisher:
        """The robot's detections publisher (called with the lock held, for admitted robots)."""
        pub = self._pubs.get(robot)
        if pub is None:
            assert self._session is not None, "frames arrive only after start()"
            pub = self._session.declare_publisher(self.keys.detections(robot, self.edge_id), express=True,
                                                  congestion_control=zenoh.CongestionControl.DROP)
            self._pubs[robot] = pub
        return pub

    def _count(self, what: str) -> None:
        with self._cond:
            self.counters[what] += 1

    # Zenoh callback: ours?, decode, check, queue
    def _on_frame(self, sample: zenoh.Sample) -> None:
        arrival = time.monotonic()
        self._count("samples")
        robot = robot_in_key(sample, self.keys, self.drops, "frame")
        if robot is None:
            return
        data = sample.payload.to_bytes()
        edge = frame_edge(data)
        if edge and edge != self.edge_id:  # another edge's frame: nothing else is looked at
            self._count("other_edge")
            return
        if not self.admission.admit(robot, arrival):
            self._refuse(data, robot, arrival)
            return
        try:
            frame = wire.decode(data, expect=wire.Frame, limits=self.limits)
        except wire.WireError as exc:
            self.drops.drop("malformed", f"frame on {str(sample.key_expr)[:100]}: {exc}")
            return
        if frame.robot != robot:
            self.drops.drop("foreign", f"frame: robot {frame.robot!r} in the payload, {robot!r} in the key")
            return
        if frame.edge and frame.edge != self.edge_id:  # the peek could not read it; the decode did
            self._count("other_edge")
            return
        self._count("received")
        p = _Pending(frame, arrival)
        try:
            check_frame(frame, self.limits)  # before it waits in a queue, let alone reaches a decoder
        except ValueError as exc:
            self._count("errors")
            self._reply(p, "error", detail=str(exc)[:200])
            return
        dropped = None
        with self._cond:
            q = self._pending.setdefault(frame.robot, deque())
            q.append(p)
            if len(q) > self.queue_len:
                dropped = q.popleft()
                self.counters["dropped"] += 1
            self._cond.notify()
        if dropped is not None:
            self._reply(dropped, "dropped", detail="edge detector overloaded")

    def _refuse(self, data: bytes, robot: str, arrival: float = float("nan")) -> None:
        why = self.admission.why_refused(robot)
        self.drops.drop("refused", why)
        if self._session is None or not self.admission.answer_refusal():
            return
        try:
            frame = wire.decode(data, expect=wire.Frame, limits=self.limits)
        except wire.WireError:
            return
        if frame.robot == robot:  # Detections has no "refused" status: an error that says so
            self._session.put(self.keys.detections(robot, self.edge_id),
                              wire.encode(self._answer(frame, "error", f"refused: {why}", arrival=arrival)),
                              congestion_control=zenoh.CongestionControl.DROP, express=True)

    def _take(self) -> list[_Pending]:
        """This pass's frames (module docstring): up to ``batch`` robots' newest, the robot waiting
        longest first, their older frames answered ``dropped``; or (``serve="oldest"``) up to
        ``batch`` frames, oldest first across robots."""
        superseded: list[_Pending] = []
        with self._cond:
            while not self._stop.is_set() and not any(self._pending.values()):
                self._cond.wait(0.2)
            if self.serve == "newest":
                queues = sorted((q for q in self._pending.values() if q), key=lambda q: q[0].arrival)
                taken = []
                for q in queues[: self.batch]:
                    taken.append(q.pop())
                    superseded.extend(q)
                    q.clear()
                self.counters["dropped"] += len(superseded)
                self.counters["superseded"] += len(superseded)
            else:
                items = [p for q in self._pending.values() for p in q]
                items.sort(key=lambda p: p.arrival)
                taken = items[: self.batch]
                for p in taken:
                    self._pending[p.frame.robot].remove(p)
            self._in_pass += len(taken)
        for p in superseded:
            self._reply(p, "dropped", detail="superseded by a newer frame of this robot")
        return taken

    def _work(self) -> None:
        while not self._stop.is_set():
            items = self._take()
            for p in items:
                self._serve(p, len(items))

    def _serve(self, p: _Pending, batch: int) -> None:
        start = time.monotonic()
        with self._cond:
            self._busy_since = start
        try:
            img = decode_image(p.frame, self.limits)
            det = to_camera(self.detector.detect(img), p.frame)
        except Exception as exc:  # a bad frame is answered and counted, the service carries on
            self._served("errors", start)
            log.warning("robot %s frame %d: %s", p.frame.robot, p.frame.seq, exc)
            self._reply(p, "error", detail=str(exc)[:200], queue_time=start - p.arrival)
            return
        self._served("served", start)
        self.infer_times.append(self.detector.last_infer_time)
        self._reply(p, "ok", queue_time=start - p.arrival, infer_time=time.monotonic() - start,
                    batch=batch, det=det)

    def _served(self, what: str, start: float) -> None:
        end = time.monotonic()
        with self._cond:
            self.counters[what] += 1
            self._in_pass -= 1
            self._busy_since = None
            self._busy.append((start, end))
            while self._busy and self._busy[0][1] < end - BUSY_WINDOW:
                self._busy.popleft()

    def busy_share(self, now: float | None = None) -> float:
        """The share of the last ``BUSY_WINDOW`` seconds (less, just after start) the inference
        thread spent on frames."""
        now = time.monotonic() if now is None else now
        since = max(now - BUSY_WINDOW, self._started)
        with self._cond:
            spans = [*self._busy, *([(self._busy_since, now)] if self._busy_since is not None else [])]
        busy = sum(max(0.0, min(end, now) - max(start, since)) for start, end in spans)
        return min(1.0, busy / (now - since)) if now > since else 0.0

    def _answer(self, frame: wire.Frame, status: str, detail: str = "", queue_time: float = float("nan"),
                infer_time: float = float("nan"), batch: int = 0,
                det: Detections | None = None, arrival: float = float("nan")) -> wire.Detections:
        """The answer to ``frame``; stamped with its ``arrival`` (this edge's clock) only when the
        robot said it reads codec version 4 (an older robot refuses the field)."""
        def duration(x: float) -> float:  # what the codec accepts; NaN = not measured
            return x if 0.0 <= x <= 3600.0 else float("nan")

        return wire.Detections(
            robot=frame.robot, seq=frame.seq, send_stamp=frame.send_stamp, edge=self.edge_id,
            model=self.detector.name, status=status, infer_time=duration(infer_time),
            queue_time=duration(queue_time), batch=batch, detail=detail,
            boxes=det.boxes if det is not None else np.zeros((0, 4), np.float32),
            scores=det.scores if det is not None else np.zeros(0, np.float32),
            classes=det.classes if det is not None else np.zeros(0, np.int32),
            arrival=arrival if frame.reads >= 4 else float("nan"),
        )

    def _reply(self, p: _Pending, status: str, detail: str = "", queue_time: float = float("nan"),
               infer_time: float = float("nan"), batch: int = 0, det: Detections | None = None) -> None:
        msg = self._answer(p.frame, status, detail, queue_time, infer_time, batch, det, p.arrival)
        try:
            if not self.admission.is_admitted(p.frame.robot):  # evicted meanwhile: no publisher again
                assert self._session is not None
                self._session.put(self.keys.detections(p.frame.robot, self.edge_id), wire.encode(msg),
                                  congestion_control=zenoh.CongestionControl.DROP, express=True)
                return
            with self._cond:
                pub = self._pub(p.frame.robot)
            pub.put(wire.encode(msg))
        except Exception as exc:  # session closing
            log.debug("detections not published: %s", exc)

    # Eviction (the server's housekeeping)
    def evict(self, robot: str) -> None:
        """Answer the robot's waiting frames as dropped and forget it."""
        with self._cond:
            waiting = list(self._pending.pop(robot, ()))
            self.counters["evicted"] += len(waiting)
        for p in waiting:
            self._reply(p, "dropped", detail="robot evicted from the edge")
        with self._cond:
            pub = self._pubs.pop(robot, None)
        undeclare(pub)

    def balance(self) -> dict[str, int]:
        """The counters of the invariant (module docstring), with what is waiting now."""
        with self._cond:
            out = {k: int(self.counters[k]) for k in ("samples", "other_edge", "received", "served", "errors",
                                                      "dropped", "evicted")}
            out["queued"] = sum(len(q) for q in self._pending.values())
            out["in_pass"] = self._in_pass
        out["drops"] = sum(self.drops.snapshot().values())
        return out

    def balanced(self) -> bool:
        b = self.balance()
        return (b["samples"] == b["drops"] + b["other_edge"] + b["received"]
                and b["received"] == sum(b[k] for k in ("served", "errors", "dropped", "evicted", "queued",
                                                         "in_pass")))

    def status(self) -> dict[str, float]:
        free = 1.0 - self.busy_share()
        with self._cond:
            values = {f"detector.{k}": float(v) for k, v in self.counters.items()}
            values["detector.queued"] = float(sum(len(q) for q in self._pending.values()))
        values["detector.free"] = free
        drops = self.drops.snapshot()
        values.update({f"detector.drop.{k}": float(v) for k, v in drops.items()})
        values["detector.drops"] = float(sum(drops.values()))
        # What frames can be shrunk to on the way here (robot/camera.py reads it; detect/detector.py)
        net_h, net_w = self.detector.input_hw
        values.update({"detector.input_w": float(net_w), "detector.input_h": float(net_h),
                       "detector.stretch": float(self.detector.stretch)})
        if self.infer_times:
            values["detector.infer_ms"] = float(np.mean(self.infer_times) * 1e3)
        return values
