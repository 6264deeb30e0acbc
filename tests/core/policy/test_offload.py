"""The offloading strategies: the thesis' rules and ours."""

from __future__ import annotations

import math

import pytest

from zoffload.policy.dispatch import Dispatcher
from zoffload.policy.offload import BOTH, EDGE, HOLD, LOCAL, SKIP, EdgeReply, OffloadState, make_strategy


def _st(**kw: object) -> OffloadState:
    base: dict[str, object] = {"now": 0.0, "edge_available": True}
    base.update(kw)
    return OffloadState(**base)  # type: ignore[arg-type]


def test_fixed_ratio_is_algorithm_1() -> None:
    s = make_strategy("ratio:0.3")
    sides = [s.decide(_st()) for _ in range(100)]
    assert sides.count(EDGE) == 30
    assert sides[:4] == [EDGE, LOCAL, LOCAL, EDGE]  # offload while offloaded/total < r
    with pytest.raises(ValueError):
        make_strategy("ratio:1.5")
    with pytest.raises(ValueError):
        make_strategy("sometimes")


def test_thesis_rule_constraints_then_rtt() -> None:
    s = make_strategy("thesis", cpu_max=80, bw_max_mbps=100)
    s.on_local_result(0.05)
    s.on_edge_result(0.10)
    assert s.decide(_st()) == LOCAL  # local is faster
    assert s.decide(_st(cpu_percent=85)) == EDGE  # CPU bound first
    s.on_edge_result(0.01)
    s.on_edge_result(0.01)
    assert s.decide(_st()) == EDGE  # edge average 0.04 < 0.05
    assert s.decide(_st(mbps_out=120)) == LOCAL  # bandwidth bound
    assert s.decide(_st(edge_available=False)) == LOCAL  # no edge: local whatever the rule says


def test_frames_that_never_return_count_in_our_rule_but_not_in_the_thesis() -> None:
    """The thesis' failure under a cap: the few edge frames that return look fast."""
    thesis, ours = make_strategy("thesis"), make_strategy("dynamic", max_in_flight=10)
    for s in (thesis, ours):
        s.on_local_result(0.15)
        for _ in range(3):
            s.on_edge_result(0.08)  # the frames that made it
        for _ in range(7):
            s.on_edge_timeout(0.5)  # the ones the link dropped
    assert thesis.decide(_st()) == EDGE
    assert ours.decide(_st()) == LOCAL


def test_our_rule_sees_an_edge_that_stopped_answering() -> None:
    ours = make_strategy("dynamic", max_in_flight=5)
    ours.on_local_result(0.15)
    ours.on_edge_result(0.08)
    assert ours.decide(_st()) == EDGE
    assert ours.decide(_st(in_flight=1, oldest_in_flight_age=0.3)) == LOCAL  # already slower than local
    # window full: held back while local is the slower side ...
    assert ours.decide(_st(in_flight=5, oldest_in_flight_age=0.01)) == HOLD
    # ... detected locally when only the CPU bound sent it to the edge and local is faster
    cpu_bound = make_strategy("dynamic", cpu_max=90, max_in_flight=5)
    cpu_bound.on_local_result(0.03)
    cpu_bound.on_edge_result(0.04)
    assert cpu_bound.decide(_st(cpu_percent=95)) == EDGE
    assert cpu_bound.decide(_st(cpu_percent=95, in_flight=5, oldest_in_flight_age=0.01)) == LOCAL
    # while local, one frame in probe_every goes to the edge once nothing is in flight
    ours.on_edge_timeout(0.5)
    sides = [ours.decide(_st()) for _ in range(20)]
    assert sides.count(EDGE) == 2


