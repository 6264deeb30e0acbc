"""The robot's fleet decisions without Zenoh: when it moves, which acks and checkpoints count,
what the next attach carries, the failover timings."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

import zoffload.robot.fleet as fleet_module
from zoffload.mapping.checkpoint import take_checkpoint
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire
from zoffload.robot.fleet import (
    DRAIN_WAIT,
    OWN_CHECKPOINT_AFTER,
    RETRY_MIN,
    STAY_SILENT,
    FleetState,
    Sensor,
    attach_message,
    backfill_budget,
    backfill_grids,
    backfill_payload,
)
from zoffload.robot.odometry import Backfilled, Snapshot
from zoffload.sources.base import open_scan_source


def checkpoint(edge: str, epoch: int, seq: int, final: bool = False, robot: str = "r1") -> wire.Checkpoint:
    return wire.Checkpoint(robot=robot, edge=edge, epoch=epoch, seq=seq, stamp=0.0, voxel_size=0.4,
                           max_range=40.0, min_range=0.0, max_points_per_voxel=20, pose=np.eye(4),
                           delta=np.eye(4), points=np.zeros((0, 3), np.float32), final=final)


def reply(edge: str, epoch: int, accepted: bool = True, detail: str = "") -> wire.AttachReply:
    return wire.AttachReply(robot="r1", edge=edge, epoch=epoch, accepted=accepted, detail=detail,
                            robots=1, capacity=4)


def attached(f: FleetState, now: float = 0.0) -> tuple[str, int]:
    ask = f.next_attach(now, int(now * 1000) + 1000)
    assert ask is not None
    assert f.attach_result(*ask, reply(*ask), now) == "attached"
    assert f.target() == ask
    return ask


def test_attach_then_silence_moves_and_the_failover_is_timed() -> None:
    f = FleetState("r1", failover_after=0.5)
    assert f.next_attach(0.0, 1000) is None  # nobody to ask
    f.edge_present("e1")
    f.edge_present("e2")
    edge, epoch = attached(f)
    assert f.next_attach(0.1, 1100) is None  # attached: nothing to ask
    f.on_sent(1.0)
    assert not f.silent(1.4)
    assert not f.on_ack(edge, epoch, "ok", 1.45, in_flight=1)  # answered: the clock restarts
    assert not f.silent(2.0)  # the scan still in flight went before that ack: lost alone, maybe
    f.no_scans_in_flight()  # it expired
    assert not f.silent(3.0)
    f.on_sent(3.0)
    assert not f.silent(3.5)
    assert f.silent(3.6) and f.target() is None and f.moves["silence"] == 1
    other = "e2" if edge == "e1" else "e1"
    ask = f.next_attach(3.6, 4000)
    assert ask is not None and ask[0] == other and ask[1] > epoch  # the silent edge is asked last
    assert f.attach_result(*ask, reply(*ask), 3.7) == "attached"
    f.on_sent(3.8)
    f.on_ack(other, ask[1], "ok", 3.9, in_flight=1)  # one more in flight, sent before this ack
    assert not f.silent(4.85) and f.silent(4.95)  # no ack at all for twice failover_after
    m = f.metrics()
    # silent at 3.6, first ok ack from the next edge at 3.9
    assert len(m["failover_s"]) == 1 and abs(m["failover_s"][0] - 0.3) < 1e-9
    assert m["moves"] == {"silence": 2} and m["attaches"] == 2 and m["failovers"] == 1
    assert m["per_edge"] == {edge: 1, other: 1}


def test_token_drain_final_checkpoint_and_refusal_each_move_the_robot() -> None:
    f = FleetState("r1", failover_after=0.5)
    for e in ("e1", "e2", "e3"):
        f.edge_present(e)
    edge, epoch = attached(f)
    assert not f.edge_status(edge, {"capacity": 4, "robots": 1, "draining": 0.0}, 1.0)
    # Our edge drains: the robot waits for its final checkpoint (the whole local map) ...
    assert not f.edge_status(edge, {"capacity": 4, "robots": 1, "draining": 1.0}, 1.0)
    assert f.target() == (edge, epoch) and not f.silent(1.0 + DRAIN_WAIT - 0.1)
    # ... and moves anyway if it does not come in time
    assert f.silent(1.0 + DRAIN_WAIT + 0.1) and f.target() is None and f.moves["draining"] == 1
    edge, epoch = attached(f, 2.0)
    # Draining, then the final checkpoint: the move comes with it, at once
    assert not f.edge_status(edge, {"capacity": 4, "robots": 1, "draining": 1.0}, 2.1)
    assert f.on_checkpoint(checkpoint(edge, epoch, 4, final=True), 2.2) == "final" and f.target() is None
    assert not f.silent(10.0)  # nothing left to time out
    edge, epoch = attached(f, 4.0)
    assert not f.on_ack(edge, epoch - 1, "refused", 5.0, 0)  # another epoch's refusal: not ours
    assert f.on_ack(edge, epoch, "refused", 5.0, 0) and f.target() is None
    # e1..e3 all left or refused us: the remaining one is the only candidate
    assert f.moves == {"draining": 1, "final": 1, "refused": 1}
    f.edge_present("e4")
    edge, epoch = attached(f, 5.1)
    assert f.edge_gone(edge, 6.0) and f.moves["token"] == 1 and f.target() is None
    assert not f.edge_gone("nobody", 6.0)


def test_only_the_current_assignment_gives_checkpoints_and_the_newest_wins() -> None:
    f = FleetState("r1", failover_after=0.5)
    f.edge_present("e1")
    edge, epoch = attached(f)
    assert f.on_checkpoint(checkpoint(edge, epoch - 1, 50), 1.0) == "stale"
    assert f.on_checkpoint(checkpoint("e9", epoch, 50), 1.0) == "stale"
    assert f.on_checkpoint(checkpoint(edge, epoch, 50, robot="r2"), 1.0) == "stale"
    # one that came before this assignment was made (so its coded map was not decoded) is stale
    assert f.on_checkpoint(checkpoint(edge, epoch, 30), 1.0, checked=False) == "stale"
    assert f.on_checkpoint(checkpoint(edge, epoch, 20), 1.0) == "kept"
    assert f.on_checkpoint(checkpoint(edge, epoch, 10), 1.0) == "older"
    assert f.checkpoint is not None and f.checkpoint.seq == 20
    assert f.current(edge, epoch) and not f.current(edge, epoch + 1) and not f.current("e9", epoch)


def test_the_attach_carries_the_edges_checkpoint_unless_the_robots_own_is_much_newer() -> None:
    f = FleetState("r1", failover_after=0.5)
    f.edge_present("e1")
    edge, epoch = attached(f)
    f.on_checkpoint(checkpoint(edge, epoch, 20), 1.0)
    poses = np.repeat(np.eye(4)[None], 6, axis=0)
    seqs = np.arange(25, 31, dtype=np.int64)
    # The robot's own (its local odometry's, a coarser map) only a few scans newer: the edge's
    # goes, with every local pose after it
    cp, s, p = f.attach_payload(Snapshot(checkpoint("", 0, 27), seqs, poses))
    assert cp is not None and cp.edge == edge and list(s) == list(range(25, 31)) and p.shape == (6, 4, 4)
    # Far newer (the robot went on alone): its own, and the poses after it
    mine = checkpoint("", 0, 20 + OWN_CHECKPOINT_AFTER + 1)
    far = np.arange(40, 46, dtype=np.int64)
    cp, s, p = f.attach_payload(Snapshot(mine, far, poses))
    assert cp is mine and list(s) == [42, 43, 44, 45] and p.shape == (4, 4, 4)
    cp, s, _ = f.attach_payload(Snapshot(checkpoint("", 0, 10), seqs, poses))
    assert cp is not None and cp.edge == edge and list(s) == list(range(25, 31))  # the edge's is fresher
    cp, s, _ = f.attach_payload(None)
    assert cp is not None and cp.seq == 20 and len(s) == 0


def test_an_edge_that_reads_5_gets_a_version_5_attach_with_a_float32_map() -> None:
    """The robot's checkpoint is coded (version 6). An edge whose status said it reads 6 gets it
    so, with the robot saying it reads 6 or newer (the edge then codes its checkpoints too); an older edge
    gets the same map as float32 points in an attach that version 5 reads."""
    pytest.importorskip("kiss_icp")
    from zoffload.mapping.mapper import RobotMapper
    from zoffload.sources.simulated import SimulatedSource

    src = SimulatedSource()
    m = RobotMapper(voxel_size=0.8, max_range=src.max_range)
    for i in range(3):
        m.register(i, src.read(i).points)
    cp = take_checkpoint(m.odometry, "r1", "", 0, 2, 0.0, 0.8)
    assert cp.packed is not None
    sensor = Sensor(40.0, 0.07, 10.0)
    seqs, poses = np.arange(3, 5, dtype=np.int64), np.repeat(np.eye(4)[None], 2, 0)
    new = wire.decode(wire.encode(attach_message("r1", 7, sensor, cp, seqs, poses, 6)), expect=wire.Attach)
    assert new.reads == max(wire.READS) >= 6
    assert wire.decode(new.checkpoint, expect=wire.Checkpoint).packed is not None
    for edge_reads in (3, 5):
        data = wire.encode(attach_message("r1", 7, sensor, cp, seqs, poses, edge_reads))
        old = msgpack.unpackb(data)
        assert old["v"] <= 5 and "reads" not in old  # what a version-5 edge decodes
        inner = msgpack.unpackb(old["checkpoint"])
        assert inner["v"] <= 5 and "packed" not in inner
        got = wire.decode(old["checkpoint"], expect=wire.Checkpoint)
        np.testing.assert_array_equal(got.points, cp.cloud())
    assert attach_message("r1", 7, sensor, None, seqs, poses, 5).checkpoint == b""


def test_the_turn_rate_goes_only_to_an_edge_that_reads_8() -> None:
    """Version 8: the checkpoint the robot hands on keeps the turn rate its mapper learnt for an
    edge that reads 8; an older edge gets the checkpoint without it, as the version it reads."""
    cp = dataclasses.replace(checkpoint("e1", 3, 20), turn_rate=0.09)
    sensor = Sensor(40.0, 0.07, 10.0)
    seqs, poses = np.zeros(0, np.int64), np.zeros((0, 4, 4))
    for edge_reads, rate, newest in ((8, 0.09, 8), (7, 0.0, 2), (6, 0.0, 2), (5, 0.0, 2)):
        data = wire.encode(attach_message("r1", 4, sensor, cp, seqs, poses, edge_reads))
        inner = msgpack.unpackb(msgpack.unpackb(data)["checkpoint"])
        assert inner["v"] == newest and inner.get("turn_rate", 0.0) == rate, (edge_reads, inner["v"])
        assert wire.decode(wire.decode(data, expect=wire.Attach).checkpoint, expect=wire.Checkpoint).seq == 20


def test_a_new_edge_is_asked_once_its_status_says_which_version_it_reads() -> None:
    """The attach depends on the version the edge reads, which its status says: an edge that just
    appeared is asked once its status came, or after ``status_wait`` without one (an edge too old
    to say it)."""
    f = FleetState("r1", failover_after=0.5, status_wait=2.0)
    f.edge_present("e1", 10.0)
    assert f.next_attach(10.5, 10_500) is None
    f.edge_status("e1", {"capacity": 4, "robots": 0, "wire.reads": 6.0}, 10.6)
    ask = f.next_attach(10.6, 10_600)
    assert ask is not None and ask[0] == "e1" and f.reads("e1") == 6
    g = FleetState("r1", failover_after=0.5, status_wait=2.0)
    g.edge_present("old", 10.0)  # says nothing
    assert g.next_attach(11.9, 11_900) is None
    ask = g.next_attach(12.1, 12_100)
    assert ask is not None and ask[0] == "old" and g.reads("old") == 3


def test_unanswered_or_refused_attaches_back_off() -> None:
    f = FleetState("r1", failover_after=0.5)
    f.edge_present("e1")
    ask = f.next_attach(0.0, 1000)
    assert ask is not None
    assert f.attach_result(*ask, None, 0.0) == "no_answer"
    assert f.next_attach(RETRY_MIN / 2, 1001) is None  # backing off
    again = f.next_attach(RETRY_MIN + 0.01, 1002)
    assert again is not None and again[1] > ask[1]
    assert f.attach_result(*again, None, 0.3) == "no_answer"
    assert f.next_attach(0.3 + RETRY_MIN + 0.01, 1003) is None  # the backoff doubled
    third = f.next_attach(0.3 + 2 * RETRY_MIN + 0.01, 1004)
    assert third is not None
    assert f.attach_result(*third, reply(third[0], third[1] + 1), 1.0) == "stale"  # not our epoch
    fourth = f.next_attach(5.0, 5000)
    assert fourth is not None
    full = reply(*fourth, accepted=False, detail="full: 4 of 4 robots")
    assert f.attach_result(*fourth, full, 5.0) == "refused"
    assert f.next_attach(5.1, 5100) is None  # refused: not asked again for a while
    m = f.metrics()
    assert m["attach_no_answer"] == 2 and m["attach_refused"] == 1 and m["attach_stale"] == 1
    assert m["attaches"] == 0 and m["edge"] == ""


def test_the_first_scan_waits_for_the_attach_while_the_fleet_state_knows_no_edge_yet() -> None:
    """At startup an edge's token let the robot start before the fleet link's own presence
    callback told its state: "no edge known" then read as "none to ask", the robot mapped its
    first scans itself and the edge began its map mid-drive. It waits for the edge (bounded), and
    returns at once only when edges are known and none may take it."""
    import threading
    import time

    from zoffload.protocol.keys import Keys
    from zoffload.robot.fleet import FleetLink

    f = FleetState("r1", failover_after=0.5)
    link = FleetLink(Keys("zoffload"), f, sensor=None, attach_timeout=1.0)  # type: ignore[arg-type]

    def later() -> None:
        time.sleep(0.2)
        f.edge_present("e1")  # the presence callback
        time.sleep(0.1)
        attached(f)  # the fleet thread's attach

    t = threading.Thread(target=later)
    t0 = time.monotonic()
    t.start()
    assert link.wait_settled(3.0) and 0.25 < time.monotonic() - t0 < 2.0
    t.join()
    t0 = time.monotonic()
    assert link.wait_settled(3.0) and time.monotonic() - t0 < 0.1  # attached: at once
    g = FleetState("r1", failover_after=0.5)
    g.edge_present("e1")
    now = time.monotonic()
    ask = g.next_attach(now, int(now * 1000))
    assert ask is not None and g.attach_result(*ask, reply(*ask, accepted=False), now) != "attached"
    t0 = time.monotonic()  # the only edge refused us: none to ask, at once
    assert not FleetLink(Keys("zoffload"), g, None, 1.0).wait_settled(3.0)  # type: ignore[arg-type]
    assert time.monotonic() - t0 < 0.1
    lone = FleetLink(Keys("zoffload"), FleetState("r1", failover_after=0.5), None, 1.0)  # type: ignore[arg-type]
    t0 = time.monotonic()  # no edge known (its token there, the callback not yet): it waits, bounded
    assert not lone.wait_settled(0.3, present=lambda: True)
    assert time.monotonic() - t0 >= 0.3
    t0 = time.monotonic()  # the token that let the robot start went again: no wait
    assert not lone.wait_settled(3.0, present=lambda: False) and time.monotonic() - t0 < 0.1


def test_a_silent_edge_is_kept_while_no_other_edge_could_take_the_robot() -> None:
    f = FleetState("r1", failover_after=0.5)
    f.edge_present("e1")
    edge, epoch = attached(f)
    f.on_sent(1.0)
    # Alone: a busy edge (a restart that just took every robot) is not re-attached, which would
    # cost a second's backoff and a re-seed; the local odometry bridges meanwhile
    assert not f.silent(1.6) and f.target() == (edge, epoch)
    assert not f.silent(2.0) and f.counters["silence_stayed"] == 1  # one silence, counted once
    assert not f.on_ack(edge, epoch, "ok", 2.1, in_flight=0)  # it caught up: no move, no failover
    assert f.metrics()["failover_s"] == [] and f.moves == {}
    # A second edge appears during the next silence: the robot goes there
    f.on_sent(3.0)
    assert not f.silent(3.6)
    f.edge_present("e2")
    assert f.silent(3.7) and f.moves["silence"] == 1 and f.counters["silence_stayed"] == 2
    ask = f.next_attach(3.7, 5000)
    assert ask is not None and ask[0] == "e2"


def test_a_lone_silent_edge_is_re_attached_after_stay_silent_times_failover_after() -> None:
    f = FleetState("r1", failover_after=0.5)
    f.edge_present("e1")
    edge, epoch = attached(f)
    f.on_sent(1.0)
    assert not f.silent(1.6)  # silent for more than failover_after: kept, the stay starts
    # the robot stops sending to a silent edge and its scans expire: that restarts no clock
    t = 1.6
    while t < 1.6 + STAY_SILENT * 0.5 - 0.1:
        f.no_scans_in_flight()
        f.on_sent(t)
        assert not f.silent(t + 0.05), t
        t += 0.3
    assert f.counters["silence_stayed"] == 1  # one silence, counted once
    assert f.silent(1.6 + STAY_SILENT * 0.5 + 0.05) and f.moves["silence"] == 1
    ask = f.next_attach(5.3, 9000)  # the same edge, asked again after its second
    assert ask is not None and ask[0] == edge and ask[1] > epoch


def test_the_robot_knows_which_codec_version_each_live_edge_reads() -> None:
    """From the edges' status (``wire.reads``): a scan's prior (version 5) goes only to an edge
    that said it reads 5; an edge that said nothing, or nonsense, reads 3 as far as the robot knows."""
    f = FleetState("r1", failover_after=0.5)
    for e in ("e1", "e2", "e3"):
        f.edge_present(e)
    assert f.reads("e1") == 3 and f.reads("nobody") == 3
    f.edge_status("e1", {"capacity": 4, "robots": 1, "wire.reads": 5.0}, 1.0)
    f.edge_status("e2", {"capacity": 4, "robots": 1}, 1.0)
    f.edge_status("e3", {"capacity": 4, "robots": 1, "wire.reads": float("nan")}, 1.0)
    f.edge_status("gone", {"wire.reads": 5.0}, 1.0)  # no token: not recorded
    assert [f.reads(e) for e in ("e1", "e2", "e3", "gone")] == [5, 3, 3, 3]
    f.edge_status("e3", {"wire.reads": 1e9}, 2.0)
    assert f.reads("e3") == 3


def test_the_backfill_goes_only_to_an_edge_that_reads_9_and_within_its_bytes() -> None:
    """Version 9: the scans the robot registered itself go with the attach, each a q16d scan of
    its coarse grid, only to an edge that reads 9; beyond the byte budget they are thinned
    evenly, the first and the last kept; nothing when not one fits."""
    rng = np.random.default_rng(3)
    fill = [Backfilled(seq, 100.0 + seq / 10, 28_000, rng.uniform(-30, 30, (900, 3)).astype(np.float32), 0.8)
            for seq in range(40, 60)]
    sensor = Sensor(40.0, 0.07, 10.0)
    seqs, poses = np.zeros(0, np.int64), np.zeros((0, 4, 4))
    old = wire.decode(wire.encode(attach_message("r1", 4, sensor, None, seqs, poses, 8, fill)),
                      expect=wire.Attach)
    assert old.backfill is None and old.backfill_sizes is None
    full = wire.decode(wire.encode(attach_message("r1", 4, sensor, None, seqs, poses, 9, fill, 10**7)),
                       expect=wire.Attach)
    scans = full.backfill_scans()
    assert [s.seq for s in scans] == list(range(40, 60))
    assert all(s.coding == "q16d" and s.voxel == 0.8 and s.epoch == 4 and s.robot == "r1" for s in scans)
    cloud = scans[0].cloud_and_times()[0]
    assert np.abs(cloud - fill[0].points).max() <= 0.04 + 1e-6  # a tenth of the grid for a step
    each = len(full.backfill) // 20
    thin = wire.decode(wire.encode(attach_message("r1", 4, sensor, None, seqs, poses, 9, fill, 7 * each)),
                       expect=wire.Attach)
    kept = [s.seq for s in thin.backfill_scans()]
    assert thin.backfill is not None and len(thin.backfill) <= 7 * each
    assert kept[0] == 40 and kept[-1] == 59 and 4 <= len(kept) <= 7
    assert max(np.diff(kept)) - min(np.diff(kept)) <= 1  # evenly
    none = attach_message("r1", 4, sensor, None, seqs, poses, 9, fill, each // 2)
    assert none.backfill is None and none.backfill_sizes is None


def test_the_backfill_goes_at_the_finest_grid_its_bytes_allow(monkeypatch: pytest.MonkeyPatch) -> None:
    """The ring keeps its scans at a quarter of the local odometry's voxel; an attach sends all of
    them at the finest of 0.2, 0.4 and 0.8 m where their coded scans fit its bytes (a scan's
    ``voxel`` says which, one centroid per cell of it) and thins them only at the odometry's 0.8 m.
    The bytes: what the link was seen to carry in half the attach's timeout, within the floor and
    the cap; the points: at most ``BACKFILL_POINTS``."""
    assert backfill_grids(0.2, 0.8) == [0.2, 0.4, 0.8]
    assert backfill_grids(0.3, 1.0) == [0.3, 0.6, 1.0]
    assert backfill_grids(0.8, None) == backfill_grids(0.8, 0.5) == [0.8]
    assert backfill_budget(0.0, 131_072, 1 << 20, 1.0) == 131_072  # nothing seen: the floor
    assert backfill_budget(float("nan"), 131_072, 1 << 20, 1.0) == 131_072
    assert backfill_budget(1e6, 131_072, 1 << 20, 1.0) == 500_000  # 1 MB/s for half a second
    assert backfill_budget(1e9, 131_072, 1 << 20, 1.0) == 1 << 20  # the cap
    assert backfill_budget(1e9, 131_072, 0, 1.0) == 131_072  # a cap below the floor: the floor
    assert backfill_budget(1e9, 0, 1 << 20, 1.0) == 0  # a floor of 0: no backfill
    src = open_scan_source("sim")
    fill = [Backfilled(seq, 100.0 + seq / 10, 28_000,
                       voxel_downsample(src.read(seq).points, 0.2).astype(np.float32), 0.2, None, 0.8)
            for seq in range(40, 52)]
    sensor = Sensor(40.0, 0.07, 10.0)
    seqs, poses = np.zeros(0, np.int64), np.zeros((0, 4, 4))

    def attach(budget: int) -> tuple[list[wire.Scan], int]:
        a = wire.decode(wire.encode(attach_message("r1", 4, sensor, None, seqs, poses, 10, fill, budget)),
                        expect=wire.Attach)
        return a.backfill_scans(), len(a.backfill) if a.backfill is not None else 0

    fine, fine_bytes = attach(10**7)
    assert [s.seq for s in fine] == list(range(40, 52)) and {s.voxel for s in fine} == {0.2}
    assert [s.n_points for s in fine] == [len(b.points) for b in fill]
    mid, mid_bytes = attach(fine_bytes - 1)
    assert [s.seq for s in mid] == list(range(40, 52)) and {s.voxel for s in mid} == {0.4}
    assert mid_bytes < fine_bytes / 1.5
    for s, b in zip(mid, fill, strict=True):  # one centroid per 0.4 m cell of the ring's points
        assert s.n_points == len(voxel_downsample(b.points, 0.4)) < len(b.points) / 1.5
    coarse, coarse_bytes = attach(mid_bytes - 1)
    assert len(coarse) == 12 and {s.voxel for s in coarse} == {0.8} and coarse_bytes < mid_bytes
    thin, thin_bytes = attach(coarse_bytes // 2)
    kept = [s.seq for s in thin]
    assert {s.voxel for s in thin} == {0.8} and kept[0] == 40 and kept[-1] == 51 and len(kept) < 12
    assert thin_bytes <= coarse_bytes // 2
    # and, finer than the odometry's voxel, within BACKFILL_POINTS (an edge's max_points together)
    monkeypatch.setattr("zoffload.robot.fleet.BACKFILL_POINTS", sum(len(b.points) for b in fill) - 1)
    capped, _ = attach(10**7)
    assert len(capped) == 12 and {s.voxel for s in capped} == {0.4}
    coarse_points = sum(s.n_points for s in coarse)  # and at the coarsest, thinned to them
    monkeypatch.setattr("zoffload.robot.fleet.BACKFILL_POINTS", coarse_points // 2)
    few, _ = attach(10**7)
    assert {s.voxel for s in few} == {0.8} and len(few) < 12
    assert sum(s.n_points for s in few) <= coarse_points // 2


def test_a_grid_clearly_over_the_budget_is_left_after_coding_a_few_of_its_scans(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``backfill_payload`` codes ``BACKFILL_PROBE`` scans of a grid finer than the coarsest
    first and leaves the grid without coding the rest when their bytes a point put all over the
    budget by ``BACKFILL_PROBE_MARGIN``: the same backfill as coding every scan at every grid, for
    budgets from below the coarsest to above the finest, with fewer scans coded."""
    src = open_scan_source("sim")
    fill = [Backfilled(seq, 100.0 + seq / 10, 28_000,
                       voxel_downsample(src.read(seq).points, 0.2).astype(np.float32), 0.2, None, 0.8)
            for seq in range(0, 120, 4)]
    sensor = Sensor(40.0, 0.07, 10.0)
    coded: list[float] = []
    real = fleet_module._backfill_scan

    def counting(*args: object) -> bytes:
        coded.append(float(args[-1]))  # type: ignore[arg-type]
        return real(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(fleet_module, "_backfill_scan", counting)

    def payload(budget: int, probe: int) -> tuple[list[int], list[float], int]:
        monkeypatch.setattr(fleet_module, "BACKFILL_PROBE", probe)
        coded.clear()
        data, sizes, kept = backfill_payload("r1", 4, sensor, fill, budget)
        grids = sorted({s.voxel for s in wire.Attach(
            robot="r1", epoch=4, max_range=40.0, voxel_max=0.07, rate_hz=10.0,
            local_seqs=np.zeros(0, np.int64), local_poses=np.zeros((0, 4, 4)), backfill=data,
            backfill_sizes=sizes).backfill_scans()})
        return kept, grids, len(coded)

    whole = payload(10**8, len(fill))[1]
    assert whole == [0.2]
    chosen = set()
    fewer = 0
    for budget in (20_000, 60_000, 131_072, 250_000, 400_000, 600_000, 10**7):
        kept, grids, n = payload(budget, 5)
        every_kept, every_grids, every_n = payload(budget, len(fill))  # every scan coded at each grid tried
        assert (kept, grids) == (every_kept, every_grids), budget
        assert n <= every_n
        fewer += n < every_n
        chosen.update(grids)
    assert chosen == {0.2, 0.4, 0.8}  # the budgets cover every grid
    assert fewer >= 3  # and where a finer grid did not fit, it was left after its probe


def test_the_robots_pose_of_each_backfilled_scan_goes_to_an_edge_that_reads_10() -> None:
    """Version 10: with the backfill, the local odometry's pose of each scan kept (thinned alike);
    an edge that reads 9 gets the scans without them."""
    rng = np.random.default_rng(4)
    fill = []
    for seq in range(40, 60):
        pose = np.eye(4)
        pose[0, 3] = seq / 10
        cloud = rng.uniform(-30, 30, (900, 3)).astype(np.float32)
        fill.append(Backfilled(seq, 100.0 + seq / 10, 28_000, cloud, 0.8, pose))
    sensor = Sensor(40.0, 0.07, 10.0)
    seqs, poses = np.zeros(0, np.int64), np.zeros((0, 4, 4))
    v9 = wire.decode(wire.encode(attach_message("r1", 4, sensor, None, seqs, poses, 9, fill, 10**7)),
                     expect=wire.Attach)
    assert v9.backfill_sizes is not None and v9.backfill_poses is None
    each = len(v9.backfill) // 20 if v9.backfill is not None else 0
    thin = wire.decode(wire.encode(attach_message("r1", 4, sensor, None, seqs, poses, 10, fill, 7 * each)),
                       expect=wire.Attach)
    kept = [s.seq for s in thin.backfill_scans()]
    assert thin.backfill_poses is not None and len(thin.backfill_poses) == len(kept) < 20
    np.testing.assert_allclose(thin.backfill_poses[:, 0, 3], np.array(kept) / 10)
    unposed = [dataclasses.replace(b, pose=None) for b in fill]  # a ring of an older robot: none sent
    assert attach_message("r1", 4, sensor, None, seqs, poses, 10, unposed, 10**7).backfill_poses is None
