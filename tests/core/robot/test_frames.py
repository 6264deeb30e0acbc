"""The camera pipeline's bookkeeping and fallback state machine, driven by hand: no threads, no
clock, no Zenoh, no model files."""

from __future__ import annotations

import math

import numpy as np
import pytest

from zoffload.policy.offload import (
    BOTH,
    EDGE,
    HOLD,
    LOCAL,
    SKIP,
    DeliveryAwareDynamic,
    EdgeOnly,
    EdgeReply,
    FixedRatio,
    OffloadState,
    RobotOnly,
    Strategy,
)
from zoffload.robot.frames import DONE, DROPPED, FallbackRules, FrameBook, RobotView

RULES = FallbackRules(reply_timeout=0.5, fallback_losses=3, probe_period=0.5, resume_after=3)
NONE = (np.zeros((0, 4), np.float32), np.zeros(0, np.float32))
ONE = (np.array([[1, 2, 3, 4]], np.float32), np.array([0.9], np.float32))


def book(strategy: Strategy | None = None) -> FrameBook:
    b = FrameBook(strategy or EdgeOnly(), RULES)
    b.edges_changed(True, 0.0)
    return b


def test_every_frame_ends_in_exactly_one_bucket() -> None:
    b = book(FixedRatio(ratio=0.5))
    t = 0.0
    sides = []
    for seq in range(8):
        t += 0.04
        side, probe = b.decide(seq, seq, capture=t, now=t)
        assert not probe
        sides.append(side)
        if side == EDGE:
            b.sent(seq, t, probe)
    assert sides.count(EDGE) == 4 and sides.count(LOCAL) == 4  # algorithm 1 alternates
    edge = [s for s, side in zip(range(8), sides, strict=True) if side == EDGE]
    local = [s for s, side in zip(range(8), sides, strict=True) if side == LOCAL]
    assert b.edge_result(edge[0], "ok", t + 0.1, 0.05, 0.01, *ONE) == "edge_done"
    assert b.edge_result(edge[1], "dropped", t + 0.1, float("nan"), float("nan"), *NONE) == "edge_dropped"
    b.send_replaced(edge[2])  # a newer frame took the sender's slot
    b.local_result(local[0], t + 0.1, service=0.02, infer_time=0.02, boxes=ONE[0], scores=ONE[1])
    b.local_replaced(local[1])  # a newer frame took the local detector's slot
    b.failed(local[2])  # undecodable
    assert b.edge_result(99, "ok", t, 0.0, 0.0, *NONE) == "unknown"  # never sent: counted, no bucket
    bal = b.balance()
    assert bal["pending"] == 2 and b.balanced()  # edge[3] in flight, local[3] still detecting
    lost = b.expire(t + 1.0)
    assert lost == [edge[3]] and b.records[edge[3]]["status"] == "edge_lost"
    b.close(t + 1.0, send_waiting=None, local_waiting=local[3])
    bal = b.balance()
    assert bal["pending"] == 0 and b.balanced()
    assert bal["frames_in"] == 8 == sum(bal[k] for k in (*DONE, *DROPPED))
    b.camera_dropped(2, unreadable=1)  # two replaced by newer ones, one its source could not read
    bal = b.balance()
    assert bal["frames_in"] == 11 and bal["dropped_camera"] == 2 and bal["dropped_unreadable"] == 1
    assert b.balanced()
    assert b.counters["late_or_unknown_results"] == 1
    assert b.records[edge[0]]["n_persons"] == 1 and b.persons[local[0]][1][0] == pytest.approx(0.9)
    # a result after its frame was booked lost is late: counted, the bucket stays
    assert b.edge_result(edge[3], "ok", t + 1.1, 0.05, 0.0, *NONE) == "unknown"
    assert b.records[edge[3]]["status"] == "edge_lost" and b.balanced()


def test_edge_liveliness_loss_books_in_flight_lost_and_falls_back_then_probes_resume() -> None:
    b = book()
    for seq in range(3):
        side, _ = b.decide(seq, seq, capture=0.1 * seq, now=0.1 * seq)
        b.sent(seq, 0.1 * seq, False)
    b.edges_changed(False, 0.25)
    assert b.fallback and len(b.fallback_events) == 1
    assert all(b.records[s]["status"] == "edge_lost" for s in range(3)) and not b.in_flight
    # no edge: every frame local, no probe
    side, probe = b.decide(3, 3, capture=0.3, now=0.3)
    assert (side, probe) == (LOCAL, False)
    # the edge is back: one probe per probe_period, and only with nothing in flight
    b.edges_changed(True, 1.0)
    seq, now, resumed_at = 4, 1.0, None
    probes = []
    while now < 5.0 and resumed_at is None:
        side, probe = b.decide(seq, seq, capture=now, now=now)
        if probe:
            probes.append(now)
            assert side == EDGE
            b.sent(seq, now, True)
            b.edge_result(seq, "ok", now + 0.1, 0.05, 0.0, *NONE)  # a prompt answer
            if not b.fallback:
                resumed_at = now
        else:
            assert side == LOCAL  # in fallback everything else stays local
        seq += 1
        now += 0.04
    assert resumed_at is not None and len(probes) == RULES.resume_after
    assert all(b2 - a >= RULES.probe_period - 1e-9 for a, b2 in zip(probes, probes[1:], strict=False))
    assert b.fallback_events[0]["end"] == pytest.approx(resumed_at + 0.1)
    side, probe = b.decide(seq, seq, capture=now, now=now)
    assert (side, probe) == (EDGE, False)  # offloading again