def test_our_window_halves_on_losses_and_grows_back() -> None:
    ours = make_strategy("dynamic", max_in_flight=4)
    assert ours.flight_window == 4  # type: ignore[attr-defined]
    ours.on_local_result(0.5, service=0.5)
    ours.on_edge_result(0.1)
    ours.on_edge_timeout(0.5)
    assert ours.flight_window == 2  # type: ignore[attr-defined]
    ours.on_edge_timeout(0.5)
    assert ours.flight_window == 2  # type: ignore[attr-defined]  # never below two
    assert ours.decide(_st(in_flight=2, oldest_in_flight_age=0.05)) == HOLD  # local is slower
    for _ in range(8):
        ours.on_edge_result(0.1)
    assert ours.flight_window == 4  # type: ignore[attr-defined]
    # a frame the edge answered dropped for a newer one of ours is no loss; an error is
    dropped = EdgeReply(sent=1.0, result=1.01, bytes=1e6, service=float("nan"), status="dropped")
    ours.on_edge_refused(dropped, 0.5)
    assert ours.flight_window == 4  # type: ignore[attr-defined]
    error = EdgeReply(sent=1.0, result=1.01, bytes=1e6, service=float("nan"), status="error")
    ours.on_edge_refused(error, 0.5)
    assert ours.flight_window == 2  # type: ignore[attr-defined]


# The work-conserving dispatcher (policy/dispatch.py)
def _reply(sent: float, result: float, service: float = 0.04, rate: float = float("nan")) -> EdgeReply:
    return EdgeReply(sent=sent, result=result, bytes=1e6, service=service, delivery_rate=rate)


def _measured(local: float = 0.1, edge: float = 0.06, **kw: float) -> Dispatcher:
    """A dispatcher that has seen results of each side (local service, edge send-to-answer); the
    first local one, at start-up, is not taken as a measure."""
    d = Dispatcher(**kw)  # type: ignore[arg-type]
    d.on_local_result(1.0, service=1.0, cpu=local)  # the robot was starting: ignored
    d.on_local_result(local, service=local, cpu=local)
    d.on_edge_result(edge, _reply(0.0, edge))
    return d


def test_dispatch_sends_each_frame_to_the_side_that_finishes_it_first() -> None:
    d = _measured(local_bias=0.0)
    assert d.decide(_st(now=1.0, capture=1.0)) == EDGE  # 60 ms against 100 ms
    # two frames already on their way: a third would queue behind them, local is sooner
    busy = {"edge_sends": ((0.99, 1e6), (0.995, 1e6)), "in_flight": 2}
    assert d.decide(_st(now=1.0, capture=1.0, **busy)) == LOCAL
    # three keep the edge busy for a base latency (60 ms at 40 ms each) with one waiting; local is
    # busy, with 20 ms of its 100 done, and would not start this frame in time: rather than skip
    # it, the edge takes it as a spare while its window (4) has room, not once it is full
    full = {"edge_sends": ((0.98, 1e6), (0.99, 1e6), (0.995, 1e6)), "in_flight": 3}
    assert d.depth(1.0) == 3 and d.window == 4
    local_busy = {"local_busy": True, "local_busy_for": 0.02}
    assert d.decide(_st(now=1.0, capture=1.0, **local_busy, **full)) == EDGE and d.spares == 1
    window = {"edge_sends": ((0.97, 1e6), *full["edge_sends"]), "in_flight": 4}  # type: ignore[misc]
    assert d.decide(_st(now=1.0, capture=1.0, **local_busy, **window)) == SKIP and d.spares == 1
    # a spare only instead of a skip: with the local detector free, the fourth frame is local's
    assert d.decide(_st(now=1.0, capture=1.0, **full)) == LOCAL and d.spares == 1
    # the local bias (its lighter model) tips a close call towards the edge
    close = _measured(local=0.05, edge=0.06, local_bias=0.04)
    assert close.decide(_st(now=1.0, capture=1.0)) == EDGE


