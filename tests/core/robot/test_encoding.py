"""The per-frame encoding choice (robot/encoding.py): JPEG while the link would hold raw frames up,
raw while it carries them as fast as the edge's detector takes them, trials with back-off."""

from __future__ import annotations

import math

import numpy as np
import pytest

from zoffload.policy.dispatch import Dispatcher
from zoffload.policy.offload import EDGE, EdgeOnly, Strategy
from zoffload.robot.encoding import JPEG, RAW, EncodingChoice
from zoffload.robot.frames import FallbackRules, FrameBook

SERVICE = 0.040  # the edge detector's time per frame


def jpeg_answer(c: EncodingChoice, sent: float, path: float = 0.010) -> bool:
    """A JPEG frame answered: ``path`` s on the way besides the edge's time and the encoding."""
    return c.answered(JPEG, False, sent, sent + 0.005 + path + SERVICE, SERVICE, 0.005, SERVICE, math.nan)


def trial(c: EncodingChoice, now: float, link: float) -> bool:
    """Run one trial at ``now`` whose raw frame takes the link ``link`` s more than a JPEG one."""
    assert c.pick(now) == (RAW, True)
    assert c.pick(now) == (JPEG, False)  # one trial at a time
    return c.answered(RAW, True, now, now + 0.010 + link + SERVICE, SERVICE, 0.0, SERVICE, math.nan)


EMPTY = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32))  # an answer without persons


def book_at_a_trial(strategy: Strategy, answered: float, trial_at: float, copy: bool = False,
                    puts: tuple[float, float] | None = None) -> FrameBook:
    """A book with ``auto`` encoding whose first frame (JPEG, sent at 0) was answered at
    ``answered`` and whose second, handed to the sender at ``trial_at`` (as a copy if ``copy``), is
    the first trial of raw frames; ``puts``: when each went to Zenoh."""
    b = FrameBook(strategy, FallbackRules(reply_timeout=1.0), encodings=EncodingChoice("auto"))
    b.edges_changed(True, 0.0)
    b.decide(1, 1, 0.0, 0.0)
    b.sent(1, 0.0, False)
    b.encoding_for(1, 0.0)
    if puts is not None:
        b.records[1]["put"] = puts[0]
    b.edge_result(1, "ok", answered, SERVICE, 0.0, *EMPTY)
    b.decide(2, 2, trial_at, trial_at)
    b.sent(2, trial_at, False, copy=copy)
    assert b.encoding_for(2, trial_at) == (RAW, True)
    if puts is not None:
        b.records[2]["put"] = puts[1]
    return b


def test_auto_starts_with_jpeg_and_takes_raw_frames_when_a_trial_finds_the_link_fast() -> None:
    c = EncodingChoice()
    assert c.pick(0.0) == (JPEG, False)  # nothing known yet: JPEG (a raw frame may take seconds)
    jpeg_answer(c, 0.0)
    assert c.pick(0.5) == (JPEG, False)  # the first trial waits first_trial after the first answer
    assert trial(c, 1.1, link=0.008)  # 8 ms of link for a raw frame, the detector takes 40
    assert c.current == RAW and c.pick(2.0) == (RAW, False)
    assert c.switches == 1 and c.summary()["events"][0]["to"] == RAW


def test_a_trial_that_would_add_much_latency_keeps_jpeg_though_the_link_keeps_pace() -> None:
    """25 ms of link per raw frame keeps pace with a detector at 40 ms, but adds 25 ms to every
    frame's age: more than a quarter of the service time, so frames stay JPEG."""
    c = EncodingChoice()
    jpeg_answer(c, 0.0)
    assert not trial(c, 1.1, link=0.025)
    assert c.current == JPEG and c.next_trial > 1.1 + 2.0


def test_a_slow_trial_keeps_jpeg_and_backs_off_to_one_trial_a_minute() -> None:
    c = EncodingChoice()
    jpeg_answer(c, 0.0)
    now, waits = 1.1, []
    for _ in range(9):
        assert not trial(c, now, link=0.100)  # 100 ms per raw frame: the link would be the bottleneck
        waits.append(round(c.next_trial - (now + 0.150), 3))  # from the answer
        assert c.pick(c.next_trial - 0.01) == (JPEG, False)
        now = c.next_trial
    assert waits[:4] == [2.0, 4.0, 8.0, 16.0] and waits[-1] == c.max_wait == 60.0
    assert c.current == JPEG and c.switches == 0 and c.trials == 9


