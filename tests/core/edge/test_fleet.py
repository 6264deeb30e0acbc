"""The edge's fleet decisions without Zenoh: attach table and epochs, capacity, how scans are
routed, shedding from the busy-share window, drain bookkeeping, attach checks, the scan peek."""

from __future__ import annotations

import time
from unittest import mock

import numpy as np

from zoffload.edge.fleet import MAP, OTHER, PEER_FRESH, REFUSE, Fleet, Peers, check_attach, peek_route
from zoffload.protocol import wire


def fleet(**kw: object) -> Fleet:
    return Fleet("e1", capacity=kw.pop("capacity", 2), **kw)  # type: ignore[arg-type]


def test_attach_needs_a_newer_epoch_room_and_no_drain() -> None:
    f = fleet()
    assert f.decide("r1", 0, robots=0, has_session=False, now=0.0) == "stale epoch"  # 0: no attach
    assert f.decide("r1", 3, 0, False, 0.0) == ""
    f.attach("r1", 3, 0.0)
    assert f.decide("r1", 3, 1, True, 1.0) == "stale epoch"
    assert f.decide("r1", 2, 1, True, 1.0) == "stale epoch"
    f.attach("r2", 1, 0.0)
    assert f.decide("r3", 1, 2, False, 1.0) == "full: 2 of 2 robots"
    assert f.decide("r1", 4, 2, True, 1.0) == ""  # a robot coming back does not count against itself
    f.forget("r1")
    assert "r1" not in f.attached and f.decide("r1", 3, 1, False, 1.0) == "stale epoch"  # epoch kept
    f.begin_drain(2.0)
    assert f.decide("r1", 9, 0, False, 2.0) == "draining"


def test_an_epoch_from_the_future_is_accepted_and_forgotten_with_its_session() -> None:
    """Was: an attach with epoch 2**63 - 1 was accepted and its epoch kept after the session, so
    every later attach of that robot (its wall clock in ms) was refused as stale. Then refusing it
    locked every robot out of an edge whose clock is wrong (booted in 1970, no NTP)."""
    f = fleet()
    now_ms = int(time.time() * 1e3)
    assert f.decide("r1", 2**63 - 1, 0, False, 0.0) == ""
    f.attach("r1", 2**63 - 1, 0.0)
    f.forget("r1")
    assert "r1" not in f.epochs and f.decide("r1", now_ms, 0, False, 1.0) == ""
    f.attach("r1", now_ms + 3_600_000, 1.0)  # an hour of clock skew is remembered
    f.forget("r1")
    assert f.decide("r1", now_ms, 0, False, 2.0) == "stale epoch"
    # an edge whose clock is 56 years behind takes a correctly-set robot's attach
    with mock.patch.object(time, "time", return_value=0.0):
        assert f.decide("r2", now_ms, 0, False, 3.0) == ""


def test_scans_are_routed_by_edge_and_epoch() -> None:
    f = fleet()
    f.attach("r1", 5, 0.0)
    assert f.route("r1", "e2", 7, 1.0).action == OTHER
    assert f.attached["r1"].moved
    assert f.route("r9", "e2", 1, 1.0).action == OTHER and "r9" not in f.attached  # no state for strangers
    ok = f.route("r1", "e1", 5, 2.0)
    assert ok.action == MAP and f.attached["r1"].last_scan == 2.0 and not f.attached["r1"].moved
    stale = f.route("r1", "e1", 4, 2.0)
    assert (stale.action, stale.detail, stale.reason) == (REFUSE, "not attached (epoch 4)", "stale_epoch")
    assert f.route("r2", "e1", 1, 2.0).detail == "not attached (epoch 1)"
    assert f.route("r1", "", 5, 2.0).action == REFUSE  # an epoch without an edge: not the legacy protocol
    assert f.route("r3", "", 0, 2.0).action == MAP  # no attach protocol: mapped as before
    strict = fleet(require_attach=True)
    r = strict.route("r3", "", 0, 2.0)
    assert (r.action, r.detail, r.reason) == (REFUSE, "attach first", "attach_first")
    f.begin_drain(3.0)
    assert f.route("r2", "e1", 1, 3.0).detail == "draining"
    assert f.route("r1", "e1", 5, 3.0).action == MAP  # the old epoch is mapped while the robot moves