def test_dispatch_skips_what_no_side_finishes_while_fresh() -> None:
    d = _measured(local=0.5, edge=0.6, max_age=0.3)
    assert d.decide(_st(now=1.0, capture=1.0)) == SKIP
    assert d.estimates[0] == pytest.approx(1.5) and d.estimates[1] == pytest.approx(1.6)
    # a frame that already waited at the camera has less time left
    d = _measured(local=0.2, edge=0.25, max_age=0.3)
    assert d.decide(_st(now=1.0, capture=1.0)) != SKIP
    assert d.decide(_st(now=1.15, capture=1.0)) == SKIP


@pytest.mark.parametrize("window", [3, 4])
def test_dispatch_learns_the_delivered_rate_and_keeps_the_link_busy_not_queued(window: int) -> None:
    """A capped link: 1 MB frames at 16 MB/s take 62.5 ms each, more than the camera's 40 ms. A fixed
    ratio queues frames in the link's buffers; the dispatcher keeps as many in flight as keep the
    link busy for a base latency, plus one, and sends a frame local cannot take as a spare while its
    window has room: the link is used fully and no frame waits long."""
    d = _measured(local=2.0, edge=0.11, max_age=1.0, local_bias=0.0,  # local: too slow to matter
                  max_in_flight=window)
    sends: list[tuple[float, float]] = []  # (sent, answered) of the frames on their way
    rtts, last_answer, sides = [], 0.0, []
    for k in range(40):
        now = 1.0 + 0.04 * k
        for sent, answered in [x for x in sends if x[1] <= now]:  # the link's answers meanwhile
            sends.remove((sent, answered))
            d.on_edge_result(answered - sent, _reply(sent, answered, rate=1e6 / 0.0625))
            rtts.append(answered - sent)
        side = d.decide(_st(now=now, capture=now, edge_sends=tuple((s, 1e6) for s, _ in sends),
                            in_flight=len(sends)))
        sides.append(side)
        if side == EDGE:  # the pipeline: 110 ms alone, one frame per 62.5 ms at the bottleneck
            last_answer = max(now + 0.11, last_answer + 0.0625)
            sends.append((now, last_answer))
    assert d.interval(1e6, now) == pytest.approx(0.0625)
    assert d.depth(now) == 3  # 110 ms / 62.5 ms, rounded up, plus one waiting
    assert sides.count(EDGE) >= 24  # the link's 16 frames a second (1.6 s) are used ...
    # ... and none waits for it more than about a frame, or two with the spare the window allows
    assert max(rtts) <= 0.11 + (window - 1) * 0.0625 + 1e-9
    assert set(sides) == {EDGE, SKIP}
    assert (d.spares > 0) == (window > d.depth(now))


