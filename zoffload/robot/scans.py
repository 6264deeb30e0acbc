"""The robot's scan pipeline: replays a scan source at sensor rate, sizes each scan with the scale
policy, streams it to the edge, books every ack.

Inputs:  a scan source (``sim`` or a folder), ``<ns>/data/<robot>/scan_ack/**`` (wire.ScanAck), the
         edges present (the robot server's ``EdgePresence``), the fleet link (robot/fleet.py:
         which edge maps the robot, under which epoch).
Outputs: ``<ns>/data/<robot>/scan`` (wire.Scan, congestion control BLOCK_FIRST: the first scan that
         meets a full queue waits, on the sender thread; newer ones replace it in the sender's slot
         and are counted, never sent in pieces); status values for the robot's 1 Hz status
         message; results in ``out_dir`` (metrics, per-scan CSV, poses).

Three parts, kept apart: sizing (robot/sizer.py: policy, grid pass, payload layout, on the loop
thread), sending (robot/sender.py: compression, the wire message and ``put()`` on their own
thread) and booking (robot/ledger.py). The robot's CPU time per scan is measured on both threads
(``time.thread_time``) and reported with the process's whole CPU time.

With the attach protocol (``fleet.attach``) every scan carries its edge and epoch, acks count only
from that assignment, and while no edge maps the robot its scans are registered here by a light
KISS-ICP (robot/odometry.py, booked ``local``) so the pose never stops. Without it (legacy) scans
go to any edge present and are dropped as ``edge_absent`` when there is none.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from zoffload.mapping.voxel import warmup
from zoffload.policy.onnx_scale import load_scale_policy
from zoffload.policy.rate import LinkView
from zoffload.policy.scale import ScalePolicy
from zoffload.protocol import coding, wire
from zoffload.protocol.intake import answer_from
from zoffload.protocol.keys import Keys
from zoffload.robot.fleet import (
    BACKFILL_BYTES,
    BACKFILL_BYTES_MAX,
    STATUS_WAIT,
    FleetLink,
    FleetState,
    Sensor,
    backfill_budget,
)
from zoffload.robot.ledger import ScanLedger
from zoffload.robot.localpose import PoseKeeper
from zoffload.robot.odometry import LocalOdometry
from zoffload.robot.presence import EdgePresence
from zoffload.robot.scanlog import ScanLog, ScanTotals
from zoffload.robot.sender import Sender
from zoffload.robot.sensor import Reading, SensorThread
from zoffload.robot.sizer import ScanSizer, Sized, finish, scan_message
from zoffload.runtime.config import RobotSettings
from zoffload.runtime.drops import Drops
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.results import write_figures
from zoffload.runtime.session import has_subscribers, undeclare
from zoffload.sources import ScanSource, open_scan_source

log = logging.getLogger("zoffload.robot.scans")

STEADY_AFTER = 10  # scans read before the process's steady-state CPU window opens (robot_metrics.json)
DELIBERATE = ("pace", "skip", "stall")  # scans the policy chose not to send: announced in ``skipped``


@dataclass(frozen=True)
class StreamOptions:
    """How the streamer sends: the robot settings this pipeline uses, unpacked."""

    robot_id: str
    rate_hz: float  # the sensor's rate
    replay: str = "once"
    max_scans: int | None = None
    voxel_range: tuple[float, float] = (0.01, 0.07)
    coding: str = "q16d"  # "f32", "q16z" or "q16d"
    quant_fraction: float = 0.1
    zstd_level: int = 1  # q16d's compression level
    ack_timeout: float = 1.0
    ack_timeout_max: float | None = 4.0  # the timeout follows the route's round trip up to it; None: fixed
    max_in_flight: int = 3  # unanswered scans before the next is held back; 0 = no limit
    window_edge_time: bool = True  # ... plus the scans the edge holds (ScanLedger.window)
    window_path: bool = True  # ... and at least the scans the path's round trip holds
    window_hold: bool = True  # a scan the window holds back waits up to a period for a slot
    out_dir: Path | None = None  # records retire onto disk here as the run goes (robot/scanlog.py)
    keep_records: int = 4096  # records held in memory
    # The fleet (RobotFleetSettings)
    attach: bool = False  # the attach protocol; off: any present edge, edge "" and epoch 0
    attach_timeout: float = 1.0
    failover_after: float = 0.5
    local_odometry: bool = True
    local_voxel: float | None = None
    local_threads: int = 1
    catch_up: int = 20
    backfill_scans: int = 50  # scans kept for the next attach (robot/odometry.py)
    backfill_voxel: float | None = None  # None: a quarter of the local odometry's voxel
    backfill_bytes: int = BACKFILL_BYTES  # an attach's backfill may take at least ...
    backfill_bytes_max: int = BACKFILL_BYTES_MAX  # ... and at most (robot/fleet.py backfill_budget)
    bridge_after: float | None = None  # None: automatic (robot/localpose.py)


@dataclass
class _Outgoing:
    seq: int
    capture_stamp: float
    n_raw: int
    sized: Sized
    cpu_loop: float  # seconds of the loop thread's CPU for this scan
    edge: str = ""
    epoch: int = 0
    prior: tuple[int, np.ndarray, int] | None = None  # the robot's own estimate: ``Scan.prior`` and its frame
    held: tuple[float, str] | None = None  # the window was full: (robot clock, the window's reason)


class ScanStreamer:
    """A pipeline (robot/pipeline.py): sensor thread → size → sender thread → book acks."""

    name = "scans"

    def __init__(self, source: ScanSource, policy: ScalePolicy, keys: Keys, options: StreamOptions,
                 stop: StopSignal) -> None:
        self.source = source
        self.policy = policy
        self.keys = keys
        self.opts = options
        self.stop = stop
        self.ledger = ScanLedger(ScanLog(options.keep_records, options.out_dir))
        self.drops = Drops(log)
        self._lock = threading.Lock()  # the ack callback, the loop and the sender share the ledger
        self.sizer = ScanSizer(policy, options.coding, options.quant_fraction)
        self.sender: Sender[_Outgoing] = Sender(self._send, name="scan-sender", gate=self._window_slot,
                                                on_drop=self._held_out)
        self.presence: EdgePresence | None = None
        self._sensor: SensorThread | None = None
        self._booked_overwrites = 0
        self._skipped: deque[int] = deque()  # deliberately skipped since the last scan sent
        self._window_max = 0  # the widest window of unanswered scans so far (metrics)
        self._coded: deque[tuple[int, int]] = deque(maxlen=5)  # (bytes, points) of compressed scans
        self._refused_at = -math.inf
        self._cpu = {"process_s": 0.0, "sensor_s": 0.0, "wall_s": 0.0}
        o = options
        self.fleet: FleetLink | None = None
        self.fleet_state = (FleetState(o.robot_id, o.failover_after, status_wait=STATUS_WAIT)
                            if o.attach else None)
        self.odometry = (LocalOdometry(o.robot_id, source.max_range, o.local_voxel, o.local_threads,
                                       o.catch_up, backfill_scans=o.backfill_scans,
                                       backfill_voxel=o.backfill_voxel)
                         if o.attach and o.local_odometry else None)
        self.poses = (PoseKeeper(self.odometry, self.fleet_state, self.ledger, self._lock, 1.0 / o.rate_hz,
                                 o.failover_after, o.bridge_after, alive=self._edge_alive)
                      if self.fleet_state is not None else None)

    @property
    def voxel(self) -> float:
        return self.sizer.voxel

    # Startup
    def start(self, session: zenoh.Session, presence: EdgePresence) -> None:
        warmup()  # compile the kernels before the first scan, not during it
        coding.warmup()
        self.presence = presence
        robot = self.opts.robot_id
        self._ack_sub = session.declare_subscriber(self.keys.scan_acks(robot),
                                                   self.drops.guard(self._on_ack, "ack"))
        # BLOCK_FIRST: on a congested link the first scan waits for room (on the sender thread;
        # newer scans replace it in its slot) and others are dropped whole. With DROP every
        # fragment of a large scan gets only 50 ms to find room, so on a narrow link every large
        # scan loses some fragments and none reassembles (KITTI-360 raw at 20 Mbps: 0 of 100 scans
        # received with DROP, 16 with BLOCK_FIRST).
        self._scan_pub = session.declare_publisher(
            self.keys.scan(robot), congestion_control=zenoh.CongestionControl.BLOCK_FIRST)
        self.sender.start()
        if self.fleet_state is not None:
            assert self.poses is not None
            self.fleet = FleetLink(self.keys, self.fleet_state,
                                   Sensor(self.source.max_range, self.opts.voxel_range[1], self.opts.rate_hz),
                                   self.opts.attach_timeout, self.poses.handover, self.opts.backfill_bytes,
                                   self._backfilled, self._backfill_budget)
            self.fleet.start(session, presence)
        log.info("scans from %s (%d), policy %s, coding %s", self.source.name, len(self.source),
                 self.policy.name, self.opts.coding)

    def _backfilled(self, scans: list[tuple[int, float]]) -> None:
        """Scans an edge took in an attach's backfill, (seq, grid) (the fleet thread): marked in
        their records (``backfill``, and the grid it went at: ``backfill_voxel``), their bucket
        unchanged."""
        with self._lock:
            for seq, grid in scans:
                rec = self.ledger.records.get(seq)
                if rec is not None:
                    rec["backfill"], rec["backfill_voxel"] = 1, grid

    def _backfill_budget(self) -> int:
        """The bytes the next attach's backfill may take (the fleet thread): what the link was seen
        to carry, within the settings' floor and cap."""
        with self._lock:
            carried = self.ledger.carried_rate()
        o = self.opts
        return backfill_budget(carried, o.backfill_bytes, o.backfill_bytes_max, o.attach_timeout)

    def close(self) -> None:
        if self.fleet is not None:
            self.fleet.close()
        undeclare(getattr(self, "_ack_sub", None), getattr(self, "_scan_pub", None))
        close = getattr(self.source, "close", None)  # a ROS 2 topic's session, a bag's file
        if close is not None:
            close()

    def _on_ack(self, sample: zenoh.Sample) -> None:
        recv = time.monotonic()
        try:
            ack = wire.decode(sample.payload.to_bytes(), expect=wire.ScanAck)
        except wire.WireError as exc:
            self.drops.drop("malformed_ack", str(exc))
            return
        if ack.robot != self.opts.robot_id:
            self.drops.drop("foreign_ack", f"an ack for robot {ack.robot!r}")
            return
        if not answer_from(sample, self.keys, self.drops, ack.edge, "ack"):  # in another edge's name
            return
        fleet = self.fleet_state
        if fleet is None:
            # Answers come from an edge that is present (an ACL'd router lets only edge identities
            # put acks; without one, a forged ack from nowhere is refused here at least)
            if ack.edge and self.presence is not None and ack.edge not in self.presence.edges:
                self.drops.drop("foreign_ack", f"ack from {ack.edge!r}, not a present edge")
                return
        elif not (fleet.current(ack.edge, ack.epoch) or self._sent_under(ack)):
            self.drops.drop("stale_ack", f"ack of scan {ack.seq} from {ack.edge!r} under epoch {ack.epoch}")
            return
        with self._lock:
            bucket = self.ledger.on_ack(ack, recv)
            refused = self.ledger.counters["edge_refused"]
            in_flight = self.ledger.in_flight_here
            if bucket == "acked" and self.poses is not None:
                self.poses.edge_pose(ack.seq, np.array(ack.pose))
        if fleet is not None and bucket != "unknown" and fleet.on_ack(ack.edge, ack.epoch, ack.status, recv,
                                                                      in_flight):
            log.warning("edge %s refused scan %d under our epoch: moving", ack.edge, ack.seq)
            if self.fleet is not None:
                self.fleet.wake()
        if bucket != "unknown":
            self.sender.poke()  # a slot in the window may be free for a scan it holds
        if bucket == "edge_refused" and recv - self._refused_at >= 1.0:  # one line a second at most
            self._refused_at = recv
            log.warning("edge %s refused scan %d (%d refused so far): %s", ack.edge or "?", ack.seq,
                        refused, ack.detail[:200])

    def _edge_alive(self, edge: str) -> bool:
        return self.presence is not None and edge in self.presence.edges

    def _sent_under(self, ack: wire.ScanAck) -> bool:
        """Whether ``ack`` answers a scan in flight under that very edge and epoch (an edge the
        robot has just left still answers the scans it was sent, as a draining edge does)."""
        with self._lock:
            rec = self.ledger.records.get(ack.seq)
            return (bool(ack.edge) and rec is not None and ack.seq in self.ledger.pending
                    and rec.get("edge") == ack.edge and rec.get("epoch") == ack.epoch)

    def _target(self, reading: Reading, record: dict[str, Any]) -> tuple[str, int] | None:
        """Where this scan goes: (edge, epoch); None when it is done with here (registered
        locally or dropped as ``edge_absent``). Legacy: ("", 0) while any edge is present."""
        fleet = self.fleet_state
        if fleet is None:
            if self.presence is not None and self.presence.any:
                return "", 0
        else:
            target = fleet.target()
            if target is not None:
                return target
            assert self.poses is not None
            if self.poses.no_edge(reading, record):
                return None
        with self._lock:
            self.ledger.drop_at_source(reading.seq, "edge_absent", record)
        return None

    # Per-scan work (the loop thread)
    def process(self, reading: Reading) -> None:
        bridged = None
        try:
            bridged = self._process(reading)
        finally:
            if bridged is not None and self.poses is not None:  # the scan has its record now
                self.poses.book_bridged(reading.seq, *bridged)

    def _process(self, reading: Reading) -> tuple[np.ndarray, float] | None:
        """Size the scan and hand it to the sender; returns its local pose (and CPU ms) when
        the robot bridges an overdue edge with local odometry."""
        c0, t0 = time.thread_time(), time.perf_counter()
        frame = reading.frame
        record: dict[str, Any] = {"index": frame.index, "capture_stamp": reading.capture_stamp,
                                  "n_raw": len(frame.points)}
        if frame.gt_pose is not None:
            self.ledger.gt_poses[reading.seq] = frame.gt_pose
        target = self._target(reading, record)
        if target is None:
            return None
        l0 = time.thread_time()
        bridged = self.poses.attached(reading, target) if self.poses is not None else None
        local_s = time.thread_time() - l0  # local odometry's (and its catch-up's), booked apart
        record.update(edge=target[0], epoch=target[1])
        with self._lock:
            self.ledger.on_route(target, time.monotonic())
            window, full = self._window()
            self._window_max = max(self._window_max, window)
        held: tuple[float, str] | None = None
        if full:
            # in a stall the policy skips it on purpose (announced); else the window holds it back:
            # it waits up to a period for a slot (``window_hold``), or is dropped
            stall = self.sizer.held_back(self._link_view)
            with self._lock:
                if stall is not None:
                    record.update(voxel=stall.voxel, reason=stall.reason)
                    self.ledger.drop_at_source(reading.seq, stall.cause, record)
                    self._skipped.append(reading.seq)
                    return bridged
                base = self.opts.max_in_flight
                why = (f"window full: {self.ledger.in_flight_here} unanswered "
                       f"({base} + {window - base} for the edge's queue and the path)")
                self.ledger.window_drops += 1  # (held back: the policy's sign of a queue)
                now, period = time.monotonic(), self._period()
                # held only when an answer is due within the period: else no slot can free in
                # time, and sizing the scan would be work for nothing (at 1000 Hz offered, a grid
                # pass for every scan)
                if not self.opts.window_hold or self.ledger.overdue(now) < -period:
                    record["reason"] = why
                    self.ledger.drop_at_source(reading.seq, "window", record)
                    return bridged
                held = (now, why)
        # Size: the policy's choice, the grid pass, the payload's layout
        sized = self.sizer.size(frame.points, getattr(frame, "times", None), self._link_view)
        d = sized.decision
        record.update(voxel=sized.voxel, n_raw=sized.n_valid, n_nonfinite=sized.n_invalid, reason=d.reason)
        cpu_loop = time.thread_time() - c0 - local_s
        record.update(cpu_loop_ms=cpu_loop * 1e3, cpu_ms=cpu_loop * 1e3,
                      work_ms=(time.perf_counter() - t0 - local_s) * 1e3)
        if sized.skip or sized.n_points == 0:
            reason = d.cause if sized.skip else "empty"
            with self._lock:
                self.ledger.drop_at_source(reading.seq, reason, record)
                if reason in DELIBERATE:
                    self._skipped.append(reading.seq)
            self.sizer.pool.give(sized.buffer)
            return bridged
        record.update(n_sent=sized.n_points, coding=sized.coding)
        # Hand over to the sender thread: the loop goes back to the sensor whatever the link does
        with self._lock:
            self.ledger.handed_off(reading.seq, record)
        prior = None  # the robot's own estimate, for an edge that missed scans (reads codec 5)
        reads = self.fleet_state.reads(target[0]) if self.fleet_state is not None else 0
        if self.poses is not None and reads >= 5:
            prior = self.poses.prior_for(reading.seq, reads)
        out = _Outgoing(reading.seq, reading.capture_stamp, sized.n_valid, sized, cpu_loop, *target, prior,
                        held)
        replaced = self.sender.offer(out)
        if replaced is not None:
            if replaced.held is not None:
                self._held_out(replaced)
            else:
                with self._lock:
                    self.ledger.drop_at_source(replaced.seq, "replaced")
                self.sizer.pool.give(replaced.sized.buffer)
        return bridged

    # The window's holds (the sender thread's gate)
    def _window_slot(self, item: _Outgoing) -> bool | None:
        """Whether a scan the window held back may go now: True once the window has room for it,
        False while it is full, None when it has waited a period (the next scan is due: its turn)
        or was booked meanwhile. Without the wait the window dropped the scan although an ack
        freed a slot within the period for about 6 in 10 of them (``cellular-heldout``: 32-41 a
        run, 4 % of the scans, the only ones with neither a pose nor an announcement)."""
        if item.held is None:
            return True
        with self._lock:
            if item.seq not in self.ledger.sending or time.monotonic() - item.held[0] > self._period():
                return None
            return not self._window()[1]

    def _window(self) -> tuple[int, bool]:
        """The window of unanswered scans now (``ScanLedger.window``) and whether the scans in
        flight on the current route fill it (under the lock)."""
        window = self.ledger.window(self.opts.max_in_flight, self._period(),
                                    edge=self.opts.window_edge_time, path=self.opts.window_path)
        return window, bool(window) and self.ledger.in_flight_here >= window

    def _held_out(self, item: _Outgoing) -> None:
        """A scan the window held back and no slot came for (or a newer scan came first): dropped
        at the source, as the window drops, unannounced."""
        assert item.held is not None
        waited = time.monotonic() - item.held[0]
        with self._lock:
            if item.seq in self.ledger.sending:
                rec = self.ledger.records.get(item.seq, {})
                self.ledger.drop_at_source(item.seq, "window", {
                    "reason": f"{rec.get('reason', '')}; {item.held[1]}: no slot in {1e3 * waited:.0f} ms"})
        self.sizer.pool.give(item.sized.buffer)

    # Sending (the sender thread)
    def _send(self, item: _Outgoing) -> None:
        c0 = time.thread_time()
        sized = item.sized
        try:
            compressed = finish(sized, self.opts.zstd_level)
            with self._lock:  # deliberate skips since the last scan sent, before this one
                skipped = 0
                while self._skipped and self._skipped[0] < item.seq:
                    self._skipped.popleft()
                    skipped += 1
            send_stamp = time.monotonic()
            o = self.opts
            data = wire.encode(scan_message(
                sized, robot=o.robot_id, seq=item.seq, send_stamp=send_stamp,
                capture_stamp=item.capture_stamp, voxel_max=o.voxel_range[1],
                max_range=self.source.max_range, n_raw=item.n_raw, skipped=skipped, edge=item.edge,
                epoch=item.epoch, prior=item.prior))
            with self._lock:
                self.ledger.published(item.seq, send_stamp, {"bytes": len(data), "skipped": skipped,
                                                             "compressed": compressed})
                if item.held is not None:  # the window held it until an ack freed a slot
                    self.ledger.window_released += 1
                    sent = self.ledger.records[item.seq]
                    sent["reason"] = (f"{sent.get('reason', '')}; {item.held[1]}: sent "
                                      f"{1e3 * (send_stamp - item.held[0]):.0f} ms later, in a freed slot")
                if compressed or sized.coding != "q16d":
                    self._coded.append((len(data), sized.n_points))
            self._scan_pub.put(data)
            if self.fleet_state is not None:
                self.fleet_state.on_sent(send_stamp)
        except Exception as exc:  # not published: the scan is booked, the thread carries on
            with self._lock:
                if item.seq in self.ledger.sending:
                    self.ledger.drop_at_source(item.seq, "error")
            log.error("scan %d not sent: %s", item.seq, exc)
        finally:
            self.sizer.pool.give(sized.buffer)
            cpu_send = time.thread_time() - c0
            with self._lock:
                rec = self.ledger.records.get(item.seq)
                if rec is not None:
                    rec["cpu_send_ms"] = cpu_send * 1e3
                    rec["cpu_ms"] = (item.cpu_loop + cpu_send) * 1e3

    def _period(self) -> float:
        """The sensor's period: a live topic's measured one (``SensorThread.period_now``)."""
        return self._sensor.period_now() if self._sensor is not None else 1.0 / self.opts.rate_hz

    def _link_view(self) -> LinkView:
        """The link as the acks show it (the ledger keeps the figures up to date on every ack)."""
        now = time.monotonic()
        with self._lock:
            led = self.ledger
            coded = list(self._coded)
            return LinkView(
                last_t=led.last_interarrival,
                acked_bytes_per_s=led.acked_bytes_per_s(now),
                bytes_per_point=sum(b for b, _ in coded) / max(1, sum(n for _, n in coded)) if coded
                else math.nan,
                period=self._period(),
                acks=led.interarrivals_seen,
                last_slot=led.last_slot,
                recent=tuple(led.recent),
                since_ack=led.since_answer(now),
                in_flight=led.in_flight_here,
                window_drops=led.window_drops,
                newest_net=led.newest_net,
                floor_net=led.floor_net,
                queued=led.queued_here,
                overdue=led.overdue(now),
                raw_bytes_per_point=6.0 if self.opts.coding == "q16d" else math.nan)

    # Main loop
    def run(self) -> None:
        o = self.opts
        if self.fleet is not None and self.presence is not None and self.presence.any:
            # an edge is there: let the first attach finish before the first scan (else it
            # would be registered locally for no reason)
            presence = self.presence
            self.fleet.wait_settled(o.attach_timeout + 0.5, lambda: presence.any)
        elif self.fleet is None and self.presence is not None and self.presence.any:
            # without the attach protocol, an edge is there (its liveliness token came) but its
            # scan subscriber may not be matched yet: a scan published before would reach no one
            # and be booked lost a second later (suspected in a CI 112 flake)
            self._wait_matched(o.attach_timeout + 0.5)
        sensor = self._sensor = SensorThread(self.source, o.rate_hz, o.replay, o.max_scans)
        p0, w0 = time.process_time(), time.monotonic()
        steady: tuple[float, float, int] | None = None  # (process CPU, sensor CPU, scans) once warm
        n_read = 0
        sensor.start()
        try:
            while not self.stop.is_set():
                reading = sensor.take(timeout=0.05)
                with self._lock:
                    expired = self.ledger.expire(time.monotonic(), self._ack_timeout())
                    self._book_overwrites(sensor)
                    idle = expired and self.ledger.in_flight_here == 0
                if expired:
                    self.sender.poke()
                if idle and self.fleet_state is not None:
                    self.fleet_state.no_scans_in_flight()
                if reading is None:
                    if sensor.exhausted:
                        break
                    continue
                with self._lock:
                    self.ledger.produced()
                n_read += 1
                if n_read == STEADY_AFTER:
                    steady = (time.process_time(), sensor.cpu_s, n_read)
                try:
                    self.process(reading)
                except Exception as exc:  # one bad scan must not end the run
                    with self._lock:
                        self.ledger.drop_at_source(reading.seq, "error")
                    log.error("scan %d: %s", reading.seq, exc)
        finally:
            sensor.stop()
            with self._lock:
                self.ledger.counters["read_errors"] += sensor.read_errors
                self._book_overwrites(sensor)
            p1, s1 = time.process_time(), sensor.cpu_s
            self._drain()
            self._cpu = {"process_s": time.process_time() - p0, "sensor_s": sensor.cpu_s,
                         "wall_s": time.monotonic() - w0}
            if steady is not None and n_read > steady[2]:
                # the process from its STEADY_AFTER-th scan to its last read: start-up (imports,
                # compiling, connecting) and the final drain left out
                self._cpu.update(steady_process_s=p1 - steady[0], steady_sensor_s=s1 - steady[1],
                                 steady_scans=n_read - steady[2])

    def _wait_matched(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for a subscriber to match the scan publisher; whether one did.
        Any subscriber to the robot's scans matches (a viewer's too), so this narrows the race
        rather than closing it; the real edge declares its token after its subscribers."""
        deadline = time.monotonic() + timeout
        while not has_subscribers(self._scan_pub):
            if self.stop.is_set():
                return False
            if time.monotonic() >= deadline:
                log.warning("no subscriber matched the scans after %.1f s; sending anyway", timeout)
                return False
            time.sleep(0.01)
        return True

    def _book_overwrites(self, sensor: SensorThread) -> None:
        """Scans the sensor replaced before the loop took them: produced, dropped at source."""
        new = sensor.overwritten - self._booked_overwrites
        for _ in range(new):
            self.ledger.produced()
            self.ledger.drop_at_source(None, "overrun")
        self._booked_overwrites += new

    def _ack_timeout(self) -> float:
        """The current route's ack timeout (``ScanLedger.ack_timeout``; under the lock)."""
        return self.ledger.ack_timeout(self.opts.ack_timeout, self.opts.ack_timeout_max)

    def _drain(self) -> None:
        """Let the sender finish, give in-flight scans their ack timeout, book the rest as lost."""
        with self._lock:
            timeout = self._ack_timeout()
        deadline = time.monotonic() + timeout
        left = self.sender.close(timeout=timeout)
        with self._lock:
            if left is not None:
                self.ledger.drop_at_source(left.seq, "unsent")
        while time.monotonic() < deadline:
            with self._lock:
                if self.ledger.in_flight == 0:
                    break
            time.sleep(0.02)
        with self._lock:
            self.ledger.finish()

    def status(self) -> dict[str, float]:
        with self._lock:
            values = {k: float(v) for k, v in self.ledger.balance().items()}
            values["voxel"] = float(self.voxel)
            values["last_T"] = float(self.ledger.last_interarrival)
            values["skipped"] = float(sum(self.ledger.dropped_source[r] for r in DELIBERATE))
            recent = list(self.ledger.records.values())[-20:]
            current = self.poses.pose if self.poses is not None else None
            if current is not None:
                pose, src = current
                values.update(pose_x=float(pose[0, 3]), pose_y=float(pose[1, 3]), pose_z=float(pose[2, 3]),
                              pose_source=src)
        if self.fleet_state is not None:
            values["attached"] = float(self.fleet_state.target() is not None)
        answered = [r for r in recent if "rtt" in r]
        if answered:
            values["rtt_ms"] = float(np.mean([r["rtt"] for r in answered]) * 1e3)
            values["map_points"] = float(answered[-1]["map_points"])
        cpu = [r["cpu_ms"] for r in recent if "cpu_send_ms" in r]
        if cpu:
            values["cpu_ms"] = float(np.median(cpu))
        return values

    # Results
    def metrics(self) -> dict[str, Any]:
        with self._lock:
            totals = self.ledger.log.totals.with_records(self.ledger.records.values(), self.ledger.poses)
            balance = self.ledger.balance()
            out: dict[str, Any] = {
                "robot": self.opts.robot_id,
                "source": self.source.name,
                "policy": self.policy.name,
                "coding": self.opts.coding,
                "balance": balance,
                "balanced": self.ledger.balanced(),
                "dropped_source": dict(self.ledger.dropped_source),
                "other": {k: v for k, v in self.ledger.counters.items() if k not in balance},
                "drops": self.drops.snapshot(),
                # what a live or recorded source refused (a malformed ROS message, a bad row)
                "source_drops": _source_drops(self.source),
                "sender": {"sent": self.sender.sent, "replaced": self.sender.replaced,
                           "errors": self.sender.errors},
            }
        out["scans"] = totals.scans(sum(out["dropped_source"].get(r, 0) for r in DELIBERATE))
        out["records_retired"] = self.ledger.log.retired
        # the period the policy judged lateness by: a live topic's measured one (its real rate)
        out["sensor_period_s"] = {"nominal": 1.0 / self.opts.rate_hz,
                                  "used": self._period()}
        # a replay more than a period behind restarts its clock (no burst of overdue scans)
        out["sensor_resynced"] = self._sensor.resynced if self._sensor is not None else 0
        # why the source ended the replay early (a failed read, READ_ERRORS_IN_A_ROW unreadable
        # scans); None: it did not (each unreadable scan alone is skipped: ``other.read_errors``)
        out["source_failed"] = self._sensor.failed if self._sensor is not None else None
        # the window of unanswered scans: its base, the widest it grew (the edge's queue, the
        # path's round trip), the quickest round trip of the current route and the path's
        rtt_min, path_rtt = self.ledger.route_rtt_min, self.ledger.path_rtt
        out["window"] = {"base": self.opts.max_in_flight, "max": self._window_max,
                         "held": self.ledger.window_drops, "released": self.ledger.window_released,
                         "route_rtt_min_s": rtt_min if math.isfinite(rtt_min) else None,
                         "path_rtt_s": path_rtt if math.isfinite(path_rtt) else None}
        out["cpu"] = cpu_summary(totals, self._cpu, balance["produced"])
        if self.fleet_state is not None:
            out["fleet"] = self._fleet_metrics(totals, balance)
        if hasattr(self.policy, "counts"):
            out["policy_counts"] = dict(self.policy.counts)
        return out

    def _fleet_metrics(self, totals: ScanTotals, balance: dict[str, int]) -> dict[str, Any]:
        assert self.fleet_state is not None
        p = totals.poses
        assert self.poses is not None
        return {**self.fleet_state.metrics(),
                "local_scans": balance["local"],
                **self.poses.metrics(),
                "max_pose_gap_scans": p.max_gap_scans, "max_pose_gap_s": p.max_gap_s,
                "switch_jumps_m": list(p.jumps),
                # capture to the first pose the robot had for a scan (edge ack or local odometry)
                "pose_lag_ms": {"median": p.lag.quantile(0.5), "p95": p.lag.quantile(0.95),
                                "max": p.lag.quantile(1.0)},
                "stale_acks": self.drops.snapshot().get("stale_ack", 0)}

    def write_results(self, out_dir: Path) -> None:
        out_dir.mkdir(parents=True, exist_ok=True)
        write_figures(out_dir / "robot_metrics.json", self.metrics())
        with self._lock:
            self.ledger.log.write(out_dir)


