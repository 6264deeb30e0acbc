from __future__ import annotations

import math

import numpy as np
import pytest

from zoffload.protocol import wire
from zoffload.robot.ledger import FLOOR_SPAN, ScanLedger


def ack(seq: int, stamp: float, status: str = "ok", t: float = 0.1) -> wire.ScanAck:
    return wire.ScanAck(robot="r", seq=seq, send_stamp=stamp, status=status, interarrival=t,
                        queue_time=0.001, proc_time=0.02, icp_time=0.015, map_points=10 * seq, keypoints=5,
                        sigma=0.3, pose=np.eye(4))


def test_every_bucket_and_the_balance() -> None:
    led = ScanLedger()
    for seq in range(8):
        led.produced()
        if seq == 7:
            led.drop_at_source(seq, "edge_absent")
            continue
        led.published(seq, send_stamp=100.0 + seq, record={"n_raw": 10})
    assert led.balanced() and led.in_flight == 7
    assert led.on_ack(ack(0, 100.0), recv_stamp=100.05) == "acked"
    assert led.on_ack(ack(1, 101.0, "dropped"), 101.01) == "edge_dropped"
    assert led.on_ack(ack(2, 102.0, "error"), 102.01) == "edge_error"
    assert led.balanced()
    # seq 3 and 4 time out; 3's ack then arrives late
    assert led.expire(now=105.5, timeout=1.0) == 2
    assert led.records[4]["status"] == "lost"
    assert led.on_ack(ack(3, 103.0), 105.6) == "late"
    assert led.records[3]["late_status"] == "ok"  # what the edge said, late
    assert led.on_ack(ack(0, 100.0), 105.7) == "duplicate"
    assert led.on_ack(ack(99, 1.0), 105.7) == "unknown"
    assert led.on_ack(ack(5, 999.0), 105.7) == "unknown"  # stamp does not match what was sent
    led.finish()
    b = led.balance()
    assert b == {"produced": 8, "published": 7, "dropped_source": 1, "sending": 0, "local": 0, "acked": 1,
                 "edge_dropped": 1, "edge_error": 1, "edge_refused": 0, "lost": 3, "late": 1, "in_flight": 0}
    assert led.balanced()


def test_rtt_is_robot_clock_and_network_time_excludes_edge_time() -> None:
    led = ScanLedger()
    led.produced()
    led.published(0, send_stamp=50.0, record={})
    led.on_ack(ack(0, 50.0, t=0.12), recv_stamp=50.2)
    rec = led.records[0]
    assert abs(rec["rtt"] - 0.2) < 1e-9
    assert abs(rec["network_time"] - (0.2 - 0.021)) < 1e-9
    assert led.last_interarrival == 0.12 and led.interarrivals_seen == 1


def test_refused_scans_their_own_bucket_and_scans_with_the_sender_in_theirs() -> None:
    led = ScanLedger()
    for seq in range(4):
        led.produced()
        led.handed_off(seq, {"n_raw": 10})
    assert led.balance()["sending"] == 4 and led.balanced()
    led.drop_at_source(1, "replaced")  # the sender's slot took a newer scan
    led.published(0, 10.0, {"bytes": 100})
    led.published(2, 10.1, {"bytes": 100})
    assert led.records[0]["n_raw"] == 10 and led.records[1]["status"] == "source:replaced"
    assert led.on_ack(ack(0, 10.0, "refused"), 10.05) == "edge_refused"
    assert led.on_ack(ack(2, 10.1), 10.15) == "acked"
    led.finish()  # scan 3 never left: unsent
    b = led.balance()
    assert b["edge_refused"] == 1 and b["sending"] == 0 and led.dropped_source["unsent"] == 1
    assert led.balanced()


