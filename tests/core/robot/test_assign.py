"""Edge ranking and the robot's assignment, driven by hand."""

from __future__ import annotations

from collections import Counter

from zoffload.robot.assign import ATTACHED, UNASSIGNED, Assignment, EdgeInfo, rank


def test_rendezvous_spreads_robots_and_moves_only_those_of_a_vanished_edge() -> None:
    edges = [EdgeInfo(f"e{i}") for i in range(3)]
    robots = [f"r{i}" for i in range(300)]
    first = {r: rank(r, edges, 0.0)[0] for r in robots}
    share = Counter(first.values())
    assert all(70 < n < 130 for n in share.values()), share  # about a third each
    without = {r: rank(r, edges[:2], 0.0)[0] for r in robots}
    moved = [r for r in robots if first[r] != without[r]]
    assert set(moved) == {r for r in robots if first[r] == "e2"}  # only e2's robots move


def test_free_capacity_weighs_and_full_or_draining_edges_take_no_one() -> None:
    roomy, busy = EdgeInfo("roomy", capacity=10, robots=0), EdgeInfo("busy", capacity=10, robots=8)
    wins = Counter(rank(f"r{i}", [roomy, busy], 0.0)[0] for i in range(500))
    assert wins["roomy"] > 3 * wins["busy"] > 0
    full, draining = EdgeInfo("full", capacity=2, robots=2), EdgeInfo("d", draining=True)
    assert rank("r1", [full, draining], 0.0) == []
    refused = EdgeInfo("x", refused_until=10.0)
    assert rank("r1", [refused], 5.0) == [] and rank("r1", [refused], 11.0) == ["x"]


def test_attach_failover_epochs_and_stale_answers() -> None:
    a = Assignment("r1")
    for e in ("e1", "e2"):
        a.edge_present(e)
    first = a.next_candidate(0.0)
    assert first is not None
    epoch = a.begin_attach(first, now_ms=1000)
    assert epoch == 1000 and not a.current(first, epoch)  # not attached yet
    assert not a.attached(first, epoch + 1)  # an answer to another attach
    assert a.attached(first, epoch) and a.state == ATTACHED and a.current(first, epoch)
    # the edge dies: the robot must move; the other edge is next; the epoch grows
    assert a.edge_gone(first) and a.state == UNASSIGNED
    second = a.next_candidate(1.0)
    assert second is not None and second != first
    epoch2 = a.begin_attach(second, now_ms=500)  # even with a clock that went back
    assert epoch2 == epoch + 1
    assert a.attached(second, epoch2) and a.failovers == 1
    assert not a.current(first, epoch)  # the old edge's late acks are stale
    # a refusal keeps the robot away from that edge for a while
    a.refused(second, now=2.0)
    assert a.state == UNASSIGNED and a.next_candidate(3.0) is None and a.next_candidate(8.0) == second


def test_draining_edge_sends_its_robot_elsewhere() -> None:
    a = Assignment("r1")
    a.edge_present("e1")
    a.edge_present("e2")
    edge = a.next_candidate(0.0)
    assert edge is not None
    a.attached(edge, a.begin_attach(edge, 1))
    other = "e2" if edge == "e1" else "e1"
    assert not a.edge_status(other, capacity=4, robots=1, draining=True)  # not ours: nothing to do
    assert a.edge_status(edge, capacity=4, robots=1, draining=True)  # ours: move
    assert a.next_candidate(0.0) is None  # the other one drains too
    a.edge_status(other, capacity=4, robots=1, draining=False)
    assert a.next_candidate(0.0) == other
    assert not a.edge_status("unknown", 4, 0, False)  # status without a token: not live


def test_a_status_with_nan_or_inf_counts_still_says_it_drains() -> None:
    """Was: int(NaN) raised in the status callback, and the draining flag was lost with it."""
    a = Assignment("r1")
    a.edge_present("e1")
    a.attached("e1", a.begin_attach("e1", 1))
    assert a.edge_status("e1", capacity=float("nan"), robots=float("inf"), draining=True)
    info = a.edges["e1"]
    assert info.capacity == 0 and info.robots == 0 and info.draining