def test_drain_asks_final_checkpoints_and_ends_when_robots_moved_or_went_quiet() -> None:
    f = fleet(capacity=4)
    for i, r in enumerate(["r1", "r2", "r3"]):
        f.attach(r, 1, float(i))
    assert sorted(f.begin_drain(10.0)) == ["r1", "r2", "r3"]
    assert f.begin_drain(10.5) == []  # asked once
    assert f.status(10.0)["draining"] == 1.0
    assert not f.drained(20.0)  # final checkpoints still owed
    for r in ("r1", "r2", "r3"):
        f.final_sent(r, 19.0)
    f.route("r1", "e1", 1, 20.0)  # r1 still sends under the old epoch
    f.route("r2", "e2", 2, 20.0)  # r2 moved
    assert not f.drained(20.5)  # r1 sent 0.5 s ago
    assert f.drained(21.0)  # r1 quiet for 1 s, r2 moved, r3 quiet since long


def window(f: Fleet, busy_per_s: float, drops: bool, start: float = 0.0, n: int = 6) -> float:
    for i in range(n):
        t = start + i
        f.sample(t, busy_per_s * t, (int(t) if drops else 0))
    return start + n - 1


def test_shedding_takes_the_newest_robot_when_busy_and_dropping() -> None:
    f = fleet(capacity=3)
    for i, r in enumerate(["r1", "r2", "r3"]):
        f.attach(r, 1, float(i))
    now = window(f, busy_per_s=1.9, drops=False)  # busy, but nothing dropped: keep everyone
    assert f.busy_share(2) > 0.9 and f.to_shed(now, workers=2) is None
    g = fleet(capacity=3)
    for i, r in enumerate(["r1", "r2", "r3"]):
        g.attach(r, 1, float(i))
    now = window(g, busy_per_s=1.0, drops=True)  # dropping, but half idle: keep
    assert g.to_shed(now, workers=2) is None
    now = window(g, busy_per_s=1.95, drops=True, start=100.0)
    assert abs(g.busy_share(2) - 0.975) < 1e-6
    assert g.to_shed(now, workers=2) == "r3"
    assert g.attached["r3"].shed and g.attached["r3"].final == "pending"
    assert g.effective_capacity(now) == 2 and g.status(now)["capacity"] == 2.0
    assert g.to_shed(now + 1, workers=2) is None  # at most one per window
    # Mapped until its final checkpoint has been out for ``quiet`` s (the scans it sent before the
    # final reached it get poses), refused after; its session may go when it moved or went quiet
    assert g.route("r3", "e1", 1, now + 1).action == MAP
    g.final_sent("r3", now + 1)
    assert g.route("r3", "e1", 1, now + 1.5).action == MAP
    assert g.route("r3", "e1", 1, now + 2.0).detail == "shed: over capacity"
    assert g.shed_gone(now + 2.4) == [] and g.shed_gone(now + 2.6) == ["r3"]
    # Moved (its scans name another edge): its session goes, but not within the grace, whose
    # mapped scans would be answered "dropped" with it
    g.route("r3", "e2", 2, now + 1.6)
    assert g.shed_gone(now + 1.7) == [] and g.shed_gone(now + 2.0) == ["r3"]
    assert g.effective_capacity(now + 29) == 2 and g.effective_capacity(now + 31) == 3
    # Never the last robot, never when shedding is off
    h = fleet(capacity=3, shed=False)
    h.attach("r1", 1, 0.0)
    h.attach("r2", 1, 0.0)
    assert h.to_shed(window(h, 2.0, True), 2) is None
    k = fleet(capacity=3)
    k.attach("r1", 1, 0.0)
    assert k.to_shed(window(k, 2.0, True), 2) is None