def test_the_base_latency_comes_from_frames_sent_alone_and_a_drain_renews_it() -> None:
    """Frames that queued behind others answer late by their wait: a base latency learnt from them
    grows with the queue, and the depth of frames in flight with it. Only answers to frames sent
    alone (none other unanswered) make the base; when none came for ``base_period`` s, the edge
    path is drained (no edge frame until none is in flight) and the next frame goes alone."""
    d = _measured(local=0.3, edge=0.11, max_age=1.0, local_bias=0.0, max_in_flight=8, base_period=5.0)
    rate = 1e6 / 0.0625  # 62.5 ms a frame at the bottleneck
    d.on_edge_result(0.11, EdgeReply(sent=1.0, result=1.11, bytes=1e6, service=0.04,
                                     delivery_rate=rate, alone=True))
    queued = [EdgeReply(sent=1.2 + 0.04 * k, result=1.2 + 0.04 * k + 0.235, bytes=1e6, service=0.04,
                        delivery_rate=rate) for k in range(75)]  # 3 s of frames two deep in a queue
    for reply in queued:
        d.on_edge_result(0.235, reply)
    now = queued[-1].result
    assert d.r0(now) == pytest.approx(0.11) and d.depth(now) == 3  # 110 ms / 62.5 ms, +1 waiting
    blind = _measured(local=0.3, edge=0.235, max_age=1.0, local_bias=0.0, max_in_flight=8)
    for reply in queued:  # the same answers, none known to be alone: the queue is taken for base
        blind.on_edge_result(0.235, reply)
    assert blind.r0(now) == pytest.approx(0.235) and blind.depth(now) == 5
    # a delivered-rate sample far off (10 s a frame: a gap that held idle time) does not enter the
    # base: only the edge's own time on each frame is taken off its answer time (taking off the
    # bottleneck's estimate then, and adding it now, made the base negative in real runs)
    noisy = _measured(edge=0.11)
    for k, r in enumerate((1e5, 2e7, 2e7, 2e7)):
        noisy.on_edge_result(0.05, EdgeReply(sent=2.0 + k, result=2.05 + k, bytes=1e6, service=0.04,
                                             delivery_rate=r, alone=True))
    assert noisy.r0(5.05) == pytest.approx(0.05)
    # 5 s after the last frame sent alone was answered, the edge path is drained ...
    in_flight = {"edge_sends": ((6.0, 1e6), (6.04, 1e6)), "in_flight": 2}
    assert d.decide(_st(now=6.05, capture=6.05, **in_flight)) == EDGE and d.drains == 0
    assert d.decide(_st(now=6.12, capture=6.12, **in_flight)) in (LOCAL, SKIP) and d.draining
    assert d.decide(_st(now=6.16, capture=6.16, edge_sends=((6.04, 1e6),), in_flight=1)) in (LOCAL, SKIP)
    # ... until none is in flight: the next frame goes alone, and its answer renews the base
    assert d.decide(_st(now=6.2, capture=6.2)) == EDGE and not d.draining and d.drains == 1
    # while that frame is on its way the next ones go as usual: one drain, not one per frame
    alone_out = {"edge_sends": ((6.2, 1e6),), "in_flight": 1}
    assert d.decide(_st(now=6.24, capture=6.24, **alone_out)) == EDGE and d.drains == 1
    d.on_edge_result(0.1, EdgeReply(sent=6.2, result=6.3, bytes=1e6, service=0.04, delivery_rate=rate,
                                    alone=True))
    assert d.decide(_st(now=6.32, capture=6.32, **in_flight)) == EDGE and d.drains == 1
    # frames of the other encoding take the link longer or shorter: the base is measured again, by
    # a drain at the next frame
    d.on_encoding_change()
    assert not d.base.samples
    assert d.decide(_st(now=6.36, capture=6.36, **in_flight)) in (LOCAL, SKIP) and d.drains == 2


def test_frames_that_never_return_keep_the_dispatcher_local_the_thesis_rule_does_not() -> None:
    """The thesis' failure case: 3 edge frames come back fast, 7 never do."""
    thesis, ours = make_strategy("thesis"), make_strategy("dispatch")
    for s in (thesis, ours):
        s.on_local_result(0.15, service=0.15)
        s.on_local_result(0.15, service=0.15)
        for k in range(3):
            s.on_edge_result(0.08, _reply(k, k + 0.08))
        for _ in range(7):
            s.on_edge_timeout(0.5)
    assert thesis.decide(_st()) == EDGE
    assert ours.decide(_st(now=10.0, capture=10.0)) in (LOCAL, BOTH)  # blocked until it answers
    # one more answer unblocks it, but the edge loses most frames: local still finishes more
    ours.on_edge_result(0.08, _reply(10.0, 10.08))
    assert ours.decide(_st(now=11.0, capture=11.0)) in (LOCAL, BOTH)
    # a run of prompt answers restores trust
    for k in range(15):
        ours.on_edge_result(0.08, _reply(12.0 + k, 12.08 + k))
    assert ours.decide(_st(now=30.0, capture=30.0)) == EDGE


