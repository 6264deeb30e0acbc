"""The robot's local odometry continues the edge's trajectory from a checkpoint (simulator scans)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from zoffload.mapping.checkpoint import take_checkpoint
from zoffload.mapping.mapper import RobotMapper
from zoffload.protocol import wire
from zoffload.robot.odometry import Backfilled, LocalOdometry, local_voxel_size
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")


@pytest.fixture(scope="module")
def edge_run() -> tuple[SimulatedSource, RobotMapper, wire.Checkpoint]:
    """An edge's mapper over scans 0-29, its checkpoint after scan 29, and the same mapper
    carried on to scan 59 (the reference)."""
    src = SimulatedSource()
    mapper = RobotMapper(voxel_size=0.4, max_range=src.max_range)
    cp = None
    for i in range(60):
        mapper.register(i, src.read(i).points)
        if i == 29:
            cp = take_checkpoint(mapper.odometry, "robot1", "edge1", 7, 29, stamp=2.9,
                                 turn_rate=mapper.turn_rate)
    assert cp is not None
    return src, mapper, cp


def test_seeded_local_odometry_continues_the_trajectory(edge_run: tuple) -> None:
    src, mapper, cp = edge_run
    odo = LocalOdometry("robot1", src.max_range, threads=1)
    assert odo.voxel == local_voxel_size(40.0) == 0.8 and not odo.active
    odo.begin(cp, [(28, mapper.poses[28]), (29, mapper.poses[29])])
    for i in range(30, 60):
        pose, cpu = odo.register(i, src.read(i).points, 3.0 + i / 10)
        assert cpu > 0
    edge_xyz = mapper.poses[59][:3, 3]
    assert np.linalg.norm(pose[:3, 3] - edge_xyz) < 0.5, (pose[:3, 3], edge_xyz)
    assert np.linalg.norm(edge_xyz - mapper.poses[29][:3, 3]) > 3.0  # it really moved meanwhile
    # Unseeded, the same scans start again at the origin: the checkpoint is what continues it
    fresh = LocalOdometry("robot1", src.max_range)
    fresh.begin(None, [])
    for i in range(30, 35):
        p, _ = fresh.register(i, src.read(i).points, 0.0)
    assert np.linalg.norm(p[:3, 3] - mapper.poses[34][:3, 3]) > 2.0
    assert odo.cpu_summary()["median"] is not None and odo.registered == 30


def test_unanswered_scans_are_caught_up_and_the_snapshot_carries_the_rest(edge_run: tuple) -> None:
    src, mapper, cp = edge_run
    odo = LocalOdometry("robot1", src.max_range, catch_up=4, checkpoint_every=10)
    for i in range(28, 36):  # sent while attached; only 28 and 29 got an answer, by the time 30 went
        odo.hold(i, src.read(i).points, i / 10, posed_upto=29 if i >= 30 else -1)
    # bounded, spread over the scans after the newest answered one: 30..35 every other and the newest
    assert [h.seq for h in odo.ring] == [30, 32, 34, 35]
    odo.begin(cp, [(29, mapper.poses[29])])
    done = odo.catch_up(before=36, posed={34})
    assert [s for s, _, _ in done] == [30, 32, 35] and not odo.ring
    for i in range(36, 48):
        pose, _ = odo.register(i, src.read(i).points, i / 10)
    assert np.linalg.norm(pose[:3, 3] - mapper.poses[47][:3, 3]) < 0.5
    snap = odo.snapshot()
    assert snap.checkpoint is not None and snap.checkpoint.edge == "" and snap.checkpoint.robot == "robot1"
    # the period's first registration took one, then every 10th registration: 30, then 43
    assert snap.checkpoint.seq == 43 and list(snap.seqs) == [30, 32, *range(35, 48)]
    assert snap.poses.shape == (15, 4, 4)
    wire.decode(wire.encode(snap.checkpoint), expect=wire.Checkpoint)  # a valid message
    # the edge's turn rate (version 8) carries on in the robot's own checkpoints, for the next edge
    assert snap.checkpoint.turn_rate == cp.turn_rate > 0
    odo.end()
    assert not odo.active and len(odo.snapshot().seqs) == 0 and odo.snapshot().checkpoint is not None


def test_overdue_acks_bridge_with_local_poses_and_an_ack_ends_it(edge_run: tuple) -> None:
    """Attached to an edge that stops answering: before the robot gives up on it, each scan is
    registered locally as well, the unanswered ones first; the next ack ends the bridge."""
    import time

    from zoffload.robot.ledger import ScanLedger
    from zoffload.robot.localpose import PoseKeeper
    from zoffload.robot.sensor import Reading

    src, mapper, cp = edge_run
    fleet, ask, ledger, lock, odo, keeper = _attached_keeper(edge_run)  # the edge's checkpoint after scan 29
    fleet.checkpoint = dataclasses.replace(cp, epoch=ask[1])  # made under this attach: the edge's frame

    def scan(i: int) -> tuple[np.ndarray, float] | None:
        reading = Reading(i, src.read(i), time.time())
        out = keeper.attached(reading, ask)
        ledger.handed_off(i, {"capture_stamp": reading.capture_stamp})
        if out is not None:
            keeper.book_bridged(i, *out)
        return out

    for i in range(30, 34):  # sent, answers not yet due
        assert scan(i) is None
    assert not odo.active and len(odo.ring) == 4
    fleet.on_sent(time.monotonic() - 0.5)  # scan 30 went half a second ago, unanswered
    bridged = scan(34)
    assert bridged is not None and odo.active
    assert set(ledger.poses) == {30, 31, 32, 33, 34}  # the unanswered ones caught up first
    assert all(ledger.records[s]["pose_source"] == "local" for s in range(30, 35))
    assert all(ledger.records[s]["pose_lag_ms"] >= 0 for s in range(30, 35))
    assert np.linalg.norm(bridged[0][:3, 3] - mapper.poses[34][:3, 3]) < 0.5
    # What the scans carry to the edge (``Scan.prior``): this pose and the local motion per scan
    got = keeper.prior_for(34)
    assert got is not None and got[0] == 34 and keeper.prior_for(34 + 50) is None  # too old then
    assert got[2] == 0  # begun from this edge's checkpoint under this attach: in its frame (version 11)
    assert keeper.prior_for(34, reads=10)[2] == -1  # an older edge: not said, the bridge's prior still sent
    prior = got[1]
    assert prior.shape == (2, 4, 4) and np.array_equal(prior[0], bridged[0])
    step = np.linalg.inv(mapper.poses[33]) @ mapper.poses[34]
    assert np.linalg.norm(prior[1][:3, 3] - step[:3, 3]) < 0.1 and wire.rigid_error(prior) < 1e-6
    assert keeper.pose is not None and keeper.pose[1] == 1.0
    assert scan(35) is not None  # still overdue: still bridging
    # The edge answers again, but only a scan sent before the bridge (delivered late): the edge
    # has not seen the bridge's scans yet, so the bridge and its priors go on
    fleet.on_ack(ask[0], ask[1], "ok", time.monotonic(), in_flight=0)
    with lock:
        keeper.edge_pose(31, mapper.poses[31])
    assert scan(36) is not None and odo.active and keeper.prior_for(36)[0] == 36
    # It acks a scan of the bridge (here without a pose, as an edge that does not map answers):
    # the bridge ends with the next scan, which carries no prior
    with lock:
        keeper.edge_pose(34, np.full((4, 4), np.nan))
    assert keeper.prior_for(37) is None
    assert scan(37) is None and not odo.active
    m = keeper.metrics()
    assert m["bridged_scans"] == 3 and m["bridges"] == 1 and m["caught_up"] == 4
    # Without an explicit setting the threshold is two periods, at most half the failover time
    auto = PoseKeeper(odo, fleet, ScanLedger(), lock, period=0.1, failover_after=1.0)
    assert auto.threshold() == pytest.approx(0.2)
    assert PoseKeeper(odo, fleet, ScanLedger(), lock, period=0.4, failover_after=1.0).threshold() == 0.5


def test_scans_in_flight_to_a_dead_edge_get_local_poses_after_the_move(edge_run: tuple) -> None:
    """A SIGKILLed edge's token goes at once and the robot attaches elsewhere before its next scan:
    the scans in flight to the dead edge are registered locally then (no bridge happened)."""
    import threading
    import time

    from zoffload.robot.fleet import FleetState
    from zoffload.robot.ledger import ScanLedger
    from zoffload.robot.localpose import PoseKeeper
    from zoffload.robot.sensor import Reading

    src, mapper, cp = edge_run
    fleet = FleetState("robot1", failover_after=1.0)
    fleet.checkpoint = cp
    ledger, lock = ScanLedger(), threading.Lock()
    odo = LocalOdometry("robot1", src.max_range, catch_up=10)
    alive = {"edge1": True, "edge2": True}
    keeper = PoseKeeper(odo, fleet, ledger, lock, period=0.1, failover_after=1.0, alive=lambda e: alive[e])
    keeper.edge_pose(29, mapper.poses[29])
    for i, target in [(30, ("edge1", 1)), (31, ("edge1", 1)), (32, ("edge1", 1))]:
        assert keeper.attached(Reading(i, src.read(i), time.time()), target) is None
        ledger.handed_off(i, {"capture_stamp": time.time()})
    ledger.poses[30] = mapper.poses[30]  # edge1 answered scan 30 before it died
    alive["edge1"] = False
    assert keeper.attached(Reading(33, src.read(33), time.time()), ("edge2", 2)) is None
    assert set(ledger.poses) == {30, 31, 32} and ledger.records[31]["pose_source"] == "local"
    assert not odo.active and keeper.metrics()["caught_up"] == 2
    # A planned move (the old edge still there, answering what it was sent) registers nothing
    alive["edge2"] = True
    ledger.handed_off(33, {"capture_stamp": time.time()})
    assert keeper.attached(Reading(34, src.read(34), time.time()), ("edge1", 3)) is None
    assert 33 not in ledger.poses and keeper.metrics()["caught_up"] == 2


def test_after_a_slow_attach_the_next_edge_gets_the_newest_local_pose_until_it_answers(
        edge_run: tuple) -> None:
    """The dead edge's move goes through an attach that takes longer than a period: the scans
    read meanwhile are mapped here with no edge, after the poses the attach handed over. The next
    edge's first scans carry the newest of them as their prior (the edge moves it as it moved the
    handed-over poses, mapping/mapper.py ``predict_from``) until that edge acks one of them; a
    late ack of an older scan does not end it."""
    import time

    from zoffload.robot.sensor import Reading

    src, mapper, _ = edge_run
    _, ledger, lock, odo, keeper = _slow_attach_keeper(edge_run)
    assert {30, 31, 32, 33} <= set(ledger.poses) and ledger.records[31]["pose_source"] == "local"
    for i in (34, 35):
        assert keeper.attached(Reading(i, src.read(i), time.time()), ("edge2", 2)) is None
        got = keeper.prior_for(i)
        assert got is not None and got[0] == 33 and np.array_equal(got[1][0], ledger.poses[33])
        assert got[2] == 1  # in the frame of the poses the attach handed over (version 11)
        assert keeper.prior_for(i, reads=10) is None  # an older edge could not tell that frame
    assert not odo.active  # edge2 is not overdue: no bridge, the odometry's period is over
    assert np.linalg.norm(got[1][0][:3, 3] - mapper.poses[33][:3, 3]) < 0.5
    with lock:
        keeper.edge_pose(31, mapper.poses[31])  # a late answer of edge1's: the prior goes on
    assert keeper.prior_for(36) is not None
    with lock:
        keeper.edge_pose(34, mapper.poses[34])  # edge2 answers its first scan
    assert keeper.prior_for(36) is None


def test_a_bridge_going_on_with_a_no_edge_periods_odometry_gives_an_older_edge_no_prior(
        edge_run: tuple) -> None:
    """As above, but the next edge's acks are overdue at once: the robot bridges with the odometry
    of the period that mapped the scans read with no edge (no new period begins), so its priors are
    in that period's frame. An edge that reads < 11 gets no prior of them, as of the no-edge scans
    (it would take them as its own frame); one that reads 11 gets them, said in the handed-over
    frame. (Before: the bridge's priors went to the older edge as its own.)"""
    import time

    from zoffload.robot.sensor import Reading

    src = edge_run[0]
    fleet, _, _, odo, keeper = _slow_attach_keeper(edge_run, bridge_after=0.3)
    assert odo.active
    ask = _attach(fleet, "edge2")
    fleet.on_sent(time.monotonic() - 0.5)  # edge2's first scan half a second unanswered
    bridged = keeper.attached(Reading(34, src.read(34), time.time()), ask)
    assert bridged is not None and odo.active and keeper.bridges == 1  # the same period goes on
    keeper.book_bridged(34, *bridged)
    got = keeper.prior_for(35)
    assert got is not None and got[0] == 34 and got[2] == 1
    assert keeper.prior_for(35, reads=10) is None


def test_a_bridge_begun_for_a_dead_edge_goes_on_to_the_next_in_the_handed_over_frame(edge_run: tuple) -> None:
    """edge1's acks are overdue: the robot bridges from edge1's checkpoint, in edge1's frame. edge1
    dies, the robot attaches to edge2, whose acks are overdue at once: the same period goes on (a
    bridge of its own). The poses the attach handed over are that period's and edge1's, so its
    priors are in the handed-over frame: said so (1) to an edge that reads 11, and given unsaid
    (-1) to an older one, as every bridge's prior has gone since version 5 (the priors of a move
    off a dead edge are the same case). An edge since 854b98d (the last of version 10) moves such
    an estimate of a scan before its first live one by the correction it found for the
    handed-over poses (mapping/mapper.py ``predict_from``: the right frame); an earlier one takes
    it as sent and contests it with its own guess, as it always did."""
    import time

    from zoffload.robot.sensor import Reading

    src, _, cp = edge_run
    dead: set[str] = set()
    fleet, first, ledger, _, odo, keeper = _attached_keeper(edge_run, alive=lambda e: e not in dead)
    fleet.on_sent(time.monotonic() - 0.5)  # edge1's scan half a second unanswered
    bridged = keeper.attached(Reading(30, src.read(30), time.time()), first)
    assert bridged is not None and odo.active and keeper.bridges == 1
    ledger.handed_off(30, {"capture_stamp": time.time()})
    keeper.book_bridged(30, *bridged)
    got = keeper.prior_for(31)
    assert got is not None and got[2] == (0 if (cp.edge, cp.epoch) == first else 1)
    dead.add("edge1")
    fleet.edge_gone("edge1", time.monotonic())
    second = _attach(fleet, "edge2")
    fleet.on_sent(time.monotonic() - 0.5)  # edge2's first scan half a second unanswered
    bridged = keeper.attached(Reading(31, src.read(31), time.time()), second)
    assert bridged is not None and odo.active and keeper.bridges == 2  # the same period, a new bridge
    keeper.book_bridged(31, *bridged)
    new, old = keeper.prior_for(32), keeper.prior_for(32, reads=10)
    assert new is not None and new[0] == 31 and new[2] == 1
    assert old is not None and old[0] == 31 and old[2] == -1 and np.array_equal(old[1], new[1])


def test_a_period_starts_from_the_newest_poses_the_robot_has_its_own_included(edge_run: tuple) -> None:
    """The robot mapped scans 30-37 itself (no edge), reattached and sent 38-40, and the edge's
    acks are overdue: the bridge starts from its own pose of scan 37, not from the checkpoint of
    scan 29 with a nine-scan gap to stretch a motion over (on KITTI-360 that put the bridge 4 m
    off along the road, and its scans carried that to the edge)."""
    import time

    from zoffload.robot.sensor import Reading

    src, mapper, cp = edge_run
    fleet, ask, ledger, lock, odo, keeper = _attached_keeper(edge_run)  # the edge's checkpoint after scan 29
    for s in range(30, 38):  # the robot's own poses of an earlier period (here exact)
        ledger.local(s, {"capture_stamp": time.time()}, mapper.poses[s])
    ledger.poses[36] = np.full((4, 4), np.nan)  # an ack without a pose is not a pose
    begun: list[list[int]] = []
    begin = odo.begin
    odo.begin = lambda c, newest: (begun.append([s for s, _ in newest]), begin(c, newest))[1]  # type: ignore[method-assign]
    for i in range(38, 41):
        assert keeper.attached(Reading(i, src.read(i), time.time()), ask) is None
        ledger.handed_off(i, {"capture_stamp": time.time()})
    fleet.on_sent(time.monotonic() - 0.5)
    out = keeper.attached(Reading(41, src.read(41), time.time()), ask)
    assert out is not None and begun == [[35, 37]]
    for s in (38, 39, 40, 41):
        pose = ledger.poses[s] if s < 41 else out[0]
        assert np.linalg.norm(pose[:3, 3] - mapper.poses[s][:3, 3]) < 0.3, s


def test_a_move_in_the_middle_of_a_bridge_ends_it_and_the_new_edge_gets_its_own(edge_run: tuple) -> None:
    """Bridging to edge1, the robot is moved to edge2 whose acks are overdue too: that is a new
    bridge, which lasts until edge2 acks one of its scans; the old bridge's estimate does not ride
    on edge2's scans after it (it did, for up to MAX_GAP scans, once edge2 answered anything)."""
    import time

    from zoffload.robot.sensor import Reading

    src, mapper, cp = edge_run
    fleet, ask, ledger, lock, odo, keeper = _attached_keeper(edge_run)  # the edge's checkpoint after scan 29

    def scan(i: int, target: tuple[str, int]) -> tuple[np.ndarray, float] | None:
        out = keeper.attached(Reading(i, src.read(i), time.time()), target)
        ledger.handed_off(i, {"capture_stamp": time.time()})
        return out

    assert scan(30, ask) is None
    fleet.on_sent(time.monotonic() - 0.5)
    assert scan(31, ask) is not None and keeper.metrics()["bridges"] == 1
    moved = ("edge2", ask[1] + 1)
    assert scan(32, moved) is not None  # edge2 overdue as well: a bridge of its own
    assert keeper.metrics()["bridges"] == 2 and keeper.prior_for(32)[0] == 32
    assert keeper.prior_for(32)[2] == 1  # begun from edge1's checkpoint: not edge2's frame
    # edge2 answers, but nothing of its bridge yet: the bridge and its estimate go on
    fleet.on_ack(ask[0], ask[1], "ok", time.monotonic(), in_flight=0)
    assert scan(33, moved) is not None and keeper.prior_for(33)[0] == 33
    with lock:
        keeper.edge_pose(32, mapper.poses[32])  # edge2 acks a scan of its bridge
    assert keeper.prior_for(34) is None and scan(34, moved) is None and not odo.active


def _attach(fleet: Any, edge: str) -> tuple[str, int]:
    """``fleet`` attached to ``edge``, which was seen and accepted: the attach target."""
    fleet.edge_present(edge)
    ask = fleet.next_attach(0.0, 1000)
    assert ask is not None and ask[0] == edge
    fleet.attach_result(*ask, wire.AttachReply(robot="robot1", edge=ask[0], epoch=ask[1], accepted=True,
                                               detail="", robots=1, capacity=4), 0.0)
    return ask


def _slow_attach_keeper(edge_run: tuple, **keeper_kw: Any) -> tuple:
    """edge1 answered scan 29, was sent 30 and 31 and died; 32 and 33 were read with no edge while
    the attach to the next edge was under way: (fleet, ledger, lock, odometry, keeper)."""
    import threading
    import time

    from zoffload.robot.fleet import FleetState
    from zoffload.robot.ledger import ScanLedger
    from zoffload.robot.localpose import PoseKeeper
    from zoffload.robot.sensor import Reading

    src, mapper, cp = edge_run
    fleet = FleetState("robot1", failover_after=1.0)
    fleet.checkpoint = cp
    ledger, lock = ScanLedger(), threading.Lock()
    odo = LocalOdometry("robot1", src.max_range, catch_up=10)
    keeper = PoseKeeper(odo, fleet, ledger, lock, period=0.1, failover_after=1.0,
                        alive=lambda e: e != "edge1", **keeper_kw)
    keeper.edge_pose(29, mapper.poses[29])
    for i in (30, 31):
        assert keeper.attached(Reading(i, src.read(i), time.time()), ("edge1", 1)) is None
        ledger.handed_off(i, {"capture_stamp": time.time()})
    for i in (32, 33):  # edge1 died; the attach to edge2 is under way: these have no edge
        assert keeper.no_edge(Reading(i, src.read(i), time.time()), {"capture_stamp": time.time()})
    return fleet, ledger, lock, odo, keeper


def _attached_keeper(edge_run: tuple, alive: Any = None) -> tuple:
    """A robot attached to edge1, whose newest checkpoint (after scan 29) and pose of scan 29 it has,
    with its local odometry and pose keeper (``alive``: whether an edge's token is there; None:
    all): (fleet, attach target, ledger, lock, odometry, keeper)."""
    import threading

    from zoffload.robot.fleet import FleetState
    from zoffload.robot.ledger import ScanLedger
    from zoffload.robot.localpose import PoseKeeper

    src, mapper, cp = edge_run
    fleet = FleetState("robot1", failover_after=1.0)
    ask = _attach(fleet, "edge1")
    fleet.checkpoint = cp
    ledger, lock = ScanLedger(), threading.Lock()
    odo = LocalOdometry("robot1", src.max_range, catch_up=10)
    keeper = PoseKeeper(odo, fleet, ledger, lock, period=0.1, failover_after=1.0, bridge_after=0.3,
                        alive=alive)
    keeper.edge_pose(29, mapper.poses[29])
    return fleet, ask, ledger, lock, odo, keeper


def test_the_period_keeps_its_scans_at_the_backfills_grid_for_the_next_attach(edge_run: tuple) -> None:
    """The backfill (codec version 9): every scan the local odometry registers, caught-up ones
    included, is kept at its grid (a quarter of the odometry's voxel by default; an attach may
    send it up to the odometry's voxel) with its pose, at most ``backfill_scans`` thinned over the
    period; the snapshot hands them to the attach and the period's end forgets them."""
    src, mapper, cp = edge_run
    fixed = LocalOdometry("robot1", src.max_range, backfill_scans=8, backfill_voxel=0.8)
    assert fixed.backfill_voxel == fixed.backfill_coarsest == 0.8  # set: sent at it or thinned
    odo = LocalOdometry("robot1", src.max_range, catch_up=4, backfill_scans=8)
    assert odo.voxel == 0.8 and odo.backfill_voxel == 0.2 and odo.backfill_coarsest == 0.8
    for i in range(30, 32):
        odo.hold(i, src.read(i).points, i / 10)
    odo.begin(cp, [(29, mapper.poses[29])])
    odo.catch_up(before=32, posed=set())
    for i in range(32, 36):
        odo.register(i, src.read(i).points, i / 10)
    assert [b.seq for b in odo.snapshot().backfill] == list(range(30, 36))  # the caught-up two too
    for i in range(36, 40):
        odo.register(i, src.read(i).points, i / 10)
    fill = odo.snapshot().backfill
    # bounded by 8: full, every other one is dropped but the period's first and the newest, so
    # the ring covers the whole period (a long outage's start too), densest where newest
    assert [b.seq for b in fill] == [30, 32, 34, 36, 38, 39]
    snap = odo.snapshot()
    np.testing.assert_allclose(fill[-1].pose, snap.poses[list(snap.seqs).index(39)])  # its pose (v10)
    for i in range(40, 60):
        odo.register(i, src.read(i).points, i / 10)
    seqs = [b.seq for b in odo.snapshot().backfill]
    assert seqs[0] == 30 and seqs[-1] == 59 and len(seqs) <= 8 and seqs == sorted(seqs)
    raw = src.read(39).points
    assert fill[-1].n_raw == int(np.isfinite(raw).all(axis=1).sum()) and fill[-1].stamp == 3.9
    assert fill[-1].points.dtype == np.float32 and 1000 < len(fill[-1].points) < len(raw) / 4
    assert fill[-1].voxel == 0.2 and fill[-1].coarsest == 0.8
    keys = np.floor(fill[-1].points / 0.2)  # one centroid per voxel of the grid
    assert len(np.unique(keys, axis=0)) == len(keys)
    odo.end()
    assert odo.snapshot().backfill == ()
    off = LocalOdometry("robot1", src.max_range)  # not asked for: none kept
    off.begin(cp, [])
    off.register(30, src.read(30).points, 3.0)
    assert off.snapshot().backfill == ()


def test_the_catch_up_ring_spreads_over_the_scans_since_the_newest_answered_one() -> None:
    """Scans sent and not answered, more than the ring holds: the first after the newest answered
    one, the newest, and every stride-th between (a gap at most twice the even spread); those up
    to a scan answered since are let go, and the stride starts again at 1 from the scan after it
    (the ones left are kept as they are, and new ones are all held while there is room)."""
    from zoffload.robot.odometry import CatchUpRing, Held

    ring = CatchUpRing(10)
    for seq in range(100, 140):  # 99 answered, then nothing
        ring.append(Held(seq, np.zeros((1, 3)), 0.0), posed_upto=99)
        held = [h.seq for h in ring]
        assert held[0] == 100 and held[-1] == seq and len(held) <= 10 and held == sorted(held)
    assert np.diff(held).max() <= 2 * 40 / 10 and len(ring) >= 5, held
    ring.append(Held(140, np.zeros((1, 3)), 0.0), posed_upto=120)  # 120's answer came
    left = [h.seq for h in ring]
    assert left[0] > 120 and left[-1] == 140 and ring.stride == 1  # the stretch begins after 120 now
    for seq in range(141, 141 + 10 - len(left)):  # room again: every new scan is held
        ring.append(Held(seq, np.zeros((1, 3)), 0.0), posed_upto=120)
    assert [h.seq for h in ring] == left + list(range(141, 141 + 10 - len(left)))
    ring.append(Held(200, np.zeros((1, 3)), 0.0), posed_upto=199)
    assert [h.seq for h in ring] == [200] and ring.stride == 1
    off = CatchUpRing(0)
    off.append(Held(1, np.zeros((1, 3)), 0.0))
    assert len(off) == 0


def test_a_hole_before_the_odometry_begins_is_caught_up_across_a_turn_back(kitti_dir) -> None:
    """KITTI-360 replayed ping-pong (at 10 m/s the replay turns back between two scans): a fade
    held the acks back, so the robot's newest poses were from before the turn and its local
    odometry began 21 scans after them (``satellite-heldout``, 2026-12-07: the newest pose 388,
    the turn at 392, the period begun at 409). Holding only the newest 10 left 10 scans with no
    pose across the turn, the motion before it was stretched over them, and the robot's poses, and
    the prior it sent, were 13 m off. Here the newest pose is five scans before the replay's first
    turn and 21 scans follow: the ring of 20 holds every other one and stays within centimetres; a
    ring of 10, every fourth, and the newest 10 alone are metres off."""
    from itertools import islice

    from zoffload.mapping.cloud import drop_non_finite
    from zoffload.mapping.mapper import mapper_voxel_size
    from zoffload.sources.base import open_scan_source, replay_order

    src = open_scan_source(str(kitti_dir))
    n = len(src)
    order = list(islice(replay_order(n, "pingpong"), n + 16))  # turns back at seq n - 1

    def points(seq: int) -> np.ndarray:
        return drop_non_finite(src.read(order[seq]).points)[0]

    edge = RobotMapper(voxel_size=mapper_voxel_size(src.max_range, 0.5), max_range=src.max_range)
    last = n - 6  # the robot's newest pose, five scans before the turn; the hole 21 scans after it
    for seq in range(n + 16):  # (carried on: the reference)
        edge.register(seq, points(seq))
        if seq == last:
            cp = take_checkpoint(edge.odometry, "robot1", "edge1", 1, seq, 0.0)
    held = range(last + 1, n + 16)

    def caught_up(ring: list[int] | None, size: int = 20) -> float:
        """How far the pose of the newest held scan is from the edge's."""
        odo = LocalOdometry("robot1", src.max_range, catch_up=size)
        odo.begin(cp, [(last - 1, edge.poses[last - 1]), (last, edge.poses[last])])
        if ring is None:
            for seq in held:
                odo.hold(seq, points(seq), 0.0, posed_upto=last)
            assert np.diff([last, *(h.seq for h in odo.ring)]).max() <= (2 if size == 20 else 4)
        else:  # as the ring held them before: the newest ten
            for seq in ring:
                odo.hold(seq, points(seq), 0.0, posed_upto=last)
            assert [h.seq for h in odo.ring] == ring
        done = odo.catch_up(held[-1] + 1, set())
        assert done[-1][0] == held[-1]
        return float(np.linalg.norm(done[-1][1][:3, 3] - edge.poses[held[-1]][:3, 3]))

    assert np.linalg.norm(edge.poses[held[-1]][:3, 3] - edge.poses[last][:3, 3]) > 5  # it drove on
    assert caught_up(None) < 0.3  # (LocalOdometry's default, 20: every other scan)
    assert caught_up(None, size=10) > 3  # 10 held: every fourth scan, too far apart at the turn
    assert caught_up(list(held)[-10:]) > 3  # the newest ten alone


def test_the_backfill_ring_spreads_over_an_outage_longer_than_it() -> None:
    """A 25 s outage at 10 Hz into a ring of 50: every stride-th scan from the period's first on,
    and the newest, the stride doubling as it fills; no gap between two kept scans beyond twice
    the even spread (the edge registers a backfill only when it reaches back to its last scan)."""
    from zoffload.robot.odometry import BackfillRing

    ring = BackfillRing(50)
    for seq in range(1000, 1255):
        ring.add(Backfilled(seq, 0.0, 1, np.zeros((1, 3), np.float32), 0.8))
        kept = [b.seq for b in ring.scans()]
        assert kept[0] == 1000 and kept[-1] == seq and len(kept) <= 50 and kept == sorted(kept)
    gaps = np.diff(kept)
    assert gaps.max() <= 2 * 255 / 50 and len(kept) >= 25, (gaps.max(), len(kept))
    ring.clear()
    ring.add(Backfilled(7, 0.0, 1, np.zeros((1, 3), np.float32), 0.8))
    assert [b.seq for b in ring.scans()] == [7] and ring.stride == 1


@pytest.mark.parametrize("same_epoch", [True, False])
def test_a_bridge_says_its_priors_frame_only_when_its_checkpoint_and_first_pose_agree(
        edge_run: tuple, same_epoch: bool) -> None:
    """The edge answered scans 30-33 under this attach and its acks are then overdue: the bridge
    begins from the newest checkpoint and its pose of scan 33. When that checkpoint is the same
    edge's under this attach, its priors are in the edge's frame (``Scan.prior_frame`` 0); when it
    is one from before the attach (here the same edge under an earlier epoch), the map it
    registers against and the pose it starts from are in different frames, and the prior says it
    does not know (-1: the edge tries both)."""
    import time

    from zoffload.robot.sensor import Reading

    src, mapper, cp = edge_run
    fleet, ask, ledger, lock, odo, keeper = _attached_keeper(edge_run)
    fleet.checkpoint = dataclasses.replace(cp, epoch=ask[1] if same_epoch else ask[1] - 1)
    for i in range(30, 34):
        assert keeper.attached(Reading(i, src.read(i), time.time()), ask) is None
        ledger.handed_off(i, {"capture_stamp": time.time(), "edge": ask[0], "epoch": ask[1]})
        ledger.records[i]["pose_source"] = "edge"  # answered, as ``ScanLedger.acked`` books it
        ledger.poses[i] = mapper.poses[i]
    fleet.on_sent(time.monotonic() - 0.5)
    assert keeper.attached(Reading(34, src.read(34), time.time()), ask) is not None
    got = keeper.prior_for(34)
    assert got is not None and got[0] == 34 and got[2] == (0 if same_epoch else -1)
