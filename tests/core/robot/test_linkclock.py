"""The link's time per frame from the edge's arrival stamps (robot/linkclock.py), driven by hand:
the edge's clock far off the robot's, the link and the stalls modelled frame by frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from zoffload.policy.offload import EdgeOnly
from zoffload.robot.encoding import AUTO, JPEG, RAW, EncodingChoice
from zoffload.robot.frames import FallbackRules, FrameBook
from zoffload.robot.linkclock import LinkClock

EDGE_CLOCK = 81_234.5  # the edge's monotonic clock minus the robot's wall clock: any number
NONE = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32))


def link_arrivals(puts: list[float], per_frame: float, delay: float,
                  tx_stall: dict[int, float] | None = None) -> list[float]:
    """When each frame reaches the edge (robot clock): a serial link of ``per_frame`` seconds per
    frame after ``delay``; ``tx_stall``: frames the robot's sender held after their put."""
    out, free = [], -math.inf
    for i, put in enumerate(puts):
        start = max(put + (tx_stall or {}).get(i, 0.0), free)
        free = start + per_frame
        out.append(free + delay)
    return out


def test_frames_queued_on_a_slow_link_read_its_time_per_frame_whatever_the_answers_did() -> None:
    """Frames put every 10 ms on a link that takes 25 ms each: once a queue has built, every pair
    reads 25 ms, though the answers come back with stalls of up to 90 ms (the robot's receive
    side under a CPU quota), which the old answer-gap reading would have taken for the link."""
    rng = np.random.default_rng(3)
    puts = [0.01 * i for i in range(40)]
    arrivals = link_arrivals(puts, 0.025, 0.002)
    clock = LinkClock()
    samples = []
    for i, (put, arr) in enumerate(zip(puts, arrivals, strict=True)):
        answered = arr + 0.05 + rng.uniform(0.0, 0.09)  # detector + a stall
        link, _ = clock.answered("e1", arr + EDGE_CLOCK, put, i, answered)
        if math.isfinite(link):
            samples.append(link)
    assert len(samples) >= 30
    assert samples == pytest.approx([0.025] * len(samples))


def test_a_frame_held_by_a_stalled_sender_reads_the_link_not_the_stall() -> None:
    """Frames put every 40 ms on a fast link (1 ms a frame): no pair queued, no sample. One frame
    the robot's sender held 80 ms after its put (the process throttled) arrives 80 ms late and the
    next one, put meanwhile, right behind it: that pair did queue and reads the link's 1 ms, not
    the stall; the late frame's delay beyond the shortest shows the 80 ms."""
    puts = [0.04 * i for i in range(20)]
    arrivals = link_arrivals(puts, 0.001, 0.002, tx_stall={10: 0.08})
    clock = LinkClock()
    out = [clock.answered("e1", a + EDGE_CLOCK, p, i, a + 0.06)
           for i, (p, a) in enumerate(zip(puts, arrivals, strict=True))]
    assert [i for i, (link, _) in enumerate(out) if math.isfinite(link)] == [11, 12]
    assert out[11][0] == pytest.approx(0.001) and out[12][0] == pytest.approx(0.001)
    assert out[10][1] == pytest.approx(0.08)
    assert math.isnan(out[0][1])  # the first answer: no offset to measure its delay against yet
    others = [excess for i, (_, excess) in enumerate(out) if i not in (0, 10, 11, 12)]
    assert max(others) == pytest.approx(0.0, abs=1e-9)


def test_only_consecutive_puts_to_one_edge_pair_up_and_a_new_clock_starts_again() -> None:
    clock = LinkClock()
    link, excess = clock.answered("e1", 100.0, 0.0, 0, 0.1)
    assert math.isnan(link) and math.isnan(excess)
    link, _ = clock.answered("e1", 100.05, 0.01, 2, 0.2)  # put 2, not 1: another frame between them
    assert math.isnan(link)
    link, excess = clock.answered("e1", 100.08, 0.02, 3, 0.25)  # put before frame 2 arrived
    assert link == pytest.approx(0.03) and excess == pytest.approx(0.06)
    link, excess = clock.answered("e2", 5.0, 0.03, 4, 0.3)  # another edge: another clock
    assert math.isnan(link) and math.isnan(excess) and clock.resets == 1 and clock.edge == "e2"
    clock.answered("e2", 5.01, 0.04, 5, 0.32)
    link, excess = clock.answered("e2", 5.0 + 3600.0, 0.05, 6, 0.35)  # e2 restarted on another host
    assert math.isnan(link) and math.isnan(excess) and clock.resets == 2
    for bad in (math.nan, math.inf):  # not stamped, or nonsense: nothing measured, nothing kept
        assert all(math.isnan(x) for x in clock.answered("e2", bad, 0.06, 7, 0.4))
        assert all(math.isnan(x) for x in clock.answered("e2", 3700.0, 0.06, 7, bad))
    assert clock.samples == 1 and len(clock._floor) == 1


def test_the_kept_minimum_is_bounded_and_forgets_old_offsets() -> None:
    clock = LinkClock(horizon=5.0, bucket=1.0)
    for i in range(2000):  # 40 s of answers at 50 Hz, the offset rising 0.5 ms an answer
        clock.answered("e1", 10.0 + 0.02 * i + 0.0005 * i, 0.02 * i, i, 0.02 * i)
    assert len(clock._floor) <= 7
    # the oldest bucket kept started at 35.0 s (answer 1750), within 5 s of the last answer (39.98 s)
    assert clock.offset(39.98) == pytest.approx(10.0 + 0.0005 * 1750)


