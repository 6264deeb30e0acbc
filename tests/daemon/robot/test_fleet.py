"""The robot's fleet protocol over Zenoh against fake edges written here (stand-ins for the edge
daemon: a session holding an edge token, answering attach queries and acking scans)."""

from __future__ import annotations

import csv
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from tests.helpers import KEYS, connect_to, listen_on, wait_for
from zoffload.protocol import wire
from zoffload.robot.fleet import OWN_CHECKPOINT_AFTER
from zoffload.robot.scans import scan_streamer
from zoffload.robot.server import RobotServer
from zoffload.runtime.config import RobotSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import open_session

pytest.importorskip("kiss_icp")


class FakeEdge:
    """A stand-in edge: accepts every attach, acks the scans sent to it under that epoch (the pose:
    1 cm further along x per scan) and, with ``stale``, first sends each ack again under another
    epoch and another edge id, which the robot must ignore. A checkpoint after every 5th scan."""

    def __init__(self, port: int, edge: str, stale: bool = False) -> None:
        self.edge, self.stale = edge, stale
        self.session = open_session(connect_to(port))
        self.attaches: list[wire.Attach] = []
        self.scans: list[wire.Scan] = []
        self.epoch = 0
        self.acking = True
        self._lock = threading.Lock()
        self.token = self.session.liveliness().declare_token(KEYS.edge_alive(edge))
        self.queryable = self.session.declare_queryable(KEYS.all_attaches(edge), self._on_attach)
        self.sub = self.session.declare_subscriber(KEYS.all_scans(), self._on_scan)
        # As a real edge, a status at once and every half second: the robot asks an edge once it
        # knows which codec version it reads (or after robot/fleet.py's STATUS_WAIT without one)
        self._status = threading.Thread(target=self._say_status, daemon=True)
        self._status.start()

    def _say_status(self) -> None:
        while self.acking:
            values = {"capacity": 4.0, "robots": 1.0, wire.READS_KEY: float(max(wire.READS))}
            status = wire.Status(source="edge", id=self.edge, stamp=time.time(), values=values)
            try:
                self.session.put(KEYS.edge_status(self.edge), wire.encode(status))
            except Exception:  # the session closed under us
                return
            time.sleep(0.5)

    def _on_attach(self, query: zenoh.Query) -> None:
        assert query.payload is not None
        att = wire.decode(query.payload.to_bytes(), expect=wire.Attach)
        with self._lock:
            self.attaches.append(att)
            self.epoch = att.epoch
        query.reply(query.key_expr, wire.encode(wire.AttachReply(
            robot=att.robot, edge=self.edge, epoch=att.epoch, accepted=True, robots=1, capacity=4)))

    def _on_scan(self, sample: zenoh.Sample) -> None:
        scan = wire.decode(sample.payload.to_bytes(), expect=wire.Scan)
        if scan.edge != self.edge or not self.acking:
            return
        with self._lock:
            self.scans.append(scan)
            mine = scan.epoch == self.epoch
        pose = np.eye(4)
        pose[0, 3] = 0.01 * scan.seq
        key = KEYS.scan_ack(scan.robot)

        def ack(edge: str, epoch: int) -> bytes:
            return wire.encode(wire.ScanAck(
                robot=scan.robot, seq=scan.seq, send_stamp=scan.send_stamp, status="ok", interarrival=0.1,
                queue_time=0.0, proc_time=0.01, icp_time=0.01, map_points=100, keypoints=10, sigma=0.1,
                pose=pose, epoch=epoch, edge=edge))

        if self.stale:
            self.session.put(key, ack(self.edge, scan.epoch + 1))
            self.session.put(key, ack("edge9", scan.epoch))
        if mine:
            self.session.put(key, ack(self.edge, scan.epoch))
            if scan.seq % 5 == 0:
                cp = wire.Checkpoint(robot=scan.robot, edge=self.edge, epoch=scan.epoch, seq=scan.seq,
                                     stamp=scan.capture_stamp, voxel_size=0.4, max_range=40.0, min_range=0.0,
                                     max_points_per_voxel=20, pose=pose, delta=np.eye(4),
                                     points=scan.cloud()[::4])
                self.session.put(KEYS.checkpoint(scan.robot), wire.encode(cp))

    def leave(self) -> None:
        """The edge's token goes (as when its process dies) and it stops answering."""
        self.acking = False
        self.token.undeclare()

    def close(self) -> None:
        self.acking = False
        self._status.join(2)
        self.sub.undeclare()
        self.queryable.undeclare()
        self.session.close()


