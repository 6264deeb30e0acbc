"""The mapping service on its own: a real Zenoh session on a loopback port, no server around it,
and a stand-in mapper that registers on cue so the queue's behaviour is deterministic."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import zenoh

from tests.daemon.edge.acks import Acks
from tests.helpers import KEYS, client, listen_on, wait_for, wait_token
from zoffload.edge.mapping import MappingService
from zoffload.edge.server import edge_zenoh
from zoffload.mapping.mapper import Registration
from zoffload.protocol import wire
from zoffload.runtime.session import open_session


class CuedMapper:
    """Holds each registration until ``gate`` is set; remembers which scans reached it."""

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.entered: list[int] = []
        self.seqs: list[int] = []
        self.clouds: list[np.ndarray] = []

    @property
    def map_points(self) -> int:
        return sum(len(c) for c in self.clouds)

    @property
    def scans(self) -> int:
        return len(self.seqs)

    def register(self, seq: int, points: np.ndarray, times: np.ndarray | None = None) -> Registration:
        self.entered.append(seq)
        self.gate.wait(10)
        self.seqs.append(seq)
        self.clouds.append(points)
        pose = np.eye(4)
        pose[0, 3] = float(seq)
        return Registration(pose=pose, keypoints=len(points), sigma=0.1, map_points=self.map_points,
                            proc_time=1e-3, icp_time=1e-3)

    def map_cloud(self) -> np.ndarray:
        return np.concatenate(self.clouds) if self.clouds else np.zeros((0, 3), np.float32)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        poses = [np.eye(4) for _ in self.seqs]
        for seq, pose in zip(self.seqs, poses, strict=True):
            pose[0, 3] = float(seq)
        return np.asarray(self.seqs, np.int64), np.asarray(poses).reshape(-1, 4, 4)


class CuedRecipe:
    """The stand-in factory: every robot gets a cued mapper (held, or already let through), kept
    here for the test to drive."""

    def __init__(self, held: bool = True) -> None:
        self.held = held
        self.mappers: dict[str, CuedMapper] = {}

    def warm_up(self) -> None:
        pass  # nothing to compile: the stand-in is plain Python

    def __call__(self, scan: wire.Scan, spill: object = None) -> CuedMapper:
        mapper = self.mappers.setdefault(scan.robot, CuedMapper())
        if not self.held:
            mapper.gate.set()
        return mapper


def scan(robot: str, seq: int, n: int = 100, bad: bool = False) -> bytes:
    """A scan of ``n`` random points; ``bad``: one that decodes but has no point to register."""
    pts = np.random.default_rng(seq).uniform(-10, 10, (0 if bad else n, 3)).astype(np.float32)
    return wire.encode(wire.Scan(robot=robot, seq=seq, send_stamp=float(seq), capture_stamp=0.0,
                                 voxel=0.05, voxel_max=0.07, max_range=40.0, n_raw=n, points=pts))


@contextmanager
def serving(service: MappingService, port: int) -> Iterator[zenoh.Session]:
    """The service on its own listening session, stopped on exit; a token declared after its
    declarations (as the server does) tells the test's client when it may send. The session is
    the edge's (``edge_zenoh``: acks wait up to 50 ms for room before they are dropped)."""
    session = open_session(edge_zenoh(listen_on(port)))
    try:
        service.start(session)
        token = session.liveliness().declare_token(KEYS.edge_alive("edge1"))  # held while served
        yield session
        token.undeclare()
    finally:
        service.stop()
        session.close()


