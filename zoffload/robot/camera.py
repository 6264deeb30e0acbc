"""The robot's camera pipeline: each camera frame is detected on the robot or on the edge.

Inputs:  an image source (``coco-clips``, a folder, a video), ``<ns>/data/<robot>/detections/**``
         (wire.Detections), the edges present (the robot server's ``EdgePresence``) and their
         status (``<ns>/status/edge/*``: the detector's free share, draining, its network's input:
         frames to that edge are shrunk to it, ``perception.send_size``).
Outputs: ``<ns>/data/<robot>/frame`` (wire.Frame, put by one sender thread that blocks while the
         link is busy, newest frame waiting; each names the edge asked to detect it, chosen by
         robot/edgechoice.py among the present edges: sticky, moving when that edge goes, drains or
         is full; only that edge's answer counts, another's is a counted ``wrong_edge`` drop);
         ``<ns>/view/<robot>/preview`` (wire.Preview, a few per second while a viewer subscribes:
         robot/preview.py); status values (frame counters,
         CPU, Mbps, power, ping); results in ``out_dir``: ``frames.csv`` (one row per camera
         frame), ``detections.npz`` (person boxes of every processed frame),
         ``vision_metrics.json``, ``monitor.csv``. Only the newest ``keep_frames`` records stay in
         memory; older ones go to ``frames.csv`` (and a hidden detections file) as the run goes
         (robot/framelog.py).

Threads: the camera (paces the source, keeps only the newest frame), this pipeline's loop
(decides and dispatches, never waits on a detector or on the link), the frame sender (one slot),
the local detector (one slot; it waits for the strategy's ``local_ready_at``, the pacing that
keeps it within the robot's CPU budget), the preview publisher, a 1 Hz monitor (CPU, outgoing
Mbps, RAPL power, ping-pong RTT to the edge). The bookkeeping and the fallback state machine are
robot/frames.py's ``FrameBook``; every call into it holds ``self._lock``.
"""

from __future__ import annotations

import csv
import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import zenoh

from zoffload.detect.detector import Detections, resize_to
from zoffload.policy.offload import BOTH, EDGE, LOCAL, Strategy, make_strategy
from zoffload.protocol import wire
from zoffload.protocol.intake import answer_from
from zoffload.protocol.keys import Keys
from zoffload.robot.edgechoice import EdgeChoice
from zoffload.robot.encoding import JPEG, RAW, EncodingChoice
from zoffload.robot.frames import FallbackRules, FrameBook, RobotView
from zoffload.robot.presence import EdgePresence
from zoffload.robot.preview import Offer, PreviewPublisher
from zoffload.robot.sensor import FrameSource, Reading, SensorThread
from zoffload.runtime.config import RobotSettings
from zoffload.runtime.drops import Drops
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.monitor import RaplMonitor, ResourceMonitor
from zoffload.runtime.results import write_figures
from zoffload.runtime.session import has_subscribers, undeclare
from zoffload.sources.images import open_image_source

log = logging.getLogger("zoffload.robot.camera")

# A put Zenoh holds longer than this is counted (``slow_puts``) and its wall-clock span kept (the
# newest ``SLOW_PUT_SPANS``, in vision_metrics.json). Zenoh (1.10) holds a BLOCK put while its
# queue to the edge is full; when that edge's connection closes meanwhile, Zenoh's transport close
# waits for the held put, up to its ``wait_before_close`` (5 s by default), before the edge's
# liveliness token is seen to go: the fallback then comes when the put is let go, not at the kill
# (README, Perception offloading). On a slow link every raw frame may take this long: logged at
# most once a minute.
SLOW_PUT_S = 1.0
SLOW_PUT_SPANS = 20


class LocalDetector(Protocol):
    """What the pipeline needs of the robot's own detector (detect/detector.py's ``Detector``)."""

    last_infer_time: float

    @property
    def name(self) -> str: ...

    def detect(self, bgr: np.ndarray) -> Detections: ...


