"""``dispatch``: a work-conserving dispatcher of camera frames over two servers working in
parallel, the robot's detector and the edge.

Each frame goes to the side expected to finish it soonest given what that side is already doing:

* **local**: the detector's current frame ends after its service time (a moving average of the
  measured ones) less what it has already spent; the new frame starts then, or later if the
  robot's CPU budget says so (below), and takes one service time.
* **edge**: the edge path (sender, link, edge queue, edge detector, answer) is one pipeline with a
  bottleneck time per frame, ``max(edge service time, bytes / delivered rate)`` (the delivered rate:
  the bytes per second that reached the edge while frames queued behind each other on the link,
  robot/frames.py and robot/linkclock.py), and a base
  latency ``r0``: the send-to-answer time of a frame with nothing ahead of it, the shortest recent
  one of the frames *sent alone* (none other unanswered) less the edge's own time on it (queue and
  detector, as the edge reports them), plus the edge detector's service time now. The frames in
  flight are laid out on that pipeline after the last answer, oldest first (one overdue is assumed
  to take as long again as it is late already); a new frame comes one bottleneck time after the
  last of them, and never sooner than ``r0`` from now.

The base from frames sent alone: with frames always in flight, every answer time holds some queue,
and a base learnt from all of them grew with the queue, the depth (below) with the base, and the
queue with the depth. When no frame sent alone was answered for ``base_period`` (20 s), the edge
path is *drained*: no edge frame until none is in flight (a few frames go to the local detector or
are skipped), and the next one goes alone (``drains``; the next drain a ``base_period`` later at
the soonest). The robot (robot/frames.py) does not count a frame as alone after a loss until an
answer came (the lost frame may still be on the link), nor a trial of the other encoding; a switch
of encoding clears the base and drains at the next frame. Before, the base also took off the
bottleneck's estimated time then and added it back now; a delivered-rate sample far off made it
negative (docs/perception-log.md: "The base latency from frames sent alone").

Fresh frames, not queues: the edge path holds as many frames as keep its bottleneck busy for a
base latency, ``ceil(r0 / bottleneck time)``, plus ``queue_frames`` waiting (at most ``window``),
not as many as it takes (a fixed ratio fills the link's buffers, and its frames arrive late); the
local detector takes a frame only if it would start it within ``slack`` camera periods (a later,
fresher frame would be finished just as soon). A frame that neither side takes so goes to the edge
all the same, a *spare*, while the window has room and the edge would finish it within
``max_age``: a skipped frame scores nothing, one a frame time later nearly what a fresh one does,
and on a robot under a CPU quota the spare keeps the link busy while the whole process stalls. A
frame that no side finishes within ``max_age`` of its capture is skipped (its own bucket). A
frame that would replace one already waiting in a side's one-slot queue counts against that side
(one of the two is lost).

``local_bias`` (one camera period, 40 ms) is how much sooner the local side must finish to be
chosen: on the tuning half of the images NanoDet-m on a fresh frame scores what PicoDet-S scores
one frame late (78.3 vs 78.2 AP50), and PicoDet-S is the stronger model in general (COCO mAP 30.6
against 20.6). With ``learn_bias`` (off by default) the bias is measured online instead
(policy/agreement.py): each edge answer stands as the truth for the answers to the frames just
before it, and the bias is how many camera periods older an edge answer may be and still agree
with it as well as a local answer does, pulled towards ``local_bias`` while few answers were
compared (``bias_prior`` pairs weigh as much as the prior), and then at most half of ``max_age``.
It measures the models' agreement, not their accuracy, and within a 50 s run on the held-out
images it scored no better than the constant (0.8 lower on Wi-Fi, level on the other links;
docs/perception-log.md: "The local bias, measured online").

Each edge frame carries the recent share of frames the edge lost (timeouts,
errors) times ``max_age``: the offloading thesis' failure was an edge whose few returning frames
looked fast. A frame the edge answers ``dropped`` is none of them: the edge serves each robot's
newest waiting frame and drops the older ones (and the oldest when its queue of two overflows),
so it serves the fresher one. It used
to count as a loss and shrink the window by a frame; the spares that overflowed the edge's queue
(60-130 a run) then held the path below its depth, and a fixed "edge only", whose frames the edge
drops in the same way all the time, finished more frames (docs/perception-log.md:
"A frame the edge's queue replaced is not a loss").

The robot's CPU is a server too: under a CPU quota the detector is paced (``local_ready_at``) to
use at most what the rest of the process leaves of ``cpu_share`` × quota (process CPU time minus
the detector's own), instead of starving the camera and the frame sender. Even so, a quarter-core
robot's detection (20 ms of CPU against a 25 ms quota per 100 ms period) stalls the whole process,
sender and answers included, for most of a period. A detector that stalls the robot so (its wall
time less its CPU time over half a camera period) takes only the frames the edge cannot finish
within ``max_age`` (the edge blocked, gone or too slow); one that does not (a robot with the CPU to
spare) is the second server throughout. Before, the stalling detector also took a frame whenever
its stall fitted in the work the edge path's bottleneck had queued, but the stall delayed the
*following* sends all the same (docs/perception-log.md: "A stalling local detector takes only what the edge
cannot finish in time"). A slow local measurement drifts back towards the detector's
CPU time while it is idle (half-life ``recover``), so one slow spell does not idle it for good.

Overflow (``overflow``, since 2026-12-07): that rule left a stalling detector idle while the edge
path was full and the edge, serving its newest frame, dropped one of ours for every frame it could
not keep up with (an edge at 53-63 ms a frame against the camera's 40 ms: 239-365 of 1250 a run),
and a fixed ratio 0.9, detecting every tenth frame on the robot, finished more frames. So a
stalling detector also takes a frame the edge path is too full to take (it holds its depth), one
every ``overflow_gap`` seconds at most (``overflows`` counts the frames so chosen; one may still
be replaced in the detector's slot by the next). Spaced out, a quarter-core robot's detection can
run within one or two quota periods: ratio 0.9's, 0.40 s apart, took 35 ms (median) in one run,
the rule's without the spacing, 0.24 s apart, 107 ms; on a slower host both took 53-97 ms.
``overflow_gap`` is 0.4 s (ratio 0.9's spacing at 25 Hz) until a detection is measured; after
each local detection of a frame taken while the edge was usable (an overflow frame, a frame the
edge could not finish in time; since 2026-12-07 evening not fallback's frames, taken back to back
with the edge gone or blocked), it grows by a factor 1.5 when the detection stalled the robot (wall
time beyond CPU time by half a camera period) and by 0.9 when it did not, within 0.1-2 s. The stall rule
needs a measured detection first, so the first overflow frame comes after at least one such
update. On a host slow enough that every detection stalls the gap ends at 2 s and the rule takes
a few frames a run; a gap held at 0.4 s at most, tried on the tuning half, scored no better
(docs/perception-log.md: "Overflow frames for a stalling detector").

Losses: an edge frame unanswered within the reply timeout blocks the edge until an answer comes and
shrinks the window of frames in flight by one, once per outage (the frames that time out while it
is blocked went into the same outage: each counts as a loss, none shrinks the window again; it
grows back by a quarter frame per answer). While
blocked, the edge is asked again every ``retry_period``: a frame the local detector takes goes as a
copy, one it does not take (it would be skipped) goes to the edge itself. Before, a second's Wi-Fi
outage left a window of one frame and the edge blocked until the next copy, ``refresh_period``
later, while the quarter-core detector alone skipped every other frame.

Copies: when no frame went to the edge for ``refresh_period``, a frame detected locally is also
sent to the edge and only its answer time is used, so the edge's estimate stays fresh and no frame
is sacrificed to a probe.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from zoffload.policy.agreement import Agreement
from zoffload.policy.offload import BOTH, EDGE, LOCAL, NAN, SKIP, EdgeReply, OffloadState, Strategy

OVERFLOW_GAP = (0.1, 2.0)  # s: the range of the overflow frames' spacing
GAP_TRAINS_KEPT = 8  # local frames whose answer is awaited, at most (one detecting, one waiting: 2)


class Ewma:
    """Exponentially weighted moving average (NaN until the first finite value)."""

    def __init__(self, alpha: float) -> None:
        self.alpha = alpha
        self.value = NAN

    def add(self, x: float | None) -> None:
        if x is None or not math.isfinite(x):
            return
        self.value = x if math.isnan(self.value) else self.value + self.alpha * (x - self.value)


class Recent:
    """The last ``n`` samples no older than ``horizon`` seconds (the newest always kept)."""

    def __init__(self, n: int, horizon: float) -> None:
        self.samples: deque[tuple[float, float]] = deque(maxlen=n)
        self.horizon = horizon

    def add(self, t: float, x: float) -> None:
        if math.isfinite(x):
            self.samples.append((t, x))

    def values(self, now: float) -> list[float]:
        while len(self.samples) > 1 and now - self.samples[0][0] > self.horizon:
            self.samples.popleft()
        return [x for _, x in self.samples]

    def min(self, now: float) -> float:
        xs = self.values(now)
        return min(xs) if xs else NAN

    def median(self, now: float) -> float:
        xs = sorted(self.values(now))
        return xs[len(xs) // 2] if xs else NAN


class CpuMeter:
    """CPU used by the robot process apart from its local detector, in cores, over ``span`` s."""

    def __init__(self, span: float = 1.0) -> None:
        self.span = span
        self.points: deque[tuple[float, float]] = deque()  # (wall time, CPU time of the others)

    def add(self, now: float, cpu_time: float, local_cpu_time: float) -> None:
        if math.isfinite(cpu_time) and math.isfinite(local_cpu_time):
            self.points.append((now, cpu_time - local_cpu_time))
            while len(self.points) > 2 and now - self.points[1][0] >= self.span:
                self.points.popleft()

    def others(self) -> float:
        if len(self.points) < 2 or self.points[-1][0] - self.points[0][0] < 0.2:
            return NAN
        (t0, c0), (t1, c1) = self.points[0], self.points[-1]
        return max(0.0, (c1 - c0) / (t1 - t0))


@dataclass
class Dispatcher(Strategy):
    max_age: float = 0.6  # s from capture: a later result is not worth the work
    local_bias: float = 0.04  # s the local side must finish sooner to be chosen (a lighter model)
    learn_bias: bool = False  # measure the bias from the answers (policy/agreement.py)
    bias_prior: float = 100.0  # compared answer pairs that weigh as much as local_bias
    refresh_period: float = 1.0  # s without an edge frame before a copy measures the edge
    retry_period: float = 0.2  # s between frames (or copies) sent to a blocked edge
    cpu_share: float = 1.0  # of the CPU quota the process may fill
    overflow: bool = True  # a stalling local detector takes, spaced, frames the full edge path cannot
    overflow_gap: float = 0.4  # s between such frames at least: grows while they stall the robot
    max_in_flight: int = 4  # unanswered edge frames (and copies) at most
    slack: float = 1.5  # camera periods a frame may wait for the local detector to start it
    recover: float = 1.0  # s: half-life of a slow local measurement while the detector is idle
    queue_frames: int = 1  # edge frames that may wait at the edge path's bottleneck
    name: str = "dispatch"
    local_service: Ewma = field(default_factory=lambda: Ewma(0.2))
    local_cpu: Ewma = field(default_factory=lambda: Ewma(0.2))
    edge_service: Ewma = field(default_factory=lambda: Ewma(0.2))
    frame_bytes: Ewma = field(default_factory=lambda: Ewma(0.2))
    losses: Ewma = field(default_factory=lambda: Ewma(0.2))  # share of edge frames never detected
    fixed_latency: Recent = field(default_factory=lambda: Recent(32, 10.0))  # r0 less the edge's time
    base: Recent = field(default_factory=lambda: Recent(64, 40.0))  # the same, of frames sent alone
    base_period: float = 20.0  # s without a frame sent alone before the edge path is drained for one
    draining: bool = False  # no edge frames until none is in flight: the next one measures the base
    drains: int = 0
    delivered: Recent = field(default_factory=lambda: Recent(8, 3.0))
    cpu: CpuMeter = field(default_factory=CpuMeter)
    window: float = 4.0
    blocked: bool = False  # an edge frame went unanswered: no edge frames until an answer
    estimates: tuple[float, float] = (NAN, NAN)  # the last decision's finish times, local and edge
    agreement: Agreement = field(default_factory=Agreement)
    bias_used: float = NAN  # s: the last decision's local bias
    frame_period: Ewma = field(default_factory=lambda: Ewma(0.1))  # between camera frames
    _last_capture: float = NAN
    _last_edge_send: float = -math.inf
    _last_answer: float = -math.inf
    _base_at: float = NAN  # the last answer to a frame sent alone (or the first answer)
    _local_seen: float = -math.inf  # when the local detector last finished a frame
    _local_fresh: bool = False
    _local_results: int = 0
    # capture time -> whether the edge was usable when the frame went local (on_local_result); the
    # newest GAP_TRAINS_KEPT (a frame replaced in the detector's slot never gets an answer)
    _gap_trains: dict[float, bool] = field(default_factory=dict)
    spares: int = 0  # frames sent beyond the depth instead of being skipped
    retries: int = 0  # frames sent to a blocked edge instead of being skipped
    overflows: int = 0  # frames a stalling local detector took because the edge path was full

    def __post_init__(self) -> None:
        self.window = float(self.max_in_flight)
        # two drains' samples at least: one stalled frame alone does not set the base
        self.base.horizon = max(self.base.horizon, 2 * self.base_period)

    # Estimates
    def bottleneck(self, nbytes: float, now: float) -> float:
        """Seconds the edge path's bottleneck spends on a frame of ``nbytes``: the edge detector's
        service time, or the bytes at the delivered rate, whichever is longer (NaN: not known); at
        most the base latency, which holds a whole frame's way through the path. (Only frames that
        queued behind another give a rate sample, and the newest is kept: one far too low made
        frames go one at a time, which gives no new sample, and held the edge at 0.7-1.7 s a frame
        for a whole run.)"""
        rate = self.delivered.median(now)
        link = nbytes / rate if math.isfinite(rate) and rate > 0 and math.isfinite(nbytes) else NAN
        parts = [x for x in (self.edge_service.value, link) if math.isfinite(x)]
        if not parts:
            return NAN
        r0 = self.r0(now)
        return min(max(parts), r0) if math.isfinite(r0) and r0 > 0 else max(parts)

    def r0(self, now: float) -> float:
        """Send-to-answer time of a frame that queues behind none: the shortest recent one of the
        frames sent alone (none other unanswered; all frames until one is known) less the edge's
        own time on it, plus the edge detector's service time now (see the module's docstring)."""
        fixed = self.base.min(now) if self.base.samples else self.fixed_latency.min(now)
        service = self.edge_service.value
        return fixed + (service if math.isfinite(service) else 0.0)

    def interval(self, nbytes: float, now: float) -> float:
        """Spacing of frames through the edge path; before any delivered rate is known, one frame
        per base latency (the safe guess: no frame queues behind another)."""
        if math.isfinite(self.delivered.median(now)):
            return self.bottleneck(nbytes, now)
        return self.r0(now)

    def depth(self, now: float) -> int:
        """Edge frames to keep in flight: enough to keep the bottleneck busy for a base latency
        (``r0`` / its time per frame, rounded up), plus ``queue_frames`` waiting for it; at most the
        window."""
        r0, per_frame = self.r0(now), self.bottleneck(self.frame_bytes.value, now)
        busy = math.ceil(r0 / per_frame) if math.isfinite(r0) and per_frame > 0 else 1
        return max(1, min(int(self.window), busy + self.queue_frames))

    def edge_finish(self, st: OffloadState) -> float:
        """When a frame sent now would be answered (inf when the edge was never measured)."""
        r0 = self.r0(st.now)
        if not math.isfinite(r0):
            return math.inf
        default_bytes = self.frame_bytes.value
        done = self._last_answer  # the bottleneck served that one last
        for sent, nbytes in st.edge_sends:
            expected = max(sent + r0, done + self.interval(nbytes if math.isfinite(nbytes) else default_bytes,
                                                           st.now))
            if expected < st.now:  # overdue: assume it takes as long again as it is late already
                expected = 2 * st.now - expected
            done = expected
        if st.send_waiting:  # the new frame takes the place of the one waiting for the link
            return done
        return max(st.now + r0, done + self.interval(default_bytes, st.now))

    def local_time(self, now: float) -> float:
        """The local detector's service time, as measured, drifting back towards its CPU time (half
        of the difference every ``recover`` seconds) while it does not run: a slow spell (the start,
        a busy moment) must not keep it idle for the rest of the run."""
        wall, cpu = self.local_service.value, self.local_cpu.value
        if not all(map(math.isfinite, (wall, cpu, self._local_seen))) or wall <= cpu:
            return wall
        return cpu + (wall - cpu) * 0.5 ** (max(0.0, now - self._local_seen) / self.recover)

    def stall(self, now: float) -> float:
        """How long a local detection stops the robot process beyond its own CPU time: under a CPU
        quota the detector spends its wall time mostly waiting for the next quota period, and every
        thread of the process (the camera, the frame sender) waits with it."""
        wall, cpu = self.local_time(now), self.local_cpu.value
        return max(0.0, wall - cpu) if math.isfinite(wall) and math.isfinite(cpu) else 0.0

    def local_finish(self, st: OffloadState) -> tuple[float, float]:
        """When a frame handed to the local detector now would be done, and when it would start."""
        service = self.local_time(st.now)
        if math.isnan(service):
            return math.inf, math.inf
        start = st.now
        if st.local_busy:
            start += max(service - st.local_busy_for, 0.1 * service)
        start = max(start, self.local_ready_at)
        return start + service, start

    def pace(self, st: OffloadState) -> float:
        """When the local detector may start its next frame within the CPU budget."""
        self.cpu.add(st.now, st.cpu_time, st.local_cpu_time)
        cost, others = self.local_cpu.value, self.cpu.others()
        if not (math.isfinite(st.cpu_quota) and math.isfinite(cost) and math.isfinite(others)):
            return -math.inf
        room = max(self.cpu_share * st.cpu_quota - others, 0.02 * st.cpu_quota)
        return st.local_last_start + cost / room

    def camera_period(self) -> float:
        """Seconds between camera frames as measured (25 Hz's 40 ms until two frames came)."""
        return self.frame_period.value if math.isfinite(self.frame_period.value) else 0.04

    def bias(self, period: float) -> float:
        """Seconds sooner the local detector must finish to take a frame: ``local_bias``, or with
        ``learn_bias`` the learnt offset in camera frames (at the camera's period: the gap between
        frame numbers, which count the frames the camera dropped; else ``period``), weighed
        against ``local_bias`` by the pairs behind it (``bias_prior`` pairs: half and half), and
        then between 0 and half of ``max_age``."""
        offset = self.agreement.offset if self.learn_bias else NAN
        bias = self.local_bias
        if math.isfinite(offset):
            per_frame = self.agreement.seq_period if math.isfinite(self.agreement.seq_period) else period
            w = self.agreement.weight / (self.agreement.weight + self.bias_prior)
            bias = min(max(bias + w * (offset * per_frame - bias), 0.0), 0.5 * self.max_age)
        self.bias_used = bias
        return bias

    def bias_summary(self) -> dict[str, object]:
        """The bias for the run's summary: as set, as learnt (periods), the last one used (s),
        whether a local age agreed less than the oldest edge age measured, the edge answers
        compared, and the agreement curves behind the last estimate (AP50 against the edge's
        answers, by frames of age); None where a figure is not known."""
        def known(x: float) -> float | None:
            return round(x, 4) if math.isfinite(x) else None

        edge, local = self.agreement.curves
        return {"set_s": self.local_bias, "learn": self.learn_bias, "edge_answers": self.agreement.answers,
                "below_the_edge_curve": bool(self.agreement.floor),
                "learnt_periods": known(self.agreement.offset),
                "used_s": known(self.bias_used), "edge_curve": [known(a) for a in edge],
                "local_curve": [known(a) for a in local]}

    # Decision
    def choose(self, st: OffloadState) -> str:
        if self._local_fresh:
            self._local_seen, self._local_fresh = st.now, False
        self.local_ready_at = self.pace(st)
        if math.isfinite(self._last_capture) and 0 < st.capture - self._last_capture < 1.0:
            self.frame_period.add(st.capture - self._last_capture)
        self._last_capture = st.capture
        edge_ok = st.edge_available and not self.blocked
        # Measure each side once before comparing them
        if edge_ok and self._last_answer == -math.inf and not st.edge_sends:  # never answered yet
            return self._to_edge(st)
        if math.isnan(self.local_service.value) and not st.local_busy:
            return self._to_local(st, edge_ok)
        deadline = (st.capture if math.isfinite(st.capture) else st.now) + self.max_age
        period = self.camera_period()
        # A side that would not start on this frame within a camera period would finish a later,
        # fresher frame just as soon: it does not take this one (just in time, not queued)
        options = []  # (kills a waiting frame, score, side)
        f_edge = self.edge_finish(st) if edge_ok else math.inf
        # A local detector that stalls the robot (beyond half a camera period, the soonest the next
        # frame could need the sender) takes only frames the edge cannot finish in time
        local_fits = f_edge > deadline or self.stall(st.now) <= 0.5 * period
        # ... or, spaced by ``overflow_gap``, a frame the edge path is too full to take (it would
        # go as a spare, if at all, and the edge serving its newest frame would drop one of them)
        take_overflow = (not local_fits and self.overflow and not st.local_busy and not st.local_waiting
                         and st.now - st.local_last_start >= self.overflow_gap
                         and len(st.edge_sends) >= self.depth(st.now))
        f_local, start = self.local_finish(st)
        if f_local <= deadline and start < st.now + self.slack * period and (local_fits or take_overflow):
            options.append((st.local_waiting, f_local + self.bias(period), LOCAL))
        else:
            take_overflow = False
        # Just in time: the edge path takes a frame while it holds fewer than its depth; beyond
        # that, only a frame the local detector does not take either, while the window has room
        # (a skipped frame scores nothing, one a frame time later nearly what a fresh one does,
        # and the spare frame keeps the link busy through the robot's CPU stalls)
        in_depth = len(st.edge_sends) < self.depth(st.now)
        if self._drain(st, edge_ok):  # the edge path empties, so the next frame measures its base
            in_depth = False
        spare = not options and not in_depth and not self.draining and len(st.edge_sends) < int(self.window)
        if not (in_depth or spare):
            f_edge = math.inf
        if f_edge <= deadline:
            # A frame the edge loses is worth nothing: each loss weighs as a whole max_age
            loss = self.losses.value if math.isfinite(self.losses.value) else 0.0
            options.append((st.send_waiting, f_edge + loss * self.max_age, EDGE))
        self.estimates = (f_local, f_edge)
        # A blocked edge is asked again every retry_period (while the window has room): with a
        # copy of a local frame, or with a frame no side takes (it would score nothing skipped)
        since = st.now - self._last_edge_send
        retry = (self.blocked and st.edge_available and not st.send_waiting and since >= self.retry_period
                 and len(st.edge_sends) < self.max_in_flight)
        if not options:
            if retry:
                self.retries += 1
                return self._to_edge(st)
            return SKIP
        if spare:
            self.spares += 1
        side = min(options)[2]
        if side == EDGE:
            return self._to_edge(st)
        if take_overflow:  # (the edge path is full and the window too: LOCAL is the only option)
            self.overflows += 1
        self._to_local(st, edge_ok)
        if retry or (st.edge_available and not st.edge_sends and not st.send_waiting
                     and since >= self.refresh_period):
            self._last_edge_send = st.now
            return BOTH
        return LOCAL

    def _drain(self, st: OffloadState, edge_ok: bool) -> bool:
        """Whether the edge path is being drained: when no frame sent alone was answered for
        ``base_period`` s, no edge frame goes until none is in flight (a few frames, the local
        detector's or skipped, once a ``base_period`` at most), and the next one is sent alone."""
        if (not self.draining and edge_ok and st.edge_sends and not math.isnan(self._base_at)
                and st.now - self._base_at > self.base_period):
            self.draining = True
            self.drains += 1
        if self.draining and (not edge_ok or not (st.edge_sends or st.send_waiting)):
            self.draining = False  # empty: this frame goes alone (or the edge is gone anyway)
            self._base_at = st.now  # the next drain a base_period on, answered or not
        return self.draining

    def _to_local(self, st: OffloadState, edge_ok: bool) -> str:
        """A frame goes local (or both): whether the edge was usable is kept for its answer (a
        fallback's back-to-back frames do not train the overflow spacing: on_local_result)."""
        self._gap_trains[st.capture] = edge_ok
        while len(self._gap_trains) > GAP_TRAINS_KEPT:
            del self._gap_trains[next(iter(self._gap_trains))]
        return LOCAL

    def _to_edge(self, st: OffloadState) -> str:
        self._last_edge_send = st.now
        return EDGE

    # Observations
    def observe(self, seq: int, side: str, boxes: np.ndarray, scores: np.ndarray,
                capture: float = NAN) -> None:
        if self.learn_bias:
            self.agreement.observe(seq, side, boxes, scores, capture)

    def on_local_result(self, rtt: float, service: float | None = None, cpu: float | None = None,
                        capture: float | None = None) -> None:
        if self._local_results:  # the first one runs while the whole robot is starting: not a measure
            self.local_service.add(service if service is not None else rtt)
        self._local_results += 1
        self.local_cpu.add(cpu)
        # (an answer whose frame's decision is not kept, 8 frames on, trains nothing)
        trains = self._gap_trains.pop(capture, False) if capture is not None else True
        if (self._local_results > 1 and trains and service is not None and cpu is not None
                and math.isfinite(service) and math.isfinite(cpu)):
            # Overflow frames spaced so a detection does not stall the robot: a detection whose
            # wall time passed its CPU time by half a camera period (it waited for the CPU quota)
            # spaces them more, one that did not, less. Only detections of frames taken while the
            # edge was usable: in fallback (the edge gone or blocked) the detector takes frame after
            # frame, which says nothing of spaced ones (they pushed the gap to its 2 s ceiling, where
            # it stayed long after the edge was back)
            grow = 1.5 if service - cpu > 0.5 * self.camera_period() else 0.9
            self.overflow_gap = min(max(self.overflow_gap * grow, OVERFLOW_GAP[0]), OVERFLOW_GAP[1])
        self._local_fresh = True  # timed at the next decision (the hooks carry no clock)

    def on_edge_result(self, rtt: float, reply: EdgeReply | None = None) -> None:
        if reply is None:
            return
        self._answered(reply)
        self.losses.add(0.0)
        self.window = min(float(self.max_in_flight), self.window + 0.25)

    def on_edge_refused(self, reply: EdgeReply, penalty: float) -> None:
        """An error counts as a lost frame. A frame the edge answers ``dropped`` was superseded by a
        newer one of ours, which it serves instead: the edge lost nothing, and the path
        holds the freshest frame (the newer one could have waited there no sooner)."""
        self._answered(reply)
        if reply.status != "dropped":
            self.losses.add(1.0)

    def on_edge_timeout(self, waited: float) -> None:
        """An edge frame (or copy) unanswered for the reply timeout: no edge frames until the edge
        answers again (retries find out when), and one fewer in flight after. The frames that time
        out while the edge is blocked went into the same outage (or are the retries into it): each
        counts as a loss, but the window shrinks once per outage, not once per frame (a second's
        outage used to leave a window of one, regrown by a quarter frame per answer)."""
        if not self.blocked:
            self.window = max(1.0, self.window - 1.0)
        self.blocked = True
        self.losses.add(1.0)

    def on_encoding_change(self) -> None:
        """The delivered rate, frame size and base latency were of the other encoding (its bytes
        take the link longer or shorter): measured again, the base by a drain at the next frame."""
        self.delivered.samples.clear()
        self.frame_bytes = Ewma(self.frame_bytes.alpha)
        self.base.samples.clear()
        if not math.isnan(self._base_at):
            self._base_at = -math.inf

    def _answered(self, reply: EdgeReply) -> None:
        self.blocked = False
        self._last_answer = reply.result
        self.delivered.add(reply.result, reply.delivery_rate)
        self.edge_service.add(reply.service)
        self.frame_bytes.add(reply.bytes)
        # The path apart from the edge's own time on this frame (its queue, its detector)
        edge_time = sum(x for x in (reply.service, reply.edge_queue) if math.isfinite(x))
        rtt = reply.result - reply.sent
        # an edge time covering it all is a path too short to see (loopback): 0; a send-to-answer
        # time that is not a time (the wall clock stepped back) is no sample
        fixed = max(0.0, rtt - edge_time) if rtt > 0 else NAN
        self.fixed_latency.add(reply.result, fixed)
        if reply.alone:
            self.base.add(reply.result, fixed)
        if reply.alone or math.isnan(self._base_at):
            self._base_at = reply.result
