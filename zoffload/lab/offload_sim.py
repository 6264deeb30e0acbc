"""A seeded simulation of the camera pipeline, to tune offloading strategies without a quiet machine.

The robot's real bookkeeping (robot/frames.py ``FrameBook``) and the real strategy objects are
driven on a simulated clock (1 ms steps) against models of what they decide over:

* the camera: one frame every period, prepared by a camera thread that needs CPU (a late frame is
  delivered late; a frame the loop has not taken is replaced and counted, as on the robot);
* the robot's CPU: the camera, the frame sender and the local detector share two cores and
  ``quota`` cores' worth of time per 100 ms period, as a CFS quota hands it out (all threads stall
  once it is spent; the threads that mostly sleep run first when they wake);
* the local detector and the frame sender, one slot each (a newer frame replaces a waiting one);
* the link: a serial pipe at the trace's rate and delay with the link emulator's queue in front
  (``link_queue`` seconds of transmission, as ``zoffload link --queue-ms``); a put blocks while that
  queue is full (Zenoh's BLOCK congestion control on a small send buffer);
* the edge: a queue of ``edge_queue`` frames per robot (the oldest answered ``dropped``) in front
  of one detector with a random service time, which takes the newest waiting frame and answers the
  older ones ``dropped`` (``edge_serve="newest"``, the edge's default) or the oldest (``"oldest"``),
  slowed while the robot's detector runs (robot and edge share the development machine's two
  cores).

Detections are the real detectors' outputs on the clip frames, computed once and cached
(``clip_detections``), scored as ``lab/eval/detection.py`` scores a run (asynchronous AP50: each
result against the ground truth of the frame current when it arrived). The models' constants are
calibrated on short real runs (see docs/perception-log.md); the simulation ranks
strategies, the real runs measure them. Where they disagree the real runs decide: the simulation
does not reproduce what a quarter-core robot's stalling detector costs the edge path (the frames
sent after a stall), and ranked the rule that holds such a detector back below the old one
(capped 37.5 against 44.0 async AP50, Wi-Fi 26.7 against 33.9, 500 frames, seed 0) where the real
runs on the held-out half measured it above (35.5 against 33.7, 32.6 against 29.3).
"""

from __future__ import annotations

import math
import random
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.lab.eval.ap import average_precision
from zoffload.lab.link.trace import Trace, constant, load_trace
from zoffload.policy.offload import BOTH, EDGE, LOCAL, Strategy, make_strategy
from zoffload.robot.frames import FallbackRules, FrameBook, RobotView

DT = 0.001  # simulation step, s
PERIOD_CFS = 0.1  # CFS quota period, s


@dataclass(frozen=True)
class SimConfig:
    fps: float = 25.0
    frame_bytes: float = 848 * 480 * 3 + 200
    quota: float = 0.25  # robot cores; NaN: no quota (two cores)
    camera_cpu: float = 0.005  # CPU s to prepare and dispatch a frame (read, warp, decide)
    send_cpu: float = 0.0028  # CPU s to encode and put a raw frame (msgpack, Zenoh)
    local_cpu: float = 0.02  # CPU s of one local detection (median)
    local_sigma: float = 0.15  # log-normal spread of it
    edge_service: float = 0.045  # s, median edge detection (one thread, as the experiments run it)
    edge_sigma: float = 0.2
    edge_queue: int = 2
    edge_serve: str = "newest"  # which waiting frame the edge's detector takes (edge/detection.py)
    edge_slowdown: float = 0.1  # the edge detector runs this much slower while the robot's runs
    reply_timeout: float = 0.5
    link_queue: float = 0.1  # s of transmission the emulator queues before it stops reading
    seed: int = 0

    def __post_init__(self) -> None:
        if self.edge_serve not in ("newest", "oldest"):
            raise ValueError(f"edge_serve must be 'newest' or 'oldest', not {self.edge_serve!r}")


@dataclass
class _Job:
    seq: int
    cpu_left: float
    started: float = 0.0
    cpu_used: float = 0.0


@dataclass
class _Edge:
    queue: deque[tuple[int, float]] = field(default_factory=deque)  # (seq, arrival)
    busy: tuple[int, float, float, float] | None = None  # (seq, finish, service, queued)


CACHE = Path.home() / ".cache" / "zoffload" / "sim"  # the clips' detections, computed once


def detections_cache(images: str, model: str, cache: Path = CACHE) -> Path:
    """Where ``model``'s detections on the clips named ``images`` are cached."""
    tag = images.replace(":", "_").replace("/", "_").replace("@", "_")
    return cache / f"{tag}-{model}.npz"