def test_attach_stale_acks_local_odometry_and_reattach_with_checkpoint(free_port: int,
                                                                       tmp_path: Path) -> None:
    hub = open_session(listen_on(free_port))
    edges: list[FakeEdge] = []
    stop = StopSignal()
    try:
        a = FakeEdge(free_port, "edgeA", stale=True)
        edges.append(a)
        settings = RobotSettings(zenoh=connect_to(free_port), rate_hz=20, max_scans=1000,
                                 scale_policy="fixed", wait_edge=5, out_dir=str(tmp_path))
        robot = scan_streamer(settings, stop)
        server = RobotServer(settings, [robot], stop)
        thread = threading.Thread(target=server.run, daemon=True)
        thread.start()
        led = robot.ledger
        wait_for(lambda: len(a.scans) >= 15 and led.counters["acked"] >= 10, 30, "edge A acking")
        # Attached: every scan names edge A and the epoch it accepted
        assert len(a.attaches) == 1 and a.attaches[0].checkpoint == b""
        assert {(s.edge, s.epoch) for s in a.scans} == {("edgeA", a.epoch)}
        assert robot.drops.snapshot().get("stale_ack", 0) >= 2 * 10  # other epoch and other edge
        assert robot.fleet_state is not None and robot.fleet_state.checkpoint is not None
        last_a = robot.fleet_state.checkpoint.seq

        a.leave()
        # long enough alone that the robot's own checkpoint is more than OWN_CHECKPOINT_AFTER scans
        # newer than A's: then the attach carries its own (else A's, with the local poses after it)
        wait_for(lambda: led.counters["local"] >= OWN_CHECKPOINT_AFTER + 20, 30, "local odometry")
        status = robot.status()
        assert status["pose_source"] == 1.0 and status["attached"] == 0.0 and "pose_x" in status

        b = FakeEdge(free_port, "edgeB")
        edges.append(b)
        state = robot.fleet_state
        assert state is not None
        wait_for(lambda: state.per_edge.get("edgeB", 0) >= 10, 30, "edge B acking")
        stop.set()
        thread.join(30)
        assert not thread.is_alive()
    finally:
        stop.set()
        for e in edges:
            e.close()
        hub.close()
    # The attach to B carried the robot's own checkpoint (far newer than A's) and the poses after it
    att = b.attaches[0]
    cp = wire.decode(att.checkpoint, expect=wire.Checkpoint)
    assert cp.edge == "" and cp.robot == "robot1" and cp.seq > last_a and len(cp.cloud()) > 0
    assert att.reads == 6 and cp.packed is not None  # edge B said it reads 6: coded (version 6)
    assert all(s > cp.seq for s in att.local_seqs) and list(att.local_seqs) == sorted(att.local_seqs)
    assert att.epoch > a.epoch and {s.epoch for s in b.scans} == {att.epoch}
    m = robot.metrics()
    f = m["fleet"]
    assert m["balanced"] and m["balance"]["local"] >= 15, m["balance"]
    assert f["attaches"] == 2 and f["failovers"] == 1 and f["moves"] == {"token": 1}
    assert f["per_edge"]["edgeA"] >= 10 and f["per_edge"]["edgeB"] >= 10
    assert len(f["failover_s"]) == 1 and 0 < f["failover_s"][0] < 20
    assert f["max_pose_gap_scans"] <= 1, f  # local odometry covered the edge's absence
    assert len(f["switch_jumps_m"]) >= 2 and f["local_cpu_ms_per_scan"]["median"] > 0
    assert f["stale_acks"] >= 20
    sources = {r.get("pose_source") for r in robot.ledger.records.values()}
    assert {"edge", "local"} <= sources
    rows = list(csv.DictReader(open(tmp_path / "robot_scans.csv")))
    assert {r["edge"] for r in rows if r["status"] == "acked"} == {"edgeA", "edgeB"}
    assert {r["pose_source"] for r in rows if r["status"] == "local"} == {"local"}
    poses = np.load(tmp_path / "robot_poses.npz")
    assert len(poses["acked_seqs"]) >= m["balance"]["acked"] + m["balance"]["local"]