@dataclass(frozen=True)
class CameraOptions:
    robot_id: str
    fps: float
    max_frames: int | None = None
    replay: str = "once"  # a recorded source: once, loop or pingpong
    encoding: str = RAW  # bgr8, jpeg, or auto: chosen per frame (robot/encoding.py)
    jpeg_quality: int = 80
    send_size: str = "detector"  # frames to the edge shrunk to its detector's input, or "camera": whole
    wait_edge: float = 5.0  # seconds to wait for the edge's subscriber to match at start
    cpu_quota: float | None = None  # reported in the metrics (applied by the server)
    quota_mode: str | None = None
    preview_period: float = 0.25  # seconds between previews at most (0: no previews)
    keep_frames: int = 4096  # finished frame records held in memory (robot/framelog.py)
    out_dir: Path | None = None  # older records retire onto disk here as the run goes


class CameraOffloader:
    name = "camera"

    def __init__(self, source: FrameSource, detector: LocalDetector, strategy: Strategy,
                 rules: FallbackRules, keys: Keys, options: CameraOptions, stop: StopSignal) -> None:
        self.source = source
        self.local = detector
        self.strategy = strategy
        self.rules = rules
        self.keys = keys
        self.opts = options
        self.stop = stop
        self.book = FrameBook(strategy, rules, keep=options.keep_frames, folder=options.out_dir,
                              encodings=EncodingChoice(options.encoding))
        self.choice = EdgeChoice(options.robot_id)  # the edge each frame goes to
        self.drops = Drops(log)
        self.camera = SensorThread(source, options.fps, options.replay, options.max_frames, name="camera")
        self._lock = threading.RLock()
        self._local_slot: Reading | None = None
        self._local_cond = threading.Condition(self._lock)
        self._local_busy = False
        self._local_started = -math.inf  # when the local detector last started a frame
        self._local_cpu = 0.0  # CPU seconds the local detector spent so far
        # The strategy's pacing counts on the robot's CPU budget only where a cgroup enforces it
        applied = options.quota_mode is not None and options.quota_mode.startswith("cgroup")
        self._quota = float(options.cpu_quota) if options.cpu_quota and applied else math.nan
        self._edge_images: dict[int, np.ndarray] = {}  # frames at the edge, kept for previews
        self.preview: PreviewPublisher | None = None
        self._send_slot: Reading | None = None
        self._send_cond = threading.Condition(self._lock)
        self._stopping = False
        self.bytes_sent = 0
        self.slow_puts: deque[tuple[int, float, float]] = deque(maxlen=SLOW_PUT_SPANS)  # (seq, start, end)
        self._slow_put_logged = -math.inf
        self.monitor: ResourceMonitor | None = None
        self._threads: list[threading.Thread] = []

    # Startup
    def start(self, session: zenoh.Session, presence: EdgePresence) -> None:
        self.session = session
        self.local.detect(np.zeros((64, 64, 3), np.uint8))  # allocate before the first frame
        presence.subscribe(self._on_edges)
        with self._lock:
            self.book.edge_present = presence.any
            self.choice.present(presence.edges)
        presence.subscribe_status(self._on_edge_status)
        self._det_sub = session.declare_subscriber(self.keys.detections_to(self.opts.robot_id),
                                                   self.drops.guard(self._on_result, "detections"))
        self._pub = session.declare_publisher(self.keys.frame(self.opts.robot_id),
                                              congestion_control=zenoh.CongestionControl.BLOCK)
        if self.opts.preview_period > 0:
            key = self.keys.preview(self.opts.robot_id)
            self.preview = PreviewPublisher(session, key, self.opts.robot_id,
                                            period=self.opts.preview_period).start()
        def ping() -> str | None:
            """The ping key of the edge frames go to now, or would go to first (the rule's round
            trip is to that edge: in a fleet, another edge's link says nothing of it)."""
            with self._lock:
                edge = self.choice.current
                if edge is None or edge not in self.choice.edges:
                    order = self.choice.rank(skip_full=False)
                    edge = order[0] if order else None
            return self.keys.ping(self.opts.robot_id, edge) if edge is not None else None

        spool = self.opts.out_dir / "monitor.csv" if self.opts.out_dir else None
        self.monitor = ResourceMonitor(session, ping, lambda: float(self.bytes_sent),
                                       ping_timeout=self.rules.reply_timeout, spool=spool).start()
        for target, name in ((self._local_worker, "local-detector"), (self._sender, "frame-sender")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        log.info("camera %s (%d frames at %.0f FPS), strategy %s, local %s", self.source.name,
                 len(self.source), self.opts.fps, self.strategy.name, self.local.name)
        if self.opts.wait_edge > 0 and self.strategy.name != "robot":
            # Present (liveliness) and subscribed: a frame published before the edge's subscriber
            # is matched would be lost on the way
            deadline = time.monotonic() + self.opts.wait_edge
            while time.monotonic() < deadline and not (presence.any and has_subscribers(self._pub)):
                time.sleep(0.01)

    def close(self) -> None:
        self._stop_threads()
        if self.monitor is not None:
            self.monitor.close()
        if self.preview is not None:
            self.preview.close()
        undeclare(getattr(self, "_det_sub", None), getattr(self, "_pub", None))

    # Zenoh callback threads
    def _on_edges(self, edge: str, present: bool, edges: frozenset[str]) -> None:
        now = time.time()
        with self._lock:
            self.choice.present(edges)
            if not present and edges:  # frames sent to it will not be answered; others stay
                self.book.edge_gone(edge, now)
            self.book.edges_changed(bool(edges), now)

    def _on_edge_status(self, msg: wire.Status) -> None:
        """An edge's status (read and checked by the robot's EdgePresence): its detector's room."""
        with self._lock:
            self.choice.status(msg.id, msg.values)

    def _on_result(self, sample: zenoh.Sample) -> None:
        now = time.time()
        try:
            msg = wire.decode(sample.payload.to_bytes(), expect=wire.Detections)
        except wire.WireError as exc:
            with self._lock:
                self.book.counters["malformed_results"] += 1
            self.drops.drop("malformed_detections", str(exc))
            return
        if msg.robot != self.opts.robot_id:
            self.drops.drop("foreign_detections", f"detections for robot {msg.robot!r}")
            return
        if not answer_from(sample, self.keys, self.drops, msg.edge, "detections"):  # another edge's name
            return
        keep = msg.classes == 0
        boxes, scores = msg.boxes[keep].copy(), msg.scores[keep].copy()
        with self._lock:
            bucket = self.book.edge_result(msg.seq, msg.status, now, msg.infer_time, msg.queue_time,
                                           boxes, scores, edge=msg.edge, arrival=msg.arrival)
            image = self._edge_images.pop(msg.seq, None) if bucket != "wrong_edge" else None
        if bucket == "wrong_edge":
            self.drops.drop("wrong_edge", f"frame {msg.seq} answered by edge {msg.edge!r}, not the one asked")
        elif bucket == "unknown":
            log.debug("result for frame %d that is not in flight (late or unknown)", msg.seq)
        elif bucket == "edge_done" and image is not None and self.preview is not None:
            self.preview.offer(Offer(msg.seq, now, EDGE, image, boxes, scores))

    # Local detector (one slot: a newer frame replaces one still waiting)
    def _local_worker(self) -> None:
        while not self.stop.is_set() and not self._stopping:
            with self._local_cond:
                while not self.stop.is_set() and not self._stopping:
                    # A frame, and the strategy's pacing lets the detector start (meanwhile a newer
                    # frame may take the slot)
                    wait = 0.1 if self._local_slot is None else self.strategy.local_ready_at - time.time()
                    if wait <= 0:
                        break
                    self._local_cond.wait(min(wait, 0.1))
                reading, self._local_slot = self._local_slot, None
                if reading is None:
                    continue
                self._local_busy = True
                self._local_started = started = time.time()
            cpu_start = time.thread_time()  # onnxruntime with one thread runs in this one
            try:
                det: Detections | None = self.local.detect(reading.frame.image).of_class(0)
            except Exception as exc:  # a bad frame is counted, the worker carries on
                det = None
                log.warning("local detection of frame %d failed: %s", reading.seq, exc)
            cpu = time.thread_time() - cpu_start
            now = time.time()
            with self._lock:
                self._local_busy = False
                self._local_cpu += cpu
                if det is None:
                    self.book.failed(reading.seq)
                else:
                    self.book.local_result(reading.seq, now, now - started, self.local.last_infer_time,
                                           det.boxes, det.scores, cpu=cpu)
            if det is not None and self.preview is not None:
                self.preview.offer(Offer(reading.seq, now, LOCAL, reading.frame.image, det.boxes, det.scores))

    def _to_local(self, reading: Reading) -> None:
        with self._local_cond:
            if self._local_slot is not None:
                self.book.local_replaced(self._local_slot.seq)
            self._local_slot = reading
            self._local_cond.notify()

    # Edge (one slot: the sender blocks while the link is busy; only the newest frame waits)
    def _to_edge(self, reading: Reading, probe: bool, copy: bool = False, edge: str = "") -> None:
        with self._send_cond:
            self.book.sent(reading.seq, time.time(), probe, copy=copy, edge=edge)
            if self._send_slot is not None:  # the link has not taken the previous one yet
                self.book.send_replaced(self._send_slot.seq)
                self._edge_images.pop(self._send_slot.seq, None)
            self._send_slot = reading
            if self.preview is not None and self.preview.wanted and not copy:
                self._edge_images[reading.seq] = reading.frame.image
                while len(self._edge_images) > 16:  # bounded: frames lost on the way leave theirs
                    del self._edge_images[next(iter(self._edge_images))]
            self._send_cond.notify()

    def _sender(self) -> None:
        """Encodes and puts edge frames one at a time. The publisher blocks while the link is busy
        (a raw frame, 0.52 MB shrunk to PicoDet's input, 1.2 MB whole, takes 26 or 61 ms at 160 Mbps)
        instead of letting Zenoh drop fragments of it;
        meanwhile only the newest frame waits in the slot, older ones are dropped and counted."""
        while not self.stop.is_set() and not self._stopping:
            with self._send_cond:
                while self._send_slot is None and not self.stop.is_set() and not self._stopping:
                    self._send_cond.wait(0.1)
                reading, self._send_slot = self._send_slot, None
                if reading is None or not self.book.waiting_to_send(reading.seq):
                    continue  # already booked (lost when the edge went)
                edge = self.book.edge_of(reading.seq)
                encoding, _ = self.book.encoding_for(reading.seq, time.time())
                h, w = reading.frame.image.shape[:2]
                size = self.choice.send_size(edge, w, h) if self.opts.send_size == "detector" else (w, h)
                reads = self.choice.reads(edge)
            encode_start = time.time()
            try:
                data = frame_message(reading.frame.image, self.opts.robot_id, reading.seq, encode_start, edge,
                                     encoding, self.opts.jpeg_quality, size, reads)
            except Exception as exc:  # one bad frame must not end the run
                with self._lock:
                    self.book.send_failed(reading.seq, time.time())
                log.error("frame %d: %s", reading.seq, exc)
                continue
            encode_ms = (time.time() - encode_start) * 1e3
            with self._lock:
                put_start = time.time()  # when its bytes went to Zenoh (robot/frames.py _reply)
                self.book.putting(reading.seq, put_start, time.monotonic(), bytes=len(data),
                                  encode_ms=encode_ms, sent_size=f"{size[0]}x{size[1]}")
                self.bytes_sent += len(data)
            try:
                self._pub.put(data)
            except Exception as exc:  # a closing session; the frame's timeout books it
                log.debug("frame %d not sent: %s", reading.seq, exc)
            put_end = time.time()
            if put_end - put_start > SLOW_PUT_S:
                with self._lock:
                    self.book.counters["slow_puts"] += 1
                    self.slow_puts.append((reading.seq, put_start, put_end))
                    count = self.book.counters["slow_puts"]
                if put_end - self._slow_put_logged > 60.0:
                    self._slow_put_logged = put_end
                    log.warning("frame %d: Zenoh held its put %.2f s (%d such puts so far): the link to "
                                "the edge is congested or gone", reading.seq, put_end - put_start, count)

    # Main loop
    def dispatch(self, reading: Reading) -> None:
        with self._lock:
            now = time.time()
            side, probe = self.book.decide(reading.seq, reading.frame.index, reading.capture_stamp,
                                           now, self._robot_view())
            # "" only in the instant between the last edge going and the book hearing of it
            edge = (self.choice.pick(now) or "") if side in (EDGE, BOTH) else ""
            try:
                if side in (LOCAL, BOTH):
                    self._to_local(reading)
                if side == BOTH:  # a copy only measures the edge
                    self._to_edge(reading, False, copy=True, edge=edge)
                elif side == EDGE:
                    self._to_edge(reading, probe, edge=edge)
            except Exception as exc:  # one bad frame must not end the run
                self.book.failed(reading.seq)
                log.error("frame %d: %s", reading.seq, exc)

    def _robot_view(self) -> RobotView:
        """The robot side as the strategy sees it (called with the lock held)."""
        now = time.time()
        cpu, mbps = self._smoothed()
        return RobotView(cpu_percent=cpu, mbps_out=mbps, local_busy=self._local_busy,
                         local_busy_for=now - self._local_started if self._local_busy else 0.0,
                         local_waiting=self._local_slot is not None, local_last_start=self._local_started,
                         send_waiting=self._send_slot is not None, cpu_time=time.process_time(),
                         local_cpu_time=self._local_cpu, cpu_quota=self._quota)

    def run(self) -> None:
        self.camera.start()
        booked_overwrites = booked_unreadable = 0
        try:
            while not self.stop.is_set():
                reading = self.camera.take(timeout=0.02)
                with self._lock:
                    self.book.expire(time.time())
                    new = self.camera.overwritten - booked_overwrites
                    bad = self.camera.read_errors - booked_unreadable
                    self.book.camera_dropped(new, bad)
                    booked_overwrites += new
                    booked_unreadable += bad
                if reading is None:
                    if self.camera.exhausted:
                        break
                    continue
                self.dispatch(reading)
        finally:
            self.camera.stop()
            with self._lock:
                self.book.camera_dropped(self.camera.overwritten - booked_overwrites,
                                         self.camera.read_errors - booked_unreadable)
            self._drain()

    def _drain(self) -> None:
        """Let the local detector and in-flight edge frames finish, then book what is left."""
        deadline = time.time() + self.rules.reply_timeout + 1.0
        while time.time() < deadline:
            with self._lock:
                if not self.book.in_flight and self._local_slot is None and not self._local_busy:
                    break
            time.sleep(0.02)
        with self._lock:
            send = self._send_slot.seq if self._send_slot is not None else None
            local = self._local_slot.seq if self._local_slot is not None else None
            self._send_slot = self._local_slot = None
            self.book.close(time.time(), send, local)
        self._stop_threads()

    def _stop_threads(self) -> None:
        self._stopping = True
        if self.monitor is not None:
            self.monitor.stop()
        with self._lock:
            self._local_cond.notify_all()
            self._send_cond.notify_all()

    def _smoothed(self) -> tuple[float, float]:
        return self.monitor.smoothed() if self.monitor else (float("nan"), float("nan"))

    def _latest_sample(self) -> dict[str, float] | None:
        return self.monitor.latest() if self.monitor else None

    def _monitor_means(self) -> dict[str, float | None]:
        return self.monitor.means() if self.monitor else {}

    def status(self) -> dict[str, float]:
        """Frame counters and the latest monitor readings, for the robot's status message."""
        with self._lock:
            values = {k: float(v) for k, v in self.book.balance().items()}
            values.update(fallback=float(self.book.fallback), offloaded=float(self.strategy.offloaded),
                          detector_edge_switches=float(self.choice.switches))
            last = self._latest_sample()
            if last:
                values.update({k: float(last[k]) for k in ("cpu_system", "cpu_process", "mbps_out",
                                                            "power_w", "ping_ms")})
        return values

    # Results
    def metrics(self) -> dict[str, Any]:
        with self._lock:
            summary = self.book.summary(self._monitor_means())
            switches = self.choice.switches
            slow = list(self.slow_puts)
        return {"robot": self.opts.robot_id, "source": self.source.name, "strategy": self.strategy.name,
                "local_model": self.local.name, "encoding": self.opts.encoding,
                "send_size": self.opts.send_size,
                "cpu_quota": self.opts.cpu_quota, "cpu_quota_applied": self.opts.quota_mode,
                "power_available": RaplMonitor().available, "edge_switches": switches,
                "slow_put_spans": [{"seq": q, "start": a, "end": b} for q, a, b in slow],
                # frames the source could not read (each skipped), and why it ended early if it did
                "read_errors": self.camera.read_errors, "source_failed": self.camera.failed, **summary}

    def write_results(self, out_dir: Path) -> None:
        out_dir.mkdir(parents=True, exist_ok=True)
        write_figures(out_dir / "vision_metrics.json", self.metrics())
        with self._lock:  # the pipeline has stopped: nothing changes the records any more
            self.book.log.write(out_dir, self.camera.period)
        if self.monitor is not None:
            self.monitor.write_csv(out_dir / "monitor.csv")
        else:
            with open(out_dir / "monitor.csv", "w", newline="") as f:
                csv.DictWriter(f, fieldnames=ResourceMonitor.FIELDS).writeheader()


def frame_message(image: np.ndarray, robot: str, seq: int, now: float, edge: str = "", encoding: str = RAW,
                  jpeg_quality: int = 80, size: tuple[int, int] | None = None, reads: int = 3) -> bytes:
    """The encoded ``wire.Frame`` of a BGR ``image``: shrunk to ``size`` (width, height) first when
    that differs (with the edge detector's own interpolation, so its resize of what arrives is the
    identity), then raw or JPEG; ``reads`` the codec version the robot tells the edge it reads (4
    only for an edge that said it reads 4). The frame sender's whole work per frame besides the put
    (``benchmarks/bench_frame_send.py`` times it)."""
    cam_h, cam_w = image.shape[:2]
    img = image if size is None else resize_to(image, size)
    h, w = img.shape[:2]
    shrunk = (w, h) != (cam_w, cam_h)
    if encoding == JPEG:
        import cv2

        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        if not ok:
            raise ValueError("JPEG encoding failed")
        data = buf.ravel()
    else:
        data = np.ascontiguousarray(img).reshape(-1)
    return wire.encode(wire.Frame(robot=robot, seq=seq, send_stamp=now, capture_stamp=now, encoding=encoding,
                                  width=w, height=h, data=data, edge=edge,
                                  camera_width=cam_w if shrunk else 0, camera_height=cam_h if shrunk else 0,
                                  reads=reads))


def camera_offloader(settings: RobotSettings, stop: StopSignal, quota_mode: str | None = None,
                     detector: LocalDetector | None = None) -> CameraOffloader:
    """The camera pipeline for these settings (``detector`` to inject another local detector)."""
    if not settings.images:
        raise ValueError("no image source configured (robot.images)")
    p = settings.perception
    source = open_image_source(settings.images, p.fps)
    if detector is None:
        from zoffload.detect.detector import Detector

        detector = Detector(p.local_model, p.local_model_path, threads=p.local_threads)
    dispatch = ({"max_age": p.max_age, "local_bias": p.local_bias, "learn_bias": p.learn_bias,
                 "refresh_period": p.refresh_period,
                 "retry_period": p.retry_period, "base_period": p.base_period, "cpu_share": p.cpu_share,
                 "overflow": p.overflow}
                if p.strategy == "dispatch" else {})
    strategy = make_strategy(p.strategy, p.cpu_max, p.bw_max_mbps or math.inf, p.max_in_flight, **dispatch)
    rules = FallbackRules(reply_timeout=p.reply_timeout, fallback_losses=p.fallback_losses,
                          probe_period=p.probe_period, resume_after=p.resume_after)
    options = CameraOptions(robot_id=settings.robot_id, fps=p.fps or source.rate_hz, max_frames=p.max_frames,
                            replay=p.replay,
                            encoding=p.encoding, jpeg_quality=p.jpeg_quality, send_size=p.send_size,
                            wait_edge=settings.wait_edge,
                            cpu_quota=p.cpu_quota, quota_mode=quota_mode, preview_period=p.preview_period,
                            out_dir=Path(settings.out_dir) if settings.out_dir else None)
    return CameraOffloader(source, detector, strategy, rules, Keys(settings.namespace), options, stop)
