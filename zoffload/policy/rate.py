"""Our scale policy: size each scan for the link, using what the paper's DQN ignores.

The DQN sees only ``[T, v]``. This policy also uses:

* the link's delivery rate, measured from the acks (bytes of the scans acked in the last second);
* the bytes each voxel size will produce for *this* scan: point counts per candidate size,
  predicted from the last scans and verified on this one (``decide``), times the bytes per point
  the last sent scans really cost on the wire (so payload coding is accounted for);
* the deadline: a scan should reach the edge within ``deadline`` of the previous one (default
  1.05 sensor periods per slot, 0.105 s at 10 Hz: a little inside the paper's 0.11 s, since
  arrival times jitter around the period; measured against 1.1 and 1.0 in docs/scan-policy-log.md);
* what each late scan says: whether its network time rose above all the last scans' (it queued:
  its size, or a slower link) or stayed within what the link's jitter does.

**Budget.** A byte budget per sensor period follows the link, updated once per new ack; while
scans arrive on time it grows 5 % per period. A scan late for its slot (T above the deadline times
the periods it was meant to take) is one of three kinds (``late_cause``):

* it queued (``size``: its network time rose above all the last scans'): the budget drops at
  once to what the measured delivery rate carries in one period (times ``margin``), never above
  80 % of before nor below half;
* its delay moved within the link's jitter (``jitter``): held. Cutting would not have saved it,
  and on a jittery link the cuts otherwise balance growth at a late share of
  ln(1+g) / (ln(1+g) - ln(1-c)) (18 % for g = 5 %, c = 20 %, tests/core/policy/test_rate.py) with
  the budget far below what the link carries (docs/scan-policy-log.md, "Ours");
* the first scan after a stall (``stall``): held.

**A standing queue** (``_queue``): late scans in a queue that has stood a while do not rise above
the last ones, so the rule above reads them as jitter and holds the budget, and the window of
unanswered scans (the robot's ``max_in_flight``) holds the surplus back before the policy sees it.
So when the window held scans back while the edge kept answering and the newest network times
stand a period above the path's floor (``ScanLedger.floor_net``, the quickest of the last 10 s: a
long path fills the window too, at its floor), the budget is capped at what the link delivered in
the last second (times ``margin``; with the window full, that is its capacity), at most once a
second.

Growth stops at what the link has shown it carries (``validated``): 1.5 times the largest recent
scan, or the bytes per period a scan moved at (its bytes over its network time), whichever is
larger. Without that, scans that do not fill the budget (sent as they are) let it grow unchecked.

**Choice.** The finest size of ``voxel_range`` whose predicted bytes fit the budget. When none
fits, the policy first widens the range (up to ``widen`` times its upper end: the edge's KISS-ICP
registers on a grid 1.5 times its voxel, which the edge sizes to at least twice the range's end, so
the odometry keeps its keypoints and the map loses detail), then lowers the scan rate: a scan that
needs ``s`` periods of the link is sent and the next ``s - 1`` are skipped (at most ``max_skip`` in
a row); the scan after a skip says so (``wire.Scan.skipped``) and the edge's motion model bridges
the gap. Optionally (``jitter_pace`` > 1, off by default) the rate is also lowered for the link's
jitter: arrivals that jitter by a good part of the period are late for a 1-period slot whatever the
scan's size, and a slot of ``jitter_pace`` periods at most absorbs them (chosen so that about
``jitter_late`` of the scans would be late, from the spread of T around the slots). Off by default:
robot, edge and emulator share one machine in the experiments, and the edge's KISS-ICP on HDL-64
scans makes T jitter by 20 ms on the strong Wi-Fi link too, where pacing skipped a third of the
scans for nothing (docs/scan-policy-log.md, "Ours"). While the link delivers nothing (no ack for
``stall_after`` seconds with scans in flight, the oldest of them past its expected answer) scans
are skipped too: anything sent then would queue behind the stall and arrive stale; and likewise
(``queue_stall``) while the newest ack's network time stands ``stall_after`` above the path's floor
with scans queued behind it (a queue that deep stands on the link: a rain fade on a satellite path,
where the window is 7 scans deep), at most ``queue_stall_max`` in a row (a path whose delay rose
for good is not a queue: its floor follows in 10 s, and meanwhile one scan in five goes).

**Counting.** A grid pass costs about as much as everything else the robot does per scan, so the
policy does not search: it keeps a curve of point counts per candidate (measured on the first
scan, then corrected by every pass: the measured sizes exactly, the others shifted by the same
ratio), predicts the size, and verifies it with the one pass the robot needs anyway; a second
pass only when the prediction missed (coarser) or a finer size now fits. Every ``refresh`` scans
one neighbour is measured too, so the curve's slope stays the scene's.

**Compression.** Where the budget holds the scan uncompressed twice over (``compress_share``), it
is sent uncompressed (coding ``q16d``): the link has room, the robot's CPU is the scarcer thing.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from zoffload.mapping.voxel import voxel_downsample

QUEUE_EVERY = 10  # scans between two queue caps at most (a second at 10 Hz)
SILENT = 0.5  # seconds without an ack that make a silence (``_queue``) where ``stall_after`` is 0


@dataclass(frozen=True)
class AckInfo:
    """One answered scan, as the robot measured it."""

    bytes: int  # its size on the wire
    net: float  # network time [s]: RTT - the edge's queue and processing time
    t: float  # inter-arrival T at the edge [s]
    slot: int = 1  # sensor periods the robot meant it to take (scans skipped before it + 1)


@dataclass(frozen=True)
class LinkView:
    """What the robot knows about the link when a scan is ready."""

    last_t: float  # the edge's last inter-arrival T [s]; 0 before the first ack
    acked_bytes_per_s: float  # bytes of the scans acked in the last second; NaN before any
    bytes_per_point: float  # what the last sent scans cost per point on the wire; NaN before any
    period: float  # the sensor's period [s]
    acks: int = -1  # acks received so far; the budget moves only when it changes (-1: always)
    last_slot: int = 1  # the slot of the scan ``last_t`` belongs to
    recent: tuple[AckInfo, ...] = ()  # the last acked scans, oldest first
    since_ack: float = 0.0  # seconds since the last ack arrived
    in_flight: int = 0  # scans sent and not answered yet
    raw_bytes_per_point: float = math.nan  # bytes per point uncompressed (q16d); NaN: always coded
    window_drops: int = 0  # scans held back so far because the window of unanswered ones was full
    newest_net: float = math.nan  # network time of the newest ack, late ones too [s]; NaN: none
    floor_net: float = math.nan  # the path's floor on this route (ScanLedger.floor_net) [s]; NaN: < 10
    queued: int = 0  # scans of this route sent after the newest answered one, unanswered (expired too)
    # seconds the oldest unanswered scan of this route is past its expected answer
    # (``ScanLedger.overdue``); inf: not known (a silence is then counted from the last ack alone)
    overdue: float = math.inf


@dataclass(frozen=True)
class Decision:
    """The policy's answer for one scan."""

    voxel: float
    skip: bool = False  # do not send this scan
    compress: bool = True  # (q16d) compress the payload
    reason: str = ""  # why, for scans.csv
    cause: str = ""  # short tag: fit, widen, pace, skip, stall, start