def clip_detections(source: Any, model: str, n: int, cache: Path | None = None) -> list[tuple[np.ndarray,
                                                                                                np.ndarray]]:
    """Person boxes and scores of ``model`` on the first ``n`` frames of ``source`` (cached)."""
    if cache is not None and cache.is_file():
        z = np.load(cache)
        if int(z["n"]) >= n:
            ends = np.cumsum(z["counts"])
            return [(z["boxes"][e - c:e], z["scores"][e - c:e]) for c, e in zip(z["counts"][:n], ends[:n],
                                                                                  strict=True)]
    from zoffload.detect.detector import Detector

    det = Detector(model, None, threads=2)
    out = []
    for i in range(n):
        d = det.detect(source.read(i).image).of_class(0)
        out.append((d.boxes.astype(np.float32), d.scores.astype(np.float32)))
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, n=n, counts=np.array([len(s) for _, s in out]),
                 boxes=np.concatenate([b for b, _ in out]).reshape(-1, 4),
                 scores=np.concatenate([s for _, s in out]))
    return out


class Simulation:
    def __init__(self, strategy: Strategy, cfg: SimConfig, trace: Trace, n_frames: int) -> None:
        self.cfg = cfg
        self.trace = trace
        self.n = n_frames
        self.rng = random.Random(cfg.seed)
        self.book = FrameBook(strategy, FallbackRules(reply_timeout=cfg.reply_timeout))
        self.book.edges_changed(True, 0.0)
        self.strategy = strategy
        self.period = 1.0 / cfg.fps

    def _lognormal(self, median: float, sigma: float) -> float:
        return median * math.exp(self.rng.gauss(0.0, sigma))

    def run(self) -> FrameBook:
        cfg, book = self.cfg, self.book
        quota = cfg.quota if math.isfinite(cfg.quota) else math.inf
        t, budget, next_refill = 0.0, quota * PERIOD_CFS, PERIOD_CFS
        cpu_total = local_cpu_total = 0.0
        camera = _Job(0, cfg.camera_cpu)  # preparing frame 0
        camera_ready: int | None = None  # a frame prepared, waiting for its due time
        produced = 0
        local_slot: int | None = None
        local: _Job | None = None
        local_last_start = -math.inf
        send_slot: int | None = None
        sender: _Job | None = None  # CPU part of a put
        sender_blocked: int | None = None  # seq whose put waits for the link
        link: deque[tuple[int, float]] = deque()  # (seq, bytes left) being transmitted, FIFO
        to_edge: list[tuple[float, int]] = []  # (arrival at the edge, seq)
        to_robot: list[tuple[float, int, str, float, float]] = []  # (arrival, seq, status, service, queued)
        arrived_at: dict[int, float] = {}  # seq -> when it reached the edge, until answered
        edge = _Edge()
        end = (self.n + 2) * self.period + 2 * cfg.reply_timeout + 1.0
        while t < end:
            t += DT
            if t >= next_refill:
                budget, next_refill = quota * PERIOD_CFS, next_refill + PERIOD_CFS
            # CPU: two cores and the period's quota; the threads that mostly sleep (camera, sender)
            # run first when they wake, as CFS favours them over the detector that computes
            cores = 2
            for j in (camera if produced < self.n else None, sender, local):
                if j is None or j.cpu_left <= 0 or budget <= 0 or cores == 0:
                    continue
                step = min(DT, j.cpu_left, budget)
                j.cpu_left -= step
                j.cpu_used += step
                budget -= step
                cores -= 1
                cpu_total += step
                if j is local:
                    local_cpu_total += step
            # Camera: a prepared frame is delivered at its due time (late if prepared late)
            if produced < self.n and camera.cpu_left <= 0 and camera_ready is None:
                camera_ready = camera.seq
            if camera_ready is not None and t >= (camera_ready + 1) * self.period:
                seq = camera_ready
                produced += 1
                camera_ready = None
                camera = _Job(seq + 1, cfg.camera_cpu)
                view = RobotView(local_busy=local is not None,
                                 local_busy_for=t - local.started if local is not None else 0.0,
                                 local_waiting=local_slot is not None, local_last_start=local_last_start,
                                 send_waiting=send_slot is not None, cpu_time=cpu_total,
                                 local_cpu_time=local_cpu_total, cpu_quota=cfg.quota)
                book.expire(t)
                side, probe = book.decide(seq, seq, capture=t, now=t, robot=view)
                if side in (LOCAL, BOTH):
                    if local_slot is not None:
                        book.local_replaced(local_slot)
                    local_slot = seq
                if side in (EDGE, BOTH):
                    book.sent(seq, t, probe, copy=side == BOTH)
                    if send_slot is not None:
                        book.send_replaced(send_slot)
                    send_slot = seq
            else:
                book.expire(t)
            # Local detector: starts when paced, finishes when its CPU is done
            if local is None and local_slot is not None and t >= self.strategy.local_ready_at:
                local = _Job(local_slot, self._lognormal(cfg.local_cpu, cfg.local_sigma), started=t)
                local_last_start, local_slot = t, None
            if local is not None and local.cpu_left <= 0:
                book.local_result(local.seq, t, t - local.started, t - local.started,
                                  *_EMPTY, cpu=local.cpu_used)
                local = None
            # Sender: the put's CPU, then it waits until the link has room (one frame on the wire)
            if sender is None and sender_blocked is None and send_slot is not None:
                if book.waiting_to_send(send_slot):
                    sender = _Job(send_slot, cfg.send_cpu)
                    book.records[send_slot]["bytes"] = cfg.frame_bytes
                send_slot = None
            if sender is not None and sender.cpu_left <= 0:  # encoded: put (robot/camera.py)
                book.putting(sender.seq, t)
                sender_blocked, sender = sender.seq, None
            state = self.trace.at(t)
            room = state.rate_bps("up") * cfg.link_queue
            if sender_blocked is not None and sum(left for _, left in link) <= room:
                link.append((sender_blocked, cfg.frame_bytes))
                sender_blocked = None
            # Link: serial, at the trace's rate; the delay after the last byte
            if link and not state.outage:
                seq, left = link[0]
                left -= state.rate_bps("up") * DT
                if left <= 0:
                    link.popleft()
                    to_edge.append((t + state.delay_ms / 1e3, seq))
                else:
                    link[0] = (seq, left)
            # Edge: queue (the oldest answered dropped), one detector
            dropped: list[int] = []
            for arrival in [x for x in to_edge if x[0] <= t]:
                to_edge.remove(arrival)
                edge.queue.append((arrival[1], t))
                arrived_at[arrival[1]] = t
                if len(edge.queue) > cfg.edge_queue:
                    dropped.append(edge.queue.popleft()[0])
            if edge.busy is None and edge.queue:
                if cfg.edge_serve == "newest":  # the older ones superseded
                    seq, arrived = edge.queue.pop()
                    dropped.extend(older for older, _ in edge.queue)
                    edge.queue.clear()
                else:
                    seq, arrived = edge.queue.popleft()
                service = self._lognormal(cfg.edge_service, cfg.edge_sigma)
                edge.busy = (seq, t + service, service, t - arrived)
            to_robot.extend((t + state.delay_ms / 1e3, k, "dropped", math.nan, math.nan) for k in dropped)
            if edge.busy is not None:
                seq, finish, service, queued = edge.busy
                if local is not None:  # the robot's detector takes a share of the shared cores
                    finish += DT * cfg.edge_slowdown
                    service += DT * cfg.edge_slowdown
                    edge.busy = (seq, finish, service, queued)
                if t >= finish:
                    to_robot.append((t + state.delay_ms / 1e3, seq, "ok", service, queued))
                    edge.busy = None
            for answer in [x for x in to_robot if x[0] <= t]:
                to_robot.remove(answer)
                book.edge_result(answer[1], answer[2], t, answer[3], answer[4], *_EMPTY,
                                 arrival=arrived_at.pop(answer[1], math.nan))  # the edge stamps it
            if produced >= self.n and not book.in_flight and local is None and local_slot is None:
                break
        book.close(t, send_slot, local_slot)
        return book