def run(events: list[tuple[float, int, int, float, float]], enc: EncodingChoice, stamped: bool,
        nbytes: float = 519_168, trial: set[int] | None = None) -> FrameBook:
    """Replay (time, 0 = put or 1 = answer, frame, its arrival at the edge, its wait there) through
    a FrameBook, the answers stamped with the arrival on the edge's clock or not."""
    b = FrameBook(EdgeOnly(), FallbackRules(reply_timeout=0.5), encodings=enc)
    b.edges_changed(True, 0.0)
    for now, kind, i, arrival, waited in sorted(events):
        if kind == 0:
            b.decide(i, i, capture=now, now=now)
            b.sent(i, now, False, edge="e1")
            b.encoding_for(i, now)
            if trial and i in trial:
                b.records[i].update(encoding=RAW, trial=1)
            b.putting(i, now, bytes=nbytes)
        else:
            b.edge_result(i, "ok", now, 0.05, waited, *NONE, edge="e1",
                          arrival=arrival + EDGE_CLOCK if stamped else math.nan)
    return b


def stalled_events() -> list[tuple[float, int, int, float, float]]:
    """Raw frames on an unconstrained link (2 ms to the edge), an edge detector of 50 ms, and a
    robot whose process freezes now and then (a quarter-core quota), as a run at that quota read
    it: every 0.7 s two frames put 9 ms apart (the second put after the first arrived: no queue),
    the first's answer read 15 ms late and the second's 70 ms late. By the robot's own clock the
    first reached the edge 15 ms later than it did, the second looks queued behind it, and the
    answers' gap reads ~120 ms of link for a raw frame."""
    events = []
    for pair in range(6):
        t = 1.0 + 0.7 * pair
        a, b = 2 * pair, 2 * pair + 1
        events += [(t, 0, a, 0.0, 0.0), (t + 0.009, 0, b, 0.0, 0.0),
                   (t + 0.002 + 0.05 + 0.015, 1, a, t + 0.002, 0.0),  # done at t + 0.052
                   (t + 0.002 + 0.1 + 0.07, 1, b, t + 0.011, 0.041)]  # done at t + 0.102
    return events


def test_the_robots_stalls_no_longer_send_raw_frames_to_jpeg_on_a_fast_link() -> None:
    """The same run read by the answers' gaps and by the edge's arrival stamps: the stalls made
    the answers' gaps read the link slower than the edge's detector and raw frames went as JPEG;
    the stamps read no queued pair, and raw frames stay."""
    old, new = EncodingChoice(AUTO, current=RAW), EncodingChoice(AUTO, current=RAW)
    run(stalled_events(), old, stamped=False)
    b = run(stalled_events(), new, stamped=True)
    assert old.switches == 1 and "raw frames take the link" in old.events[0][2]
    assert new.switches == 0 and new.current == RAW
    assert b.link_clock.samples == 0 and b.summary()["link_clock"]["stamped"] == 12


def test_raw_frames_queued_on_a_slow_link_still_go_to_jpeg_by_the_stamps() -> None:
    """A raw frame put every 40 ms on a link that takes 100 ms for one: the frames queue, the
    arrival stamps read 100 ms a frame against the edge detector's 50, and frames go as JPEG."""
    events, free = [], -math.inf
    for i in range(12):
        put = 1.0 + 0.04 * i
        free = max(put, free) + 0.1
        events += [(put, 0, i, 0.0, 0.0), (free + 0.052, 1, i, free + 0.002, 0.0)]
    enc = EncodingChoice(AUTO, current=RAW)
    b = run(events, enc, stamped=True)
    assert enc.current == JPEG and "raw frames take the link 100 ms" in enc.events[0][2]
    assert b.link_clock.samples >= 3
    links = [float(r["link_ms"]) for r in b.records.values() if math.isfinite(r.get("link_ms", math.nan))]
    assert links and links == pytest.approx([100.0] * len(links))


def test_a_raw_trial_right_after_the_edge_came_back_is_tried_again_not_taken_for_fast() -> None:
    """JPEG frames, then the edge gone and back (the link clock starts again): the first answer
    after it is a raw trial on a link that takes 400 ms for a raw frame. Measured against itself it
    would read no delay and switch to raw; it is no measurement, and the trial comes again after
    the same wait. A second trial, measured against the JPEG answer before it, is slow: JPEG stays."""
    enc = EncodingChoice(AUTO)  # JPEG
    b = FrameBook(EdgeOnly(), FallbackRules(reply_timeout=1.0), encodings=enc)
    b.edges_changed(True, 0.0)

    def frame(i: int, t: float, link: float, trial: bool = False) -> None:
        b.decide(i, i, capture=t, now=t)
        b.sent(i, t, False, edge="e1")
        enc.pick(t)
        b.records[i].update(encoding=RAW if trial else JPEG, trial=int(trial))
        b.putting(i, t, bytes=519_168 if trial else 34_000)
        b.edge_result(i, "ok", t + link + 0.052, 0.05, 0.0, *NONE, edge="e1", arrival=t + link + EDGE_CLOCK)

    for i in range(5):
        frame(i, 0.1 * i, 0.002)
    b.edges_changed(False, 0.6)
    b.edges_changed(True, 0.7)
    wait = enc.wait
    frame(5, 1.0, 0.4, trial=True)  # the first answer since the clock started again
    assert enc.current == JPEG and enc.switches == 0 and enc.next_trial == pytest.approx(1.452 + wait)
    frame(6, 2.0, 0.002)
    frame(7, 2.1, 0.4, trial=True)
    assert enc.current == JPEG and enc.switches == 0 and enc.wait > wait  # slow: backed off
