"""Per-frame offloading strategies: where each camera frame is detected, robot or edge.

* ``robot`` / ``edge``: always local / always offloaded (the thesis' baselines).
* ``ratio:R``: the thesis' Algorithm 1, offload while offloaded/total < R.
* ``thesis``: the thesis' Algorithm 2 as published: CPU ≥ cpu_max → edge; outgoing bandwidth ≥
  bw_max → local; else the side with the lower smoothed RTT, where the edge RTT is averaged over
  the frames that *came back* (inference + network).
* ``dynamic`` (ours before ``dispatch``): the same rule, fixed where it failed under a bandwidth cap.
  A frame that does not come back within the timeout enters the edge average *as* the timeout,
  and a frame in flight for over twice the average counts with its age so far, so an edge that
  stops answering looks slow at once. The local side is estimated by its detector's service time
  (doubled while it is busy), not by the RTT of an idle detector. Sides switch only for a 15 %
  better estimate. The edge is refused while a window of frames is unanswered (``max_in_flight``,
  halved on a loss but never below two, grown back by a quarter frame per answer), which keeps a
  slow link from queuing frames that will be stale on arrival; the frame is then held back
  (skipped, counted) when the local detector is the slower side anyway (running it would only
  take the weak robot's CPU from the frames in flight) and detected locally otherwise. While the
  rule chooses local, one frame in ``probe_every`` still goes to the edge so its estimate stays
  fresh.
* ``dispatch`` (ours, the default, policy/dispatch.py): both sides are servers working in
  parallel; each frame goes to the side expected to finish it soonest given what each is already
  doing, a frame no side can finish while fresh is skipped, and copies keep the edge's estimate
  fresh without sacrificing frames.

Strategies are pure decision objects: the offloader feeds them observations and asks ``choose``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from zoffload.policy.smoothing import MovingAverage

LOCAL, EDGE, HOLD = "local", "edge", "hold"  # hold: the frame is held back (dropped_window)
SKIP = "skip"  # no side can finish the frame while it is fresh: skipped (its own bucket)
BOTH = "both"  # detected locally, and a copy goes to the edge only to measure it (no result used)
NAN = float("nan")


@dataclass
class OffloadState:
    """What the offloader knows when a frame arrives (robot wall clock, seconds)."""

    now: float
    edge_available: bool  # an edge is present and not in fallback
    cpu_percent: float = NAN  # robot process CPU (one core = 100)
    mbps_out: float = NAN  # robot outgoing bandwidth, smoothed
    oldest_in_flight_age: float = 0.0  # seconds the oldest unanswered edge frame has waited
    in_flight: int = 0
    local_busy: bool = False  # the local detector is working on a frame
    # What the work-conserving dispatcher needs (the others ignore it)
    capture: float = NAN  # when this frame was captured
    local_busy_for: float = 0.0  # seconds the local detector has spent on its current frame
    local_waiting: bool = False  # a frame waits in the local detector's one slot
    local_last_start: float = -math.inf  # when the local detector last started a frame
    send_waiting: bool = False  # a frame waits in the sender's one slot (the link is busy)
    edge_sends: tuple[tuple[float, float], ...] = ()  # (sent at, bytes or NaN) of unanswered edge
    # frames and copies, oldest first
    cpu_time: float = NAN  # the robot process's CPU seconds so far (all threads)
    local_cpu_time: float = NAN  # of which the local detector's
    cpu_quota: float = NAN  # cores the robot process may use (a CFS quota); NaN: no quota


@dataclass(frozen=True)
class EdgeReply:
    """One answer from the edge, as the robot saw it."""

    sent: float  # handed to the sender
    result: float  # answer received
    bytes: float  # the frame's size on the wire (NaN if unknown)
    service: float  # the edge's own processing time (decode + inference), NaN if it says none
    delivery_rate: float = NAN  # bytes/s the link delivered this frame at, when it queued behind another
    status: str = "ok"  # ok, dropped (a newer frame of ours came behind it, or the queue overflowed), error
    edge_queue: float = NAN  # how long it waited in the edge's queue (the edge says), NaN if unknown
    alone: bool = False  # sent with no other edge frame unanswered: no queue in its answer time


@dataclass
class Strategy:
    name: str = "base"
    offloaded: int = 0
    total: int = 0

    # When the local detector may start its next frame (robot clock): a pacing strategy keeps the
    # detector within the robot's CPU budget; the others never hold it back.
    local_ready_at: float = -math.inf

    def choose(self, st: OffloadState) -> str:
        raise NotImplementedError

    def decide(self, st: OffloadState) -> str:
        """``choose``, with the edge replaced by local when no edge is available, and counted."""
        side = self.choose(st)
        if side in (EDGE, BOTH) and not st.edge_available:
            side = LOCAL
        self.total += 1
        self.offloaded += side == EDGE
        return side

    # Observations (no-ops for the static strategies)
    def on_local_result(self, rtt: float, service: float | None = None,  # noqa: B027 - optional
                        cpu: float | None = None, capture: float | None = None) -> None:
        """A local detection's answer: ``rtt`` from capture, the detector's wall (``service``) and
        CPU time, and the frame's ``capture`` time (which decision took it)."""

    def on_edge_result(self, rtt: float, reply: EdgeReply | None = None) -> None:  # noqa: B027
        pass

    def observe(self, seq: int, side: str, boxes: np.ndarray, scores: np.ndarray,  # noqa: B027
                capture: float = NAN) -> None:
        """A frame's detections (persons), from ``local`` or ``edge`` (a copy's answer too), and
        when the frame was captured."""

    def on_edge_refused(self, reply: EdgeReply, penalty: float) -> None:
        """The edge answered without detections (``dropped``: a newer frame of ours came behind it,
        or its queue overflowed; ``error``: the frame was bad): by default as bad as a frame that
        timed out after ``penalty`` seconds."""
        self.on_edge_timeout(penalty)

    def on_edge_timeout(self, waited: float) -> None:  # noqa: B027 - optional hook
        pass

    def on_encoding_change(self) -> None:  # noqa: B027 - optional hook
        """Frames to the edge now go in the other encoding (robot/encoding.py): estimates in
        bytes of the old one no longer hold."""