def test_a_full_queue_is_thinned_and_every_scan_gets_one_ack(free_port: int) -> None:
    recipe = CuedRecipe()
    service = MappingService(KEYS, recipe, queue=2)
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        acks = Acks(s, "r1")
        pub = s.declare_publisher(KEYS.scan("r1"), congestion_control=zenoh.CongestionControl.BLOCK)
        pub.put(scan("r1", 0))
        wait_for(lambda: recipe.mappers.get("r1") is not None and recipe.mappers["r1"].entered == [0],
                 what="scan 0 in registration")
        # Scan 0 is held in the mapper: 1 and 2 fill the queue; 3 pushes out the oldest, 1, and
        # 4 then 3, not 2: dropping 2 would leave 1 and 2 without a pose, two in a row
        for seq in range(1, 5):
            pub.put(scan("r1", seq))
        wait_for(lambda: acks.seqs("dropped") == [1, 3], what="1 and 3 acked as dropped")
        assert all(a.detail == "edge mapper overloaded" and np.isnan(a.pose).all()
                   for a in acks.items)
        status = service.status()
        assert status["received"] == 5 and status["dropped"] == 2 and status["robots"] == 1
        assert status["r1.queue"] == 2 and status["r1.map_points"] == 0

        recipe.mappers["r1"].gate.set()
        wait_for(lambda: len(acks.items) == 5, what="an ack for every scan")
        ok = [a for a in acks.items if a.status == "ok"]
        assert [a.seq for a in ok] == [0, 2, 4] and recipe.mappers["r1"].entered == [0, 2, 4]
        assert [a.pose[0, 3] for a in ok] == [0.0, 2.0, 4.0] and ok[-1].map_points == 300
        assert all(a.queue_time >= 0 and a.keypoints == 100 for a in ok)
        assert np.isnan(ok[0].interarrival) and all(a.interarrival > 0 for a in ok[1:])
        assert service.status()["registered"] == 3 and service.status()["r1.queue"] == 0


def test_map_queries_errors_and_export_on_stop(free_port: int, tmp_path: Path) -> None:
    service = MappingService(KEYS, CuedRecipe(held=False), map_dir=tmp_path, map_format="ply")
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        acks = Acks(s, "r1")
        for seq in range(3):
            s.put(KEYS.scan("r1"), scan("r1", seq, bad=seq == 1))
            acks.wait(seq + 1)
        assert [a.status for a in acks.items] == ["ok", "error", "ok"]
        assert "no points" in acks.items[1].detail and service.counters["errors"] == 1

        replies = list(s.get(KEYS.map("r1", "edge1"), timeout=5))
        assert str(replies[0].ok.key_expr) == KEYS.map("r1", "edge1")
        m = wire.decode(replies[0].ok.payload.to_bytes(), expect=wire.MapReply)
        assert isinstance(m, wire.MapReply)
        assert m.robot == "r1" and m.scans == 2 and list(m.seqs) == [0, 2] and len(m.points) == 200
        assert m.edge == "edge1"  # the reply names its edge
        # only its own key: not another edge's, nor the key before per-edge maps
        for key in (KEYS.map("r1", "edge2"), KEYS.map_before("r1")):
            assert list(s.get(key, timeout=2)) == [], key
        unknown = list(s.get(KEYS.map("nobody", "edge1"), timeout=5))
        assert unknown[0].err is not None and b"no map" in unknown[0].err.payload.to_bytes()
    # Stopped: the map, trajectory and counters are on disk
    assert (tmp_path / "r1_map.ply").stat().st_size > 1000
    assert list(np.load(tmp_path / "r1_trajectory.npz")["seqs"]) == [0, 2]
    summary = json.loads((tmp_path / "r1_edge.json").read_text())
    assert summary == {"received": 3, "registered": 2, "errors": 1, "map_points": 200}


def test_without_a_mapper_it_only_receives_and_acks(free_port: int, tmp_path: Path) -> None:
    service = MappingService(KEYS, None, map_dir=tmp_path)
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        acks = Acks(s, "r1")
        s.put(KEYS.scan("r1"), scan("r1", 0, bad=True))  # not even registered
        wait_for(lambda: len(acks.items) == 1, what="the ack")
        assert acks.items[0].status == "ok" and acks.items[0].detail == "mapping disabled"
        assert service.robots["r1"].counters["received_only"] == 1
        err = list(s.get(KEYS.map("r1", "edge1"), timeout=5))[0].err
        assert err is not None and b"no map" in err.payload.to_bytes()
    assert list(tmp_path.iterdir()) == []