def cpu_summary(totals: ScanTotals, process: dict[str, float], produced: int) -> dict[str, Any]:
    """The robot's CPU: per scan sent (the offload path on the loop and sender threads), over all
    scans (skipped ones cost a decision), and the process's whole CPU time (every thread: Zenoh's,
    the sensor's) with the sensor thread's own share (a replayed or simulated sensor is not
    offloading work) taken out."""
    own = process["process_s"] - process["sensor_s"]
    n_steady = process.get("steady_scans", 0)
    steady = (1e3 * (process["steady_process_s"] - process["steady_sensor_s"]) / n_steady if n_steady
              else None)
    return {
        "per_scan_ms": totals.cpu.quantile(0.5),  # median over scans sent (1 % histogram bins)
        "mean_per_scan_ms": totals.cpu.mean(),
        "p95_per_scan_ms": totals.cpu.quantile(0.95),
        "loop_ms": totals.cpu_loop.quantile(0.5),
        "send_ms": totals.cpu_send.quantile(0.5),
        "path_ms_per_produced": totals.cpu_all_ms / produced if produced else None,
        "process_s": process["process_s"],
        "sensor_s": process["sensor_s"],
        "wall_s": process["wall_s"],
        "process_ms_per_scan": 1e3 * own / produced if produced else None,
        # the same, in steady state: from the STEADY_AFTER-th scan read to the last (start-up and
        # the final drain left out), the sensor thread's own CPU taken out
        "steady_process_ms_per_scan": steady,
        "steady_scans": n_steady,
    }