def candidate_grid(low: float, high: float, n: int = 12) -> list[float]:
    """Voxel sizes from ``low`` to ``high``, geometrically spaced (point counts fall roughly with
    the cube of the size indoors, the square outdoors: even ratios suit both)."""
    if not 0 < low < high:
        raise ValueError(f"voxel range [{low}, {high}] must satisfy 0 < low < high")
    return [float(v) for v in np.geomspace(low, high, n)]


def widened_grid(low: float, high: float, widen: float, n: int = 12) -> list[float]:
    """Sizes beyond ``high`` up to ``high * widen`` at the in-range grid's ratio (its end included)."""
    if widen <= 1:
        return []
    ratio = (high / low) ** (1 / (n - 1))
    out: list[float] = []
    v = high * ratio
    while v < high * widen * (1 - 1e-9):
        out.append(float(v))
        v *= ratio
    return [*out, float(high * widen)]


def _median(xs: Sequence[float]) -> float:
    return float(statistics.median(xs)) if xs else math.nan


def robust_sd(xs: Sequence[float]) -> float:
    """1.4826 x the median absolute deviation: the standard deviation of the bulk, unmoved by a
    few outliers (a scan after an outage)."""
    if len(xs) < 2:
        return math.nan
    m = _median(xs)
    return 1.4826 * _median([abs(x - m) for x in xs])