def test_shedding_when_scans_are_answered_late_with_nothing_dropped() -> None:
    """Queued into lateness: each robot's queue holds its scans long enough to answer every one, so
    nothing is dropped, but more than 5 % are answered after their robot's period: shed, whatever
    the workers' busy share (a CPU quota throttles them while they look idle)."""
    g = fleet(capacity=3)
    for i, r in enumerate(["r1", "r2", "r3"]):
        g.attach(r, 1, float(i))
    for i in range(6):  # 20 scans answered a second, 1 late: 5 %, not more
        g.sample(float(i), 0.5 * i, 0, 20 * i, i)
    assert abs(g.late_share() - 0.05) < 1e-9 and g.to_shed(5.0, workers=2) is None
    for i in range(6):  # 3 of 20 late, half idle, nothing dropped
        g.sample(100.0 + i, 0.5 * i, 0, 20 * i, 3 * i)
    assert abs(g.late_share() - 0.15) < 1e-9 and g.busy_share(2) < 0.9
    assert g.to_shed(105.0, workers=2) == "r3"
    assert "late" in g.overload_reason()
    # Too few scans in the window to say: no shedding on a handful
    k = fleet(capacity=3)
    k.attach("r1", 1, 0.0)
    k.attach("r2", 1, 0.0)
    for i in range(6):
        k.sample(float(i), 0.0, 0, i, i)
    assert k.late_share() == 0.0 and k.to_shed(5.0, workers=2) is None


def test_no_shedding_into_a_full_fleet() -> None:
    """Busy and dropping, but no other edge has room: the robots stay (shedding would only bounce
    them between full edges and into their local odometry)."""
    g = fleet(capacity=3)
    for i, r in enumerate(["r1", "r2", "r3"]):
        g.attach(r, 1, float(i))
    now = window(g, busy_per_s=1.95, drops=True)
    peers = Peers("e1")
    assert not peers.room_elsewhere(now)  # no other edge heard of
    peers.update("e1", {"capacity": 9, "robots": 0}, now)  # our own status does not count
    peers.update("e2", {"capacity": 2, "robots": 2}, now)  # full
    peers.update("e3", {"capacity": 4, "robots": 1, "draining": 1}, now)  # leaving
    peers.update("e5", {"capacity": 4, "robots": 1, "late_share": 0.2}, now)  # room by count, behind
    peers.update("e6", {"capacity": 4, "robots": 1, "late_share": float("nan")}, now)  # unreadable: behind
    assert not peers.room_elsewhere(now)
    assert g.to_shed(now, 2, peers.room_elsewhere(now)) is None
    peers.update("e4", {"capacity": 4, "robots": 1}, now)
    assert peers.room_elsewhere(now) and not peers.room_elsewhere(now + PEER_FRESH + 1)  # stale: gone
    peers.update("e4", {"capacity": 4, "robots": 1}, now)
    assert g.to_shed(now, 2, peers.room_elsewhere(now)) == "r3"


