"""How each frame to the edge is encoded: raw (``bgr8``), JPEG, or ``auto`` (chosen per frame).

A raw 848 x 480 frame is 1.2 MB whole (0.52 MB shrunk to PicoDet's 416 x 416), its JPEG ~68 kB
(~34 kB); JPEG costs the robot its encoding (~1 ms of a core per whole frame, 0.8 ms shrunk:
benchmarks/bench_frame_send.py; under a CPU quota it may wait for the next period) and the edge its
decoding.
Which is better depends on the link: raw wins where the link carries raw frames as fast as the
edge's detector takes them (on an unconstrained link, a quarter-core robot with raw frames scores
61.1 async AP50 against 57.2 with JPEG, held-out images), JPEG wherever it does not (a 160 Mbps
cap: 55.0 against 46.4; a Wi-Fi walk 52.4 against 22.9). ``auto`` measures which case it is in:

* **Raw frames** (the edge path's replies): when frames queue on the link, the gap between two
  arrivals at the edge is the link's time for the later frame's bytes (robot/frames.py: from the
  edge's arrival stamps, robot/linkclock.py; from an older edge, the gap between the answers), a
  sample of the link's time per raw frame. When the median of the recent samples is above the
  edge's detector service time (``leave`` x: the link, not the detector, is the bottleneck) or a
  raw frame is lost, frames go as JPEG. (An encoding that fails, or an edge that refuses a frame,
  says nothing of the link: only a trial frame lost so ends its trial.) The samples cannot see a
  link that slows to between the trial's bound and the edge's pace (frames then queue at the edge,
  not on the link): raw frames stay until the link is the bottleneck or a frame is lost (a known
  gap).
* **JPEG frames** do not show whether the link would carry raw ones (the edge's detector is then
  the bottleneck, and the gaps show its pace). So one frame now and then goes raw, a *trial*: its
  link time is its send-to-answer time less the edge's time, less its encoding, less the path's
  base latency (the shortest recent one of the JPEG frames, measured the same way; from an edge
  that stamps arrivals, its put-to-arrival delay over the shortest recent one, and none in the
  first answer after the link clock started again: the trial comes again). A trial within
  a quarter of the edge's service time switches to raw (a raw frame's link time adds to every
  frame's latency, and asynchronous AP counts latency as well as pace); a slower one, and every
  switch back to JPEG, doubles
  the wait before the next trial (``first_trial`` s up to ``max_wait``; back to twice
  ``first_trial`` when raw frames held for ``settled`` s), so a slow link pays one raw frame a
  minute at most and a link on the edge of the two does not flutter. No trial while the JPEG
  frames themselves are link-bound (their link samples over ``leave`` x the service time): a raw
  frame, ~15 times the bytes, would hold a slow link for seconds (a held-out cellular uplink,
  2-40 Mbps: 5 trials in a 50 s run cost 5.7 async AP50 points against plain JPEG); the trial
  waits, doubling, instead.

The trial frame is a real frame (detected and counted like the others); the strategy is told its
reply without bytes and rate, so its size does not distort the dispatcher's estimates, and every
switch clears the dispatcher's delivered-rate samples (they are in bytes per second of the other
encoding). Pure (no clock, no Zenoh): the camera pipeline passes the times in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from zoffload.policy.dispatch import Ewma, Recent

RAW, JPEG, AUTO = "bgr8", "jpeg", "auto"
ENCODINGS = (RAW, JPEG, AUTO)


@dataclass
class EncodingChoice:
    mode: str = AUTO  # bgr8, jpeg or auto
    first_trial: float = 1.0  # s before the first trial of raw frames (the wait then doubles)
    max_wait: float = 60.0  # s between trials at most (the wait doubles after each slow trial)
    # A trial switches to raw when its link time <= this x edge service: raw frames then cost each
    # frame at most a quarter of a service time more latency than JPEG ones (1.0 until frames were
    # shrunk to the edge's input: a 0.5 MB raw frame on a 160 Mbps cap took 26 ms against the
    # detector's 36, went raw, and scored 73.7 async AP50 against JPEG's 78.5, tuning images)
    headroom: float = 0.25
    leave: float = 1.3  # raw frames leave when their link time > this x edge service (an edge-bound
    # path's answers come one service time apart, give or take: the margin keeps noise from leaving)
    settled: float = 30.0  # s of raw frames after which a switch to JPEG waits first_trial again
    current: str = JPEG  # auto starts with JPEG: the first raw frame on a slow link would take seconds
    edge_service: Ewma = field(default_factory=lambda: Ewma(0.2))
    raw_link: Recent = field(default_factory=lambda: Recent(5, 3.0))  # s of link per raw frame
    base: Recent = field(default_factory=lambda: Recent(32, 10.0))  # JPEG frames' path latency
    jpeg_link: Recent = field(default_factory=lambda: Recent(5, 3.0))  # answer gaps of JPEG frames
    wait: float = 0.0
    raw_since: float = -math.inf
    next_trial: float = math.inf  # set at the first JPEG answer
    trial_out: bool = False  # a trial frame is on its way
    trial_at: float = -math.inf
    trials: int = 0
    trials_skipped: int = 0  # due, but JPEG frames were link-bound already
    switches: int = 0
    events: list[tuple[float, str, str]] = field(default_factory=list)  # (time, to, why), last 50

    def __post_init__(self) -> None:
        if self.mode not in ENCODINGS:
            raise ValueError(f"encoding {self.mode!r}: expected one of {', '.join(ENCODINGS)}")
        if self.mode != AUTO:
            self.current = self.mode
        self.wait = self.first_trial

    def pick(self, now: float) -> tuple[str, bool]:
        """The encoding of the next frame to the edge, and whether it is a trial of raw frames."""
        if self.trial_out and now - self.trial_at > self.max_wait:  # its answer or loss never came
            self.lost(RAW, True, now)
        if (self.mode == AUTO and self.current == JPEG and not self.trial_out
                and now >= self.next_trial
                and math.isfinite(self.edge_service.value) and self.base.samples):
            if self.jpeg_bound(now):  # the link holds up even JPEG frames: a raw one would take ~15x
                self.trials_skipped += 1
                self._back_off(now)
                return JPEG, False
            self.trial_out, self.trial_at = True, now
            self.trials += 1
            return RAW, True
        return self.current, False

    def jpeg_bound(self, now: float) -> bool:
        """Whether the link, not the edge's detector, is the bottleneck even for JPEG frames: the
        gaps between answers to JPEG frames that queued (last 5, 3 s) are over ``leave`` x the
        edge's service time."""
        gaps = self.jpeg_link.values(now)
        return len(gaps) >= 3 and self.jpeg_link.median(now) > self.leave * self.edge_service.value

    def answered(self, encoding: str, trial: bool, sent: float, result: float, edge_time: float,
                 encode_time: float, service: float, link_time: float, path: float | None = None) -> bool:
        """An edge frame's answer: ``sent`` when it was handed to the sender, ``result`` when its
        answer came, ``edge_time`` what the edge spent on it (queue + service), ``encode_time`` the
        robot's encoding, ``service`` the edge detector's, ``link_time`` the link's time for its bytes
        when it queued behind another (NaN otherwise); ``path``, when the edge stamped the frame's
        arrival, its put-to-arrival delay beyond the shortest recent one (robot/linkclock.py; NaN:
        stamped but not measurable yet), else (None) the answer time less the edge's and the
        encoding's. True when the encoding switched."""
        self.edge_service.add(service)
        if self.mode != AUTO:
            return False
        if path is None:
            path = result - sent - _finite(edge_time) - _finite(encode_time)
        if encoding == JPEG:
            self.base.add(result, path)
            self.jpeg_link.add(result, link_time)
            if self.next_trial == math.inf and self.trials == 0:
                self.next_trial = result + self.wait
            return False
        limit = self.headroom * self.edge_service.value
        if trial:
            self.trial_out = False
            if not math.isfinite(path):  # no measurement (the first answer after a reset): again later
                self.next_trial = result + self.wait
                return False
            base = self.base.min(result)
            link = path - (base if math.isfinite(base) else 0.0)
            if self.current == JPEG and math.isfinite(limit) and link <= limit:
                return self._switch(RAW, result, f"a raw frame took the link {1e3 * link:.0f} ms, the "
                                                  f"edge's detector {1e3 * self.edge_service.value:.0f} ms")
            self._back_off(result)
            return False
        if self.current == RAW and math.isfinite(link_time):
            self.raw_link.add(result, link_time)
            slow, limit = self.raw_link.median(result), self.leave * self.edge_service.value
            if len(self.raw_link.values(result)) >= 3 and math.isfinite(limit) and slow > limit:
                return self._to_jpeg(result, f"raw frames take the link {1e3 * slow:.0f} ms each, the "
                                             f"edge's detector {1e3 * self.edge_service.value:.0f} ms")
        return False

    def lost(self, encoding: str, trial: bool, now: float) -> bool:
        """An edge frame unanswered (timed out): a raw frame lost means JPEG frames until a trial
        says otherwise. True when the encoding switched."""
        if self.mode != AUTO or encoding != RAW:
            return False
        if trial:
            self.trial_out = False
            self._back_off(now)
            return False
        return self._to_jpeg(now, "a raw frame was lost") if self.current == RAW else False

    def untried(self, now: float) -> None:
        """A trial frame the edge did not detect because a newer frame came behind it (the edge
        serves each robot's newest frame): no measurement, so the next trial comes after the same
        wait, not a doubled one."""
        if self.mode == AUTO:
            self.trial_out = False
            self.next_trial = now + self.wait

    def _to_jpeg(self, now: float, why: str) -> bool:
        if now - self.raw_since > self.settled:  # raw held long: the link changed, not a flutter
            self.wait = self.first_trial
        self._back_off(now)
        return self._switch(JPEG, now, why)

    def _back_off(self, now: float) -> None:
        """The next trial twice as far off as the last wait (at most ``max_wait``), from ``now``."""
        self.wait = min(2 * self.wait, self.max_wait)
        self.next_trial = now + self.wait

    def _switch(self, to: str, now: float, why: str) -> bool:
        self.current = to
        self.raw_since = now
        self.switches += 1
        self.raw_link.samples.clear()
        self.events.append((now, to, why))
        del self.events[:-50]
        return True

    def summary(self) -> dict[str, Any]:
        return {"mode": self.mode, "now": self.current, "switches": self.switches, "trials": self.trials,
                "trials_skipped": self.trials_skipped,
                "edge_service_ms": 1e3 * self.edge_service.value if math.isfinite(self.edge_service.value)
                else None, "events": [{"t": t, "to": to, "why": why} for t, to, why in self.events]}


def _finite(x: float) -> float:
    return x if math.isfinite(x) else 0.0