def test_dispatch_copies_a_local_frame_to_keep_the_edge_estimate_fresh() -> None:
    d = _measured(local=0.02, edge=0.2, refresh_period=1.0)
    sides = [d.decide(_st(now=5.0 + 0.04 * k, capture=5.0 + 0.04 * k)) for k in range(50)]  # 2 s
    # every frame is detected locally; once a second one is also copied to the edge
    assert set(sides) == {LOCAL, BOTH} and sides.count(BOTH) == 2
    assert d.offloaded == 0  # a copy is no offload
    # no copy while frames are on their way, nor without an edge
    assert d.decide(_st(now=9.0, capture=9.0, edge_sends=((8.9, 1e6),), in_flight=1)) == LOCAL
    assert d.decide(_st(now=12.0, capture=12.0, edge_available=False)) == LOCAL


def test_a_blocked_dispatcher_asks_the_edge_again_every_retry_period_without_losing_frames() -> None:
    """A Wi-Fi outage: an edge frame times out and blocks the edge. The link may be back a moment
    later; the dispatcher finds out within a retry period, with a copy of a frame it detects locally
    or with a frame it would otherwise skip, never one the local detector would have taken."""
    d = _measured(local=0.1, edge=0.06, retry_period=0.19, refresh_period=1.0)
    for _ in range(4):  # the frames in flight when the link went: one outage, one smaller window
        d.on_edge_timeout(0.5)
    assert d.blocked and d.window == d.max_in_flight - 1
    sides, t = [], 2.0
    for k in range(25):  # 1 s of frames at 25 Hz, the local detector busy on every other one
        t = 2.0 + 0.04 * k
        busy = {"local_busy": True, "local_busy_for": 0.0, "local_waiting": True} if k % 2 else {}
        sides.append((k % 2, d.decide(_st(now=t, capture=t, **busy))))
    asked = [(k, side) for k, (b, side) in enumerate(sides) if side in (EDGE, BOTH)]
    # one question every 5th frame (0.2 s), not one a second as the refresh alone would ask
    assert [k for k, _ in asked] == [0, 5, 10, 15, 20]
    # a frame the robot detects goes as a copy; only a frame it would skip goes to the edge itself
    assert all((side == BOTH) == (k % 2 == 0) for k, side in asked)
    assert {side for b, side in sides if not b} <= {LOCAL, BOTH}
    assert d.retries == sum(1 for _, side in asked if side == EDGE) == 2
    # at most max_in_flight unanswered questions, none while the sender still holds a frame
    full = tuple((t - 0.1 * i, 1e6) for i in range(d.max_in_flight))
    assert d.decide(_st(now=t + 1.0, capture=t + 1.0, edge_sends=full, in_flight=4)) == LOCAL
    assert d.decide(_st(now=t + 2.0, capture=t + 2.0, send_waiting=True)) == LOCAL
    # an answer unblocks it: the edge is an option again, and no more questions are asked
    d.on_edge_result(0.06, _reply(t + 2.9, t + 2.96))
    assert not d.blocked and d.window == d.max_in_flight - 1 + 0.25
    d.on_edge_timeout(0.5)  # a new loss after an answer is a new outage
    assert d.window == d.max_in_flight - 2 + 0.25
    d.on_edge_result(0.06, _reply(t + 2.95, t + 2.99))
    d.decide(_st(now=t + 3.0, capture=t + 3.0, local_busy=True, local_waiting=True))
    assert math.isfinite(d.estimates[1]) and d.retries == 2


def test_dispatch_paces_the_local_detector_within_the_cpu_quota() -> None:
    d = _measured(local=0.02, edge=0.2)
    d.on_local_result(0.02, service=0.02, cpu=0.02)
    # the rest of the process uses 0.2 of a 0.25 quota: 0.05 cores are left, so a 20 ms detection
    # may start every 0.4 s
    for k in range(11):
        t = 1.0 + 0.1 * k
        d.decide(_st(now=t, capture=t, cpu_time=0.2 * t, local_cpu_time=0.0, cpu_quota=0.25,
                     local_last_start=1.5))
    assert d.local_ready_at == pytest.approx(1.5 + 0.02 / 0.05, rel=0.05)
    # no quota in force: never held back
    d.decide(_st(now=3.0, capture=3.0, cpu_time=0.6, local_cpu_time=0.0, local_last_start=2.9))
    assert d.local_ready_at == -math.inf


