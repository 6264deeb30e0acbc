"""The mapping service's admission, worker pool and eviction, on a real Zenoh session with stand-in
mappers (tests/daemon/edge/test_mapping.py)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from tests.daemon.edge.acks import Acks
from tests.daemon.edge.test_mapping import CuedMapper, CuedRecipe, scan, serving
from tests.helpers import KEYS, client, listen_on, running_edge, wait_for, wait_token
from zoffload.edge.admission import Admission
from zoffload.edge.mapping import MappingService
from zoffload.mapping.mapper import Registration
from zoffload.protocol import wire
from zoffload.runtime.config import AdmissionSettings, DetectorSettings, EdgeSettings, MapperSettings


def own_threads() -> int:
    """Threads started by the service: zenoh-python runs each subscriber's callback on a thread of
    its own ("pyo3-closure"), and the test's client declares one per robot."""
    return sum(not isinstance(t, threading._DummyThread) and "pyo3-closure" not in t.name
               for t in threading.enumerate())


class WatchedMapper(CuedMapper):
    """Registers at once, but slowly enough for workers to overlap, and records any overlap."""

    def __init__(self, overlaps: list[str], robot: str) -> None:
        super().__init__()
        self.gate.set()
        self.robot, self.overlaps, self.active = robot, overlaps, 0

    def register(self, seq: int, points: np.ndarray, times: np.ndarray | None = None) -> Registration:
        self.active += 1
        if self.active > 1:
            self.overlaps.append(self.robot)
        time.sleep(0.002)
        try:
            return super().register(seq, points)
        finally:
            self.active -= 1


class WatchedRecipe(CuedRecipe):
    def __init__(self) -> None:
        super().__init__(held=False)
        self.overlaps: list[str] = []

    def __call__(self, scan: wire.Scan, spill: object = None) -> CuedMapper:
        return self.mappers.setdefault(scan.robot, WatchedMapper(self.overlaps, scan.robot))


def test_a_fixed_pool_serves_every_robot_in_order_never_one_robot_twice_at_once(free_port: int) -> None:
    recipe = WatchedRecipe()
    service = MappingService(KEYS, recipe, queue=50, workers=3, admission=Admission(max_robots=20))
    robots = [f"r{i}" for i in range(12)]
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        threads_before = own_threads()
        acks = {r: Acks(s, r) for r in robots}
        pubs = {r: s.declare_publisher(KEYS.scan(r), congestion_control=zenoh.CongestionControl.BLOCK)
                for r in robots}
        for seq in range(10):
            for r in robots:
                pubs[r].put(scan(r, seq, n=10))
        wait_for(lambda: all(len(a.items) == 10 for a in acks.values()), 30, "every scan acked")
        assert own_threads() <= threads_before  # no thread per robot
        assert sum(t.name.startswith("mapper-") for t in threading.enumerate()) == 3
        assert recipe.overlaps == []
        for r in robots:
            assert recipe.mappers[r].entered == list(range(10))  # each robot's scans in order
            assert acks[r].seqs("ok") == list(range(10))
        assert service.status()["workers"] == 3


def test_robots_beyond_max_robots_are_refused_without_state_and_answers_are_rate_limited(
        free_port: int) -> None:
    admission = Admission(max_robots=2, refusals_per_s=5)
    service = MappingService(KEYS, CuedRecipe(held=False), admission=admission, edge_id="edge1")
    with serving(service, free_port), client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        ok1, ok2, other = Acks(s, "r1"), Acks(s, "r2"), Acks(s, "r3")
        for r in ("r1", "r2", "r3"):
            s.put(KEYS.scan(r), scan(r, 0))
        wait_for(lambda: len(ok1.items) == len(ok2.items) == len(other.items) == 1, what="three answers")
        assert ok1.items[0].status == "ok" and ok1.items[0].edge == "edge1"
        refusal = other.items[0]
        assert refusal.status == "refused" and "at most 2 robots" in refusal.detail
        assert refusal.seq == 0 and refusal.send_stamp == 0.0 and np.isnan(refusal.pose).all()
        # A flood of ids: every scan counted, few answered, none given state
        fakes = [f"fake{i}" for i in range(300)]
        pub = s.declare_publisher("zoffload/data/**", congestion_control=zenoh.CongestionControl.BLOCK)
        pub.undeclare()
        for f in fakes:
            s.put(KEYS.scan(f), scan(f, 1, n=5))
        wait_for(lambda: service.drops.snapshot().get("refused", 0) == 301, what="301 refusals counted")
        assert set(service.robots) == {"r1", "r2"}
        assert admission.counters["refusals_answered"] <= 5 + 5 * 10  # the bucket, over <= 10 s
        st = service.status()
        assert st["samples"] == st["received"] + st["drops"] == 303


def test_idle_robots_are_evicted_with_their_map_exported_and_may_come_back(free_port: int,
                                                                          tmp_path: Path) -> None:
    settings = EdgeSettings(zenoh=listen_on(free_port), map_dir=str(tmp_path), status_period=0.1,
                            admission=AdmissionSettings(max_robots=1, idle_timeout=0.5),
                            detector=DetectorSettings(enabled=False),
                            mapper=MapperSettings(enabled=True))
    with running_edge(settings) as edge, client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        from tests.daemon.edge.test_server import scan_msg

        a, b = Acks(s, "ra"), Acks(s, "rb")
        for seq in range(3):
            s.put(KEYS.scan("ra"), scan_msg("ra", seq))
            a.wait(seq + 1, 30)
        s.put(KEYS.scan("rb"), scan_msg("rb", 0))
        b.wait(1)
        assert b.items[0].status == "refused"  # the edge is full
        wait_for(lambda: (tmp_path / "ra_map.ply").exists(), 10, "ra evicted, its map exported")
        assert edge.mapping is not None and "ra" not in edge.mapping.robots
        assert np.load(tmp_path / "ra_trajectory.npz")["seqs"].tolist() == [0, 1, 2]
        s.put(KEYS.scan("rb"), scan_msg("rb", 1))  # its place is free now
        b.wait(2)
        assert b.items[1].status == "ok"
        wait_for(lambda: (tmp_path / "rb_map.ply").exists(), 10, "rb evicted in turn")
        s.put(KEYS.scan("ra"), scan_msg("ra", 3))  # back: a new session, new files
        a.wait(4)
        assert a.items[3].status == "ok" and a.items[3].map_points < a.items[2].map_points + 10**6
        wait_for(lambda: (tmp_path / "ra_map.1.ply").exists(), 10, "ra's second session exported")
        assert edge.admission.counters["evicted"] >= 3


def test_a_ping_with_a_bad_stamp_is_answered_not_a_traceback(free_port: int) -> None:
    settings = EdgeSettings(zenoh=listen_on(free_port), mapper=MapperSettings(enabled=False),
                            detector=DetectorSettings(enabled=False))
    with running_edge(settings) as edge, client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        for params in ("stamp=garbage", "stamp=1e300", "stamp=nan", "stamp=12.5", "x=1", ""):
            replies = list(s.get(KEYS.ping("r1", "edge1") + (f"?{params}" if params else ""), timeout=5))
            pong = wire.decode(replies[0].ok.payload.to_bytes(), expect=wire.Pong)
            assert pong.edge == "edge1"
            assert pong.stamp == 12.5 if params == "stamp=12.5" else np.isnan(pong.stamp)
        assert edge.drops.total() == 0