def test_a_slow_probe_answer_does_not_count_towards_resuming() -> None:
    b = book()
    b.edges_changed(False, 0.0)
    b.edges_changed(True, 0.0)
    now = 1.0
    for i in range(6):
        side, probe = b.decide(i, i, capture=now, now=now)
        assert probe
        b.sent(i, now, True)
        late = i == 2  # the third answer is slower than the reply timeout
        b.edge_result(i, "ok", now + (0.7 if late else 0.1), 0.05, 0.0, *NONE)
        now += 1.0
        if i < 4:
            assert b.fallback, i  # streak 1, 2, reset by the slow one, 1, 2
    assert not b.fallback  # 3 prompt answers after the slow one


def test_losses_in_a_row_from_a_silent_edge_mean_fallback_one_loss_does_not() -> None:
    b = book()
    # one frame lost while the edge answers others: the link's loss, not a dead edge
    for seq in range(3):
        b.decide(seq, seq, capture=0.0, now=0.0)
        b.sent(seq, 0.0, False)
    b.edge_result(1, "ok", 0.2, 0.05, 0.0, *NONE)
    b.edge_result(2, "ok", 0.2, 0.05, 0.0, *NONE)
    assert b.expire(0.6) == [0] and not b.fallback
    # three in a row unanswered and nothing heard for a whole timeout: the edge is gone
    for seq in range(3, 6):
        b.decide(seq, seq, capture=1.0, now=1.0)
        b.sent(seq, 1.0, False)
    assert b.expire(1.4) == [] and not b.fallback
    assert b.expire(1.6) == [3, 4, 5] and b.fallback
    assert b.counters["fallbacks"] == 1 and b.balanced()


def test_robot_only_never_probes_and_held_frames_are_dropped_window() -> None:
    b = book(RobotOnly())
    b.edges_changed(False, 0.0)
    b.edges_changed(True, 0.0)
    for i in range(30):
        side, probe = b.decide(i, i, capture=i * 0.1, now=i * 0.1)
        assert side == LOCAL and not probe
    # our rule holds frames back when its window is full and local is slower
    d = DeliveryAwareDynamic(max_in_flight=2)
    b = book(d)
    d.on_local_result(0.3, service=0.3)
    d.on_edge_result(0.1)
    for seq in range(2):
        side, _ = b.decide(seq, seq, capture=0.0, now=0.0)
        assert side == EDGE
        b.sent(seq, 0.0, False)
    side, _ = b.decide(2, 2, capture=0.01, now=0.01)
    assert side == HOLD and b.records[2]["status"] == "dropped_window" and b.balanced()


class Scripted(Strategy):
    """Returns the given sides in turn and records what it was told."""

    def __init__(self, sides: list[str]) -> None:
        super().__init__(name="scripted")
        self.sides = list(sides)
        self.states: list[OffloadState] = []
        self.replies: list[EdgeReply] = []
        self.timeouts: list[float] = []
        self.seen: list[tuple[int, str, int]] = []  # (frame, side, persons) of every answer
        self.broken = False  # observe raises

    def observe(self, seq: int, side: str, boxes: np.ndarray, scores: np.ndarray,
                capture: float = math.nan) -> None:
        if self.broken:
            raise RuntimeError("broken")
        self.seen.append((seq, side, len(scores)))

    def choose(self, st: OffloadState) -> str:
        self.states.append(st)
        return self.sides.pop(0)

    def on_edge_result(self, rtt: float, reply: EdgeReply | None = None) -> None:
        assert reply is not None
        self.replies.append(reply)

    def on_edge_refused(self, reply: EdgeReply, penalty: float) -> None:
        self.replies.append(reply)

    def on_edge_timeout(self, waited: float) -> None:
        self.timeouts.append(waited)


