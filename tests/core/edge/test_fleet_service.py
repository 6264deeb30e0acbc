"""The mapping service's side of the fleet protocol over Zenoh on a loopback port: attach with a
checkpoint (the poses continue it), periodic and final checkpoints, stale epochs refused, another
edge's scans only counted, a full or draining edge refusing attaches, shedding a robot."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest
import zenoh

from tests.helpers import KEYS, client, listen_on, wait_for, wait_token
from zoffload.edge.fleet import Fleet
from zoffload.edge.mapping import MappingService
from zoffload.edge.recipe import BoundedMapper, MapperRecipe
from zoffload.edge.server import edge_zenoh
from zoffload.mapping.mapper import Registration, RobotMapper
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire
from zoffload.runtime.session import open_session
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")
SRC = SimulatedSource()


@contextmanager
def serving(service: MappingService, port: int) -> Iterator[zenoh.Session]:
    session = open_session(edge_zenoh(listen_on(port)))
    try:
        service.start(session)
        token = session.liveliness().declare_token(KEYS.edge_alive(service.edge_id))
        yield session
        token.undeclare()
    finally:
        service.stop()
        session.close()


class Inbox:
    """Every message of one type on one key."""

    def __init__(self, session: zenoh.Session, key: str, kind: type[wire.Message]) -> None:
        self.items: list = []
        self.sub = session.declare_subscriber(key, lambda s: self.items.append(
            wire.decode(s.payload.to_bytes(), expect=kind)))

    def wait(self, n: int, timeout: float = 20.0) -> None:
        wait_for(lambda: len(self.items) >= n, timeout, f"{n} messages")


def points(i: int) -> np.ndarray:
    return voxel_downsample(SRC.read(i).points, 0.05).astype(np.float32)


def scan(robot: str, seq: int, epoch: int = 0, edge: str = "", pts: np.ndarray | None = None) -> bytes:
    pts = points(seq) if pts is None else pts
    return wire.encode(wire.Scan(robot=robot, seq=seq, send_stamp=float(seq), capture_stamp=100.0 + seq,
                                 voxel=0.05, voxel_max=0.07, max_range=SRC.max_range, n_raw=len(pts),
                                 points=pts, epoch=epoch, edge=edge))


def attach(s: zenoh.Session, robot: str, epoch: int, edge: str = "e1", checkpoint: bytes = b"",
           seqs: list[int] | None = None, poses: np.ndarray | None = None, reads: int = 5
           ) -> wire.AttachReply:
    msg = wire.Attach(robot=robot, epoch=epoch, max_range=SRC.max_range, voxel_max=0.07, rate_hz=10.0,
                      checkpoint=checkpoint, local_seqs=np.asarray(seqs or [], np.int64),
                      local_poses=np.zeros((0, 4, 4)) if poses is None else poses, reads=reads)
    replies = list(s.get(KEYS.attach(robot, edge), payload=wire.encode(msg), timeout=5))
    assert len(replies) == 1 and replies[0].ok is not None
    return wire.decode(replies[0].ok.payload.to_bytes(), expect=wire.AttachReply)


def first_run(n: int) -> BoundedMapper:
    """The robot's first edge: the recipe's mapper over scans 0..n-1."""
    m = MapperRecipe()(wire.decode(scan("r1", 0), expect=wire.Scan))
    for i in range(n):
        m.register(i, points(i))
    return m


def balanced(service: MappingService) -> bool:
    st = service.status()
    return st["samples"] == st.get("received", 0) + st["drops"] + st.get("other_edge", 0)


def test_attach_continues_the_checkpoint_and_checkpoints_come_back(free_port: int) -> None:
    old = first_run(20)
    cp = old.checkpoint("r1", "e0", 1, 119.0)
    assert cp is not None and cp.seq == 19
    service = MappingService(KEYS, MapperRecipe(), edge_id="e1", workers=1, fleet=Fleet("e1", capacity=1),
                             checkpoint_every=3)
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("e1"))
        acks = Inbox(s, KEYS.scan_acks("r1"), wire.ScanAck)
        cps = Inbox(s, KEYS.checkpoints("r1"), wire.Checkpoint)
        # The robot registered scan 20 itself while it had no edge
        local = old.register(20, points(20)).pose
        reply = attach(s, "r1", 2, checkpoint=wire.encode(cp), seqs=[20], poses=local[None])
        assert reply.accepted and reply.epoch == 2 and reply.edge == "e1"
        assert (reply.robots, reply.capacity) == (1, 1)
        assert service.status()["capacity"] == 1 and service.status()["robots"] == 1
        pub = s.declare_publisher(KEYS.scan("r1"))
        for seq in range(21, 31):
            pub.put(scan("r1", seq, epoch=2, edge="e1"))
            acks.wait(seq - 20)
        ok = [a for a in acks.items if a.status == "ok"]
        assert [a.seq for a in ok] == list(range(21, 31))
        assert all(a.epoch == 2 and a.edge == "e1" for a in ok)
        for seq, a in zip(range(21, 31), ok, strict=True):  # where the first edge would have gone
            ref = old.register(seq, points(seq)).pose
            assert np.linalg.norm(a.pose[:3, 3] - ref[:3, 3]) < 0.1, (seq, a.pose[:3, 3], ref[:3, 3])
        assert np.linalg.norm(ok[0].pose[:3, 3]) > 1.0  # not back at the origin
        # Checkpoints: after the first scan of the epoch, then every 3
        cps.wait(4)
        assert [c.seq for c in cps.items] == [21, 24, 27, 30]
        assert all(c.epoch == 2 and c.edge == "e1" and not c.final and len(c.points) for c in cps.items)
        assert cps.items[0].stamp == 121.0
        np.testing.assert_allclose(cps.items[-1].pose, ok[-1].pose)
        # The map's trajectory holds the robot's own pose, then the edge's
        m = wire.decode(list(s.get(KEYS.map("r1", "e1"), timeout=5))[0].ok.payload.to_bytes(),
                        expect=wire.MapReply)
        assert m.seqs.tolist() == list(range(20, 31)) and m.scans == 10
        np.testing.assert_allclose(m.poses[0], local)

        # A stale epoch is refused, another edge's scan only counted, the epoch-less one mapped
        pub.put(scan("r1", 31, epoch=1, edge="e1"))
        acks.wait(11)
        assert acks.items[-1].status == "refused" and acks.items[-1].detail == "not attached (epoch 1)"
        assert acks.items[-1].epoch == 1 and acks.items[-1].edge == "e1"
        pub.put(scan("r1", 32, epoch=3, edge="e2"))
        wait_for(lambda: service.status().get("other_edge") == 1, what="other edge counted")
        # Attaches: stale, full, bad checkpoint
        assert attach(s, "r1", 2).detail == "stale epoch"
        full = attach(s, "r2", 1)
        assert not full.accepted and full.detail == "full: 1 of 1 robots" and full.capacity == 1
        assert attach(s, "r1", 5, checkpoint=b"junk").detail.startswith("bad checkpoint: ")
        assert "r2" not in service.robots
        time.sleep(0.3)
        assert len(acks.items) == 11  # nothing answered the other edge's scan
        st = service.status()
        assert st["drop.stale_epoch"] == 1 and st["attaches"] == 1 and st["attach_refused"] == 3
        assert st["checkpoints"] == 4 and st["checkpoint_bytes"] > 1000
        assert balanced(service)


def test_drain_sends_final_checkpoints_and_keeps_mapping_the_old_epoch(free_port: int) -> None:
    # A checkpoint after every registered scan, so one after the final would show
    service = MappingService(KEYS, MapperRecipe(), edge_id="e1", workers=1, fleet=Fleet("e1", capacity=4),
                             checkpoint_every=1)
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("e1"))
        acks = Inbox(s, KEYS.scan_acks("r1"), wire.ScanAck)
        cps = Inbox(s, KEYS.checkpoints("r1"), wire.Checkpoint)
        assert attach(s, "r1", 1).accepted and attach(s, "r2", 1).accepted  # r2 never sends a scan
        pub = s.declare_publisher(KEYS.scan("r1"))
        for seq in range(3):
            pub.put(scan("r1", seq, epoch=1, edge="e1"))
            acks.wait(seq + 1)
        cps.wait(3)  # one a scan
        service.begin_drain()
        wait_for(lambda: any(c.final for c in cps.items), 5, "the final checkpoint")  # idle: at once
        final = cps.items[-1]
        assert final.final and final.seq == 2 and final.epoch == 1
        assert service.status()["draining"] == 1.0
        assert attach(s, "r3", 1).detail == "draining"
        for seq in (3, 4, 5):  # still mapped while it moves, and no periodic checkpoint after the final
            pub.put(scan("r1", seq, epoch=1, edge="e1"))
            acks.wait(seq + 1)
        assert [a.status for a in acks.items[3:]] == ["ok"] * 3
        time.sleep(0.3)
        assert cps.items[-1] is final, [(c.seq, c.final) for c in cps.items]
        assert not service.drained()
        wait_for(service.drained, 5, "drained after a quiet second")
        assert service.status()["final_checkpoints"] == 1  # r2 had nothing to hand over
        assert balanced(service)


class SlowMapper:
    """A stand-in taking 50 ms a scan: one worker falls behind two robots at 20 Hz."""

    def __init__(self) -> None:
        self.seqs: list[int] = []

    @property
    def map_points(self) -> int:
        return 0

    @property
    def scans(self) -> int:
        return len(self.seqs)

    def register(self, seq: int, points: np.ndarray, times: np.ndarray | None = None) -> Registration:
        time.sleep(0.05)
        self.seqs.append(seq)
        return Registration(pose=np.eye(4), keypoints=1, sigma=0.1, map_points=0, proc_time=0.05,
                            icp_time=0.05)

    def map_cloud(self) -> np.ndarray:
        return np.zeros((0, 3), np.float32)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.seqs, np.int64), np.repeat(np.eye(4)[None], len(self.seqs), 0)


class SlowRecipe:
    def warm_up(self) -> None:
        pass

    def __call__(self, scan: wire.Scan, spill: object = None) -> SlowMapper:
        return SlowMapper()


@pytest.mark.parametrize("queue", [1, 100], ids=["dropping", "late-not-dropping"])
def test_an_overloaded_edge_sheds_its_newest_robot(free_port: int, queue: int) -> None:
    """One worker at 50 ms a scan, two robots at 20 Hz. A queue of 1 drops scans; a queue of 100
    drops none in the test's time but answers them later and later: both are behind."""
    # dropping: lateness alone may not shed (shed_late 1), so the drop rule is what acts
    fleet = Fleet("e1", capacity=4, window=1.0, shed_late=1.0 if queue == 1 else 0.05)
    service = MappingService(KEYS, SlowRecipe(), edge_id="e1", workers=1, queue=queue, fleet=fleet)
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("e1"))
        acks = {r: Inbox(s, KEYS.scan_acks(r), wire.ScanAck) for r in ("r1", "r2")}
        assert attach(s, "r1", 1).accepted and attach(s, "r2", 1).accepted
        pts = np.zeros((10, 3), np.float32)
        stop = threading.Event()
        sent_at: dict[int, float] = {}  # seq -> when it went (this process's monotonic clock: the edge's)

        def stream() -> None:
            pubs = {r: s.declare_publisher(KEYS.scan(r)) for r in ("r1", "r2")}
            seq = 0
            while not stop.is_set():
                sent_at[seq] = time.monotonic()
                for r, pub in pubs.items():
                    pub.put(scan(r, seq, epoch=1, edge="e1", pts=pts))
                seq += 1
                time.sleep(0.05)

        sender = threading.Thread(target=stream, daemon=True)
        sender.start()
        # another edge with room (its status, as it publishes it): shedding hands robots to it
        other = wire.Status(source="edge", id="e2", stamp=0.0, values={"capacity": 4.0, "robots": 0.0})
        try:
            def shed() -> bool:
                s.put(KEYS.edge_status("e2"), wire.encode(other))
                service.tick()
                return service.status().get("shed", 0) == 1

            wait_for(shed, 10, "a robot shed")
            status = service.status()
            if queue > 1:  # shed for lateness alone
                assert status.get("dropped", 0) == 0 and status["late"] > 0.5 * status["timed"]
            else:
                assert status["dropped"] > 0
            wait_for(lambda: any(a.detail == "shed: over capacity" for a in acks["r2"].items), 5,
                     "r2 refused")
        finally:
            stop.set()
            sender.join(5)
        assert not any(a.status == "refused" for a in acks["r1"].items)  # the oldest is kept
        # The scans r2 sent after its final checkpoint went (before it could have reached a robot)
        # are still mapped for ``quiet`` s, then refused: a robot's last scans before it moves get
        # poses. (No tick until the asserts: it would evict r2 and answer its queue "dropped".)
        final_at = service.fleet.attached["r2"].final_at

        def after() -> list[wire.ScanAck]:
            return [a for a in list(acks["r2"].items) if sent_at.get(a.seq, 0.0) > final_at]

        refused = [a.seq for a in after() if a.status == "refused"]
        assert refused and sent_at[min(refused)] > final_at + 0.9 * fleet.quiet
        # every scan sent before the first refused one answered (r2's backlog drains)
        sent_before = {q for q, t in sent_at.items() if final_at < t < sent_at[min(refused)]}
        wait_for(lambda: sent_before <= {a.seq for a in after()}, 10, "the scans of the grace answered")
        mapped = [a.seq for a in after() if a.status == "ok"]
        assert len(mapped) >= 3 and max(mapped) < min(refused), (mapped, refused)
        assert service.status()["capacity"] == 1
        assert service.fleet.attached["r2"].shed
        assert attach(s, "r3", 1).detail == "full: 2 of 1 robots"
        def shed_gone() -> bool:
            service.tick()
            return "r2" not in service.robots

        wait_for(shed_gone, 5, "the shed robot's session gone")
        wait_for(lambda: balanced(service), 5, "every sample counted")