def late_cause(recent: Sequence[AckInfo], period: float) -> str:
    """Why the newest of ``recent`` (late for its slot) was late. ``"size"``: its network time
    rose above every one of the last 20 scans' (by 2 % of a period): it queued, because its bytes
    took longer than the link gave them, or the link slowed down (the change of network time is
    set against what the link's jitter has done lately, not against the change of bytes alone: on
    a fat link a bigger scan costs no time). ``"jitter"``: otherwise; its delay moved within what
    the link's jitter does, and a smaller scan would not have arrived earlier (arrivals that keep
    jittering late get a longer slot: ``jitter_slots``)."""
    nets = [a.net for a in recent[-21:-1] if math.isfinite(a.net)]
    if len(nets) < 5 or recent[-1].net > max(nets) + 0.02 * period:
        return "size"
    return "jitter"


def jitter_slots(recent: Sequence[AckInfo], period: float, most: int, late_share: float,
                 slack: float = 1.1) -> tuple[int, float]:
    """(slots, jitter): the fewest periods per scan (at most ``most``) whose allowance, ``slack``
    - 1 of the slot, keeps the lateness the link's jitter makes under ``late_share``, taking the
    deviations of T from the slots as normal with their robust spread; and that spread."""
    dev = [a.t - a.slot * period for a in recent[-30:] if math.isfinite(a.t)]
    sd = robust_sd(dev)
    if not (len(dev) >= 10 and sd > 0):
        return 1, sd
    z = statistics.NormalDist().inv_cdf(1 - late_share)
    for slots in range(1, most + 1):
        if (slack - 1) * slots * period >= z * sd:
            return slots, sd
    return most, sd