def test_skipped_frames_and_copies_each_end_in_one_bucket() -> None:
    s = Scripted([SKIP, BOTH, BOTH, BOTH, EDGE])
    b = book(s)
    for seq in range(5):
        side, _ = b.decide(seq, seq, capture=0.1 * seq, now=0.1 * seq)
        if side == BOTH:  # detected locally, and a copy measures the edge
            b.sent(seq, 0.1 * seq, False, copy=True)
        elif side == EDGE:
            b.sent(seq, 0.1 * seq, False)
    assert b.records[0]["status"] == "skipped" and b.records[0]["side"] == SKIP
    assert all(b.records[k]["side"] == LOCAL and b.records[k]["copy"] == 1 for k in (1, 2, 3))
    # the copy's answer is an observation: the frame's bucket is its local result
    b.records[1]["bytes"] = 1000
    assert b.edge_result(1, "ok", 0.2, 0.05, 0.0, *ONE) == "copy"
    assert s.replies[-1].sent == pytest.approx(0.1) and s.replies[-1].bytes == 1000
    assert b.records[1]["status"] == "pending" and b.waiting_to_send(2) and not b.waiting_to_send(1)
    b.local_result(1, 0.25, service=0.02, infer_time=0.02, boxes=ONE[0], scores=ONE[1], cpu=0.02)
    assert b.records[1]["status"] == "local_done" and b.records[1]["copy_rtt_ms"] == pytest.approx(100)
    # a copy replaced in the sender's slot, or never answered, costs its frame nothing
    b.send_replaced(2)
    assert b.counters["copies_replaced"] == 1 and b.records[2]["status"] == "pending"
    assert b.expire(1.0) == [4] and b.counters["copies_lost"] == 1 and len(s.timeouts) == 2
    assert b.records[3]["status"] == "pending" and not b.copies
    for seq in (2, 3):
        b.local_result(seq, 1.0, service=0.02, infer_time=0.02, boxes=NONE[0], scores=NONE[1])
    bal = b.balance()
    assert b.balanced() and bal["pending"] == 0 and bal["skipped"] == 1 and bal["local_done"] == 3
    assert bal["edge_lost"] == 1 and bal["frames_in"] == 5
    assert b.counters["copies_answered"] == 1
    # every answer's detections reach the strategy (the copy's too: the edge's view of that frame)
    assert s.seen == [(1, EDGE, len(ONE[1])), (1, LOCAL, len(ONE[1])), (2, LOCAL, 0), (3, LOCAL, 0)]


def test_a_strategy_that_fails_on_detections_costs_the_frame_nothing() -> None:
    s = Scripted([EDGE, LOCAL])
    s.broken = True
    b = book(s)
    for seq, side in enumerate((EDGE, LOCAL)):
        assert b.decide(seq, seq, capture=0.1 * seq, now=0.1 * seq)[0] == side
    b.sent(0, 0.0, False)
    assert b.edge_result(0, "ok", 0.2, 0.05, 0.0, *ONE) == "edge_done"
    b.local_result(1, 0.3, service=0.02, infer_time=0.02, boxes=ONE[0], scores=ONE[1])
    assert b.records[0]["status"] == "edge_done" and b.records[1]["status"] == "local_done"
    assert b.counters["observe_errors"] == 2 and b.balanced() and len(s.replies) == 1


def test_the_strategy_sees_the_frames_in_flight_and_the_robot_side() -> None:
    s = Scripted([EDGE, EDGE, LOCAL, EDGE])
    b = book(s)
    for seq in range(2):
        b.decide(seq, seq, capture=0.04 * seq, now=0.04 * seq)
        b.sent(seq, 0.04 * seq, False)
        b.records[seq]["bytes"] = 1e6
    view = RobotView(local_busy=True, local_busy_for=0.01, local_waiting=True, send_waiting=True,
                     cpu_time=1.5, local_cpu_time=0.5, cpu_quota=0.25, local_last_start=0.07)
    b.decide(2, 2, capture=0.08, now=0.09, robot=view)
    st = s.states[-1]
    assert st.edge_sends == ((0.0, 1e6), (0.04, 1e6)) and st.in_flight == 2 and st.capture == 0.08
    assert st.local_busy and st.local_waiting and st.send_waiting and st.cpu_quota == 0.25
    assert st.cpu_time == 1.5 and st.local_cpu_time == 0.5 and st.local_last_start == 0.07
    # answers: the second was queued behind the first, so their gap is a delivery-rate sample
    b.edge_result(0, "ok", 0.10, 0.04, 0.0, *NONE)
    b.edge_result(1, "ok", 0.15, 0.04, 0.01, *NONE)
    first, second = s.replies
    assert math.isnan(first.delivery_rate) and second.delivery_rate == pytest.approx(1e6 / 0.05)
    assert second.service == pytest.approx(0.04) and second.sent == pytest.approx(0.04)
    assert second.edge_queue == pytest.approx(0.01)  # the edge's wait, as it reported it
    # the first went with nothing else unanswered: its answer time is the path's base; the second
    # went behind it
    assert first.alone and not second.alone
    assert b.records[0]["alone"] == 1 and b.records[1]["alone"] == 0
    # an edge frame the edge dropped from its queue is seen as refused, with no rate sample
    b.decide(3, 3, capture=0.2, now=0.2)
    b.sent(3, 0.2, False)
    assert b.edge_result(3, "dropped", 0.21, float("nan"), float("nan"), *NONE) == "edge_dropped"
    assert s.replies[-1].status == "dropped" and math.isnan(s.replies[-1].delivery_rate)