def _shifted(dx: float) -> np.ndarray:
    t = np.eye(4)
    t[0, 3] = dx
    return t


def test_a_scan_with_the_robots_prior_after_an_outage_is_predicted_from_it(free_port: int) -> None:
    """Two robots drive the simulator's sharp turn (scans 786-804) and their scans in it are lost
    on the way. The one whose scan after the outage carries its own odometry's estimate
    (``Scan.prior``, as a bridging robot sends it) is registered where it is; the other is
    predicted by constant velocity and its edge loses it."""
    start, last_seen, back = 776, 786, 804
    raw = {i: SRC.read(i) for i in range(start, back + 3)}
    local = RobotMapper(voxel_size=0.8, max_range=SRC.max_range)  # the robot's coarse odometry
    for i in range(start, back + 1):
        local.register(i, raw[i].points)
    prior = np.stack([local.poses[-1], local.odometry.last_delta])
    service = MappingService(KEYS, MapperRecipe(), edge_id="e1", workers=1, fleet=Fleet("e1", capacity=2))
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("e1"))
        errors = {}
        for robot in ("r1", "r2"):
            acks = Inbox(s, KEYS.scan_acks(robot), wire.ScanAck)
            assert attach(s, robot, 1).accepted
            pub = s.declare_publisher(KEYS.scan(robot))
            seqs = [*range(start, last_seen + 1), back, back + 1, back + 2]
            for n, seq in enumerate(seqs, 1):
                pts = voxel_downsample(raw[seq].points, 0.05).astype(np.float32)
                msg = wire.decode(scan(robot, seq, epoch=1, edge="e1", pts=pts), expect=wire.Scan)
                if robot == "r1" and seq == back:
                    msg = dataclasses.replace(msg, prior_seq=back, prior=prior)
                    # as after an attach whose backfill found the robot's frame 1 cm off: the
                    # estimate, said in that frame (version 11), is moved by it
                    service.robots[robot].mapper.inner._handover = _shifted(0.01)
                    msg = dataclasses.replace(msg, prior_frame=1)
                pub.put(wire.encode(msg))
                acks.wait(n)
            assert all(a.status == "ok" for a in acks.items)
            truth = [np.linalg.inv(raw[start].gt_pose) @ raw[a.seq].gt_pose for a in acks.items[-3:]]
            errors[robot] = [float(np.linalg.norm(a.pose[:3, 3] - t[:3, 3]))
                             for a, t in zip(acks.items[-3:], truth, strict=True)]
        assert max(errors["r1"]) < 0.25 and min(errors["r2"]) > 0.5, errors
        assert service.robots["r1"].counters["predicted_from_prior"] == 1
        assert service.robots["r1"].counters["prior_frame_handed"] == 1
        assert service.robots["r1"].counters["prior_moved_by_attach"] == 1
        assert service.robots["r2"].counters["predicted_from_prior"] == 0
        assert service.status()["predicted_from_prior"] == 1 and balanced(service)


