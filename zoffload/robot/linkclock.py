"""The link's time for a frame's bytes, from the edge's arrival stamps (codec version 4).

The robot times the link by pairs of frames: a frame put before the previous one reached the edge
waited behind it on the link, so the gap between their arrivals is the link's time for the later
frame's bytes. Timed on the robot alone (the gap between the two *answers*), the gap also holds
whatever delayed the answers: the edge detector's service times, which differ frame to frame, and
the robot's own stalls, which under a CPU quota last most of a scheduling period (100 ms). On an
unconstrained loopback link (quarter-core robot, raw frames of 0.52 MB, held-out images) the
answers' gaps of the frame pairs the robot took for queued read up to 111 ms (median 44), and frames
went as JPEG on that ("raw frames take the link 89 ms each"), where the edge's arrival stamps
showed that 16 of those 24 pairs had not queued at all (the second put after the first arrived)
and the other 8 held a stall of the robot's sender, not the link (docs/perception-log.md: "The
link timed on the edge's clock").

An edge that reads version 4 stamps each answer with the frame's arrival on its own clock, and
differences of one edge's stamps are the link's own (and whatever held the frame between its put
stamp and the socket: a sender stalled there delays the arrival too). Whether the later frame was
put before the earlier one arrived needs the two clocks side by side: the smallest recent
``arrival - put`` (the edge clock's offset plus the path's shortest delay, over ``horizon``
seconds) puts the earlier frame's arrival on the robot's clock *early* by that shortest delay, so a
pair taken for queued did queue (a conservative test: on a link whose queue holds less than the
shortest delay no pair is taken, and the edge's pace shows in the answers anyway). The robot's side
is its monotonic clock (a wall clock stepped or slewed would move the offset). An offset that moves
by more than ``jump`` seconds is another clock (the edge restarted elsewhere under the same id): the
state starts again, and until a second answer has set the offset no delay is measured (a frame
measured against itself would read no delay at all). Only consecutive puts to the same edge pair
up. Pure: the robot passes the times in.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

NAN = float("nan")


@dataclass
class LinkClock:
    horizon: float = 30.0  # s of answers whose smallest ``arrival - put`` is the clocks' offset
    bucket: float = 1.0  # s per kept minimum (the state holds horizon / bucket of them at most)
    jump: float = 5.0  # s an offset may move before it is taken for another clock
    edge: str | None = None  # whose clock the state holds
    resets: int = 0  # another edge's clock, or the same edge's after a restart
    samples: int = 0
    _floor: deque[tuple[float, float]] = field(default_factory=deque)  # (bucket start, min offset)
    _prev: tuple[float, float, int] | None = None  # the latest arrival: (edge clock, put, put index)

    def reset(self, edge: str | None = None) -> None:
        self.edge, self._prev = edge, None
        self._floor.clear()

    def offset(self, now: float) -> float:
        """The smallest recent ``arrival - put`` (NaN before any)."""
        while len(self._floor) > 1 and now - self._floor[0][0] > self.horizon:
            self._floor.popleft()
        return min((x for _, x in self._floor), default=NAN)

    def answered(self, edge: str, arrival: float, put: float, put_index: int,
                 now: float) -> tuple[float, float]:
        """An answer (any status) stamped with the frame's ``arrival`` on ``edge``'s clock; ``put``
        (monotonic) and ``now`` on the robot's. Returns the link's time for the frame's bytes when it
        queued behind the frame put just before it (else NaN), and the frame's delay beyond the
        path's shortest recent one before it (NaN without a stamp, or with no earlier answer since
        the state started)."""
        if not (math.isfinite(arrival) and math.isfinite(put) and math.isfinite(now)):
            return NAN, NAN
        if edge != self.edge:
            if self.edge is not None:
                self.resets += 1
            self.reset(edge)
        off = arrival - put
        floor = self.offset(now)
        if math.isfinite(floor) and abs(off - floor) > self.jump:
            self.resets += 1
            self.reset(edge)
            floor = NAN
        if self._floor and 0.0 <= now - self._floor[-1][0] < self.bucket:
            self._floor[-1] = (self._floor[-1][0], min(self._floor[-1][1], off))
        else:
            self._floor.append((now, off))
        excess = max(off - floor, 0.0) if math.isfinite(floor) else NAN
        floor = off if not math.isfinite(floor) else min(floor, off)
        prev = self._prev
        if prev is None or arrival > prev[0]:
            self._prev = (arrival, put, put_index)
        if prev is None or arrival <= prev[0] or put_index != prev[2] + 1 or put >= prev[0] - floor:
            return NAN, excess
        self.samples += 1
        return arrival - prev[0], excess