def test_a_dead_edge_has_no_room_from_the_moment_its_token_goes() -> None:
    """Its last status stays fresh for PEER_FRESH seconds; an edge that shed a robot into it then
    (a CI run: 1.1 s after the other edge was killed) left the robot with no edge to go to."""
    g = fleet(capacity=3)
    for i, r in enumerate(["r1", "r2", "r3"]):
        g.attach(r, 1, float(i))
    now = window(g, busy_per_s=1.95, drops=True)
    peers = Peers("e1")
    peers.update("e2", {"capacity": 4, "robots": 1}, now)
    assert peers.room_elsewhere(now)
    peers.gone("e2")
    assert not peers.room_elsewhere(now) and g.to_shed(now, 2, peers.room_elsewhere(now)) is None
    peers.update("e2", {"capacity": 4, "robots": 1}, now + 0.1)  # a status sent before it died
    assert not peers.room_elsewhere(now + 0.1)
    peers.back("e2")  # restarted: its token is there again, and its next status counts
    assert not peers.room_elsewhere(now + 0.2)
    peers.update("e2", {"capacity": 4, "robots": 0}, now + 0.2)
    assert peers.room_elsewhere(now + 0.2) and g.to_shed(now + 0.2, 2, True) == "r3"
    peers.gone("e1")  # our own token (at shutdown) changes nothing
    assert "e1" not in peers.dead
    for i in range(300):  # a flood of tokens from names never seen: bounded
        peers.gone(f"x{i}")
    assert len(peers.dead) <= 256


def checkpoint(robot: str = "r1", seq: int = 10, pose: np.ndarray | None = None) -> wire.Checkpoint:
    return wire.Checkpoint(robot=robot, edge="e0", epoch=1, seq=seq, stamp=1.0, voxel_size=0.5,
                           max_range=40.0, min_range=0.0, max_points_per_voxel=20,
                           pose=np.eye(4) if pose is None else pose, delta=np.eye(4),
                           points=np.zeros((5, 3), np.float32))


def attach(cp: bytes = b"", seqs: list[int] | None = None, poses: np.ndarray | None = None,
           robot: str = "r1") -> wire.Attach:
    seqs = seqs or []
    poses = np.repeat(np.eye(4)[None], len(seqs), 0) if poses is None else poses
    return wire.Attach(robot=robot, epoch=2, max_range=40.0, voxel_max=0.07, rate_hz=10.0, checkpoint=cp,
                       local_seqs=np.asarray(seqs, np.int64), local_poses=poses)


def test_attach_checks() -> None:
    assert check_attach(attach(), "r1") == (None, "")
    cp, why = check_attach(attach(wire.encode(checkpoint()), [11, 12]), "r1")
    assert cp is not None and cp.seq == 10 and why == ""
    assert check_attach(attach(b"junk"), "r1")[1].startswith("bad checkpoint: ")
    assert "made for robot" in check_attach(attach(wire.encode(checkpoint("r2"))), "r1")[1]
    skew = np.eye(4)
    skew[0, 0] = 3.0
    assert "rigid" in check_attach(attach(wire.encode(checkpoint(pose=skew))), "r1")[1]
    assert "not after" in check_attach(attach(wire.encode(checkpoint()), [10, 11]), "r1")[1]
    assert "ascending" in check_attach(attach(b"", [3, 2]), "r1")[1]
    assert "rigid" in check_attach(attach(b"", [3], np.zeros((1, 4, 4))), "r1")[1]


def test_the_peek_reads_edge_and_epoch_of_a_scan_only() -> None:
    scan = wire.Scan(robot="r1", seq=1, send_stamp=0.0, capture_stamp=0.0, voxel=0.0, voxel_max=0.0,
                     max_range=10.0, n_raw=0, points=np.ones((1000, 3), np.float32), epoch=7, edge="e2")
    assert peek_route(wire.encode(scan)) == ("e2", 7)
    legacy = wire.Scan(robot="r1", seq=1, send_stamp=0.0, capture_stamp=0.0, voxel=0.0, voxel_max=0.0,
                       max_range=10.0, n_raw=0, points=np.ones((3, 3), np.float32))
    assert peek_route(wire.encode(legacy)) == ("", 0)
    assert peek_route(b"") is None and peek_route(b"\xde\xad") is None
    assert peek_route(wire.encode(wire.Pong(edge="x", stamp=0.0))) is None
    import msgpack

    assert peek_route(msgpack.packb({"t": "scan", "edge": 3, "epoch": 1})) is None
    assert peek_route(msgpack.packb({"t": "scan", "edge": "e", "epoch": True})) is None