def test_a_robot_that_reads_6_gets_coded_checkpoints_and_a_corrupt_one_is_refused(free_port: int) -> None:
    """Version 6: a robot whose attach says it reads 6 gets its checkpoints' local map coded (a
    few bytes a point), one that does not (an older robot) float32 points; version 8 adds the
    turn rate. An attach whose coded
    map does not decode is refused there, not when the map is needed."""
    service = MappingService(KEYS, MapperRecipe(), edge_id="e1", workers=1, fleet=Fleet("e1", capacity=4),
                             checkpoint_every=3)
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("e1"))
        got = {}
        for robot, reads in (("r1", 6), ("r2", 5), ("r4", 8)):
            cps = Inbox(s, KEYS.checkpoints(robot), wire.Checkpoint)
            assert attach(s, robot, 1, reads=reads).accepted
            pub = s.declare_publisher(KEYS.scan(robot))
            for seq in range(4):
                pub.put(scan(robot, seq, epoch=1, edge="e1"))
            cps.wait(2)
            got[robot] = cps.items[-1]
        coded, plain = got["r1"], got["r2"]
        # version 8: the turn rate the mapper learnt goes to a robot that reads 8 only (the
        # simulated robot turns a little between any two scans)
        assert got["r4"].turn_rate > 0 and got["r4"].packed is not None
        assert coded.turn_rate == plain.turn_rate == 0.0
        assert coded.packed is not None and len(coded.points) == 0 and coded.n_points > 1000
        assert plain.packed is None and len(plain.points) > 1000
        # the older robot's map at the mapper's voxel, as before; the coded one at half of it, more
        # than twice the points in fewer bytes
        assert coded.n_points > 2 * len(plain.points) and len(wire.encode(coded)) < len(wire.encode(plain))
        broken = dataclasses.replace(coded, robot="r3", packed=coded.packed[:100])
        reply = attach(s, "r3", 1, checkpoint=wire.encode(broken), reads=6)
        assert not reply.accepted and reply.detail.startswith("bad checkpoint: "), reply.detail
        assert "r3" not in service.robots


