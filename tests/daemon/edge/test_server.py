"""The edge server in-process with its real services, driven through Zenoh on a loopback port."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from tests.daemon.edge.acks import Acks
from tests.helpers import KEYS, client, listen_on, running_edge, wait_for, wait_token
from zoffload.edge.mapping import MappingService
from zoffload.edge.server import EdgeServer
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire
from zoffload.runtime.config import DetectorSettings, EdgeSettings, MapperSettings
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")
SRC = SimulatedSource()


def scan_msg(robot: str, seq: int, index: int | None = None, stamp: float | None = None) -> bytes:
    f = SRC.read(seq if index is None else index)
    pts = voxel_downsample(f.points, 0.05).astype(np.float32)
    return wire.encode(wire.Scan(robot=robot, seq=seq, send_stamp=stamp or time.monotonic(),
                                 capture_stamp=time.time(), voxel=0.05, voxel_max=0.07,
                                 max_range=SRC.max_range, n_raw=len(f.points), points=pts))


def mapping(edge: EdgeServer) -> MappingService:
    assert edge.mapping is not None
    return edge.mapping


def test_acks_poses_map_query_and_export(free_port: int, tmp_path: Path) -> None:
    settings = EdgeSettings(zenoh=listen_on(free_port), map_dir=str(tmp_path))
    with running_edge(settings) as edge, client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        acks = Acks(s, "r1")
        pub = s.declare_publisher(KEYS.scan("r1"))
        for seq in range(20):
            pub.put(scan_msg("r1", seq))
            acks.wait(seq + 1)  # paced like a sensor
        ok = [a for a in acks.items if a.status == "ok"]
        assert [a.seq for a in ok] == list(range(20))
        assert np.isnan(ok[0].interarrival) and all(a.interarrival > 0 for a in ok[1:])
        assert all(a.proc_time > 0 and a.keypoints > 0 for a in ok)
        assert ok[-1].map_points > ok[0].map_points > 0
        np.testing.assert_allclose(ok[0].pose, np.eye(4), atol=1e-9)
        assert ok[-1].pose[0, 3] > 0.2  # the robot moved forward along x

        replies = list(s.get(KEYS.map("r1", "edge1"), timeout=10))
        m = wire.decode(replies[0].ok.payload.to_bytes(), expect=wire.MapReply)
        assert isinstance(m, wire.MapReply)
        assert m.scans == 20 and list(m.seqs) == list(range(20)) and len(m.points) == ok[-1].map_points
        unknown = list(s.get(KEYS.map("nobody", "edge1"), timeout=5))
        assert unknown[0].err is not None and b"no map" in unknown[0].err.payload.to_bytes()
        assert mapping(edge).counters["registered"] == 20
    assert (tmp_path / "r1_map.ply").stat().st_size > 1000
    assert (tmp_path / "r1_trajectory.npz").exists()
    assert json.loads((tmp_path / "r1_edge.json").read_text())["registered"] == 20


def test_malformed_messages_are_counted_and_the_edge_stays_up(free_port: int) -> None:
    with running_edge(EdgeSettings(zenoh=listen_on(free_port))) as edge, client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        acks = Acks(s, "r1")
        s.put(KEYS.scan("r1"), b"\x00garbage")
        s.put(KEYS.scan("r1"), wire.encode(wire.Pong(edge="x", stamp=0.0)))  # wrong type
        s.put(KEYS.scan("r2"), scan_msg("r1", 0))  # key and payload disagree
        wait_for(lambda: mapping(edge).drops.snapshot() == {"malformed": 2, "foreign": 1},
                 what="2 malformed and 1 foreign counted")
        st = mapping(edge).status()
        assert st["samples"] == 3 and st["drops"] == 3 and st["malformed"] == 2 and "received" not in st
        # an empty scan is a registration error, acked as such
        empty = wire.encode(wire.Scan(robot="r1", seq=0, send_stamp=1.0, capture_stamp=1.0, voxel=0.05,
                                      voxel_max=0.07, max_range=40.0, n_raw=0,
                                      points=np.empty((0, 3), np.float32)))
        s.put(KEYS.scan("r1"), empty)
        wait_for(lambda: len(acks.items) == 1, what="error ack")
        assert acks.items[0].status == "error" and "no points" in acks.items[0].detail
        s.put(KEYS.scan("r1"), scan_msg("r1", 1))
        wait_for(lambda: len(acks.items) == 2, what="a good scan still works")
        assert acks.items[1].status == "ok"


def test_several_robots_get_their_own_mapper(free_port: int) -> None:
    with running_edge(EdgeSettings(zenoh=listen_on(free_port))) as edge, client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        a, b = Acks(s, "ra"), Acks(s, "rb")
        for seq in range(6):
            s.put(KEYS.scan("ra"), scan_msg("ra", seq))
            s.put(KEYS.scan("rb"), scan_msg("rb", seq, index=300 + seq))  # elsewhere in the warehouse
            a.wait(seq + 1)
            b.wait(seq + 1)
        robots = mapping(edge).robots
        assert set(robots) == {"ra", "rb"}
        assert robots["ra"].mapper is not robots["rb"].mapper
        assert all(x.robot == "ra" for x in a.items) and all(x.robot == "rb" for x in b.items)


def test_overload_drops_oldest_and_says_so(free_port: int) -> None:
    settings = EdgeSettings(zenoh=listen_on(free_port), mapper=MapperSettings(queue=1))
    with running_edge(settings) as edge, client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        acks = Acks(s, "r1")
        burst = [scan_msg("r1", seq) for seq in range(30)]
        # BLOCK: every scan must reach the edge; the test is about the edge's own queue
        pub = s.declare_publisher(KEYS.scan("r1"), congestion_control=zenoh.CongestionControl.BLOCK)
        for payload in burst:  # far faster than registration
            pub.put(payload)
        wait_for(lambda: mapping(edge).counters["received"] == 30, what="all 30 scans received")
        try:
            wait_for(lambda: len(acks.items) == 30, timeout=30, what="an ack for every scan")
        except AssertionError as exc:
            got = sorted(a.seq for a in acks.items)
            raise AssertionError(f"acks {got} counters {dict(mapping(edge).counters)}") from exc
        dropped = [x for x in acks.items if x.status == "dropped"]
        assert dropped and all("overloaded" in x.detail for x in dropped)
        assert mapping(edge).counters["dropped"] == len(dropped)
        assert mapping(edge).counters["registered"] + len(dropped) == 30


def test_status_merges_the_values_of_every_service(free_port: int) -> None:
    settings = EdgeSettings(zenoh=listen_on(free_port), status_period=0.1,
                            mapper=MapperSettings(enabled=False), detector=DetectorSettings(enabled=False))
    with running_edge(settings) as edge, client(free_port) as s:
        wait_token(s, KEYS.edge_alive("edge1"))
        statuses: list[wire.Status] = []

        def on_status(sample: zenoh.Sample) -> None:
            msg = wire.decode(sample.payload.to_bytes(), expect=wire.Status)
            assert isinstance(msg, wire.Status)
            statuses.append(msg)

        sub = s.declare_subscriber(KEYS.edge_status("edge1"), on_status)
        acks = Acks(s, "r1")
        s.put(KEYS.scan("r1"), scan_msg("r1", 0))
        wait_for(lambda: acks.seqs("ok") == [0], what="the scan acked")
        assert acks.items[0].detail == "mapping disabled"
        wait_for(lambda: any(st.values.get("received") == 1 for st in statuses), what="status")
        sub.undeclare()
        last = statuses[-1]
        assert last.source == "edge" and last.id == "edge1"
        assert last.values["received"] == 1 and last.values["robots"] == 1
        assert last.values["r1.queue"] == 0 and last.values["r1.map_points"] == 0
        assert [x.name for x in edge.services] == ["mapping"]  # no detector: it was switched off


class Probe:
    """A stand-in service that records when it is stopped, and can fail to stop."""

    def __init__(self, name: str, log: list[str], fail: bool = False) -> None:
        self.name = name
        self.log = log
        self.fail = fail

    def start(self, session: zenoh.Session) -> None:
        self.log.append(f"start {self.name}")

    def status(self) -> dict[str, float]:
        return {f"{self.name}.up": 1.0}

    def evict(self, robot: str) -> None:
        self.log.append(f"evict {robot}")

    def stop(self) -> None:
        self.log.append(f"stop {self.name}")
        if self.fail:
            raise RuntimeError(f"{self.name} stuck")


def test_shutdown_stops_services_in_reverse_and_closes_the_session_when_one_fails(free_port: int) -> None:
    settings = EdgeSettings(zenoh=listen_on(free_port), mapper=MapperSettings(enabled=False),
                            detector=DetectorSettings(enabled=False))
    server = EdgeServer(settings)
    server.startup()
    log: list[str] = []
    server.services += [Probe("a", log, fail=True), Probe("b", log)]
    assert {"a.up", "b.up", "robots"} <= set(server.status().values)
    # Every edge says the newest codec version it reads (the robot sends newer fields only then)
    assert server.status().values[wire.READS_KEY] == max(wire.READS) >= 4
    with pytest.raises(RuntimeError, match="a stuck"):
        server.shutdown()
    assert log == ["stop b", "stop a"] and server.services == [] and server.session is None
    assert server.stop.is_set()