def test_a_frame_is_sent_alone_only_with_nothing_unanswered_and_no_loss_since_the_last_answer() -> None:
    """A frame booked lost may still be in the sender or on the link: the next one is not sent
    alone (its answer would hold that wait) until an answer came; a trial frame's bytes are not the
    others', so its answer is no base either."""
    s = Scripted([EDGE] * 6)
    b = book(s)
    b.decide(0, 0, capture=0.0, now=0.0)
    b.sent(0, 0.0, False)
    assert b.expire(0.6) == [0]  # unanswered for the 0.5 s timeout: lost
    b.decide(1, 1, capture=0.6, now=0.6)
    b.sent(1, 0.6, False)  # nothing in flight, but the lost frame may still be on the link
    assert b.records[1]["alone"] == 0
    b.edge_result(1, "ok", 0.7, 0.04, 0.0, *NONE)
    b.decide(2, 2, capture=0.72, now=0.72)
    b.sent(2, 0.72, False)  # an answer since the loss: the path is clear
    assert b.records[2]["alone"] == 1
    b.records[2]["trial"] = 1  # the sender made it a trial of raw frames
    b.edge_result(2, "ok", 0.8, 0.04, 0.0, *NONE)
    assert not s.replies[-1].alone


def test_a_frame_booked_lost_while_it_waits_for_the_link_is_not_booked_again() -> None:
    # Seen in the held-out sweep (mmWave link, dispatch): a blockage made the edge's token go, the
    # frame waiting in the sender's slot was booked lost with the others in flight, and when a newer
    # frame took the slot it was booked again as dropped_send: 1251 buckets for 1250 frames.
    b = book()
    for seq in range(3):
        b.decide(seq, seq, capture=0.1 * seq, now=0.1 * seq)
        b.sent(seq, 0.1 * seq, False)
    b.edges_changed(False, 0.25)  # every frame in flight, the one in the slot too, booked lost
    b.send_replaced(2)  # the slot's frame replaced afterwards
    b.send_failed(1, 0.3)  # an encoding failure reported after the loss
    bal = b.balance()
    assert bal["edge_lost"] == 3 and bal["dropped_send"] == 0 and bal["error"] == 0
    assert b.balanced() and b.counters["rebooked"] == 0
    # expiry while the link was blocked: the same
    b2 = book()
    b2.decide(0, 0, capture=0.0, now=0.0)
    b2.sent(0, 0.0, False)
    assert b2.expire(1.0) == [0]
    b2.send_replaced(0)
    assert b2.balance()["edge_lost"] == 1 and b2.balance()["dropped_send"] == 0 and b2.balanced()


def test_finish_never_books_a_frame_twice() -> None:
    b = book(RobotOnly())
    b.decide(0, 0, capture=0.0, now=0.0)
    b.local_result(0, 0.05, service=0.05, infer_time=0.05, boxes=ONE[0], scores=ONE[1])
    b.finish(0, "dropped_stale")  # a path that forgot to check
    assert b.records[0]["status"] == "local_done" and b.counters["rebooked"] == 1
    assert b.balanced() and b.summary()["other"]["rebooked"] == 1


def test_a_frame_put_after_the_previous_one_reached_the_edge_is_no_link_sample() -> None:
    """Handed to the sender before the previous frame reached the edge, but put after it (the robot
    stalled between the two): the gap between the answers holds the stall, not the link's time."""
    s = Scripted([EDGE, EDGE, EDGE])
    b = book(s)
    for seq in range(3):
        b.decide(seq, seq, capture=0.04 * seq, now=0.04 * seq)
        b.sent(seq, 0.04 * seq, False)
        b.records[seq].update(bytes=1e6, put=0.04 * seq)
    b.records[1]["put"] = 0.09  # the stall: frame 0 reached the edge at 0.10 - 0.05 = 0.05
    b.edge_result(0, "ok", 0.10, 0.05, 0.0, *NONE)
    b.edge_result(1, "ok", 0.20, 0.05, 0.0, *NONE)
    assert math.isnan(s.replies[-1].delivery_rate)
    # frame 2 was put at 0.08, before frame 1 reached the edge (0.15): a sample of the link
    b.edge_result(2, "ok", 0.26, 0.05, 0.01, *NONE)
    assert s.replies[-1].delivery_rate == pytest.approx(1e6 / 0.06)