@dataclass
class RobotOnly(Strategy):
    name: str = "robot"

    def choose(self, st: OffloadState) -> str:
        return LOCAL


@dataclass
class EdgeOnly(Strategy):
    name: str = "edge"

    def choose(self, st: OffloadState) -> str:
        return EDGE


@dataclass
class FixedRatio(Strategy):
    """Algorithm 1: offload while the offloaded share is below ``ratio``."""

    ratio: float = 0.5
    name: str = "ratio"

    def choose(self, st: OffloadState) -> str:
        return EDGE if self.offloaded < self.ratio * (self.total + 1) else LOCAL


@dataclass
class ThesisDynamic(Strategy):
    """Algorithm 2 as the thesis ran it: edge RTT from returned frames only."""

    cpu_max: float = 90.0
    bw_max_mbps: float = float("inf")
    window: int = 10
    name: str = "thesis"
    rtt_local: MovingAverage = field(default_factory=lambda: MovingAverage(10))
    rtt_edge: MovingAverage = field(default_factory=lambda: MovingAverage(10))

    def __post_init__(self) -> None:
        self.rtt_local = MovingAverage(self.window)
        self.rtt_edge = MovingAverage(self.window)

    def edge_estimate(self, st: OffloadState) -> float:
        return self.rtt_edge.value

    def local_estimate(self, st: OffloadState) -> float:
        return self.rtt_local.value

    def compare(self, local: float, edge: float) -> str:
        return EDGE if edge < local else LOCAL

    def choose(self, st: OffloadState) -> str:
        if math.isfinite(st.cpu_percent) and st.cpu_percent >= self.cpu_max:
            return EDGE
        if math.isfinite(st.mbps_out) and st.mbps_out >= self.bw_max_mbps:
            return LOCAL
        local, edge = self.local_estimate(st), self.edge_estimate(st)
        # Until both sides have been measured, try the unmeasured one
        if math.isnan(edge):
            return EDGE
        if math.isnan(local):
            return LOCAL
        return self.compare(local, edge)

    def on_local_result(self, rtt: float, service: float | None = None, cpu: float | None = None,
                        capture: float | None = None) -> None:
        self.rtt_local.add(rtt)

    def on_edge_result(self, rtt: float, reply: EdgeReply | None = None) -> None:
        self.rtt_edge.add(rtt)