def _stalling(cpu: float) -> Dispatcher:
    """A dispatcher whose detector takes 100 ms of wall time and ``cpu`` of CPU, and whose edge
    path is a link at 60 ms a frame, 110 ms for a frame alone."""
    d = make_strategy("dispatch", local_bias=0.0)
    assert isinstance(d, Dispatcher)
    for _ in range(3):  # (the first, at start-up, is no measure)
        d.on_local_result(0.1, service=0.1, cpu=cpu)
    d.on_edge_result(0.11, _reply(0.1, 0.21))
    d.on_edge_result(0.11, _reply(0.3, 0.41, rate=1e6 / 0.06))
    assert d.r0(0.41) == pytest.approx(0.11) and d.depth(0.41) == 3
    return d


def test_a_robot_whose_detector_stalls_it_detects_only_what_the_edge_cannot_finish_in_time() -> None:
    """Under a CPU quota a local detection of 20 ms CPU takes 100 ms: the whole robot process,
    frame sender included, waits 80 ms with it and delays the frames after it. Such a detector
    takes only the frames the edge cannot finish in time; one that does not stall the robot is a
    second server whenever it finishes sooner."""
    t = 0.5
    queued = {"edge_sends": ((t - 0.01, 1e6), (t - 0.005, 1e6)), "in_flight": 2}
    d = _stalling(cpu=0.02)
    assert d.stall(0.0) == pytest.approx(0.08)
    # two frames just sent, the local detector would finish sooner: the edge takes the frame
    assert d.decide(_st(now=t, capture=t, **queued)) == EDGE
    # the edge path's window full, the edge would still finish a frame in time: skipped, not local
    # (without the overflow rule, below)
    full = tuple((t - 0.01 + 0.001 * k, 1e6) for k in range(4))
    d.overflow = False
    assert d.decide(_st(now=t, capture=t, edge_sends=full, in_flight=4)) == SKIP
    # the edge stopped answering: the local detector takes the frames
    d.on_edge_timeout(0.5)
    assert d.decide(_st(now=t + 0.01, capture=t + 0.01)) in (LOCAL, BOTH)
    # the same set-up with a detector that does not stall the robot: local, being sooner
    d = _stalling(cpu=0.1)
    assert d.stall(0.0) == 0.0
    assert d.decide(_st(now=t, capture=t, **queued)) == LOCAL
    # a stalling detector idle for a few seconds: its slow measurement has faded, it is used again
    d = _stalling(cpu=0.02)
    assert d.decide(_st(now=t, capture=t, **queued)) == EDGE  # (the detector's last result timed here)
    assert d.local_time(t + 5.0) == pytest.approx(0.02, abs=0.005)
    assert d.decide(_st(now=t + 5.0, capture=t + 5.0)) in (LOCAL, BOTH)