def test_a_reattach_with_a_backfill_registers_the_outage_scans(free_port: int) -> None:
    """Version 9: a robot back after an outage sends the scans it registered itself at a coarse
    grid with its attach; its edge registers them before its next scan, which then comes with no
    gap. A backfill scan that does not decode is counted and the ones before it stand; a backfill
    that is not well formed is a malformed drop, and the attach stands without it."""
    from zoffload.robot.fleet import Sensor, backfill_payload
    from zoffload.robot.odometry import Backfilled

    sensor = Sensor(SRC.max_range, 0.07, 10.0)

    def fill(robot: str, seqs: range) -> tuple[np.ndarray, np.ndarray]:
        coarse = [Backfilled(i, 100.0 + i, 0, voxel_downsample(SRC.read(i).points, 0.8).astype(np.float32),
                             0.8) for i in seqs]
        data, sizes, _ = backfill_payload(robot, 2, sensor, coarse, 10**7)
        assert data is not None and sizes is not None
        return data, sizes

    service = MappingService(KEYS, MapperRecipe(), edge_id="e1", workers=1, fleet=Fleet("e1", capacity=4))
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("e1"))
        for robot in ("r1", "r2", "r3"):
            acks = Inbox(s, KEYS.scan_acks(robot), wire.ScanAck)
            assert attach(s, robot, 1).accepted
            pub = s.declare_publisher(KEYS.scan(robot))
            for n, seq in enumerate(range(12), 1):
                pub.put(scan(robot, seq, epoch=1, edge="e1"))
                acks.wait(n)
            data, sizes = fill(robot, range(12, 30))
            if robot == "r2":  # the 6th scan's payload cut short: it does not decode
                a, b = int(sizes[:5].sum()), int(sizes[:6].sum())
                bad = wire.decode(bytes(data[a:b]), expect=wire.Scan)
                assert bad.packed is not None
                one = wire.encode(dataclasses.replace(bad, packed=bad.packed[:-40]))
                data = np.frombuffer(bytes(data[:a]) + one + bytes(data[b:]), np.uint8)
                sizes = np.concatenate([sizes[:5], [len(one)], sizes[6:]])
            if robot == "r3":  # not well formed: sizes that do not cut it into whole scans
                sizes = np.concatenate([sizes[:-2], [int(sizes[-2]) - 1, int(sizes[-1]) + 1]])
            msg = wire.Attach(robot=robot, epoch=2, max_range=SRC.max_range, voxel_max=0.07, rate_hz=10.0,
                              local_seqs=np.zeros(0, np.int64), local_poses=np.zeros((0, 4, 4)), reads=9,
                              backfill=data, backfill_sizes=sizes.astype(np.int64))
            replies = list(s.get(KEYS.attach(robot, "e1"), payload=wire.encode(msg), timeout=5))
            assert wire.decode(replies[0].ok.payload.to_bytes(), expect=wire.AttachReply).accepted
            pub.put(scan(robot, 30, epoch=2, edge="e1"))
            acks.wait(13)
            assert acks.items[-1].status == "ok" and acks.items[-1].seq == 30
        got = {r: service.robots[r] for r in ("r1", "r2", "r3")}
        seqs = {r: got[r].mapper.trajectory()[0].tolist() for r in got}
        assert got["r1"].counters["backfilled"] == 18 and seqs["r1"] == list(range(31))
        assert got["r1"].mapper.inner.after_gap == 0  # scan 30 came with no gap
        assert got["r2"].counters["backfilled"] == 5 and got["r2"].counters["backfill_malformed"] == 13
        assert seqs["r2"] == [*range(17), 30]
        assert got["r3"].counters["backfilled"] == 0 and seqs["r3"] == [*range(12), 30]
        assert service.attach_drops.snapshot().get("malformed", 0) == 1
        assert service.status()["backfilled"] == 23 and balanced(service)
        assert list(got["r2"].mapper.backfilled_seqs) == list(range(12, 17))
        assert not got["r3"].mapper.backfilled_seqs
        # Version 10: a backfill whose first scan lies 9 after the edge's last (the robot's ring
        # shorter than its outage) is registered from the robot's pose of it (here r1's edge's:
        # the same scans, the same frame); without the poses it would be left
        r1_seqs, r1_poses = got["r1"].mapper.trajectory()
        acks = Inbox(s, KEYS.scan_acks("r4"), wire.ScanAck)
        assert attach(s, "r4", 1).accepted
        pub = s.declare_publisher(KEYS.scan("r4"))
        for n, seq in enumerate(range(12), 1):
            pub.put(scan("r4", seq, epoch=1, edge="e1"))
            acks.wait(n)
        data, sizes = fill("r4", range(20, 30))
        msg = wire.Attach(robot="r4", epoch=2, max_range=SRC.max_range, voxel_max=0.07, rate_hz=10.0,
                          local_seqs=np.zeros(0, np.int64), local_poses=np.zeros((0, 4, 4)), reads=10,
                          backfill=data, backfill_sizes=sizes.astype(np.int64),
                          backfill_poses=r1_poses[np.isin(r1_seqs, range(20, 30))])
        replies = list(s.get(KEYS.attach("r4", "e1"), payload=wire.encode(msg), timeout=5))
        assert wire.decode(replies[0].ok.payload.to_bytes(), expect=wire.AttachReply).accepted
        pub.put(scan("r4", 30, epoch=2, edge="e1"))
        acks.wait(13)
        r4 = service.robots["r4"]
        assert r4.counters["backfilled"] == 10 and list(r4.mapper.backfilled_seqs) == list(range(20, 30))
        assert r4.mapper.trajectory()[0].tolist() == [*range(12), *range(20, 31)]