def _source_drops(source: ScanSource) -> dict[str, int]:
    drops = getattr(source, "drops", None)
    return dict(drops.snapshot()) if drops is not None else {}


def scan_streamer(settings: RobotSettings, stop: StopSignal, source: ScanSource | None = None,
                  policy: ScalePolicy | None = None) -> ScanStreamer:
    """The scan pipeline for these settings (``source`` and ``policy`` to inject others)."""
    source = source or open_scan_source(settings.scans, sim_seed=settings.sim_seed,
                                        bin_fields=settings.bin_fields,
                                        ros2=settings.ros2.link(settings.ros2.node))
    policy = policy or load_scale_policy(settings.scale_policy, settings.voxel, settings.voxel_range,
                                         widen=settings.voxel_widen, max_skip=settings.max_skip,
                                         stall_after=settings.stall_after, jitter_pace=settings.jitter_pace)
    f = settings.fleet
    options = StreamOptions(
        robot_id=settings.robot_id, rate_hz=settings.rate_hz or source.rate_hz, replay=settings.replay,
        max_scans=settings.max_scans, voxel_range=settings.voxel_range, coding=settings.scan_coding,
        quant_fraction=settings.quant_fraction, zstd_level=settings.zstd_level,
        ack_timeout=settings.ack_timeout, ack_timeout_max=settings.ack_timeout_max,
        max_in_flight=settings.max_in_flight,
        window_edge_time=settings.window_edge_time, window_path=settings.window_path,
        window_hold=settings.window_hold,
        out_dir=Path(settings.out_dir) if settings.out_dir else None,
        attach=f.attach, attach_timeout=f.attach_timeout, failover_after=f.failover_after,
        local_odometry=f.local_odometry, local_voxel=f.local_voxel, local_threads=f.local_threads,
        catch_up=f.catch_up, backfill_scans=f.backfill_scans, backfill_voxel=f.backfill_voxel,
        backfill_bytes=f.backfill_bytes, backfill_bytes_max=f.backfill_bytes_max, bridge_after=f.bridge_after)
    return ScanStreamer(source, policy, Keys(settings.namespace), options, stop)