def test_a_stalling_detector_takes_spaced_frames_the_full_edge_path_cannot() -> None:
    """The edge path at its depth, the edge still in time: a stalling detector takes the frame
    (the edge would drop one of its frames: it serves the newest) when its last frame started
    ``overflow_gap`` ago or more, else the frame is a spare or skipped. The gap grows while such
    detections stall the robot (wall time beyond CPU time by half a camera period) and shrinks
    while they do not."""
    def full(now: float, n: int = 4) -> dict[str, object]:  # n frames just sent
        sends = tuple((now - 0.01 + 0.001 * k, 1e6) for k in range(n))
        return {"now": now, "capture": now, "edge_sends": sends, "in_flight": n}

    t = 0.5
    d = _stalling(cpu=0.02)
    # 0.4 s at first; the two detections _stalling measured stalled the robot: 0.9 s now
    assert d.overflow and d.overflow_gap == pytest.approx(0.4 * 1.5 ** 2)
    assert d.depth(t) == 3  # (four in flight: the window's spare among them)
    # a camera at 25 Hz, the edge path always full: a frame to the robot every 0.9 s, the others
    # skipped (the window is full, so no spare either); the detector busy 100 ms a frame
    started, sides = -math.inf, []
    for k in range(40):
        now = t + 0.04 * k
        side = d.decide(_st(**full(now), local_last_start=started, local_busy=now < started + 0.1))
        sides.append(side)
        if side == LOCAL:
            started = now
    ks = [k for k, side in enumerate(sides) if side == LOCAL]
    assert ks[0] == 0 and len(ks) == 2 and 23 <= ks[1] <= 24  # 0.9 s apart
    assert set(sides) == {LOCAL, SKIP} and d.overflows == 2
    # in its depth the edge path takes the frame, as before: the rule is only for what it cannot
    assert _stalling(cpu=0.02).decide(_st(**full(t, 2))) == EDGE
    # a detection that stalled the robot (100 ms of wall for 20 ms of CPU) spaces them more ...
    gap = d.overflow_gap
    d.on_local_result(0.1, service=0.1, cpu=0.02)
    assert d.overflow_gap == pytest.approx(1.5 * gap)
    for _ in range(20):
        d.on_local_result(0.1, service=0.1, cpu=0.02)
    assert d.overflow_gap == pytest.approx(2.0)  # at most
    # ... one that did not (a full core, or the quota's room), less, down to 0.1 s
    for _ in range(60):
        d.on_local_result(0.03, service=0.03, cpu=0.02)
    assert d.overflow_gap == pytest.approx(0.1)
    # off: the frame is skipped, as before the rule
    d = _stalling(cpu=0.02)
    d.overflow = False
    assert d.decide(_st(**full(t))) == SKIP and d.overflows == 0


def test_fallbacks_back_to_back_detections_leave_the_overflow_spacing_alone() -> None:
    """With the edge gone the detector takes frame after frame; those detections stall the robot
    but say nothing about spaced ones, so the spacing stays what the edge-time detections made it
    (before: a one-second outage pushed it to its 2 s ceiling). A detection busy or a frame
    waiting for it takes no overflow frame."""
    def full(now: float) -> dict[str, object]:
        return {"now": now, "capture": now, "in_flight": 4,
                "edge_sends": tuple((now - 0.01 + 0.001 * k, 1e6) for k in range(4))}

    d = _stalling(cpu=0.02)
    gap = d.overflow_gap
    assert gap < 2.0
    for k in range(25):  # one second with the edge gone: every frame local, each stalling
        t = 1.0 + 0.04 * k
        assert d.decide(_st(now=t, capture=t, edge_available=False)) == LOCAL
        d.on_local_result(0.1, service=0.1, cpu=0.02, capture=t)
    assert d.overflow_gap == pytest.approx(gap)
    # a blocked edge (a frame unanswered) is fallback too, its copies to the edge included; its
    # detection still running when the edge path is full again and the next frame goes local
    d.blocked = True
    assert d.decide(_st(now=2.1, capture=2.1)) in (LOCAL, BOTH)
    d.blocked = False
    # the edge back and its path full: a frame waiting for the detector, or one being detected,
    # takes no overflow frame; a free detector does
    later = 2.2 + gap
    assert d.decide(_st(**full(later), local_last_start=2.1, local_waiting=True)) == SKIP
    assert d.decide(_st(**full(later), local_last_start=2.1, local_busy=True)) == SKIP
    assert d.decide(_st(**full(later), local_last_start=2.1)) == LOCAL and d.overflows == 1
    # each answer is judged by its own frame's decision: the blocked edge's one trains nothing,
    # the overflow frame's (stalling) spaces them more
    d.on_local_result(0.1, service=0.1, cpu=0.02, capture=2.1)
    assert d.overflow_gap == pytest.approx(gap)
    d.on_local_result(0.1, service=0.1, cpu=0.02, capture=later)
    assert d.overflow_gap == pytest.approx(min(2.0, 1.5 * gap))
    assert not d._gap_trains  # both answered: nothing kept
    # a robot that starts with no edge: its first frames, which measure the detector, are
    # fallback's too; an answer whose frame's decision is not kept trains nothing
    d = make_strategy("dispatch", local_bias=0.0)
    assert isinstance(d, Dispatcher)
    for k in range(4):
        assert d.decide(_st(now=0.04 * k, capture=0.04 * k, edge_available=False)) == LOCAL
        d.on_local_result(0.1, service=0.1, cpu=0.02, capture=0.04 * k)
    d.on_local_result(0.1, service=0.1, cpu=0.02, capture=9.0)
    assert d.overflow_gap == pytest.approx(0.4)


