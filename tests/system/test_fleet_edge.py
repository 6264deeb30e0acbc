"""A real zoffload-edge process in a fleet: a Zenoh client attaches with a checkpoint from a real
KISS-ICP run on simulator scans, its acks continue that trajectory, checkpoints come back; stale
epochs, other edges' scans and a full edge; SIGTERM drains, SIGINT stops at once."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from tests.helpers import KEYS, client, wait_for
from tests.system.procs import Proc, edge_args, start_edge
from zoffload.edge.recipe import MapperRecipe
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol import wire
from zoffload.sources.simulated import SimulatedSource

pytestmark = pytest.mark.system
pytest.importorskip("kiss_icp")
SRC = SimulatedSource()


def points(i: int) -> np.ndarray:
    return voxel_downsample(SRC.read(i).points, 0.05).astype(np.float32)


def scan(robot: str, seq: int, epoch: int, edge: str) -> bytes:
    pts = points(seq)
    return wire.encode(wire.Scan(robot=robot, seq=seq, send_stamp=float(seq), capture_stamp=100.0 + seq,
                                 voxel=0.05, voxel_max=0.07, max_range=SRC.max_range, n_raw=len(pts),
                                 points=pts, epoch=epoch, edge=edge))


def attach(s: zenoh.Session, robot: str, epoch: int, checkpoint: bytes = b"") -> wire.AttachReply:
    msg = wire.Attach(robot=robot, epoch=epoch, max_range=SRC.max_range, voxel_max=0.07, rate_hz=10.0,
                      checkpoint=checkpoint, local_seqs=np.zeros(0, np.int64),
                      local_poses=np.zeros((0, 4, 4)))
    replies = list(s.get(KEYS.attach(robot, "edge1"), payload=wire.encode(msg), timeout=5))
    assert len(replies) == 1 and replies[0].ok is not None
    return wire.decode(replies[0].ok.payload.to_bytes(), expect=wire.AttachReply)


class Inbox:
    def __init__(self, session: zenoh.Session, key: str, kind: type[wire.Message]) -> None:
        self.items: list = []
        self.sub = session.declare_subscriber(key, lambda x: self.items.append(
            wire.decode(x.payload.to_bytes(), expect=kind)))


def edge(s: zenoh.Session, port: int, tmp_path: Path, *extra: str) -> Proc:
    return start_edge(s, edge_args(port, "--fleet.capacity", "1", "--fleet.checkpoint-every", "3",
                                   "--status-period", "0.2", "--mapper.workers", "1", *extra),
                      tmp_path / "edge.log")


def test_attach_continue_refuse_and_drain_on_sigterm(free_port: int, tmp_path: Path) -> None:
    # The first edge's KISS-ICP (the recipe the edge uses) over scans 0..19, and its checkpoint
    old = MapperRecipe()(wire.decode(scan("r1", 0, 0, ""), expect=wire.Scan))
    for i in range(20):
        old.register(i, points(i))
    cp = old.checkpoint("r1", "edge0", 1, 119.0)
    assert cp is not None
    with client(free_port) as s:
        proc = edge(s, free_port, tmp_path, "--map-dir", str(tmp_path / "maps"),
                    "--fleet.drain-timeout", "20")
        try:
            acks = Inbox(s, KEYS.scan_acks("r1"), wire.ScanAck)
            cps = Inbox(s, KEYS.checkpoints("r1"), wire.Checkpoint)
            status = Inbox(s, KEYS.edge_status("edge1"), wire.Status)
            reply = attach(s, "r1", 2, wire.encode(cp))
            assert reply.accepted and (reply.robots, reply.capacity) == (1, 1), reply
            pub = s.declare_publisher(KEYS.scan("r1"))
            for seq in range(20, 30):
                pub.put(scan("r1", seq, 2, "edge1"))
                wait_for(lambda n=seq - 19: len(acks.items) >= n, 20, "ack")  # type: ignore[misc]
            ok = [a for a in acks.items if a.status == "ok"]
            assert [a.seq for a in ok] == list(range(20, 30)) and all(a.epoch == 2 for a in ok)
            for a in ok:
                ref = old.register(a.seq, points(a.seq)).pose
                assert np.linalg.norm(a.pose[:3, 3] - ref[:3, 3]) < 0.1
            assert np.linalg.norm(ok[0].pose[:3, 3]) > 1.0  # continues, not at the origin
            wait_for(lambda: [c.seq for c in cps.items] == [20, 23, 26, 29], 10, "periodic checkpoints")
            # Stale epoch refused; another edge's scan counted, not answered; a full edge refuses
            pub.put(scan("r1", 30, 1, "edge1"))
            wait_for(lambda: len(acks.items) == 11, 10, "refusal")
            assert acks.items[-1].status == "refused" and acks.items[-1].detail == "not attached (epoch 1)"
            pub.put(scan("r1", 31, 3, "edge2"))
            wait_for(lambda: bool(status.items) and status.items[-1].values.get("other_edge") == 1, 10,
                     "other_edge")
            assert attach(s, "r2", 1).detail == "full: 1 of 1 robots"
            v = status.items[-1].values
            assert v["capacity"] == 1 and v["robots"] == 1 and v["draining"] == 0
            assert v["samples"] == v["received"] + v["drops"] + v["other_edge"]

            # SIGTERM: draining at once, a final checkpoint, the old epoch still mapped, then exit
            proc.p.send_signal(signal.SIGTERM)
            wait_for(lambda: any(st.values.get("draining") == 1 for st in status.items), 5, "draining")
            wait_for(lambda: any(c.final for c in cps.items), 10, "final checkpoint")
            final = [c for c in cps.items if c.final][0]
            assert final.seq == 29 and final.epoch == 2
            assert attach(s, "r3", 1).detail == "draining"
            for seq in range(32, 37):  # the robot keeps sending while it moves: mapped, acked
                pub.put(scan("r1", seq, 2, "edge1"))
                time.sleep(0.1)
            wait_for(lambda: [a.seq for a in acks.items if a.status == "ok"][-1] == 36, 10,
                     "acks while draining")
            assert proc.p.poll() is None  # not before the robot went quiet
            stopped = time.monotonic()
            assert proc.wait(20) == 0, proc.text()
            assert time.monotonic() - stopped < 10
        finally:
            if proc.p.poll() is None:
                proc.sigint(10)
    assert "drained after" in proc.text()
    traj = np.load(tmp_path / "maps" / "r1_trajectory.npz")
    assert traj["seqs"].tolist() == list(range(20, 30)) + list(range(32, 37))


def test_sigint_stops_at_once_even_with_a_robot_attached(free_port: int, tmp_path: Path) -> None:
    with client(free_port) as s:
        proc = edge(s, free_port, tmp_path, "--fleet.drain-timeout", "60")
        try:
            assert attach(s, "r1", 1).accepted
            s.put(KEYS.scan("r1"), scan("r1", 0, 1, "edge1"))
            started = time.monotonic()
            code = proc.sigint(20)
        finally:
            if proc.p.poll() is None:
                proc.p.kill()
    assert code == 0, proc.text()
    assert time.monotonic() - started < 10 and "drain" not in proc.text()