def test_the_link_figures_the_policy_reads() -> None:
    led = ScanLedger()
    for seq in range(30):
        led.produced()
        led.published(seq, 100.0 + 0.1 * seq, {"bytes": 1000, "skipped": 1 if seq == 29 else 0})
        led.on_ack(ack(seq, 100.0 + 0.1 * seq, t=0.2 if seq == 29 else 0.1), 100.05 + 0.1 * seq)
    assert len(led.recent) == 24 and led.recent[-1].slot == 2 and led.last_slot == 2
    assert led.recent[-1].net == pytest.approx(0.05 - 0.021)
    assert led.acked_bytes_per_s(103.0) == 10 * 1000  # acks of the last second
    assert math.isnan(ScanLedger().acked_bytes_per_s(1.0))  # nothing acked yet: no rate
    assert led.last_ack_at == pytest.approx(102.95)
    # the link's rate, a lower bound: the most bytes an acked scan carried per second of network time
    assert led.carried_rate() == pytest.approx(1000 / (0.05 - 0.021))
    assert ScanLedger().carried_rate() == 0.0
    led.published(30, 103.0, {"bytes": 4000})
    led.on_ack(ack(30, 103.0), 103.035)
    assert led.carried_rate() == pytest.approx(4000 / (0.035 - 0.021))


def test_local_scans_are_a_terminal_bucket_and_catch_up_poses_keep_their_bucket() -> None:
    led = ScanLedger()
    for seq in range(6):
        led.produced()
        if seq < 3:
            led.published(seq, send_stamp=10.0 + seq, record={"edge": "e1", "epoch": 5})
        else:  # no edge mapped the robot: registered on it
            led.local(seq, {"n_raw": 10}, np.eye(4) * seq)
    assert led.on_ack(ack(0, 10.0), 10.05) == "acked"
    assert led.records[0]["pose_source"] == "edge"
    assert led.local_pose(1, np.eye(4)) and led.records[1]["pose_source"] == "local"
    assert not led.local_pose(0, np.eye(4)) and not led.local_pose(99, np.eye(4))
    led.finish()
    b = led.balance()
    assert b["local"] == 3 and b["acked"] == 1 and b["lost"] == 2 and led.balanced()
    assert led.records[4]["status"] == "local" and led.records[4]["pose_source"] == "local"
    assert sorted(led.poses) == [0, 1, 3, 4, 5]
    led.counters["local"] += 1  # a scan booked twice would show
    assert not led.balanced()


def test_a_scan_lost_while_later_ones_were_answered_is_counted_as_overtaken() -> None:
    # The edge answers a robot's scans in order, one answer each: a scan unanswered while a later
    # one sent the same way was answered never reached the edge (or its answer got lost)
    led = ScanLedger()
    for seq in range(6):
        led.produced()
        edge, epoch = ("e1", 1) if seq < 4 else ("e2", 2)
        led.published(seq, send_stamp=100.0 + seq, record={"edge": edge, "epoch": epoch})
    assert led.on_ack(ack(0, 100.0), 100.1) == "acked"
    assert led.on_ack(ack(2, 102.0), 102.1) == "acked"  # 1 overtaken by 2 on e1
    # 3 is e1's newest: unanswered because e1 went, not overtaken; 4 and 5 went to e2, unanswered
    assert led.expire(now=110.0, timeout=1.0) == 4
    assert led.counters["lost"] == 4 and led.counters["lost_overtaken"] == 1
    # an answer after all (late): no longer lost, nor overtaken
    assert led.on_ack(ack(1, 101.0), 110.1) == "late"
    assert led.counters["lost"] == 3 and led.counters["lost_overtaken"] == 0
    assert led.balanced()
    # a later scan on e2 answered: what e2 left unanswered before it was overtaken
    led2 = ScanLedger()
    for seq in range(3):
        led2.produced()
        led2.published(seq, send_stamp=100.0 + seq, record={"edge": "e2", "epoch": 2})
    assert led2.on_ack(ack(2, 102.0), 102.1) == "acked"
    assert led2.expire(now=110.0, timeout=1.0) == 2 and led2.counters["lost_overtaken"] == 2


def edge_ack(seq: int, stamp: float, queue: float, proc: float, status: str = "ok") -> wire.ScanAck:
    return wire.ScanAck(robot="r", seq=seq, send_stamp=stamp, status=status, interarrival=0.1,
                        queue_time=queue, proc_time=proc, icp_time=proc, map_points=1, keypoints=1,
                        sigma=0.3, pose=np.eye(4))


