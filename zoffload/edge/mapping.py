"""The edge's mapping service: every admitted robot's scans, one bounded KISS-ICP mapper per robot,
one ack per scan.

Inputs:  ``<ns>/data/*/scan`` (wire.Scan).
Outputs: ``<ns>/data/<robot>/scan_ack/<edge>`` (wire.ScanAck, one per scan, also for scans it had to
         drop or could not register; ``refused`` for robots not admitted, rate-limited);
         ``<ns>/data/<robot>/checkpoint/<edge>`` (wire.Checkpoint, to attached robots).
Queries: ``<ns>/ctrl/<robot>/map/<edge>`` (wire.MapReply naming this edge: the robot's registered
         map and the poses in memory, for a robot this edge maps, else an error reply; one reply
         built at a time, others answered "busy"; only its own key, as attaches: a querier asks
         each edge by name, runtime/maps.py);
         ``<ns>/ctrl/<robot>/attach/<edge>`` (wire.Attach → wire.AttachReply).
On eviction and stop: with a ``map_dir``, the robot's map, trajectory and counters (edge/export.py).

The Zenoh callback only stamps, checks and queues; registration runs on a fixed pool of worker
threads serving the robots' queues in turn, one scan per turn, so a slow mapper never blocks
reception, inter-arrival T stays an arrival-time measure, and the thread count does not depend on
how many robots there are. The mappers themselves run in a fixed set of processes (edge/isolate.py,
the server's default): KISS-ICP holds the GIL through its calls, and in this process a
registration would stall the callbacks; a mapper lost with its process (``MapperLost``) is
counted (``mapper_lost``) and its robot detached, so it attaches again with its checkpoint. A
robot is held by at most one worker at a time: its scans are registered in order, never
concurrently. Each robot keeps at most ``queue`` waiting scans; the
oldest is acked ``dropped`` when a newer one comes.

Fleet (edge/fleet.py holds the decisions): a robot attaches with an epoch and maybe a checkpoint;
its mapper continues the checkpoint's trajectory (applied by the worker before its next scan, so a
mapper is only ever touched by the worker holding the robot) and it gets a checkpoint after its
first registered scan under that epoch and then every ``checkpoint_every`` scans. Scans naming
another edge are only counted (``other_edge``: read from the payload without decoding it);
scans under an epoch not attached here are refused. Draining and shedding ask the robot's worker
for a final checkpoint, taken after its next registered scan, or at once if the robot is idle.
A scan that carries the robot's own estimate (``Scan.prior``: it bridged an outage with its local
odometry, or mapped the scans read while its attach was under way) after scans this mapper
missed is predicted from it (``predicted_from_prior``; an estimate in the frame of the attach's
poses moved as the attach's backfill moved them). Such estimates are also counted by the frame the
robot said they are in (``prior_frame_handed``, ``prior_frame_edge``, ``prior_frame_unsaid``: -1 or
a robot older than version 11) and when the mapper moved one by the attach's correction
(``prior_moved_by_attach``; not ``gap_prior_moved``, which counts the scans where the moved guess
won), all when taken, as ``predicted_from_prior``: before the scan's registration, which may fail.

Every sample is counted once: ``samples`` = ``received`` + ``other_edge`` + the drops by reason
(``bad_key``, ``refused``, ``malformed``, ``foreign``, ``callback_error``, ``stale_epoch``,
``attach_first``, ``shed``: runtime/drops.py). Attach queries are counted apart (``attaches``,
``attach_refused``; a malformed one is a drop of the service's ``attach_drops``).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
import time
from collections import Counter, OrderedDict, deque
from pathlib import Path

import numpy as np
import zenoh

from zoffload.edge.admission import Admission
from zoffload.edge.export import RobotFiles
from zoffload.edge.fleet import MAP, OTHER, Fleet, Peers, check_attach, peek_route
from zoffload.edge.robots import Continue, FleetMapper, MapperFactory, MapperLost, Queued, RobotSession
from zoffload.mapping.mapper import Registration
from zoffload.protocol import wire
from zoffload.protocol.intake import edge_status, edge_token, robot_in_key
from zoffload.protocol.keys import Keys, check_id
from zoffload.runtime.drops import Drops
from zoffload.runtime.maps import BUSY, no_map_reply
from zoffload.runtime.session import undeclare

log = logging.getLogger("zoffload.edge.mapping")

# Scan.prior_frame -> its counter (the robot's word on its estimate's frame, version 11)
PRIOR_FRAMES = {1: "prior_frame_handed", 0: "prior_frame_edge", -1: "prior_frame_unsaid"}
GENERATIONS_KEPT = 4096  # robot ids whose session count is remembered (for export file names)


class MappingService:
    """Maps every admitted robot that sends scans. ``make_mapper`` None: receive and ack only (link
    checks, stream benchmarks), nothing decoded or registered."""

    name = "mapping"

    def __init__(self, keys: Keys, make_mapper: MapperFactory | None, queue: int = 2,
                 map_dir: Path | None = None, map_format: str = "ply", edge_id: str = "edge1",
                 workers: int | None = None, admission: Admission | None = None,
                 limits: wire.Limits = wire.DEFAULT_LIMITS, fleet: Fleet | None = None,
                 checkpoint_every: int = 10, checkpoint_resolution: float | None = None,
                 final_checkpoint_resolution: float | None = 0.0) -> None:
        self.keys = keys
        self.make_mapper = make_mapper
        self.queue_len = queue
        self.map_dir = map_dir
        self.map_format = map_format
        self.edge_id = check_id(edge_id, "edge id")  # its answers go under it
        self.admission = admission or Admission()
        self.limits = limits
        self.fleet = fleet or Fleet(edge_id, capacity=self.admission.max_robots)
        self.checkpoint_every = checkpoint_every
        self.checkpoint_resolution = checkpoint_resolution
        self.final_checkpoint_resolution = final_checkpoint_resolution
        self.attach_drops = Drops(log)
        self._busy = 0.0  # seconds the workers spent registering and checkpointing
        self.robots: dict[str, RobotSession] = {}
        self.counters: Counter[str] = Counter()
        self.drops = Drops(log)
        self._generations: OrderedDict[str, int] = OrderedDict()
        self._lock = threading.Condition()  # robots, queues, the ready queue and counters
        self._ready: deque[RobotSession] = deque()
        self._stop = threading.Event()
        self._map_reply = threading.Semaphore(1)
        self._workers = [threading.Thread(target=self._work, name=f"mapper-{i}", daemon=True)
                         for i in range(workers or os.cpu_count() or 1)]
        self._session: zenoh.Session | None = None
        self._sub: zenoh.Subscriber[None] | None = None
        self._map_q: zenoh.Queryable[None] | None = None
        self._attach_q: zenoh.Queryable[None] | None = None
        self.peers = Peers(edge_id, self.fleet.shed_late)
        self._peers_sub: zenoh.Subscriber[None] | None = None
        self._peers_alive: zenoh.Subscriber[None] | None = None

    def start(self, session: zenoh.Session) -> None:
        if self.make_mapper is not None:
            self.make_mapper.warm_up()
        self._session = session
        for w in self._workers:
            w.start()
        self._sub = session.declare_subscriber(self.keys.all_scans(), self.drops.guard(self._on_scan, "scan"))
        self._map_q = session.declare_queryable(self.keys.all_maps(self.edge_id),
                                                self.drops.guard(self._on_map_query, "map query"))
        self._attach_q = session.declare_queryable(self.keys.all_attaches(self.edge_id),
                                                   self.attach_drops.guard(self._on_attach, "attach"))
        # the other edges' room: a robot is shed only when another edge can take it
        self._peers_sub = session.declare_subscriber(
            self.keys.all_edge_status(), self.attach_drops.guard(self._on_peer, "edge status"))
        # and whether they are alive: a dead edge's last status stays fresh for seconds
        self._peers_alive = session.liveliness().declare_subscriber(
            self.keys.any_edge_alive(), self.attach_drops.guard(self._on_peer_token, "edge token"),
            history=True)

    def _on_peer(self, sample: zenoh.Sample) -> None:
        st = edge_status(sample, self.keys, self.attach_drops)
        if st is not None:
            with self._lock:
                self.peers.update(st.id, st.values, time.monotonic())

    def _on_peer_token(self, sample: zenoh.Sample) -> None:
        edge = edge_token(sample, self.keys, self.attach_drops)
        if edge is None:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self.peers.gone(edge)
            else:
                self.peers.back(edge)

    def stop(self) -> None:
        # No new scans first: one queued after the workers stop would never be acked. The map
        # queryable and the ack publishers go with the session, so maps are served to the end.
        undeclare(self._sub, self._attach_q, self._peers_sub, self._peers_alive)
        self._sub = self._attach_q = self._peers_sub = self._peers_alive = None
        self._stop.set()
        with self._lock:
            self._lock.notify_all()
        for w in self._workers:
            if w.is_alive():
                w.join(timeout=5)
        if self.map_dir:
            for rs in list(self.robots.values()):
                self._export(rs)
        close = getattr(self.make_mapper, "close", None)
        if close is not None:  # the mapper processes (edge/isolate.py), once the maps are out
            close()
        log.info("mapping stopped: %s, drops %s", dict(self.counters), self.drops.snapshot())

    def status(self) -> dict[str, float]:
        now = time.monotonic()
        with self._lock:
            values = {k: float(v) for k, v in self.counters.items()}
            robots = list(self.robots.values())
            values.update(self.fleet.status(now))
            values["busy_share"] = self.fleet.busy_share(len(self._workers))
        values.update({f"attach.drop.{k}": float(v) for k, v in self.attach_drops.snapshot().items()})
        drops = self.drops.snapshot()
        values.update({f"drop.{k}": float(v) for k, v in drops.items()})
        values["drops"] = float(sum(drops.values()))
        values["malformed"] = float(drops.get("malformed", 0))
        values["robots"] = float(len(robots))
        values["workers"] = float(sum(w.is_alive() for w in self._workers))
        pool_status = getattr(self.make_mapper, "status", None)
        if pool_status is not None:
            values.update(pool_status())
        for rs in robots:
            mapper = rs.mapper  # (read once: a lost mapper's worker sets it to None)
            values[f"{rs.robot}.map_points"] = float(mapper.map_points if mapper else 0)
            values[f"{rs.robot}.queue"] = float(len(rs.queue))
            overflow = getattr(mapper, "map_overflow", 0)
            if overflow:
                values[f"{rs.robot}.map_overflow"] = float(overflow)
        return values

    # Reception (Zenoh callback threads: stamp, check, queue; nothing slow)
    def _on_scan(self, sample: zenoh.Sample) -> None:
        arrival = time.monotonic()
        with self._lock:
            self.counters["samples"] += 1
        robot = robot_in_key(sample, self.keys, self.drops, "scan")
        if robot is None:
            return
        payload = sample.payload.to_bytes()
        # Whose scan: another edge's costs a counter, a refused one no per-robot state
        peeked = peek_route(payload)
        if peeked is not None:
            with self._lock:
                route = self.fleet.route(robot, peeked[0], peeked[1], arrival)
                if route.action == OTHER:
                    self.counters["other_edge"] += 1
            if route.action == OTHER:
                return
            if route.action != MAP:
                self._refuse(payload, robot, route.reason, route.detail)
                return
        if not self.admission.admit(robot, arrival):
            self._refuse(payload, robot, "refused", self.admission.why_refused(robot))
            return
        scan = self._decode_scan(payload, robot, str(sample.key_expr))
        if scan is None:
            return
        if scan.coding != "f32" and scan.n_points > self.limits.max_points:  # before it waits in a queue
            self.drops.drop("malformed", f"scan of {scan.n_points} points (at most {self.limits.max_points})")
            return
        with self._lock:
            rs = self.robots.get(robot) or self._new_robot(robot)
            interarrival = float("nan") if rs.last_arrival is None else arrival - rs.last_arrival
            rs.last_arrival = arrival
            if interarrival > 0:
                rs.gaps.append(interarrival)
            rs.counters["received"] += 1
            self.counters["received"] += 1
            overflow = rs.push(Queued(scan, arrival, interarrival), self.queue_len)  # thinned, not cut
            if not rs.scheduled:
                rs.scheduled = True
                self._ready.append(rs)
                self._lock.notify()
            for _ in overflow:
                rs.counters["dropped"] += 1
                self.counters["dropped"] += 1
        for q in overflow:
            self._ack(rs, q, status="dropped", detail="edge mapper overloaded")

    def _decode_scan(self, payload: bytes, robot: str, key: str) -> wire.Scan | None:
        """``robot``'s scan, or None after counting a ``malformed`` or ``foreign`` drop."""
        try:
            scan = wire.decode(payload, expect=wire.Scan, limits=self.limits)
        except wire.WireError as exc:
            self.drops.drop("malformed", f"scan on {key[:100]}: {exc}")
            return None
        if scan.robot != robot:
            self.drops.drop("foreign", f"scan: robot {scan.robot!r} in the payload, {robot!r} in the key")
            return None
        return scan

    def _refuse(self, payload: bytes, robot: str, reason: str, why: str) -> None:
        """A scan refused (robot not admitted, not attached, shed): counted; answered while the
        admission's refusal budget allows."""
        self.drops.drop(reason, f"robot {robot}: {why}")
        if self._session is None or not self.admission.answer_refusal():
            return
        try:
            scan = wire.decode(payload, expect=wire.Scan, limits=self.limits)
        except wire.WireError:
            return  # already counted as refused; nothing to answer
        if scan.robot != robot:
            return
        ack = _ack_message(robot, scan.seq, scan.send_stamp, "refused", self.edge_id, scan.epoch, detail=why)
        # No per-id publisher: refused ids must not cost the edge any state
        self._session.put(self.keys.scan_ack(robot, self.edge_id), wire.encode(ack),
                          congestion_control=zenoh.CongestionControl.DROP, express=True)

    def _new_robot(self, robot: str) -> RobotSession:
        """Called with the lock held, for an admitted robot without a session."""
        assert self._session is not None, "scans arrive only after start()"
        pub = self._session.declare_publisher(
            self.keys.scan_ack(robot, self.edge_id), congestion_control=zenoh.CongestionControl.DROP,
            express=True)
        rs = RobotSession(robot, pub, self._next_files(robot))
        self.robots[robot] = rs
        log.info("new robot %s%s", robot, f" (session {rs.files.generation})" if rs.files.generation else "")
        return rs

    def _next_files(self, robot: str) -> RobotFiles:
        """The export files of the robot's next map (``ROBOT_map.G.ply`` from the second on); with
        the lock held."""
        generation = self._generations.pop(robot, -1) + 1
        self._generations[robot] = generation
        while len(self._generations) > GENERATIONS_KEPT:
            self._generations.popitem(last=False)
        return RobotFiles(self.map_dir, robot, generation, self.map_format)

    # Registration (the worker pool)
    def _work(self) -> None:
        while True:
            with self._lock:
                while not self._ready and not self._stop.is_set():
                    self._lock.wait(0.2)
                if self._stop.is_set():
                    return
                rs = self._ready.popleft()
                item = rs.queue.popleft() if rs.queue else None
            start = time.perf_counter()
            if item is not None:
                try:
                    self._register(rs, item)
                except Exception as exc:  # (its checkpoint): the worker goes on with the next scan
                    self._worker_error(rs, "scan", exc)
            with self._lock:
                final, rs.final_pending = rs.final_pending, False
            if final:
                try:
                    self._send_final(rs)
                except Exception as exc:
                    self._worker_error(rs, "final checkpoint", exc)
            with self._lock:
                self._busy += time.perf_counter() - start
                if (rs.queue or rs.final_pending) and not rs.closed:
                    self._ready.append(rs)  # its next scan waits behind the other robots' turns
                    self._lock.notify()
                    continue
                rs.scheduled = False
                closed = rs.closed
            if closed:
                self._close(rs)

    def _worker_error(self, rs: RobotSession, what: str, exc: Exception) -> None:
        """Something a robot sent broke a worker's step outside registration (a checkpoint of a
        map too far out for its grid, say): counted and logged; the worker lives on. Before, the
        exception ended the worker thread and the robot's later scans were never answered."""
        if isinstance(exc, MapperLost):
            self._lost(rs, exc, rs.checkpoint_epoch)
        self._count(rs, "worker_errors")
        n = rs.counters["worker_errors"]
        if n <= 10 or n % 1000 == 0:
            log.warning("robot %s: %s failed on the mapping worker (%d so far): %s", rs.robot, what, n,
                        str(exc)[:200], exc_info=n == 1)

    def _register(self, rs: RobotSession, item: Queued) -> None:
        scan = item.scan
        if self.make_mapper is None:
            self._count(rs, "received_only")
            self._ack(rs, item, status="ok", detail="mapping disabled", queue_time=0.0)
            return
        if scan.epoch and scan.epoch == rs.lost_epoch:
            # queued before its mapper was lost: refused as the scans after it are, not mapped
            # into a new map under the epoch whose map is gone
            self._count(rs, "refused_lost")
            self._ack(rs, item, status="refused",
                      detail=f"not attached (epoch {scan.epoch}): its mapper was lost")
            return
        try:
            if rs.mapper is None:
                rs.mapper = self.make_mapper(scan, rs.files.spill)
            self._continue(rs)
            if scan.prior is not None and hasattr(rs.mapper, "predict_from"):
                # The robot bridged scans this mapper missed: predict from its estimate
                mapper: FleetMapper = rs.mapper  # type: ignore[assignment]
                moved = getattr(mapper, "priors_moved", 0)
                if mapper.predict_from(scan.seq, scan.prior_seq, scan.prior[0], scan.prior[1], contest=True,
                                       frame=scan.prior_frame):
                    self._count(rs, "predicted_from_prior")
                    # by the frame the robot said it is in, and whether the mapper moved it
                    self._count(rs, PRIOR_FRAMES.get(scan.prior_frame, "prior_frame_unsaid"))
                    # (a mapper in a process of its own: its counters come with each reply)
                    self._count(rs, "prior_moved_by_attach", getattr(mapper, "priors_moved", 0) - moved)
            # Decodes a coded payload (WireError if it is corrupt); the per-point times, when the
            # scan carries them, deskew it if the mapper was made to
            points, times = scan.cloud_and_times(self.limits)
            if len(points) == 0:  # (finite: the codec checks raw points, coded ones are by construction)
                raise ValueError("scan has no points")
            start = time.monotonic()
            reg = rs.mapper.register(scan.seq, points, times)
        except Exception as exc:  # a bad scan must not take the worker down
            if isinstance(exc, MapperLost):
                self._lost(rs, exc, scan.epoch)
            self._count(rs, "errors")
            if rs.counters["errors"] <= 10 or rs.counters["errors"] % 1000 == 0:
                log.warning("robot %s scan %d: registration failed (%d so far): %s", rs.robot, scan.seq,
                            rs.counters["errors"], str(exc)[:200])
            self._ack(rs, item, status="error", detail=str(exc)[:200])
            return
        self._count(rs, "registered")
        if reg.gap_motion:  # a scan after a gap: which guess it was registered from
            self._count(rs, f"gap_{reg.gap_motion}")
        rs.last_stamp = scan.capture_stamp
        self._ack(rs, item, status="ok", queue_time=start - item.arrival, reg=reg)
        if scan.epoch > 0 and scan.edge == self.edge_id and not rs.final_pending:
            rs.since_checkpoint += 1
            if rs.checkpoint_epoch != scan.epoch or rs.since_checkpoint >= self.checkpoint_every:
                self._send_checkpoint(rs, scan.epoch)

    def _lost(self, rs: RobotSession, exc: Exception, epoch: int) -> None:
        """The robot's mapper is gone (its process died or hung, edge/isolate.py; ``epoch``: of the
        scan or checkpoint that found it out): counted. A robot attached under that epoch is
        detached, so its next scans (those queued already too) are refused as an edge that lost
        its state refuses them, and it attaches again with its checkpoint: its new mapper
        continues its trajectory (its local odometry bridges meanwhile). An attach that came
        meanwhile stays: the new mapper is seeded from it. Another robot's next scan starts a
        new map, in the frame of that scan, with export files of their own."""
        self._count(rs, "mapper_lost")
        refused: list[Queued] = []
        with self._lock:
            rs.mapper = None
            rs.checkpoint_epoch, rs.since_checkpoint = 0, 0
            entry = self.fleet.attached.get(rs.robot)
            current = not rs.closed and self.robots.get(rs.robot) is rs
            detach = current and rs.pending is None and entry is not None and entry.epoch == epoch
            if detach:
                self.fleet.forget(rs.robot)
                rs.lost_epoch = epoch
                refused = [q for q in rs.queue if q.scan.epoch == epoch]
                rs.queue = deque(q for q in rs.queue if q.scan.epoch != epoch)
                rs.counters["refused_lost"] += len(refused)
                self.counters["refused_lost"] += len(refused)
            elif current and entry is None and rs.pending is None:
                rs.files = self._next_files(rs.robot)  # a new map: not merged with the lost one's poses
        for q in refused:
            self._ack(rs, q, status="refused", detail=f"not attached (epoch {epoch}): its mapper was lost")
        log.error("robot %s: its mapper is lost (%s); %s", rs.robot, str(exc)[:200],
                  "detached: it attaches again with its checkpoint" if detach
                  else "its next attach seeds a new one" if rs.pending is not None
                  else "its map starts again")

    # Fleet: attaches, checkpoints, drain and shedding
    def _on_attach(self, query: zenoh.Query) -> None:
        robot = self.keys.robot_of(str(query.key_expr))
        if robot is None or query.payload is None:
            self.attach_drops.drop("malformed", f"attach on {str(query.key_expr)[:100]!r}: no robot/payload")
            return
        try:
            attach = wire.decode(query.payload.to_bytes(), expect=wire.Attach, limits=self.limits)
        except wire.WireError as exc:
            self.attach_drops.drop("malformed", f"attach of {robot}: {exc}")
            return
        if attach.robot != robot:
            self.attach_drops.drop("malformed", f"attach: robot {attach.robot!r} in the payload, {robot!r} "
                                                "in the key")
            return
        checkpoint, detail = check_attach(attach, robot, self.limits)
        backfill: tuple[wire.Scan, ...] = ()
        if not detail and attach.backfill_sizes is not None:
            try:  # (their points are decoded by the worker that applies the attach)
                backfill = tuple(attach.backfill_scans(self.limits))
            except wire.WireError as exc:  # the attach stands without it
                self.attach_drops.drop("malformed", f"attach of {robot}: backfill: {exc}")
        now = time.monotonic()
        with self._lock:
            rs = self.robots.get(robot)
            detail = detail or self.fleet.decide(robot, attach.epoch, len(self.robots), rs is not None, now)
            if not detail and not self.admission.admit(robot, now):
                detail = f"not admitted: {self.admission.why_refused(robot)}"
            if not detail:
                self.fleet.attach(robot, attach.epoch, now, attach.reads)
                rs = rs or self._new_robot(robot)
                rs.pending = Continue(checkpoint, attach.local_seqs, attach.local_poses, backfill,
                                      attach.backfill_poses if backfill else None)
                rs.final_pending = False
            self.counters["attach_refused" if detail else "attaches"] += 1
            robots, capacity = len(self.robots), self.fleet.effective_capacity(now)
        if not detail and self.fleet.ahead(attach.epoch):
            log.warning("attach of %s: its epoch %d (its wall clock in ms) is more than a day ahead of this "
                        "edge's clock; is this edge's clock (NTP) or the robot's right?", robot, attach.epoch)
        log.info("attach of %s (epoch %d, checkpoint %s, %d local poses): %s", robot, attach.epoch,
                 f"seq {checkpoint.seq}" if checkpoint else "none", len(attach.local_seqs),
                 detail or "accepted")
        reply = wire.AttachReply(robot=robot, edge=self.edge_id, epoch=attach.epoch, accepted=not detail,
                                 detail=detail, robots=robots, capacity=capacity)
        query.reply(query.key_expr, wire.encode(reply))

    def _continue(self, rs: RobotSession) -> None:
        """Apply the robot's latest attach to its mapper (the worker holding the robot)."""
        with self._lock:
            pending, rs.pending = rs.pending, None
        if pending is None or rs.mapper is None or not hasattr(rs.mapper, "continue_from"):
            return
        mapper: FleetMapper = rs.mapper  # type: ignore[assignment]
        backfill: list[tuple[int, np.ndarray]] = []
        for scan in pending.backfill:
            try:
                backfill.append((scan.seq, scan.cloud_and_times(self.limits)[0]))
            except wire.WireError as exc:  # registered up to the scan that does not decode
                self._count(rs, "backfill_malformed", len(pending.backfill) - len(backfill))
                log.warning("robot %s: backfill scan %d does not decode: %s", rs.robot, scan.seq,
                            str(exc)[:200])
                break
        before = (getattr(mapper, "backfilled", 0), getattr(mapper, "backfill_unused", 0),
                  getattr(mapper, "backfill_posed", 0))
        bposes = pending.backfill_poses[:len(backfill)] if pending.backfill_poses is not None else None
        if mapper.continue_from(pending.checkpoint, pending.local_seqs, pending.local_poses, backfill,
                                bposes):
            log.info("robot %s continues from its checkpoint of scan %d", rs.robot,
                     pending.checkpoint.seq if pending.checkpoint else -1)
        if backfill:
            done = getattr(mapper, "backfilled", 0) - before[0]
            self._count(rs, "backfilled", done)
            self._count(rs, "backfill_unused", getattr(mapper, "backfill_unused", 0) - before[1])
            # of the backfills, those predicted from the robot's poses of their scans (version 10)
            self._count(rs, "backfill_posed", getattr(mapper, "backfill_posed", 0) - before[2])
            log.info("robot %s: %d of its %d backfilled scans (%d..%d) registered", rs.robot, done,
                     len(backfill), backfill[0][0], backfill[-1][0])

    def _send_checkpoint(self, rs: RobotSession, epoch: int, final: bool = False) -> bool:
        """Take and publish the robot's checkpoint (the worker holding the robot)."""
        if rs.mapper is None or not hasattr(rs.mapper, "checkpoint") or self._session is None:
            return False
        mapper: FleetMapper = rs.mapper  # type: ignore[assignment]
        t0 = time.perf_counter()
        resolution = self.final_checkpoint_resolution if final else self.checkpoint_resolution
        with self._lock:
            entry = self.fleet.attached.get(rs.robot)
            if not final and entry is not None and entry.final == "sent":
                return False  # no periodic checkpoint after the final one
            # Coded for a robot that reads 6; a final one (the whole local map) stays float32: coding
            # it took 36 ms per robot in the draining edge's worker, and the drains' moves took twice
            # as long (README, "Checkpoints")
            coded = entry is not None and entry.reads >= 6 and not final
            reads = entry.reads if entry is not None else 5
        # Counted as taken before it is: one that fails (a map too far out for its grid) is tried
        # again after checkpoint_every scans, not on every scan
        rs.checkpoint_epoch, rs.since_checkpoint = epoch, 0
        cp = mapper.checkpoint(rs.robot, self.edge_id, epoch, rs.last_stamp, resolution, final, coded)
        if cp is None:
            return False
        data = wire.encode(cp.readable_by(reads))  # (the turn rate for a robot that reads 8)
        try:
            if final:  # the one the robot must not miss: wait for room rather than drop it
                self._session.put(self.keys.checkpoint(rs.robot, self.edge_id), data,
                                  congestion_control=zenoh.CongestionControl.BLOCK)
            else:
                if rs.cp_pub is None:
                    rs.cp_pub = self._session.declare_publisher(
                        self.keys.checkpoint(rs.robot, self.edge_id),
                        congestion_control=zenoh.CongestionControl.DROP)
                rs.cp_pub.put(data)
        except Exception as exc:  # the session is closing
            log.debug("checkpoint not published: %s", exc)
            return False
        with self._lock:
            self.counters["final_checkpoints" if final else "checkpoints"] += 1
            self.counters["checkpoint_bytes"] = len(data)
            self.counters["checkpoint_us"] = int((time.perf_counter() - t0) * 1e6)
        return True

    def _send_final(self, rs: RobotSession) -> None:
        """The robot's final checkpoint (drain, shed): after its latest scan, or its attach's
        checkpoint handed back when it registered none here."""
        with self._lock:
            entry = self.fleet.attached.get(rs.robot)
        if entry is None:
            return
        try:
            if rs.mapper is not None:
                self._continue(rs)
                self._send_checkpoint(rs, entry.epoch, final=True)
            elif rs.pending is not None and rs.pending.checkpoint is not None and self._session is not None:
                # (float32, as every final: check_attach decoded the attach's coded map)
                cp = dataclasses.replace(rs.pending.checkpoint, edge=self.edge_id, epoch=entry.epoch,
                                         final=True)
                self._session.put(self.keys.checkpoint(rs.robot, self.edge_id), wire.encode(cp),
                                  congestion_control=zenoh.CongestionControl.BLOCK)
                self._count(rs, "final_checkpoints")
        finally:
            # Owed no longer, sent or not: one that failed (counted in worker_errors by the caller)
            # left the robot owed for good, so a drain waited for it to move by itself and a shed
            # robot was never refused; it moves without a checkpoint, as from a dead edge
            with self._lock:
                self.fleet.final_sent(rs.robot, time.monotonic())
        log.info("robot %s: final checkpoint sent", rs.robot)

    def _ask_final(self, robot: str) -> None:
        """Called with the lock held: the robot's worker sends its final checkpoint."""
        rs = self.robots.get(robot)
        if rs is None or rs.closed:
            return
        rs.final_pending = True
        if not rs.scheduled:
            rs.scheduled = True
            self._ready.append(rs)
            self._lock.notify()

    def begin_drain(self) -> None:
        """Draining (SIGTERM): attaches refused, every attached robot owed a final checkpoint."""
        with self._lock:
            for robot in self.fleet.begin_drain(time.monotonic()):
                self._ask_final(robot)
        log.info("draining: %d attached robots to hand over", len(self.fleet.attached))

    def drained(self, now: float | None = None) -> bool:
        with self._lock:
            return self.fleet.drained(time.monotonic() if now is None else now)

    def tick(self, now: float | None = None) -> None:
        """The server's housekeeping (about 1 Hz): the load window, shedding, shed robots' sessions."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self.fleet.sample(now, self._busy, self.counters["dropped"], self.counters["timed"],
                              self.counters["late"])
            shed = self.fleet.to_shed(now, len(self._workers), self.peers.room_elsewhere(now))
            if shed is not None:
                self.counters["shed"] += 1
                self._ask_final(shed)
            gone = self.fleet.shed_gone(now)
        if shed is not None:
            log.warning("over capacity (busy %.0f %%, %s): shedding robot %s",
                        100 * self.fleet.busy_share(len(self._workers)), self.fleet.overload_reason(), shed)
        for robot in gone:
            self.evict(robot)

    def _count(self, rs: RobotSession, what: str, n: int = 1) -> None:
        with self._lock:
            rs.counters[what] += n
            self.counters[what] += n

    def _ack(self, rs: RobotSession, item: Queued, status: str, detail: str = "",
             queue_time: float = float("nan"), reg: Registration | None = None) -> None:
        scan = item.scan
        mapper = rs.mapper
        ack = _ack_message(rs.robot, scan.seq, scan.send_stamp, status, self.edge_id, scan.epoch, detail,
                           item.interarrival, queue_time, reg,
                           reg.map_points if reg else (mapper.map_points if mapper else 0))
        try:
            rs.ack_pub.put(wire.encode(ack))
        except Exception as exc:  # the session is closing, or the robot was evicted meanwhile
            log.debug("ack not published: %s", exc)
            return
        with self._lock:
            self.counters["acks"] += 1
            if reg is not None:  # timeliness of what the mappers answered: the shedding's lateness
                self.counters["timed"] += 1
                if time.monotonic() - item.arrival > rs.period():
                    self.counters["late"] += 1

    # Eviction (the server's housekeeping, for robots the admission expired)
    def evict(self, robot: str) -> None:
        """Drop the robot's state, its map exported first; a scan it sends later starts anew."""
        with self._lock:
            self.fleet.forget(robot)
            rs = self.robots.pop(robot, None)
            if rs is None:
                return
            rs.closed = True
            busy = rs.scheduled  # a worker holds it: that worker closes it when done
        if not busy:
            self._close(rs)

    def _close(self, rs: RobotSession) -> None:
        for item in list(rs.queue):
            self._ack(rs, item, status="dropped", detail="robot evicted from the edge")
        rs.queue.clear()
        if self.map_dir:
            self._export(rs)
        close = getattr(rs.mapper, "close", None)
        if close is not None:  # a mapper in a process of its own: freed there
            close()
        undeclare(rs.ack_pub, rs.cp_pub)
        with self._lock:
            self.counters["evicted"] += 1
        log.info("robot %s evicted after %d scans", rs.robot, rs.counters["received"])

    # Map queries and export
    def _on_map_query(self, query: zenoh.Query) -> None:
        robot = self.keys.robot_of(str(query.key_expr))
        with self._lock:
            rs = self.robots.get(robot) if robot else None
        if rs is None or rs.mapper is None:
            lost = rs.counters["mapper_lost"] if rs is not None else 0
            why = f"its mapper was lost ({lost} so far); its next scan starts a new map" if lost else ""
            query.reply_err(no_map_reply(robot, why).encode())
            return
        if not self._map_reply.acquire(blocking=False):
            query.reply_err(f"{BUSY} another map reply is being built; ask again".encode())
            return
        try:
            mapper = rs.mapper
            try:
                if mapper is None:
                    raise MapperLost("its mapper was lost")
                seqs, poses = mapper.trajectory()
                points = mapper.map_cloud()
            except Exception as exc:  # its mapper process was lost, say
                query.reply_err(no_map_reply(robot, str(exc))[:300].encode())
                return
            reply = wire.MapReply(robot=rs.robot, scans=mapper.scans, points=points,
                                  seqs=seqs, poses=poses, edge=self.edge_id)
            query.reply(self.keys.map(rs.robot, self.edge_id), wire.encode(reply))
        finally:
            self._map_reply.release()

    def _export(self, rs: RobotSession) -> Path | None:
        """Export one robot's map; a failure is logged, so the other robots' maps still get written."""
        if rs.mapper is None:
            return None
        try:
            path = rs.files.export(rs.mapper, {k: int(v) for k, v in rs.counters.items()})
        except Exception as exc:  # a full disk, an unwritable folder: say so, keep going
            log.error("map of %s not written: %s", rs.robot, exc)
            return None
        if path is not None:
            log.info("map of %s written to %s", rs.robot, path)
        return path

    def export_map(self, robot: str) -> Path | None:
        """Write the robot's map, trajectory and counters to ``map_dir``; None without a map."""
        rs = self.robots.get(robot)
        return self._export(rs) if rs is not None else None


def _ack_message(robot: str, seq: int, send_stamp: float, status: str, edge: str, epoch: int,
                 detail: str = "", interarrival: float = float("nan"), queue_time: float = float("nan"),
                 reg: Registration | None = None, map_points: int = 0) -> wire.ScanAck:
    nan = float("nan")

    def duration(x: float) -> float:  # what the codec accepts of a duration; NaN = not measured
        return x if 0.0 <= x <= 3600.0 else nan

    pose = reg.pose if reg is not None and np.isfinite(reg.pose).all() else np.full((4, 4), nan)
    return wire.ScanAck(
        robot=robot, seq=seq, send_stamp=send_stamp, status=status, interarrival=duration(interarrival),
        queue_time=duration(queue_time), proc_time=duration(reg.proc_time) if reg else nan,
        icp_time=duration(reg.icp_time) if reg else nan, map_points=map_points,
        keypoints=reg.keypoints if reg else 0, sigma=reg.sigma if reg and 0 <= reg.sigma <= 1e6 else nan,
        detail=detail, pose=pose, epoch=epoch, edge=edge)
