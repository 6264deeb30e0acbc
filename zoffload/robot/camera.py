"""The robot's image offloader: each camera frame is detected on the robot or on the edge.

Inputs:  an image source (``coco-clips``, a folder, a video), ``<ns>/data/<robot>/detections``
         (wire.DetectionsMsg), liveliness ``<ns>/alive/edge/*``.
Outputs: ``<ns>/data/<robot>/frame`` (wire.Frame, put by one sender thread that blocks while the
         link is busy, newest frame waiting); results in
         ``out_dir``: ``frames.csv`` (one row per camera frame), ``detections.npz`` (person boxes
         of every processed frame), ``vision_metrics.json``.

Threads: the camera (paces the source, keeps only the newest frame: frames it overwrites are
dropped at the camera and counted), this loop (decides and dispatches, never waits on a detector
or on the link), the frame sender (one slot, like the local detector: ``dropped_send``),
the local detector (one slot: a frame still waiting when a newer local frame comes is dropped as
stale and counted; a frame the strategy holds back is dropped as ``dropped_window``), a 1 Hz
monitor (CPU, outgoing Mbps, RAPL power, ping-pong RTT to the edge). Every frame the camera
produced ends in exactly one bucket (``frames_in = processed + dropped``).

Fallback: when the edge's liveliness token goes, frames in flight are booked lost at once and
every frame is detected locally. An edge frame unanswered for ``reply_timeout`` is lost; it puts
the robot in fallback too when ``fallback_losses`` frames in a row went unanswered and nothing came
back for a whole timeout (a frame lost now and then is the link's loss: counted, and seen by the
strategy). In fallback one probe
frame goes to the edge every ``probe_period`` while its token is present; ``resume_after`` prompt
answers in a row end the fallback (hysteresis).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.detect.detector import Detector
from zoffload.policy.offload import EDGE, HOLD, LOCAL, OffloadState, make_strategy
from zoffload.protocol import wire
from zoffload.protocol.keys import Keys
from zoffload.robot.sensor import Reading, SensorThread
from zoffload.runtime.config import RobotSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.monitor import ByteRate, CpuMonitor, MovingAverage, Pinger, RaplMonitor
from zoffload.sources.images import ImageFrame, open_image_source

log = logging.getLogger("zoffload.robot.camera")

FRAME_FIELDS = ["seq", "index", "capture", "side", "probe", "send", "result", "status", "rtt_ms",
                "edge_infer_ms", "edge_queue_ms", "local_infer_ms", "bytes", "n_persons"]
# Final buckets of a camera frame
DONE = ("local_done", "edge_done")
DROPPED = ("dropped_camera", "dropped_stale", "dropped_window", "dropped_send", "edge_lost", "edge_dropped",
           "edge_error", "error")


class ImageOffloader:
    def __init__(self, settings: RobotSettings, session: Any = None, stop: StopSignal | None = None) -> None:
        if not settings.images:
            raise ValueError("no image source configured (robot.images)")
        p = self.p = settings.perception
        self.settings = settings
        self.session = session
        self.keys = Keys(settings.namespace)
        self.stop = stop or StopSignal()
        self.source = open_image_source(settings.images, p.fps)
        self.strategy = make_strategy(p.strategy, p.cpu_max, p.bw_max_mbps or math.inf, p.max_in_flight)
        self.local = Detector(p.local_model, p.local_model_path, threads=p.local_threads)
        self.camera = SensorThread(self.source, p.fps or self.source.rate_hz, "once", p.max_frames,
                                   name="camera")
        self.counters: Counter[str] = Counter()
        self.records: dict[int, dict[str, Any]] = {}
        self.persons: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.in_flight: dict[int, float] = {}  # seq -> send time (wall)
        self.edges: set[str] = set()
        self.fallback = False
        self.fallback_events: list[dict[str, float]] = []
        self._probe_streak = 0
        self._last_probe = 0.0
        self._lock = threading.RLock()
        self._slot: Reading | None = None
        self._slot_cond = threading.Condition(self._lock)
        self._local_busy = False
        self.bytes_sent = 0
        self.cpu = MovingAverage(3)
        self.mbps = MovingAverage(3)
        self.samples: list[dict[str, float]] = []
        self._edge_seen = threading.Event()
        self._last_reply = 0.0
        self._stopping = False
        self._send_slot: Reading | None = None
        self._send_cond = threading.Condition(self._lock)
        self._lost_streak = 0

    # Startup
    def start(self) -> None:
        import zenoh

        s = self.settings
        self.local.detect(np.zeros((64, 64, 3), np.uint8))  # allocate before the first frame
        self._edge_sub = self.session.liveliness().declare_subscriber(
            self.keys.any_edge_alive(), self._on_edge_liveliness, history=True)
        self._det_sub = self.session.declare_subscriber(self.keys.detections(s.robot_id), self._on_result)
        self._pub = self.session.declare_publisher(self.keys.frame(s.robot_id),
                                                   congestion_control=zenoh.CongestionControl.BLOCK)
        self._status_pub = self.session.declare_publisher(
            self.keys.robot_status(s.robot_id), congestion_control=zenoh.CongestionControl.DROP)
        self._local_thread = threading.Thread(target=self._local_worker, name="local-detector", daemon=True)
        self._local_thread.start()
        self._send_thread = threading.Thread(target=self._sender, name="frame-sender", daemon=True)
        self._send_thread.start()
        self._monitor_thread = threading.Thread(target=self._monitor, name="monitor", daemon=True)
        self._monitor_thread.start()
        log.info("camera %s (%d frames at %.0f FPS), strategy %s, local %s", self.source.name,
                 len(self.source), self.camera.period ** -1, self.strategy.name, self.local.name)
        wait = self.settings.wait_edge
        if wait > 0 and self.strategy.name != "robot":
            deadline = time.monotonic() + wait
            # Present (liveliness) and subscribed (a frame published before the edge's subscriber
            # is matched would be lost on the way)
            while time.monotonic() < deadline and not (self._edge_seen.is_set()
                                                       and self._pub.matching_status.matching):
                time.sleep(0.01)
            if not self._edge_seen.is_set():
                log.warning("no edge after %.1f s; detecting locally until one appears", wait)

    # Edge presence and results (Zenoh callback threads)
    def _on_edge_liveliness(self, sample: Any) -> None:
        import zenoh

        edge = self.keys.last_chunk(str(sample.key_expr))
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.edges.add(edge)
                self._edge_seen.set()
                log.info("edge %s present", edge)
            else:
                self.edges.discard(edge)
                if not self.edges:
                    now = time.time()
                    for seq in list(self.in_flight):
                        self._book_lost(seq, now)
                    self._enter_fallback(now, "edge liveliness lost")

    def _on_result(self, sample: Any) -> None:
        now = time.time()
        try:
            msg = wire.decode(sample.payload.to_bytes(), expect=wire.DetectionsMsg)
        except wire.WireError as exc:
            with self._lock:
                self.counters["malformed_results"] += 1
            log.warning("dropped malformed detections: %s", exc)
            return
        assert isinstance(msg, wire.DetectionsMsg)
        with self._lock:
            self._last_reply = now
            self._lost_streak = 0
            sent = self.in_flight.pop(msg.seq, None)
            rec = self.records.get(msg.seq)
            if sent is None or rec is None:
                self.counters["late_or_unknown_results"] += 1
                log.debug("result for frame %d that is not in flight (late or unknown)", msg.seq)
                return
            rec.update(result=now, edge_infer_ms=msg.infer_time * 1e3, edge_queue_ms=msg.queue_time * 1e3)
            rtt = now - rec["capture"]
            if msg.status != "ok":
                bucket = "edge_dropped" if msg.status == "dropped" else "edge_error"
                self._finish(msg.seq, bucket)
                self.strategy.on_edge_timeout(self.p.reply_timeout)
                return
            rec["rtt_ms"] = rtt * 1e3
            keep = msg.classes == 0
            self.persons[msg.seq] = (msg.boxes[keep].copy(), msg.scores[keep].copy())
            rec["n_persons"] = int(keep.sum())
            self._finish(msg.seq, "edge_done")
            self.strategy.on_edge_result(rtt)
            if rec.get("probe"):
                self._probe_answered(now - sent)

    # Fallback
    def _enter_fallback(self, now: float, why: str) -> None:
        if not self.fallback:
            self.fallback = True
            self._probe_streak = 0
            self.counters["fallbacks"] += 1
            self.fallback_events.append({"start": now, "end": float("nan")})
            log.warning("fallback to local detection: %s", why)

    def _probe_answered(self, waited: float) -> None:
        if not self.fallback:
            return
        if waited <= self.p.reply_timeout:
            self._probe_streak += 1
        else:
            self._probe_streak = 0
        if self._probe_streak >= self.p.resume_after:
            self.fallback = False
            self.fallback_events[-1]["end"] = time.time()
            log.info("edge answers again: offloading resumes")

    def _book_lost(self, seq: int, now: float) -> None:
        self.in_flight.pop(seq, None)
        self._finish(seq, "edge_lost")
        rec = self.records[seq]
        self.strategy.on_edge_timeout(now - rec["send"])
        if rec.get("probe"):
            self._probe_streak = 0

    def _expire(self, now: float) -> None:
        overdue = [seq for seq, sent in self.in_flight.items() if now - sent > self.p.reply_timeout]
        for seq in overdue:
            self._book_lost(seq, now)
        self._lost_streak += len(overdue)
        # A frame lost now and then is the link's loss (counted, and the strategy sees it); an edge
        # that lets several frames in a row go unanswered, and answered nothing for a whole
        # timeout, is gone
        if (overdue and self._lost_streak >= self.p.fallback_losses
                and now - self._last_reply > self.p.reply_timeout):
            self._enter_fallback(now, f"{self._lost_streak} edge frames in a row unanswered")

    def _finish(self, seq: int, bucket: str) -> None:
        self.records[seq]["status"] = bucket
        self.counters[bucket] += 1

    # Local detector
    def _local_worker(self) -> None:
        while not self.stop.is_set():
            with self._slot_cond:
                while self._slot is None and not self.stop.is_set():
                    self._slot_cond.wait(0.1)
                reading, self._slot = self._slot, None
                if reading is None:
                    continue
                self._local_busy = True
            started = time.time()
            try:
                det = self.local.detect(reading.frame.image).of_class(0)
                err = None
            except Exception as exc:  # a bad frame is counted, the worker carries on
                det, err = None, exc
            now = time.time()
            with self._lock:
                self._local_busy = False
                rec = self.records[reading.seq]
                if det is None:
                    log.warning("local detection of frame %d failed: %s", reading.seq, err)
                    self._finish(reading.seq, "error")
                    continue
                rec.update(result=now, rtt_ms=(now - rec["capture"]) * 1e3,
                           local_infer_ms=self.local.last_infer_time * 1e3, n_persons=len(det))
                self.persons[reading.seq] = (det.boxes, det.scores)
                self._finish(reading.seq, "local_done")
                self.strategy.on_local_result(now - rec["capture"], service=now - started)

    def _to_local(self, reading: Reading) -> None:
        with self._slot_cond:
            if self._slot is not None:
                self._finish(self._slot.seq, "dropped_stale")
            self._slot = reading
            self._slot_cond.notify()

    # Edge
    def _encode(self, frame: ImageFrame, seq: int, now: float) -> bytes:
        import cv2

        img = frame.image
        h, w = img.shape[:2]
        if self.p.encoding == "jpeg":
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, self.p.jpeg_quality])
            if not ok:
                raise ValueError("JPEG encoding failed")
            data = buf.ravel()
        else:
            data = np.ascontiguousarray(img).reshape(-1)
        msg = wire.Frame(robot=self.settings.robot_id, seq=seq, send_stamp=now, capture_stamp=now,
                         encoding=self.p.encoding, width=w, height=h, data=data)
        return wire.encode(msg)

    def _to_edge(self, reading: Reading, probe: bool) -> None:
        """Hand the frame to the sender; it is in flight (and its timeout runs) from now on."""
        now = time.time()
        with self._send_cond:
            self.records[reading.seq].update(send=now, probe=int(probe))
            self.in_flight[reading.seq] = now
            if self._send_slot is not None:  # the link has not taken the previous one yet
                self.in_flight.pop(self._send_slot.seq, None)
                self._finish(self._send_slot.seq, "dropped_send")
            self._send_slot = reading
            self._send_cond.notify()

    def _sender(self) -> None:
        """Encodes and puts edge frames one at a time. The publisher blocks while the link is busy
        (a 1.2 MB raw frame takes 61 ms at 160 Mbps) instead of letting Zenoh drop fragments of it;
        meanwhile only the newest frame waits here, older ones are dropped and counted."""
        while not self.stop.is_set() and not self._stopping:
            with self._send_cond:
                while self._send_slot is None and not self.stop.is_set() and not self._stopping:
                    self._send_cond.wait(0.1)
                reading, self._send_slot = self._send_slot, None
                if reading is None or reading.seq not in self.in_flight:
                    continue
            try:
                data = self._encode(reading.frame, reading.seq, time.time())
            except Exception as exc:  # one bad frame must not end the run
                with self._lock:
                    self.in_flight.pop(reading.seq, None)
                    self._finish(reading.seq, "error")
                log.error("frame %d: %s", reading.seq, exc)
                continue
            with self._lock:
                self.records[reading.seq]["bytes"] = len(data)
                self.bytes_sent += len(data)
            try:
                self._pub.put(data)
            except Exception as exc:  # a closing session; the frame's timeout books it
                log.debug("frame %d not sent: %s", reading.seq, exc)

    # Main loop
    def state(self, now: float) -> OffloadState:
        oldest = min(self.in_flight.values(), default=now)
        return OffloadState(now=now, edge_available=bool(self.edges) and not self.fallback,
                            cpu_percent=self.cpu.value, mbps_out=self.mbps.value,
                            oldest_in_flight_age=now - oldest, in_flight=len(self.in_flight),
                            local_busy=self._local_busy)

    def dispatch(self, reading: Reading) -> None:
        now = time.time()
        with self._lock:
            self.records[reading.seq] = {"seq": reading.seq, "index": reading.frame.index,
                                         "capture": reading.capture_stamp, "status": "pending"}
            self.counters["frames_in"] += 1
            probe = (self.fallback and bool(self.edges) and not self.in_flight
                     and now - self._last_probe >= self.p.probe_period
                     and self.strategy.name != "robot")
            side = EDGE if probe else self.strategy.decide(self.state(now))
            if probe:
                self._last_probe = now
            self.records[reading.seq]["side"] = side
            if side == HOLD:  # the edge's window is full and local is slower: skip this one
                self._finish(reading.seq, "dropped_window")
                return
        try:
            if side == LOCAL:
                self._to_local(reading)
            else:
                self._to_edge(reading, probe)
        except Exception as exc:  # one bad frame must not end the run
            with self._lock:
                self.in_flight.pop(reading.seq, None)
                self._finish(reading.seq, "error")
            log.error("frame %d: %s", reading.seq, exc)

    def run(self) -> dict[str, Any]:
        self.camera.start()
        booked_overwrites = 0
        try:
            while not self.stop.is_set():
                reading = self.camera.take(timeout=0.02)
                with self._lock:
                    self._expire(time.time())
                    new = self.camera.overwritten - booked_overwrites
                    self.counters["frames_in"] += new
                    self.counters["dropped_camera"] += new
                    booked_overwrites += new
                if reading is None:
                    if self.camera.exhausted:
                        break
                    continue
                self.dispatch(reading)
        finally:
            self.camera.stop()
            with self._lock:
                new = self.camera.overwritten - booked_overwrites
                self.counters["frames_in"] += new
                self.counters["dropped_camera"] += new
            self._drain()
        return self.metrics()

    def _drain(self) -> None:
        """Let the local detector and in-flight edge frames finish, then book what is left."""
        deadline = time.time() + self.p.reply_timeout + 1.0
        while time.time() < deadline:
            with self._lock:
                if not self.in_flight and self._slot is None and not self._local_busy:
                    break
            time.sleep(0.02)
        with self._lock:
            now = time.time()
            if self._send_slot is not None:
                self.in_flight.pop(self._send_slot.seq, None)
                self._finish(self._send_slot.seq, "dropped_send")
                self._send_slot = None
            for seq in list(self.in_flight):
                self._book_lost(seq, now)
            if self._slot is not None:
                self._finish(self._slot.seq, "dropped_stale")
                self._slot = None
        self.stop_threads()

    def stop_threads(self) -> None:
        self._stopping = True
        with self._slot_cond:
            self._slot_cond.notify_all()
            self._send_cond.notify_all()

    def _monitor(self) -> None:
        cpu, rapl = CpuMonitor(), RaplMonitor()
        rate = ByteRate(lambda: float(self.bytes_sent))
        # 1 Hz ping-pong over the edge's ping queryable: the network's share of the edge RTT
        pinger = Pinger(self.session, self.keys.ping(self.settings.robot_id), period=1.0,
                        timeout=self.p.reply_timeout).start()
        try:
            while not self.stop.wait(1.0) and not self._stopping:
                system, proc = cpu.sample()
                mbps, watts = rate.sample(), rapl.sample()
                ping = pinger.rtt.value
                with self._lock:
                    self.cpu.add(proc)
                    self.mbps.add(mbps)
                    self.samples.append({"t": time.time(), "cpu_system": system, "cpu_process": proc,
                                         "mbps_out": mbps, "power_w": watts, "ping_ms": ping})
                self._publish_status(system, proc, mbps, watts, ping)
        finally:
            pinger.stop()

    def _publish_status(self, system: float, proc: float, mbps: float, watts: float, ping: float) -> None:
        """Camera counters and monitor readings on the robot's status key (for dashboards)."""
        values = {k: float(v) for k, v in self.balance().items()}
        with self._lock:
            values.update(cpu_system=system, cpu_process=proc, mbps_out=mbps, power_w=watts, ping_ms=ping,
                          fallback=float(self.fallback), edges=float(len(self.edges)),
                          offloaded=float(self.strategy.offloaded))
        status = wire.Status(source="robot", id=self.settings.robot_id, stamp=time.time(), values=values)
        try:
            self._status_pub.put(wire.encode(status))
        except Exception as exc:  # status is best effort
            log.debug("status not published: %s", exc)

    # Results
    def balance(self) -> dict[str, int]:
        with self._lock:
            out = {k: int(self.counters[k]) for k in ("frames_in", *DONE, *DROPPED)}
            out["pending"] = sum(1 for r in self.records.values() if r["status"] == "pending")
        return out

    def metrics(self) -> dict[str, Any]:
        bal = self.balance()
        with self._lock:
            recs = list(self.records.values())
            samples = list(self.samples)
            counters = dict(self.counters)
        done = bal["local_done"] + bal["edge_done"]
        local = [r["rtt_ms"] for r in recs if r["status"] == "local_done"]
        edge = [r["rtt_ms"] for r in recs if r["status"] == "edge_done"]

        def mean(xs: list[Any]) -> float | None:
            xs = [x for x in xs if x is not None and math.isfinite(x)]
            return float(np.mean(xs)) if xs else None

        return {
            "robot": self.settings.robot_id,
            "source": self.source.name,
            "strategy": self.strategy.name,
            "local_model": self.local.name,
            "encoding": self.p.encoding,
            "balance": bal,
            "balanced": bal["frames_in"] == sum(bal[k] for k in (*DONE, *DROPPED)) + bal["pending"],
            "processed_pct": 100.0 * done / bal["frames_in"] if bal["frames_in"] else 0.0,
            "offloaded_pct": 100.0 * self.strategy.offloaded / max(self.strategy.total, 1),
            "robot_rtt_ms": mean(local),
            "edge_rtt_ms": mean(edge),
            "local_infer_ms": mean([r.get("local_infer_ms") for r in recs]),
            "edge_infer_ms": mean([r.get("edge_infer_ms") for r in recs if r["status"] == "edge_done"]),
            "cpu_process_pct": mean([s["cpu_process"] for s in samples]),
            "cpu_system_pct": mean([s["cpu_system"] for s in samples]),
            "mbps_out": mean([s["mbps_out"] for s in samples]),
            "power_w": mean([s["power_w"] for s in samples]),
            "power_available": RaplMonitor().available,
            "ping_ms": mean([s.get("ping_ms") for s in samples]),
            "fallbacks": self.fallback_events,
            "other": {k: v for k, v in counters.items() if k not in bal},
        }

    def write_results(self, out_dir: Path) -> None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "vision_metrics.json").write_text(json.dumps(self.metrics(), indent=2))
        with self._lock:
            recs = [self.records[k] for k in sorted(self.records)]
            persons = dict(self.persons)
            samples = list(self.samples)
        with open(out_dir / "frames.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=FRAME_FIELDS, extrasaction="ignore")
            w.writeheader()
            w.writerows(recs)
        seqs = np.array(sorted(persons), np.int64)
        counts = np.array([len(persons[s][1]) for s in seqs], np.int64)
        np.savez(out_dir / "detections.npz", seqs=seqs, counts=counts,
                 boxes=np.concatenate([persons[s][0] for s in seqs]).reshape(-1, 4) if len(seqs) else
                 np.zeros((0, 4), np.float32),
                 scores=np.concatenate([persons[s][1] for s in seqs]) if len(seqs)
                 else np.zeros(0, np.float32),
                 period=self.camera.period)
        with open(out_dir / "monitor.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=["t", "cpu_system", "cpu_process", "mbps_out", "power_w",
                                              "ping_ms"])
            w.writeheader()
            w.writerows(samples)