def acked_with(led: ScanLedger, times: list[tuple[float, float]], status: str = "ok") -> None:
    for queue, proc in times:
        seq = len(led.records)
        led.produced()
        led.published(seq, send_stamp=float(seq), record={})
        led.on_ack(edge_ack(seq, float(seq), queue, proc, status), recv_stamp=seq + 0.3)


def test_the_window_widens_by_the_edge_s_time_per_scan() -> None:
    led = ScanLedger()
    assert led.window(3, 0.1) == 3  # nothing measured yet
    acked_with(led, [(0.01, 0.02)] * 5)
    assert led.window(3, 0.1, path=False) == 3  # 30 ms at the edge: under half a period
    acked_with(led, [(0.03, 0.06)] * 6)  # 90 ms: the median moves to it
    assert led.window(3, 0.1, path=False) == 4
    assert led.window(0, 0.1) == 0  # no window stays no window
    acked_with(led, [(0.2, 0.1)] * 20)  # 300 ms, 3 periods
    assert led.window(3, 0.1, path=False) == 6 and led.window(2, 0.1, path=False) == 4  # at most doubled
    acked_with(led, [(5.0, 5.0)] * 20)  # an overloaded (or lying) edge gains no more
    assert led.window(3, 0.1, path=False) == 6
    assert led.window(3, 0.1, edge=False, path=False) == 3


def acked_after(led: ScanLedger, rtts: list[float], route: tuple[str, int] | None = None) -> None:
    """Scans sent a period apart, each answered ``rtt`` later by a quick edge (1 + 20 ms)."""
    for rtt in rtts:
        seq = len(led.records)
        led.produced()
        if route is not None:
            led.on_route(route, now=0.1 * seq)
        rec = {"edge": route[0], "epoch": route[1]} if route else {}
        led.handed_off(seq, rec)
        led.published(seq, send_stamp=0.1 * seq, record=rec)
        assert led.on_ack(edge_ack(seq, 0.1 * seq, 0.001, 0.02), recv_stamp=0.1 * seq + rtt) == "acked"


def test_a_long_path_widens_the_window_to_its_round_trip_and_a_queue_on_it_does_not() -> None:
    led = ScanLedger()
    acked_after(led, [0.55] * 4, route=("edgeA", 1))  # 250 ms each way + the edge
    assert led.window(3, 0.1) == 3  # four acks: not yet a measure of the path
    acked_after(led, [0.56], route=("edgeA", 1))
    assert led.window(3, 0.1) == 7  # 0.55 s: 5.5 periods, rounded up, plus one
    assert led.window(3, 0.1, path=False) == 3 and led.window(3, 0.2) == 4
    # a queue builds on the link: the round trips grow, the window does not follow them
    acked_after(led, [0.9, 1.2, 1.5, 1.8] * 10, route=("edgeA", 1))
    assert led.window(3, 0.1) == 7
    # a short path (cellular, 30-70 ms each way) changes nothing: at most 2 periods round trip
    short = ScanLedger()
    acked_after(short, [0.08, 0.19, 0.12, 0.15, 0.09, 0.3], route=("edgeA", 1))
    assert short.window(3, 0.1) == 3 and short.window(3, 0.1, edge=False) == 3
    # a move to another edge measures its path anew
    acked_after(led, [0.05] * 5, route=("edgeB", 2))
    assert led.route_acks == 5 and led.window(3, 0.1) == 3
    # a path of seconds (or an edge holding its acks) gains at most 8 x the base
    slow = ScanLedger()
    acked_after(slow, [3.0] * 6)
    assert slow.window(3, 0.1) == 24 and slow.window(2, 0.1) == 16


