"""Per-scan bookkeeping on the robot: every scan ends in exactly one bucket.

    produced  = published + dropped at source (by reason) + sending + local
    published = acked + edge_dropped + edge_error + edge_refused + lost + late + in_flight

``local``: registered by the robot's own odometry instead of being sent (no edge mapped the robot).
``lost_overtaken`` (not a bucket: a share of ``lost``): lost while a later scan sent the same way
(edge and epoch) was answered. An edge answers a robot's scans in order, one answer each, so the
scan or its answer was lost on the way (the transport), not with the edge.
``sending``: handed to the sender thread, not published yet (at most two: the one it is encoding,
or holding until the window has a slot for it, and the one waiting in its slot).
``edge_refused``: the edge did not admit this robot (allowlist, ``max_robots``). ``lost``: no ack
within the timeout. ``late``: its ack came after that (moved out of ``lost``). Round-trip times
use the robot's clock only: the send stamp travels with the scan and is echoed. The ledger also
keeps what the scale policy reads about the link: the last acked scans (bytes, network time, T,
slot), the bytes acked in the last second, the last ack's time.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zoffload.policy.rate import AckInfo
from zoffload.protocol import wire
from zoffload.robot.scanlog import ScanLog

ACK_BUCKETS = {"ok": "acked", "dropped": "edge_dropped", "refused": "edge_refused"}
PATH_ACKS = 5  # acks of a route before its quickest round trip sizes the window
PATH_MAX = 8  # the window a long path gets: at most this times the base (24: 2.3 s at 10 Hz)
FLOOR_SPAN = 10.0  # the path's floor: the quickest network time of the acks of the last this many s


@dataclass
class ScanLedger:
    log: ScanLog = field(default_factory=ScanLog)  # the records, bounded (robot/scanlog.py)
    counters: Counter[str] = field(default_factory=Counter)
    dropped_source: Counter[str] = field(default_factory=Counter)
    pending: dict[int, float] = field(default_factory=dict)  # seq -> send stamp
    sending: set[int] = field(default_factory=set)  # handed to the sender, not published yet
    last_interarrival: float = 0.0  # T_{n-1}; 0 before any ack (the paper's T0)
    last_slot: int = 1  # the slot of the scan ``last_interarrival`` came with
    interarrivals_seen: int = 0  # how many acks have brought a T (a policy reacts to new ones)
    last_ack_at: float = -math.inf  # robot clock of the newest ack, any status
    first_acked_at: float | None = None  # robot clock of the first scan acked "ok"
    recent: deque[AckInfo] = field(default_factory=lambda: deque(maxlen=24))  # acked scans
    _acked_bytes: deque[tuple[float, int]] = field(default_factory=deque)  # (ack time, bytes)
    window_drops: int = 0  # scans held back because the window of unanswered ones was full
    window_released: int = 0  # ... and sent when an ack freed a slot within a period (window_hold)
    edge_times: deque[float] = field(default_factory=lambda: deque(maxlen=20))  # queue + registration [s]
    _newest_answer: tuple[str, int, int] | None = None  # (edge, epoch, seq) of the newest answer
    route: tuple[str, int] | None = None  # the (edge, epoch) scans go to now (``on_route``)
    route_since: float = -math.inf  # robot clock of the first scan under it
    route_rtt_min: float = math.inf  # the quickest round trip of a scan acked under it [s]
    route_acks: int = 0  # scans acked under it
    # (robot clock, network time) of the current route's answers, late ones too: a queue deeper than
    # the ack timeout shows only in late acks (``recent`` holds acked scans), and the scans the
    # timeout expired while they queued no longer count in flight. Only scans the edge registered
    # ("ok") with both of its times known: a busy edge's "dropped" answer carries its queue, not the
    # link's. ``newest_net`` and ``floor_net`` read it
    route_nets: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=200))
    _route_answered: int = -1  # the newest scan of the current route the edge answered (any status)
    _route_lost: deque[int] = field(default_factory=lambda: deque(maxlen=100))  # expired on the route
    # the route's round trip as TCP estimates it (RFC 6298: smoothed, and its mean deviation), from
    # every answer of the route, late ones too; NaN before the first: what ``ack_timeout`` follows
    srtt: float = math.nan
    rttvar: float = math.nan

    @property
    def records(self) -> dict[int, dict[str, Any]]:
        return self.log.records

    @property
    def poses(self) -> dict[int, np.ndarray]:
        return self.log.poses

    @property
    def gt_poses(self) -> dict[int, np.ndarray]:
        return self.log.gt_poses

    def produced(self, n: int = 1) -> None:
        self.counters["produced"] += n

    def drop_at_source(self, seq: int | None, reason: str, record: dict[str, Any] | None = None) -> None:
        self.dropped_source[reason] += 1
        if seq is not None:
            self.sending.discard(seq)
            self.records[seq] = dict(self.records.get(seq, {}), **(record or {}), seq=seq,
                                     status=f"source:{reason}")
            self.log.trim()

    def local(self, seq: int, record: dict[str, Any], pose: np.ndarray) -> None:
        """Registered by the robot itself instead of being sent: a terminal bucket, with a pose."""
        self.counters["local"] += 1
        self.records[seq] = dict(record, seq=seq, status="local", pose_source="local", edge="")
        self.poses[seq] = pose
        _pose_known(self.records[seq])
        self.log.trim()

    def local_pose(self, seq: int, pose: np.ndarray) -> bool:
        """A pose the robot's odometry found for a scan its edge never answered (the bucket stays
        what the ack timeout makes it); False when the scan has a pose or no record already."""
        rec = self.records.get(seq)
        if rec is None or seq in self.poses:
            return False
        self.poses[seq] = pose
        rec["pose_source"] = "local"
        _pose_known(rec)
        return True

    def handed_off(self, seq: int, record: dict[str, Any]) -> None:
        """Sized and given to the sender thread."""
        self.sending.add(seq)
        self.records[seq] = dict(record, seq=seq, status="sending")
        self.log.trim()

    def published(self, seq: int, send_stamp: float, record: dict[str, Any]) -> None:
        self.sending.discard(seq)
        self.counters["published"] += 1
        self.pending[seq] = send_stamp
        self.records[seq] = dict(self.records.get(seq, {}), **record, seq=seq, send_stamp=send_stamp,
                                 status="in_flight")

    def on_ack(self, ack: wire.ScanAck, recv_stamp: float) -> str:
        """Book an ack; returns the bucket it landed in ("acked", "edge_dropped", "edge_error",
        "edge_refused", "late", "duplicate" or "unknown")."""
        rec = self.records.get(ack.seq)
        if rec is None or "send_stamp" not in rec or rec["send_stamp"] != ack.send_stamp:
            self.counters["unknown_acks"] += 1
            return "unknown"
        self.last_ack_at = recv_stamp
        rtt = recv_stamp - ack.send_stamp
        edge_time = sum(x for x in (ack.queue_time, ack.proc_time) if math.isfinite(x))
        route = _route(rec)  # the route the scan was sent under: taken before the ack names its edge
        here = self._here(rec)
        if here:
            self._route_answered = max(self._route_answered, ack.seq)
            if rtt >= 0:
                self._round_trip(rtt)
            if (ack.status == "ok" and rtt >= 0 and math.isfinite(ack.queue_time)
                    and math.isfinite(ack.proc_time)):
                self.route_nets.append((recv_stamp, rtt - edge_time))
        rec.update(rtt=rtt, network_time=rtt - edge_time, interarrival=ack.interarrival,
                   queue_time=ack.queue_time, proc_time=ack.proc_time, map_points=ack.map_points,
                   keypoints=ack.keypoints, sigma=ack.sigma)
        slot = int(rec.get("skipped") or 0) + 1
        if math.isfinite(ack.interarrival):
            self.last_interarrival = ack.interarrival
            self.last_slot = slot
            self.interarrivals_seen += 1
        if ack.seq in self.pending:
            del self.pending[ack.seq]
            newest = self._newest_answer
            if newest is None or newest[:2] != route or ack.seq > newest[2]:
                self._newest_answer = (*route, ack.seq)
            bucket = ACK_BUCKETS.get(ack.status, "edge_error")
            self.counters[bucket] += 1
            rec["status"] = bucket
            if bucket == "acked":
                self.poses[ack.seq] = np.array(ack.pose)
                rec["pose_source"], rec["edge"] = "edge", ack.edge
                _pose_known(rec)
                nbytes = int(rec.get("bytes") or 0)
                self.recent.append(AckInfo(nbytes, rtt - edge_time, ack.interarrival, slot))
                if math.isfinite(ack.queue_time) and math.isfinite(ack.proc_time):
                    self.edge_times.append(edge_time)
                self._acked_bytes.append((recv_stamp, nbytes))
                if here and rtt >= 0:
                    self.route_acks += 1
                    self.route_rtt_min = min(self.route_rtt_min, rtt)
                if self.first_acked_at is None:
                    self.first_acked_at = recv_stamp
            return bucket
        if rec.get("status") == "lost":
            self.counters["lost"] -= 1
            if rec.pop("overtaken", False):
                self.counters["lost_overtaken"] -= 1
            self.counters["late"] += 1
            rec["status"], rec["late_status"] = "late", ack.status  # what the edge said, late
            return "late"
        self.counters["duplicate_acks"] += 1
        return "duplicate"

    def carried_rate(self) -> float:
        """A lower bound of the link's rate, bytes a second: the most bytes a recently acked scan
        carried per second of its network time (its round trip less the edge's queue and
        registration: the way there and the ack's way back); 0 before any."""
        return max((a.bytes / a.net for a in self.recent if a.net > 0), default=0.0)

    def acked_bytes_per_s(self, now: float) -> float:
        """Bytes of the scans acked in the last second; NaN until acks span a full second (two
        acks in the first 0.2 s are not a rate)."""
        while self._acked_bytes and self._acked_bytes[0][0] < now - 1.0:
            self._acked_bytes.popleft()
        if self.first_acked_at is None or self.first_acked_at > now - 1.0:
            return math.nan
        return float(sum(b for _, b in self._acked_bytes))

    def expire(self, now: float, timeout: float) -> int:
        """Declare lost every scan unanswered for ``timeout`` seconds; returns how many."""
        expired = [seq for seq, stamp in self.pending.items() if now - stamp > timeout]
        newest = self._newest_answer
        for seq in expired:
            del self.pending[seq]
            self.counters["lost"] += 1
            rec = self.records[seq]
            rec["status"] = "lost"
            route = _route(rec)
            if self._here(rec):
                self._route_lost.append(seq)
            if newest is not None and newest[:2] == route and newest[2] > seq:
                rec["overtaken"] = True
                self.counters["lost_overtaken"] += 1
        return len(expired)

    def finish(self) -> None:
        """End of run: whatever is still unanswered is lost, whatever was never sent is unsent."""
        for seq in list(self.sending):
            self.drop_at_source(seq, "unsent")
        self.expire(float("inf"), 0.0)

    @property
    def in_flight(self) -> int:
        return len(self.pending)

    # The current route: what the window, the stall rule and the fleet's silence clock look at
    def on_route(self, route: tuple[str, int], now: float) -> None:
        """Scans go to ``route`` (edge, epoch) from now on (a move: a new one)."""
        if route != self.route:
            self.route, self.route_since = route, now
            self.route_rtt_min, self.route_acks = math.inf, 0
            self.route_nets.clear()
            self._route_answered = -1
            self._route_lost.clear()
            self.srtt = self.rttvar = math.nan

    def _round_trip(self, rtt: float) -> None:
        if math.isnan(self.srtt):
            self.srtt, self.rttvar = rtt, rtt / 2
        else:
            self.rttvar = 0.75 * self.rttvar + 0.25 * abs(self.srtt - rtt)
            self.srtt = 0.875 * self.srtt + 0.125 * rtt

    def ack_timeout(self, base: float, most: float | None) -> float:
        """Seconds before an unanswered scan of the current route is lost: the route's round trip
        plus four times its deviation (TCP's retransmission timeout, RFC 6298), at least ``base``
        and at most ``most`` (``base`` before the route's first answer, or when ``most`` is None or
        not above ``base``).
        A fixed second booked every scan ``late`` on a path whose round trip had risen above it
        (a satellite link rerouted 600 ms longer: 1.8 s), so no edge pose was ever used and the
        robot mapped every scan itself; and in a satellite rain fade 13-43 scans a run."""
        if most is None or math.isnan(self.srtt) or most <= base:
            return base
        return min(most, max(base, self.srtt + 4 * self.rttvar))

    def _here(self, rec: dict[str, Any]) -> bool:
        """Whether a scan's record was sent under the current route (any, before the first)."""
        return self.route is None or _route(rec) == self.route

    def _pending_here(self) -> list[tuple[int, float]]:
        """(seq, send stamp) of the unanswered scans sent under the current route."""
        recs = self.records
        return [(s, stamp) for s, stamp in self.pending.items() if self._here(recs.get(s, {}))]

    @property
    def newest_net(self) -> float:
        """The network time of the current route's newest answer in ``route_nets``; NaN: none."""
        return self.route_nets[-1][1] if self.route_nets else math.nan

    @property
    def floor_net(self) -> float:
        """The path's floor: the quickest network time of the scans the edge registered on the
        current route, late ones too, over the ``FLOOR_SPAN`` seconds before the newest of them
        (NaN before 10 on the route): another edge's path is another floor, and a path whose base
        delay rose for good (a satellite handover, a reroute) has a new floor ``FLOOR_SPAN`` later.
        Taken from on-time acks alone, of the last 100, a floor never followed such a rise (the
        acks above it were all late) and the queue stall held the robot to a scan per round trip."""
        nets = self.route_nets
        if len(nets) < 10:
            return math.nan
        since = nets[-1][0] - FLOOR_SPAN
        return min(net for at, net in nets if at >= since)

    @property
    def path_rtt(self) -> float:
        """The round trip the current route's path takes with no queue on it: the quickest round
        trip acked under the route, or the path's floor (``floor_net``, the quickest network time
        of the last ``FLOOR_SPAN`` seconds) where that stands higher; inf before the first ack.
        The quickest round trip only falls, so a path rerouted 600 ms longer for good (a satellite
        link: 0.6 s to 1.8 s) kept the window of its first minute and a silence was counted from
        the short path's round trip: 30 % of the scans held back, 62-156 silence stalls a run."""
        floor = self.floor_net
        return max(self.route_rtt_min, floor) if math.isfinite(floor) else self.route_rtt_min

    def overdue(self, now: float) -> float:
        """Seconds the oldest unanswered scan of the current route is past its expected answer
        (sent plus ``path_rtt``, or plus nothing before the route's first ack); -inf: none in
        flight. A silence counted since the last ack alone also counted the time the window held
        scans back: the first scan sent after it read as a stall, though it had just left."""
        sent = self._pending_here()
        if not sent:
            return -math.inf
        rtt = self.path_rtt
        return now - min(stamp for _, stamp in sent) - (rtt if math.isfinite(rtt) else 0.0)

    @property
    def queued_here(self) -> int:
        """Scans of the current route sent after the newest one the edge answered and not answered
        themselves: in flight, or expired by the ack timeout while they queued (no longer in
        flight, still on the link ahead of the next scan). A scan lost for good stops counting once
        a later one is answered (answers come in order)."""
        newest, recs = self._route_answered, self.records
        lost = sum(1 for s in self._route_lost if s > newest and recs.get(s, {}).get("status") == "lost")
        return lost + sum(1 for s, _ in self._pending_here() if s > newest)

    @property
    def in_flight_here(self) -> int:
        """Unanswered scans sent under the current route. The scans still in flight to an edge
        the robot left (dead, silent, draining) are not on the new edge's path: counted, they
        filled its window and made its silence for up to ``ack_timeout`` after a move, so the
        first scans to the new edge were held back as a stall, with no pose from either side
        (3-4 scans after a kill on the fleet's emulated links)."""
        return len(self._pending_here())

    def since_answer(self, now: float) -> float:
        """Seconds since the newest ack, or since the current route began if that is later (a new
        edge has not had the chance to answer before its first scan); 0 before any ack."""
        if not math.isfinite(self.last_ack_at):
            return 0.0
        return now - max(self.last_ack_at, self.route_since)

    def window(self, base: int, period: float, edge: bool = True, path: bool = True) -> int:
        """Unanswered scans allowed before the next is held back: ``base`` (0: no limit) plus the
        scans the edge itself holds, queued or being registered: the median of its time per scan
        over the last 20 acks, in periods, rounded; at most ``base`` more. Those scans are off the
        link: counted against the link's window, an edge that registers in a period (KITTI-360's
        HDL-64 on a busy edge) leaves the link a window of 2, and a path of 2-3 periods (cellular)
        drops scans without any queue on it.

        And at least the scans a long path holds with no queue on it: the route's ``path_rtt``
        (``PATH_ACKS`` acks at least) in periods, rounded up, plus one, at most ``PATH_MAX``
        times ``base``. A 0.55 s round trip (250 ms each way) needs 6-7 scans in flight at 10 Hz;
        a window of 3 held back 43 % of the scans with the link two-thirds idle. ``path_rtt`` is
        the quickest round trip of the route unless the floor of the last ``FLOOR_SPAN`` seconds
        stands higher: a queue must stand on the link for that long, unbroken, before it widens
        the window that feeds it (a round trip of the last 100 scans did: docs/scan-policy-log.md, "Unseen
        links"), and a path that grew longer for good gets its window then. (With at most 4 times
        the base, a 1.8 s path, a satellite reroute, was held to 12 scans in flight, and the scans
        the window dropped, unannounced, left the edge 7-scan gaps in turns.) ``edge`` and ``path``
        switch either term off."""
        if not base:
            return base
        window = base
        if edge and self.edge_times:
            extra = int(sorted(self.edge_times)[len(self.edge_times) // 2] / period + 0.5)
            window += min(base, extra)
        if path and self.route_acks >= PATH_ACKS and period > 0:
            on_path = math.ceil(self.path_rtt / period) + 1
            window = max(window, min(on_path, PATH_MAX * base))
        return window

    def balance(self) -> dict[str, int]:
        c = self.counters
        return {
            "produced": c["produced"],
            "published": c["published"],
            "dropped_source": sum(self.dropped_source.values()),
            "sending": len(self.sending),
            "local": c["local"],
            "acked": c["acked"],
            "edge_dropped": c["edge_dropped"],
            "edge_error": c["edge_error"],
            "edge_refused": c["edge_refused"],
            "lost": c["lost"],
            "late": c["late"],
            "in_flight": self.in_flight,
        }

    def balanced(self) -> bool:
        b = self.balance()
        return (
            b["produced"] == b["published"] + b["dropped_source"] + b["sending"] + b["local"]
            and b["published"] == b["acked"] + b["edge_dropped"] + b["edge_error"] + b["edge_refused"]
            + b["lost"] + b["late"] + b["in_flight"]
        )


def _route(rec: dict[str, Any]) -> tuple[str, int]:
    """The (edge, epoch) a scan was sent under ("", 0) without the attach protocol."""
    return str(rec.get("edge", "")), int(rec.get("epoch") or 0)


def _pose_known(rec: dict[str, Any]) -> None:
    """How long after its capture the scan's first pose came (the robot's clock, ms)."""
    if "pose_lag_ms" not in rec and "capture_stamp" in rec:
        rec["pose_lag_ms"] = (time.time() - float(rec["capture_stamp"])) * 1e3