def test_dispatch_is_the_default_and_takes_its_settings() -> None:
    from zoffload.runtime.config import PerceptionSettings

    p = PerceptionSettings()
    assert p.strategy == "dispatch"
    d = make_strategy(p.strategy, max_in_flight=p.max_in_flight, max_age=p.max_age, local_bias=p.local_bias,
                      refresh_period=p.refresh_period, retry_period=p.retry_period, cpu_share=p.cpu_share,
                      overflow=p.overflow)
    assert isinstance(d, Dispatcher) and d.max_age == p.max_age and d.overflow is p.overflow is True
    assert d.window == p.max_in_flight and d.retry_period == p.retry_period
    with pytest.raises(ValueError, match="dispatch"):
        make_strategy("fastest")


def test_a_delivered_rate_slower_than_a_lone_frame_does_not_hold_the_edge() -> None:
    """One delivered-rate sample far too low (0.7 MB/s for 0.5 MB frames: 0.7 s each at the
    bottleneck), while frames sent alone take 90 ms end to end: the bottleneck cannot take longer
    than a lone frame's whole way, so the edge still takes a fresh frame. (Uncapped, the edge
    looked too slow for any fresh frame, frames went one at a time, which gives no new rate
    sample, and one run stayed so to its end: 113 edge frames of 1,250.)"""
    d = Dispatcher()
    d.on_local_result(0.15, service=0.15, cpu=0.03)
    d.on_local_result(0.15, service=0.15, cpu=0.03)
    for k in range(3):  # answers to frames sent alone: 90 ms, 50 of them the edge's
        d.on_edge_result(0.09, EdgeReply(sent=k, result=k + 0.09, bytes=5e5, service=0.05, alone=True))
    d.on_edge_result(0.09, EdgeReply(sent=3.0, result=3.09, bytes=5e5, service=0.05, delivery_rate=7e5))
    assert d.delivered.median(3.2) == 7e5 and d.r0(3.2) == pytest.approx(0.09)
    assert d.bottleneck(5e5, 3.2) == pytest.approx(0.09)
    st = OffloadState(now=3.2, edge_available=True, capture=3.2, local_busy=True, local_busy_for=0.0)
    assert d.decide(st) == EDGE and d.estimates[1] - 3.2 < 0.2


def test_a_frame_the_edge_replaced_with_a_newer_one_is_not_a_loss() -> None:
    """The edge keeps two waiting frames per robot and answers the older ``dropped`` when a newer
    one comes, serving the newer: no loss, and the window of frames in flight stays. An error
    is a loss."""
    d = _measured()
    window = d.window
    d.on_edge_refused(EdgeReply(sent=1.0, result=1.01, bytes=1e6, service=math.nan, status="dropped"), 0.5)
    assert d.window == window and d.losses.value == 0.0 and not d.blocked
    d.on_edge_refused(EdgeReply(sent=1.0, result=1.02, bytes=1e6, service=math.nan, status="error"), 0.5)
    assert d.losses.value > 0.0