def test_late_acks_of_the_old_route_do_not_measure_the_new_path() -> None:
    led = ScanLedger()
    led.on_route(("edgeA", 1), now=0.0)
    for seq in range(6):
        led.produced()
        led.handed_off(seq, {"edge": "edgeA", "epoch": 1})
        led.published(seq, send_stamp=0.1 * seq, record={})
    led.on_route(("edgeB", 2), now=0.6)
    for seq in range(6):  # A answers after the move, 0.8 s after each scan
        assert led.on_ack(edge_ack(seq, 0.1 * seq, 0.001, 0.02), recv_stamp=0.1 * seq + 0.8) == "acked"
    assert led.route_acks == 0 and led.window(3, 0.1) == 3


def test_the_newest_network_time_counts_late_acks_and_only_the_current_route() -> None:
    """What the policy's queue stall reads: a queue deeper than the ack timeout shows only in late
    acks (``recent`` holds acked scans only)."""
    led = ScanLedger()
    acked_after(led, [0.6] * 9, route=("edgeA", 1))
    assert led.newest_net == pytest.approx(0.6 - 0.021) and math.isnan(led.floor_net)  # 9 acks
    acked_after(led, [0.7], route=("edgeA", 1))
    assert led.floor_net == pytest.approx(0.6 - 0.021)
    seq = len(led.records)
    led.produced()
    led.handed_off(seq, {"edge": "edgeA", "epoch": 1})
    led.published(seq, send_stamp=10.0, record={})
    led.expire(11.5, 1.0)  # the ack timeout: lost...
    assert led.on_ack(edge_ack(seq, 10.0, 0.001, 0.02), recv_stamp=13.0) == "late"  # ...it queued 3 s
    assert led.newest_net == pytest.approx(3.0 - 0.021) and len(led.recent) == 10  # (acked only)
    led.on_route(("edgeB", 2), now=13.1)  # a move: the old route's queue and floor are not the new one's
    assert math.isnan(led.newest_net) and math.isnan(led.floor_net) and not led.route_nets
    acked_after(led, [0.9], route=("edgeA", 1))  # (acks of the old route after a move do not count)
    led.on_route(("edgeB", 2), now=20.0)
    seq = len(led.records)
    led.produced()
    led.handed_off(seq, {"edge": "edgeA", "epoch": 1})
    led.published(seq, send_stamp=20.0, record={})
    led.on_ack(edge_ack(seq, 20.0, 0.001, 0.02), recv_stamp=22.0)
    assert math.isnan(led.newest_net)


def _sent(led: ScanLedger, stamp: float, route: tuple[str, int] = ("edgeA", 1)) -> int:
    seq = len(led.records)
    led.produced()
    led.handed_off(seq, {"edge": route[0], "epoch": route[1]})
    led.published(seq, send_stamp=stamp, record={})
    return seq


def test_the_floor_follows_a_path_whose_delay_rose_for_good() -> None:
    """The floor is the quickest network time over the ``FLOOR_SPAN`` seconds before the newest
    ack, late acks too: a base delay that rose 1.2 s (a handover) is the new floor that much later;
    taken from on-time acks of the last 100 it stayed the old one (every ack was late)."""
    led = ScanLedger()
    acked_after(led, [0.6] * 20, route=("edgeA", 1))
    assert led.floor_net == pytest.approx(0.6 - 0.021)
    t = 2.0
    while t < 2.0 + FLOOR_SPAN + 1.0:  # one scan per round trip, every one late
        seq = _sent(led, t)
        led.expire(t + 1.1, 1.0)
        assert led.on_ack(edge_ack(seq, t, 0.001, 0.02), recv_stamp=t + 1.8) == "late"
        if t + 1.8 < 2.0 + FLOOR_SPAN:
            assert led.floor_net == pytest.approx(0.6 - 0.021), t
        t += 0.5
    assert led.floor_net == pytest.approx(1.8 - 0.021) and led.newest_net == pytest.approx(1.8 - 0.021)