_EMPTY = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32))


def async_ap(book: FrameBook, period: float, dets: dict[str, list[tuple[np.ndarray, np.ndarray]]],
             gt: Any, n: int) -> float:
    """Asynchronous AP50 of a simulated run: each processed frame's detections (the real detector's
    on that frame) scored against the ground truth of the frame current at its result."""
    empty = _EMPTY
    d_all, g_all = [], []
    for seq in range(n):
        rec = book.records.get(seq)
        if rec is not None and rec["status"] in ("local_done", "edge_done"):
            current = min(max(int(math.floor(rec["result"] / period)) - 1, seq), n - 1)
            d_all.append(dets["local" if rec["status"] == "local_done" else "edge"][seq])
            g_all.append(gt(current))
        else:
            d_all.append(empty)
            g_all.append(gt(seq))
    return 100 * average_precision(d_all, g_all)


def simulate(strategy: str, trace: str, images: str = "coco-clips@tune", n: int = 1250, quota: float = 0.25,
             seed: int = 0, cache: Path | None = None, **params: float) -> dict[str, Any]:
    """One simulated run: async AP50, buckets, offloaded share."""
    from zoffload.sources.images import CocoClipSource, open_image_source

    source = open_image_source(images)
    if not isinstance(source, CocoClipSource):
        raise ValueError(f"{images}: the simulation needs clips with ground truth (coco-clips)")
    n = min(n, len(source))
    cache = cache or CACHE
    dets = {"local": clip_detections(source, "nanodet-m", n, detections_cache(images, "nanodet-m", cache)),
            "edge": clip_detections(source, "picodet-s", n, detections_cache(images, "picodet-s", cache))}
    cfg = SimConfig(quota=quota, seed=seed)
    link = constant(1e5, name="none") if trace == "none" else load_trace(trace)
    strat = make_strategy(strategy, **params)  # type: ignore[arg-type]
    book = Simulation(strat, cfg, link, n).run()
    bal = book.balance()
    return {"strategy": strategy, "trace": trace, "quota": quota, "seed": seed,
            "ap50_async": async_ap(book, 1.0 / cfg.fps, dets, source.boxes, n),
            "processed_pct": 100.0 * (bal["local_done"] + bal["edge_done"]) / max(bal["frames_in"], 1),
            "offloaded_pct": 100.0 * strat.offloaded / max(strat.total, 1), "balance": bal,
            "balanced": book.balanced()}
