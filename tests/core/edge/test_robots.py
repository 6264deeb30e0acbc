"""Which scan a robot's full queue on the edge drops (``RobotSession.victim``)."""

from __future__ import annotations

from collections import deque
from types import SimpleNamespace
from typing import Any

from zoffload.edge.robots import RobotSession


def session(kept: list[int], queued: list[int]) -> RobotSession:
    rs = RobotSession(robot="r1", ack_pub=None, files=None)  # type: ignore[arg-type]
    rs.kept = deque(kept, maxlen=rs.kept.maxlen)
    rs.queue = deque(SimpleNamespace(scan=SimpleNamespace(seq=s)) for s in queued)  # type: ignore[misc]
    return rs


def victim(kept: list[int], queued: list[int]) -> Any:
    rs = session(kept, queued)
    return rs.queue[rs.victim()].scan.seq


def test_the_oldest_goes_when_nothing_around_it_is_missing() -> None:
    assert victim([3, 4, 5, 6, 7], [5, 6, 7]) == 5
    assert victim([5, 6], [5, 6]) == 5  # a queue of one: the one waiting


def test_a_scan_next_to_a_missing_one_is_kept_and_the_newest_never_goes() -> None:
    assert victim([3, 5, 6, 7], [5, 6, 7]) == 6  # 4 was dropped: dropping 5 would leave 4, 5
    assert victim([6, 7, 9, 10, 11], [9, 10, 11]) == 10  # 8 never came (the robot skipped it)
    # every candidate next to a gap: the shortest run, then the oldest
    assert victim([1, 3, 5, 7], [3, 5, 7]) == 3  # 2-4 or 4-6: the oldest
    assert victim([1, 2, 4, 6, 7], [4, 6, 7]) == 6  # 4 would leave 3-5 without a pose, 6 leaves 5-6
    # spared once: the next time it is the oldest it goes whatever its neighbours
    rs = session([3, 5, 6, 7], [5, 6, 7])
    assert rs.victim() == 1 and rs.spared == 5
    rs.queue.remove(rs.queue[1])
    rs.kept.remove(6)
    rs.queue.append(SimpleNamespace(scan=SimpleNamespace(seq=8)))  # type: ignore[arg-type]
    rs.kept.append(8)
    assert rs.victim() == 0


def test_a_scan_is_spared_once_so_a_long_burst_keeps_the_queue_fresh() -> None:
    rs = session([0], [])
    dropped, queues = [], []
    for seq in range(1, 11):  # scan 0 is registering; nothing leaves the queue meanwhile
        out = rs.push(SimpleNamespace(scan=SimpleNamespace(seq=seq)), 2)  # type: ignore[arg-type]
        dropped += [q.scan.seq for q in out]
        queues.append([q.scan.seq for q in rs.queue])
    assert list(rs.kept) == [s for s in range(11) if s not in dropped]  # dropped ones forgotten
    # the first overflows thin (1, then 3 instead of 2); 2, spared once, goes at the next
    assert dropped[:3] == [1, 3, 2] and queues[4] == [4, 5]
    # however long the burst, the oldest waiting scan is at most two behind the newest
    assert all(q[-1] - q[0] <= 2 for q in queues) and queues[-1] in ([8, 10], [9, 10])
    assert len(dropped) == 8
    # a burst that ends after scan 4 arrives: 0, 2, 4 registered (the oldest-first rule: 0, 3, 4)
    assert queues[3] == [2, 4]