def test_a_path_rerouted_longer_gets_its_window_and_its_silence_counts_from_its_round_trip() -> None:
    """``path_rtt``: the quickest round trip, or the floor of the last ``FLOOR_SPAN`` seconds where
    that stands higher. A path 1.2 s longer for good (a satellite reroute, 0.6 s to 1.8 s) kept the
    window of 0.6 s (7 scans) and a silence was counted from the last ack, so the first scan sent
    after the window held some back read as a stall. A queue that drains once in ``FLOOR_SPAN``
    does not widen the window."""
    led = ScanLedger()
    acked_after(led, [0.6] * 20, route=("edgeA", 1))
    assert led.path_rtt == pytest.approx(0.6) and led.window(3, 0.1) == 7
    t = 2.0
    while t < 2.0 + FLOOR_SPAN + 2.0:  # the path is 1.8 s now, one scan a period, every one answered
        seq = _sent(led, t)
        assert led.on_ack(edge_ack(seq, t, 0.001, 0.02), recv_stamp=t + 1.8) == "acked"
        if t + 1.8 < 2.0 + FLOOR_SPAN:
            assert led.window(3, 0.1) == 7, t
        t += 0.1
    assert led.path_rtt == pytest.approx(1.8 - 0.021) and led.window(3, 0.1) == 19  # 17.8 periods
    assert led.window(3, 0.2) == 10 and led.window(2, 0.1) == 16  # (8.9 periods; at most 8 x 2)
    # the silence clock: the oldest scan in flight past the path's round trip
    assert led.overdue(t) == -math.inf  # nothing in flight
    _sent(led, t + 3.0)  # the first scan after 3 s without any (held back): no ack for 1.4 s
    assert led.since_answer(t + 3.1) == pytest.approx(1.4)
    assert led.overdue(t + 3.1) == pytest.approx(0.1 - 1.779)
    assert led.overdue(t + 5.3) == pytest.approx(2.3 - 1.779)  # no answer 2.3 s on: 0.52 s overdue
    # before the route's first answer the round trip is not known: the scan's age
    led.on_route(("edgeB", 2), now=30.0)
    _sent(led, 30.0, route=("edgeB", 2))
    assert led.overdue(30.4) == pytest.approx(0.4) and led.path_rtt == math.inf
    # a queue that drains now and then: the round trips swing, the floor stays the path's
    q = ScanLedger()
    acked_after(q, [0.3] * 10 + [0.9, 1.2, 1.5, 1.8, 0.3] * 40, route=("edgeA", 1))  # 20 s
    assert q.path_rtt == pytest.approx(0.3) and q.window(3, 0.1) == 4


def test_a_busy_edges_answers_are_not_a_network_time_and_expired_scans_still_queue() -> None:
    """``newest_net`` and the floor take scans the edge registered with both its times known (a
    "dropped" answer's round trip holds the edge's queue, not the link's); ``queued_here`` counts
    the route's scans after the newest answered one, the ack timeout's expired ones too, until a
    later answer shows them lost for good."""
    led = ScanLedger()
    acked_after(led, [0.6] * 10, route=("edgeA", 1))
    newest = led.newest_net
    seq = _sent(led, 5.0)
    dropped = edge_ack(seq, 5.0, math.nan, math.nan, status="dropped")
    assert led.on_ack(dropped, recv_stamp=8.0) == "edge_dropped"
    seq = _sent(led, 5.1)
    assert led.on_ack(edge_ack(seq, 5.1, 0.001, math.nan), recv_stamp=8.0) == "acked"  # (no proc time)
    assert led.newest_net == newest and len(led.route_nets) == 10
    assert led.queued_here == 0
    a, _b, c = _sent(led, 6.0), _sent(led, 6.1), _sent(led, 6.2)
    assert led.queued_here == 3
    led.expire(7.15, 1.0)  # a and b expire: still on the link
    assert led.in_flight_here == 1 and led.queued_here == 3
    assert led.on_ack(edge_ack(a, 6.0, 0.001, 0.02), recv_stamp=8.5) == "late"
    assert led.queued_here == 2
    assert led.on_ack(edge_ack(c, 6.2, 0.001, 0.02), recv_stamp=8.7) == "acked"  # b: lost for good
    assert led.queued_here == 0
    _sent(led, 9.0)
    assert led.queued_here == 1
    led.on_route(("edgeB", 2), now=9.1)  # a move: the old route's scans are not the new one's queue
    assert led.queued_here == 0
    _sent(led, 9.1, route=("edgeB", 2))
    assert led.queued_here == 1