class LinkAwareScale:
    def __init__(self, voxel_range: tuple[float, float], deadline: float | None = None,
                 margin: float = 0.85, start: float = 0.05, grow_fast: float = 0.05,
                 grow_slow: float = 0.05, quiet: int = 50, widen: float = 2.0, max_skip: int = 2,
                 stall_after: float = 0.5, jitter_aware: bool = True, compress_share: float = 0.5,
                 refresh: int = 20, raw_share: float = 0.9, jitter_pace: int = 1,
                 jitter_late: float = 0.25, headroom: float = 1.5, queue_cap: bool = True,
                 queue_stall: bool = False, queue_stall_max: int = 4) -> None:
        self.candidates = candidate_grid(*voxel_range)
        self.in_range = len(self.candidates)
        self.candidates += widened_grid(*voxel_range, widen)
        self.deadline = deadline
        self.margin = margin
        self.grow_fast, self.grow_slow, self.quiet = grow_fast, grow_slow, quiet
        self.max_skip, self.stall_after, self.jitter_aware = max_skip, stall_after, jitter_aware
        self.compress_share, self.refresh, self.raw_share = compress_share, refresh, raw_share
        self.jitter_pace, self.jitter_late = jitter_pace, jitter_late
        self.headroom = headroom
        self.queue_cap, self.queue_stall, self.queue_stall_max = queue_cap, queue_stall, queue_stall_max
        self.start = min(max(start, self.candidates[0]), self.candidates[self.in_range - 1])
        self.name = "rate"
        self.reset()

    def reset(self) -> float:
        self.since_late = self.quiet  # on-time acks since the last late one
        self.budget = math.inf
        self.last_voxel = self.start
        self._acks_seen = -1
        self._curve = np.full(len(self.candidates), np.nan)  # log point count per candidate
        self._curve_n = 1  # points of the scan the curve last learnt from
        self._scans = 0
        self._skip_left = 0
        self._stalled = False  # skipped for a stall since the last ack
        self.event = ""  # what the last new ack did to the budget
        self._queue_skips = 0  # queue stall skips in a row
        self._window_seen = 0  # window drops already looked at
        self._capped_at = -QUEUE_EVERY  # scan count of the last queue cap
        self._stall_scan = -QUEUE_EVERY  # scan count of the last silence (no ack for stall_after)
        self.counts = {"late_size": 0, "late_jitter": 0, "late_stall": 0, "queue": 0, "queue_stall": 0,
                       "queue_stall_cap": 0, "passes": 0}
        return self.start

    def choose(self, last_t: float, last_v: float) -> float:
        """The ScalePolicy interface without the scan: the last choice (the daemon calls
        ``decide``)."""
        return self.last_voxel

    # Budget
    def update_budget(self, link: LinkView) -> float:
        """Move the budget with a new ack: grown while scans arrive on time; for a scan late for
        its slot, cut (``size``) or held (``jitter``, the first after a ``stall``): ``late_cause``."""
        if link.since_ack > (self.stall_after or SILENT):  # a silence: the next second's rate is none
            self._stall_scan = self._scans
        if link.acks >= 0:
            if link.acks == self._acks_seen:
                return self.budget  # nothing new from the edge
            self._acks_seen = link.acks
        deadline = self.deadline if self.deadline is not None else 1.05 * link.period
        slot = max(1, link.last_slot)
        late = link.last_t > deadline * slot
        self.event = ""
        stalled, self._stalled = self._stalled, False
        if late:
            cause = "stall" if stalled else (
                late_cause(link.recent, link.period) if self.jitter_aware else "size")
            if cause in ("stall", "jitter"):
                self.counts[f"late_{cause}"] += 1
                self.event = f"late ({cause}): budget held"
            else:
                self._cut(link, cause)
        elif math.isfinite(self.budget):  # grows per period, not per ack: a paced link recovers as fast
            self.since_late += 1
            growth = self.grow_fast if self.since_late >= self.quiet else self.grow_slow
            grown = self.budget * (1 + growth) ** slot
            self.budget = min(grown, max(self.budget, self.validated(link)))
        drops, self._window_seen = link.window_drops - self._window_seen, link.window_drops
        if drops > 0 and self.queue_cap:
            self._queue(link)
        return self.budget

    def _queue(self, link: LinkView) -> None:
        """The window held scans back while the edge kept answering: scans were sent faster than
        the link carried them. If the newest network times also stand a period above the path's
        floor (the quickest of the last 100), a queue stands on the link, and the budget is capped
        at what the link delivered in the last second (x ``margin``), which with the window full is
        its capacity. Late scans in a standing queue do not rise above the last ones and read as
        jitter (``late_cause``), and the scans the window holds back never reach the policy, so
        without this the budget stayed at twice what a slow cellular uplink carried and the window
        dropped a quarter of the scans (docs/scan-policy-log.md, "Unseen links"). A long path
        without a queue fills the window too, but at the floor; within a second of a silence (no ack
        for ``stall_after``, or ``SILENT`` where that is 0; scans in flight or not) the last
        second's deliveries are not a rate. At most once per ``QUEUE_EVERY`` scans: the next
        second's rate is then the capped stream's, not the link's."""
        floor = link.floor_net
        if (self._scans - self._stall_scan < QUEUE_EVERY or self._scans - self._capped_at < QUEUE_EVERY
                or not math.isfinite(floor)):
            return
        newest = [a.net for a in link.recent[-3:] if math.isfinite(a.net)]
        carried = link.acked_bytes_per_s * link.period * self.margin
        if not newest or _median(newest) <= floor + link.period or not (0 < carried < self.budget):
            return
        self.budget = carried
        self.since_late = 0
        self._capped_at = self._scans
        self.counts["queue"] += 1
        self.event = (f"queue (window full, network time {1e3 * _median(newest):.0f} ms, floor "
                      f"{1e3 * floor:.0f} ms): budget capped at the delivered {carried / 1e3:.0f} kB")

    def validated(self, link: LinkView) -> float:
        """How far the budget may grow on what the link has shown (inf: nothing shown yet). On time
        is not proof of room when the scans do not fill the budget (sent as they are, or a scene
        with fewer points): grown on that alone, it ran to seven times the scans sent, turned
        compression off and put scans of three times the bytes on a 20 Mbps link, and the cuts after
        took three late scans to reach the sizes sent (the idea of TCP's congestion window
        validation, RFC 7661). The larger of ``headroom`` times the largest of the last scans sent,
        and what the link moved in a period while a scan was on it (its bytes over its network
        time, the median of the last scans: a lower bound of the link's rate, its delay included)."""
        acks = [a for a in link.recent[-20:] if a.bytes > 0 and math.isfinite(a.net) and a.net > 0]
        if self.headroom <= 0 or not acks:
            return math.inf
        rate = _median([a.bytes / a.net for a in acks])
        return max(self.headroom * max(a.bytes for a in acks), rate * link.period)

    def _cut(self, link: LinkView, cause: str) -> None:
        """To what the link delivered in a period (x ``margin``), at most 80 % of before; with
        ``jitter_aware``, at least half of before (a jitter spike taken for queueing must not wipe
        out what the budget learnt; a real drop of capacity takes two or three cuts)."""
        carried = link.acked_bytes_per_s * link.period * self.margin
        cap = self.budget * 0.8
        cut = min(cap, carried) if math.isfinite(carried) and carried > 0 else cap
        self.budget = max(cut, self.budget * 0.5) if self.jitter_aware else cut
        self.since_late = 0
        self.counts[f"late_{cause}"] += 1
        self.event = f"late ({cause}): budget cut to {self.budget / 1e3:.0f} kB"

    # Choice
    def held_back(self, link: LinkView) -> Decision | None:
        """A scan the robot's window holds back (never sized, never decided): in a stall (``_stall``)
        it is the stall skip ``decide`` would have made,
        announced to the edge like one, and the stall is marked as ``decide`` marks it (the first
        late scan after it held, the queue cap kept off for a while); else None (a window drop).
        Without this an outage that begins with the window full (a path of ~3 periods) is all
        window drops: none announced, and the policy never learns of the stall."""
        skip = self._stall(link, suffix=" (window full)")
        if skip is not None and self._silent(link):
            self._stall_scan = self._scans  # a silence (``decide`` marks it in ``update_budget``)
        return skip

    def _silent(self, link: LinkView) -> bool:
        """A silence: scans in flight, no ack for ``stall_after``, and the oldest of them past its
        expected answer (``LinkView.overdue``). The ack clock alone also counts the time the
        window held scans back: on a 1.8 s path the first scan sent after it read as a stall
        (62-156 a run on ``satellite-reroute``). The oldest ``stall_after`` past due, instead of
        due, started every stall a period later: a scan more sent into each outage, 30 lost a run
        against 18 on ``cellular-heldout``."""
        return link.in_flight > 0 and link.since_ack > self.stall_after and link.overdue > 0

    def _stall(self, link: LinkView, prefix: str = "", suffix: str = "") -> Decision | None:
        """The stall skip: in a silence (``_silent``: anything sent then would queue behind the
        stall; it holds the first late scan after it); and
        (``queue_stall``) with scans queued on the link (sent after the newest one answered, the
        ack timeout's expired ones too), when the newest ack's network time stood ``stall_after``
        above the path's floor (``LinkView.floor_net``: another edge is another path): a queue
        that deep stands on the link, and a scan sent now would wait behind it. Without it, a
        rain fade on a satellite link (the window 7 scans deep there) queued scans for up to
        3.7 s: the window kept it full, and every scan behind came after the ack timeout. At
        most ``queue_stall_max`` such skips in a row, then a scan goes: the newest network time
        is a scan's that waited, so a path whose delay rose for good would hold the robot to a
        scan per round trip until the floor follows (``FLOOR_SPAN`` of the ledger). A queue
        stall takes the place of any pacing skip left."""
        if self.stall_after <= 0:
            return None
        if self._silent(link):
            self._stalled = True
            return Decision(self.last_voxel, skip=True, cause="stall",
                            reason=f"{prefix}stall: no ack for {link.since_ack:.2f} s{suffix}")
        newest, floor = link.newest_net, link.floor_net
        if not (self.queue_stall and link.queued > 0 and math.isfinite(newest) and math.isfinite(floor)
                and newest - floor > self.stall_after):
            self._queue_skips = 0
            return None
        if self._queue_skips >= self.queue_stall_max:  # this one goes
            self._queue_skips = 0
            self.counts["queue_stall_cap"] += 1
            return None
        # (not a silence: the late scans after it are sized as the queue made them, so cut)
        self._queue_skips += 1
        self._skip_left = 0
        self.counts["queue_stall"] += 1
        return Decision(self.last_voxel, skip=True, cause="stall",
                        reason=f"{prefix}stall: a queue on the link (network time {1e3 * newest:.0f} ms, "
                               f"floor {1e3 * floor:.0f} ms){suffix}")

    def decide(self, n_points: int, link: LinkView, count: Callable[[float], int]) -> Decision:
        """The decision for a scan of ``n_points`` points; ``count(v)`` runs the grid pass at
        ``v`` on it and returns the voxels (the caller keeps the result for the chosen size)."""
        self._scans += 1
        if np.isnan(self._curve).any():  # one-off calibration: every size counted once
            counts = [count(v) for v in self.candidates]
            self.counts["passes"] += len(self.candidates)
            if max(counts) > 0:  # (a scan without a valid point teaches nothing: the next one calibrates)
                self._curve[:] = np.log(np.maximum(1, counts))
                self._curve_n = max(1, n_points)
        if not math.isfinite(link.bytes_per_point):  # nothing measured yet: the start size
            count(self.start)
            self.last_voxel = self.start
            return Decision(self.start, reason="start: nothing measured yet", cause="start")
        if not math.isfinite(self.budget):  # first measurement: start from the start size's bytes
            self.budget = count(self.start) * link.bytes_per_point
        self.update_budget(link)
        event = f"{self.event}; " if self.event else ""
        if (stall := self._stall(link, prefix=event)) is not None:
            return stall
        if self._skip_left > 0:
            self._skip_left -= 1
            return Decision(self.last_voxel, skip=True, cause="pace",
                            reason=f"{event}pace: the last scan needs the link for more than a period")
        as_is = self._raw(n_points, link.bytes_per_point, count)
        if as_is is not None:
            k, slots, n, v = 0, 1, n_points, 0.0
        else:
            k, slots, n = self._choose(n_points, link.bytes_per_point, count)
            v = self.candidates[k]
        # Lateness the link's jitter makes is not cut away by smaller scans: a longer slot absorbs it
        jslots, jitter = (jitter_slots(link.recent, link.period, self.jitter_pace, self.jitter_late)
                          if self.jitter_pace > 1 else (1, math.nan))
        paced_for_jitter = jslots > slots
        slots = max(slots, jslots)
        self.last_voxel = v
        self._skip_left = slots - 1
        raw = n * link.raw_bytes_per_point
        compress = not (math.isfinite(raw) and raw <= self.compress_share * self.budget)
        kb, bkb = n * link.bytes_per_point / 1e3, self.budget / 1e3
        if paced_for_jitter:
            cause, why = "jitter", (f"arrivals jitter by {1e3 * jitter:.0f} ms: {slots} periods per scan "
                                    f"keep them on time; {v:.3g} m")
        elif as_is is not None:
            cause, why = "fit", as_is
        elif slots > 1:
            cause, why = "skip", f"{v:.3g} m needs {slots} periods ({kb:.0f} kB, {bkb:.0f} kB per period)"
        elif k >= self.in_range:
            cause, why = "widen", f"nothing in range fits {bkb:.0f} kB: widened to {v:.3g} m ({kb:.0f} kB)"
        else:
            cause, why = "fit", f"{v:.3g} m fits {kb:.0f} of {bkb:.0f} kB"
        if not compress:
            why += ", uncompressed"
        return Decision(v, compress=compress, reason=event + why, cause=cause)

    def _raw(self, n_points: int, bpp: float, count: Callable[[float], int]) -> str | None:
        """Why to send the scan as it is, or None: the finest size would keep nearly every point
        (``raw_share``) and the whole scan fits the budget, so the grid pass would cost the robot
        its CPU for nothing. Every ``refresh`` scans the finest size is counted to check."""
        if self.raw_share >= 1 or n_points == 0 or n_points * bpp > self.budget:
            return None
        if self.refresh and self._scans % self.refresh == 0:
            self.counts["passes"] += 1
            c = count(self.candidates[0])
            if c:
                self._learn({0: c}, n_points)
        kept = min(1.0, math.exp(self._curve[0]) / self._curve_n)  # on the scans the curve learnt from
        if kept < self.raw_share:
            return None
        return f"{self.candidates[0]:.3g} m would keep {100 * kept:.0f} % of the points: sent as they are"

    def _predict(self, k: int, n_points: int) -> float:
        c = self._curve[k]
        return min(float(n_points), math.exp(c)) if math.isfinite(c) else float(n_points)

    def _fits(self, n_points: int, bpp: float) -> tuple[int, int]:
        """(candidate, slots): the finest size of the range, then of the widened range, that fits
        one period's budget; else the fewest periods that carry one, at the finest size."""
        for slots in range(1, self.max_skip + 2):
            for k in range(len(self.candidates)):
                if self._predict(k, n_points) * bpp <= slots * self.budget:
                    return k, slots
        return len(self.candidates) - 1, self.max_skip + 1

    def _choose(self, n_points: int, bpp: float, count: Callable[[float], int]) -> tuple[int, int, int]:
        """Predict, then verify with real passes (at most three per scan)."""
        measured: dict[int, int] = {}

        def measure(k: int) -> int:
            if k not in measured:
                measured[k] = count(self.candidates[k])
                self.counts["passes"] += 1
                if measured[k]:  # an empty scan teaches nothing
                    self._learn(measured, n_points)
            return measured[k]

        k, slots = self._fits(n_points, bpp)
        for _ in range(3):
            measure(k)
            k2, slots2 = self._fits(n_points, bpp)  # the curve has just learnt from the pass
            if (k2, slots2) == (k, slots) or k2 in measured:
                break
            k, slots = k2, slots2
        # the prediction was corrected: keep the finest measured size that fits
        fitting = [(s, j) for j, c in measured.items() for s in range(1, self.max_skip + 2)
                   if c * bpp <= s * self.budget]
        if fitting:
            slots, k = min(fitting)
        else:
            k = max(measured)
            slots = self.max_skip + 1
        if self.refresh and self._scans % self.refresh == 0:  # keep the curve's slope fresh
            nb = k - 1 if (self._scans // self.refresh) % 2 else k + 1
            if 0 <= nb < len(self.candidates) and nb not in measured:
                measure(nb)
        return k, slots, measured[k]

    def _learn(self, measured: dict[int, int], n_points: int) -> None:
        """Counts measured on this scan: exact where measured, the other sizes shifted by the
        ratio the newest measurement found against the prediction."""
        k = next(reversed(measured))
        self._curve += math.log(max(1, measured[k])) - self._curve[k]
        for j, c in measured.items():
            self._curve[j] = math.log(max(1, c))
        self._curve_n = max(1, n_points)
        # point counts never grow with the voxel size, and never exceed the scan's
        np.minimum(self._curve, math.log(max(1, n_points)), out=self._curve)
        for j in range(len(self._curve) - 2, -1, -1):
            if self._curve[j] < self._curve[j + 1]:
                self._curve[j] = self._curve[j + 1]

    # The interface the tests and the DQN's training use: a scan in, a size and its cloud out
    def choose_cloud(self, points: np.ndarray, link: LinkView) -> tuple[float, np.ndarray]:
        """The voxel size for this scan and the scan downsampled at it (skips ignored)."""
        clouds: dict[float, np.ndarray] = {}

        def count(v: float) -> int:
            clouds[v] = voxel_downsample(points, v)
            return len(clouds[v])

        d = self.decide(len(points), link, count)
        if d.voxel not in clouds:
            count(d.voxel)
        return d.voxel, clouds[d.voxel]