def test_raw_frames_leave_for_jpeg_when_the_link_becomes_the_bottleneck_not_on_noise() -> None:
    c = EncodingChoice()
    jpeg_answer(c, 0.0)
    trial(c, 1.1, link=0.005)
    assert c.current == RAW
    rng = np.random.default_rng(0)
    t = 2.0
    for _ in range(200):  # an edge-bound path: answers a service time apart, +- 10 %
        t += 0.04
        c.answered(RAW, False, t - 0.2, t, SERVICE, 0.0, SERVICE, SERVICE * rng.uniform(0.9, 1.1))
    assert c.current == RAW
    for _ in range(3):  # the link slows to 90 ms per raw frame
        t += 0.09
        switched = c.answered(RAW, False, t - 0.3, t, SERVICE, 0.0, SERVICE, 0.090)
    assert switched and c.current == JPEG
    assert c.next_trial == pytest.approx(t + 2.0)  # the wait doubled: no flutter at the border


def test_a_lost_raw_frame_means_jpeg_and_a_lost_trial_backs_off() -> None:
    c = EncodingChoice()
    jpeg_answer(c, 0.0)
    assert c.pick(1.1) == (RAW, True)
    assert not c.lost(RAW, True, 1.6)  # the trial frame timed out
    assert c.current == JPEG and c.next_trial == pytest.approx(3.6) and not c.trial_out
    trial(c, 3.6, link=0.001)
    assert c.current == RAW
    assert c.lost(RAW, False, 5.0) and c.current == JPEG
    assert not c.lost(JPEG, False, 6.0)  # a JPEG frame lost is the link's loss, not the encoding's


def test_a_trial_whose_answer_never_comes_does_not_stop_the_trials() -> None:
    c = EncodingChoice()
    jpeg_answer(c, 0.0)
    assert c.pick(1.1) == (RAW, True)
    assert c.pick(30.0) == (JPEG, False)
    late = 1.1 + c.max_wait + 0.1
    assert c.pick(late) == (JPEG, False)  # over, as if lost: the wait doubles
    assert not c.trial_out and c.next_trial == pytest.approx(late + 2.0)
    assert c.pick(late + 2.0) == (RAW, True)


def test_a_trial_sent_as_a_copy_is_over_when_its_edge_goes() -> None:
    """A trial frame may be a dispatcher's copy (the frame detected locally, the copy measuring the
    edge); when the edge goes, the copy is dropped and the trial is over (not waiting a minute)."""
    b = book_at_a_trial(Dispatcher(), answered=0.08, trial_at=1.2, copy=True)
    b.edges_changed(False, 1.3)
    enc = b.encodings
    assert not enc.trial_out and enc.next_trial == pytest.approx(3.3) and b.counters["copies_lost"] == 1


def test_fixed_encodings_never_change_and_a_wrong_one_is_refused() -> None:
    for mode in (RAW, JPEG):
        c = EncodingChoice(mode)
        for t in range(100):
            c.answered(mode, False, t, t + 1.0, SERVICE, 0.0, SERVICE, 1.0)
            c.lost(mode, False, t + 1.0)
            assert c.pick(t + 2.0) == (mode, False)
        assert c.switches == 0
    with pytest.raises(ValueError, match="png"):
        EncodingChoice("png")