@dataclass
class DeliveryAwareDynamic(ThesisDynamic):
    """Ours: timeouts count, in-flight age counts, a window bounds the edge queue, local probes."""

    max_in_flight: int = 4
    min_window: int = 2
    probe_every: int = 10
    margin: float = 0.15  # switch sides only for an estimate this much better (no flapping)
    stall_factor: float = 2.0  # an in-flight frame older than this x the average means a stall
    name: str = "dynamic"
    _since_probe: int = 0
    _preferred: str = EDGE
    _window: float = 0.0
    service_local: MovingAverage = field(default_factory=lambda: MovingAverage(10))

    def __post_init__(self) -> None:
        super().__post_init__()
        self._window = float(self.max_in_flight)

    def on_edge_result(self, rtt: float, reply: EdgeReply | None = None) -> None:
        super().on_edge_result(rtt)
        self._window = min(float(self.max_in_flight), self._window + 0.25)

    def edge_estimate(self, st: OffloadState) -> float:
        est = self.rtt_edge.value
        if st.in_flight and (math.isnan(est) or st.oldest_in_flight_age > self.stall_factor * est):
            # The unanswered frame already took this long, far beyond the usual: the edge (or the
            # link) is stalling and is at least this slow. Within the usual spread, pipelined
            # frames are simply on their way.
            est = st.oldest_in_flight_age
        return est

    def local_estimate(self, st: OffloadState) -> float:
        """What the next local frame would take: the detector's service time, twice if it is busy
        (the frame waits for the one running). An idle detector's lucky RTT does not make local
        look fast when every frame goes there."""
        service = self.service_local.value
        if math.isnan(service):
            return self.rtt_local.value
        return max(self.rtt_local.value, service * (2.0 if st.local_busy else 1.0))

    def compare(self, local: float, edge: float) -> str:
        if self._preferred == EDGE and local < (1 - self.margin) * edge:
            self._preferred = LOCAL
        elif self._preferred == LOCAL and edge < (1 - self.margin) * local:
            self._preferred = EDGE
        return self._preferred

    def on_local_result(self, rtt: float, service: float | None = None, cpu: float | None = None,
                        capture: float | None = None) -> None:
        self.rtt_local.add(rtt)
        if service is not None:
            self.service_local.add(service)

    @property
    def flight_window(self) -> int:
        return max(1, min(self.max_in_flight, int(self._window))) if self.max_in_flight else 0

    def choose(self, st: OffloadState) -> str:
        side = super().choose(st)
        if side == EDGE and self.max_in_flight and st.in_flight >= self.flight_window:
            local = self.local_estimate(st)
            return HOLD if math.isfinite(local) and local > self.edge_estimate(st) else LOCAL
        if side == LOCAL and st.in_flight == 0:
            self._since_probe += 1
            if self._since_probe >= self.probe_every:
                self._since_probe = 0
                return EDGE
        else:
            self._since_probe = 0
        return side

    def on_edge_refused(self, reply: EdgeReply, penalty: float) -> None:
        """A frame the edge answered ``dropped`` was superseded by a newer one of ours (the edge
        serves each robot's newest frame, edge/detection.py): no loss. Errors count as timeouts."""
        if reply.status != "dropped":
            self.on_edge_timeout(penalty)

    def on_edge_timeout(self, waited: float) -> None:
        self.rtt_edge.add(waited)
        self._window = max(float(self.min_window), self._window / 2)


STRATEGIES = "robot, edge, ratio:R, thesis, dynamic or dispatch"


def make_strategy(spec: str, cpu_max: float = 90.0, bw_max_mbps: float = float("inf"),
                  max_in_flight: int = 4, **dispatch: float) -> Strategy:
    """``robot``, ``edge``, ``ratio:R`` (0 ≤ R ≤ 1), ``thesis``, ``dynamic`` or ``dispatch`` (with
    its parameters in ``dispatch``, see policy/dispatch.py); ValueError otherwise."""
    if spec == "robot":
        return RobotOnly()
    if spec == "edge":
        return EdgeOnly()
    if spec.startswith("ratio:"):
        try:
            r = float(spec.split(":", 1)[1])
        except ValueError:
            raise ValueError(f"strategy {spec!r}: ratio:R needs a number") from None
        if not 0.0 <= r <= 1.0:
            raise ValueError(f"strategy {spec!r}: the ratio must be within [0, 1]")
        return FixedRatio(ratio=r, name=f"ratio:{r:g}")
    if spec == "thesis":
        return ThesisDynamic(cpu_max=cpu_max, bw_max_mbps=bw_max_mbps)
    if spec == "dynamic":
        return DeliveryAwareDynamic(cpu_max=cpu_max, bw_max_mbps=bw_max_mbps, max_in_flight=max_in_flight)
    if spec == "dispatch":
        from zoffload.policy.dispatch import Dispatcher

        return Dispatcher(max_in_flight=max_in_flight, **dispatch)  # type: ignore[arg-type]
    raise ValueError(f"unknown offloading strategy {spec!r} ({STRATEGIES})")