def test_only_scans_the_edge_registered_count_for_the_window() -> None:
    led = ScanLedger()
    acked_with(led, [(0.3, 0.1)] * 10, status="dropped")  # dropped by the edge: no registration time
    assert led.window(3, 0.1, path=False) == 3
    acked_with(led, [(math.nan, 0.1)] * 10)  # no queue time reported
    assert led.window(3, 0.1, path=False) == 3


def test_after_a_move_the_old_edges_unanswered_scans_neither_fill_the_window_nor_make_a_silence() -> None:
    led = ScanLedger()
    led.on_route(("edgeA", 1), now=10.0)
    for seq in range(3):
        led.produced()
        led.handed_off(seq, {"edge": "edgeA", "epoch": 1})
        led.published(seq, send_stamp=10.0 + 0.1 * seq, record={})
    assert led.on_ack(ack(0, 10.0), recv_stamp=10.05) == "acked"
    assert led.in_flight_here == 2 and led.since_answer(11.05) == pytest.approx(1.0)
    # edgeA goes silent; the robot moves to edgeB with A's two scans still unanswered
    led.on_route(("edgeB", 2), now=11.2)
    assert led.in_flight == 2 and led.in_flight_here == 0  # (the old code counted 2)
    assert led.since_answer(11.3) == pytest.approx(0.1)  # not 1.25 s since A's last ack
    led.produced()
    led.handed_off(3, {"edge": "edgeB", "epoch": 2})
    led.published(3, send_stamp=11.3, record={})
    assert led.in_flight_here == 1
    led.on_route(("edgeB", 2), now=12.0)  # the same route again: its clock goes on
    assert led.since_answer(12.0) == pytest.approx(0.8)
    # A's scans still expire and stay in the balance
    assert led.expire(now=12.5, timeout=1.0) == 3 and led.in_flight_here == 0 and led.balanced()


def test_before_any_ack_there_is_no_silence() -> None:
    led = ScanLedger()
    led.on_route(("edgeA", 1), now=10.0)
    assert led.since_answer(30.0) == 0.0


def test_the_ack_timeout_follows_the_route_s_round_trip() -> None:
    """TCP's timeout (smoothed round trip + 4 deviations, RFC 6298) between ``ack_timeout`` and
    its maximum, from every answer of the route, late ones too: with a fixed second every scan of
    a path rerouted to a 1.8 s round trip was booked late and no edge pose was ever used."""
    led = ScanLedger()
    acked_after(led, [0.3] * 5, route=("edgeA", 1))
    assert led.ack_timeout(1.0, 4.0) == 1.0  # a quick path: the floor
    t = 1.0
    seq = _sent(led, t)  # the path's round trip rises to 1.8 s: the first scan expires, then answers
    led.expire(t + 1.05, led.ack_timeout(1.0, 4.0))
    assert led.on_ack(edge_ack(seq, t, 0.001, 0.02), recv_stamp=t + 1.8) == "late"
    t += 0.1
    grown = led.ack_timeout(1.0, 4.0)
    assert 1.8 < grown <= 4.0
    seq = _sent(led, t)
    led.expire(t + 1.5, grown)
    assert led.in_flight == 1  # no longer lost at 1.5 s...
    assert led.on_ack(edge_ack(seq, t, 0.001, 0.02), recv_stamp=t + 1.8) == "acked"  # ...but acked
    assert led.ack_timeout(1.0, 1.0) == led.ack_timeout(1.0, None) == 1.0  # fixed: no maximum above it
    for _ in range(20):  # a queue of seconds: at most the maximum
        seq = _sent(led, t)
        led.on_ack(edge_ack(seq, t, 0.001, 0.02), recv_stamp=t + 9.0)
    assert led.ack_timeout(1.0, 4.0) == 4.0
    led.on_route(("edgeB", 2), now=t)  # another edge, another path: from the floor again
    assert led.ack_timeout(1.0, 4.0) == 1.0