def test_the_book_hides_a_trials_size_from_the_dispatcher_and_resets_it_on_a_switch() -> None:
    """Through FrameBook: the trial frame's answer reaches the dispatcher without bytes or rate,
    and the switch to raw clears its delivered-rate samples (bytes per second of JPEG frames)."""
    d = Dispatcher()
    b = FrameBook(d, FallbackRules(reply_timeout=1.0), encodings=EncodingChoice("auto"))
    b.edges_changed(True, 0.0)
    empty = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32))
    t, seq = 0.0, 0
    for _ in range(8):  # JPEG frames sent two at a time, so the second queues behind the first
        for _ in range(2):
            seq += 1
            b.decide(seq, seq, t, t)
            b.sent(seq, t, False)
            assert b.encoding_for(seq, t)[0] == JPEG
            b.records[seq].update(bytes=100_000, encode_ms=5.0)
        b.edge_result(seq - 1, "ok", t + 0.06, SERVICE, 0.0, *empty)
        b.edge_result(seq, "ok", t + 0.10, SERVICE, 0.0, *empty)
        t += 0.12
    assert d.delivered.samples and math.isfinite(d.frame_bytes.value)
    t, seq = t + 0.2, seq + 1  # first_trial (1 s) after the first answer
    b.decide(seq, seq, t, t)
    b.sent(seq, t, False)
    assert b.encoding_for(seq, t) == (RAW, True)
    b.records[seq].update(bytes=1_220_000, encode_ms=0.5)
    late = seq + 1  # a JPEG frame sent behind the trial, answered after the switch
    b.decide(late, late, t + 0.01, t + 0.01)
    b.sent(late, t + 0.01, False)
    assert b.encoding_for(late, t + 0.01) == (JPEG, False)
    b.records[late].update(bytes=100_000, encode_ms=5.0)
    bytes_before = d.frame_bytes.value
    b.edge_result(seq, "ok", t + 0.065, SERVICE, 0.0, *empty)  # 65 ms: 5 ms of link beyond a JPEG's
    assert b.encodings.current == RAW and b.encodings.switches == 1
    assert not d.delivered.samples and math.isnan(d.frame_bytes.value) and bytes_before < 200_000
    # The JPEG frame's answer after the switch: neither its bytes nor the rate they imply (100 kB
    # in the 25 ms since the trial's answer: 4 MB/s, a raw frame would "take" 0.3 s) nor its path
    # time reach the dispatcher as the raw frames' (once, such a rate kept ours sending one raw
    # frame in nine for a whole run)
    b.edge_result(late, "ok", t + 0.09, SERVICE, 0.0, *empty)
    assert b.records[late]["status"] == "edge_done"
    assert not d.delivered.samples and math.isnan(d.frame_bytes.value) and not d.base.samples
    assert b.records[seq]["status"] == "edge_done"  # the trial frame is a frame like the others
    assert b.summary()["encodings"]["now"] == RAW and b.counters["sent_jpeg"] == 17  # (16 + the late one)


def test_other_strategies_ignore_the_encoding() -> None:
    b = FrameBook(EdgeOnly(), FallbackRules(), encodings=EncodingChoice("auto"))
    b.edges_changed(True, 0.0)
    assert b.decide(1, 1, 0.0, 0.0)[0] == EDGE
    b.sent(1, 0.0, False)
    b.encoding_for(1, 0.0)
    b.expire(5.0)  # lost: a JPEG frame's loss switches nothing
    assert b.encodings.current == JPEG and b.balanced()


def test_no_trial_while_even_jpeg_frames_wait_for_the_link() -> None:
    """A link that holds up JPEG frames (answers 80 ms apart against a 40 ms detector) would hold a
    raw frame, ~15 times the bytes, for over a second: the trial waits (doubling) until the JPEG
    frames are edge-bound again."""
    c = EncodingChoice()
    t = 0.0
    for _ in range(20):  # 1.6 s of link-bound JPEG frames
        t += 0.08
        c.answered(JPEG, False, t - 0.2, t, SERVICE, 0.005, SERVICE, 0.080)
    assert c.pick(t) == (JPEG, False) and c.trials == 0 and c.trials_skipped == 1
    assert c.next_trial == pytest.approx(t + 2.0)
    for _ in range(60):  # the link gets faster: answers a service time apart
        t += 0.04
        c.answered(JPEG, False, t - 0.2, t, SERVICE, 0.005, SERVICE, 0.040)
    assert c.pick(t) == (RAW, True) and c.trials == 1


def test_a_trial_the_edge_dropped_for_a_newer_frame_is_tried_again_without_backing_off() -> None:
    """The edge serves each robot's newest frame: a raw trial that a JPEG frame overtook at the edge
    is answered ``dropped``, which says nothing of the link (an error still ends the trial)."""
    for status, wait in (("dropped", 1.0), ("error", 2.0)):
        b = book_at_a_trial(Dispatcher(), answered=0.08, trial_at=1.2)
        b.edge_result(2, status, 1.25, math.nan, math.nan, *EMPTY)
        enc = b.encodings
        assert not enc.trial_out and enc.current == JPEG
        assert enc.wait == pytest.approx(wait) and enc.next_trial == pytest.approx(1.25 + wait), status


def test_a_trials_link_time_counts_from_its_put() -> None:
    """Handed to the sender at 1.1 s, put at 1.185 s (the robot stalled between): the 85 ms are not
    the link's, and the trial (5 ms of link beyond a JPEG frame's path) finds raw frames fast."""
    # the first frame's path: 60 ms less the edge's 40, 20 ms
    b = book_at_a_trial(EdgeOnly(), answered=0.06, trial_at=1.1, puts=(0.0, 1.185))
    b.edge_result(2, "ok", 1.25, SERVICE, 0.0, *EMPTY)  # 1.25 - 1.185 - 0.04 - 0.02 = 5 ms of link
    assert b.encodings.current == RAW
