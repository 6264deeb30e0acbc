"""The robot's fleet protocol over Zenoh against fake edges written here (stand-ins for the edge
daemon: a session holding an edge token, answering attach queries and acking scans)."""

from __future__ import annotations

import csv
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from tests.helpers import KEYS, connect_to, listen_on, wait_for
from zoffload.protocol import wire
from zoffload.robot.fleet import OWN_CHECKPOINT_AFTER
from zoffload.robot.scans import ScanStreamer, scan_streamer
from zoffload.robot.server import RobotServer
from zoffload.runtime.config import RobotFleetSettings, RobotSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import open_session

pytest.importorskip("kiss_icp")


class FakeEdge:
    """A stand-in edge: accepts every attach, acks the scans sent to it under that epoch (the pose:
    1 cm further along x per scan) and, with ``stale``, first sends each ack again under another
    epoch and another edge id, which the robot must ignore. A checkpoint after every 5th scan
    (the first ``checkpoints`` of them)."""

    def __init__(self, port: int, edge: str, stale: bool = False, checkpoints: int = 1 << 30) -> None:
        self.edge, self.stale, self.checkpoints = edge, stale, checkpoints
        self.session = open_session(connect_to(port))
        self.attaches: list[wire.Attach] = []
        self.scans: list[wire.Scan] = []
        self.epoch = 0
        self.acking = True
        self.muted = False  # token and status stay, no scan is answered (a hung edge)
        # An attach with a backfill goes unanswered (the fault: a link too slow to carry its bytes
        # within the robot's attach_timeout, which this machine's loopback cannot be made)
        self.ignore_backfill = False
        self.proc_time = 0.01  # the registration time its acks report
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
            if self.ignore_backfill and att.backfill_sizes is not None:
                return
            self.epoch = att.epoch
        query.reply(query.key_expr, wire.encode(wire.AttachReply(
            robot=att.robot, edge=self.edge, epoch=att.epoch, accepted=True, robots=1, capacity=4)))

    def _on_scan(self, sample: zenoh.Sample) -> None:
        scan = wire.decode(sample.payload.to_bytes(), expect=wire.Scan)
        if scan.edge != self.edge or not self.acking or self.muted:
            return
        with self._lock:
            self.scans.append(scan)
            mine = scan.epoch == self.epoch
        pose = np.eye(4)
        pose[0, 3] = 0.01 * scan.seq
        key = KEYS.scan_ack(scan.robot, self.edge)

        def ack(edge: str, epoch: int) -> bytes:
            return wire.encode(wire.ScanAck(
                robot=scan.robot, seq=scan.seq, send_stamp=scan.send_stamp, status="ok", interarrival=0.1,
                queue_time=0.0, proc_time=self.proc_time, icp_time=self.proc_time, map_points=100,
                keypoints=10, sigma=0.1,
                pose=pose, epoch=epoch, edge=edge))

        if self.stale:
            self.session.put(key, ack(self.edge, scan.epoch + 1))
            self.session.put(KEYS.scan_ack(scan.robot, "edge9"), ack("edge9", scan.epoch))
        if mine:
            self.session.put(key, ack(self.edge, scan.epoch))
            if scan.seq % 5 == 0 and self.checkpoints > 0:
                self.checkpoints -= 1
                cp = wire.Checkpoint(robot=scan.robot, edge=self.edge, epoch=scan.epoch, seq=scan.seq,
                                     stamp=scan.capture_stamp, voxel_size=0.4, max_range=40.0, min_range=0.0,
                                     max_points_per_voxel=20, pose=pose, delta=np.eye(4),
                                     points=scan.cloud()[::4])
                self.session.put(KEYS.checkpoint(scan.robot, self.edge), wire.encode(cp))

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


@contextmanager
def fleet_hub(port: int) -> Iterator[tuple[list[FakeEdge], StopSignal]]:
    """A listening hub for the fake edges (added to the yielded list) and the robot; on exit the
    robot is told to stop and every edge and the hub are closed."""
    hub = open_session(listen_on(port))
    edges: list[FakeEdge] = []
    stop = StopSignal()
    try:
        yield edges, stop
    finally:
        stop.set()
        for e in edges:
            e.close()
        hub.close()


def start_robot(port: int, out: Path, stop: StopSignal, policy: str = "fixed", **fleet: Any
                ) -> tuple[ScanStreamer, threading.Thread]:
    """A robot daemon streaming the simulator's scans at 20 Hz into the hub's fleet."""
    settings = RobotSettings(zenoh=connect_to(port), rate_hz=20, max_scans=1000, scale_policy=policy,
                             wait_edge=5, out_dir=str(out), fleet=RobotFleetSettings(**fleet))
    robot = scan_streamer(settings, stop)
    thread = threading.Thread(target=RobotServer(settings, [robot], stop).run, daemon=True)
    thread.start()
    return robot, thread


def stop_robot(stop: StopSignal, thread: threading.Thread) -> None:
    stop.set()
    thread.join(30)
    assert not thread.is_alive()



def test_attach_stale_acks_local_odometry_and_reattach_with_checkpoint(free_port: int,
                                                                       tmp_path: Path) -> None:
    with fleet_hub(free_port) as (edges, stop):
        a = FakeEdge(free_port, "edgeA", stale=True)
        edges.append(a)
        robot, thread = start_robot(free_port, tmp_path, stop)
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
        stop_robot(stop, thread)
    # The attach to B carried the robot's own checkpoint (far newer than A's) and the poses after it
    att = b.attaches[0]
    cp = wire.decode(att.checkpoint, expect=wire.Checkpoint)
    assert cp.edge == "" and cp.robot == "robot1" and cp.seq > last_a and len(cp.cloud()) > 0
    assert att.reads == max(wire.READS) >= 6 and cp.packed is not None  # edge B reads 6 or newer: coded
    assert att.backfill is None  # the robot was not attached to B before: B has nothing to register it from
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


def test_the_next_edge_gets_the_robots_scans_at_once_while_the_silent_ones_are_unanswered(
        free_port: int, tmp_path: Path) -> None:
    """The robot leaves a silent edge with scans in flight to it. Those are not on the new edge's
    path: before, they filled its window and made its silence until they expired, so the policy
    held the first scans to the new edge back as a stall and they got a pose from neither side."""
    with fleet_hub(free_port) as (edges, stop):
        edges += [FakeEdge(free_port, "edgeA"), FakeEdge(free_port, "edgeB")]
        robot, thread = start_robot(free_port, tmp_path, stop, policy="rate")
        wait_for(lambda: max(len(e.scans) for e in edges) >= 20, 30, "an edge acking")
        first = max(edges, key=lambda e: len(e.scans))
        nxt = next(e for e in edges if e is not first)
        first.muted = True  # alive but silent: the robot moves after failover_after
        wait_for(lambda: len(nxt.scans) >= 20, 30, "the robot on the other edge")
        stop_robot(stop, thread)
    m = robot.metrics()
    f = m["fleet"]
    assert m["balanced"] and f["failovers"] == 1 and f["moves"] == {"silence": 1}, f
    rows = list(csv.DictReader(open(tmp_path / "robot_scans.csv")))
    moved = min(int(r["seq"]) for r in rows if r["edge"] == nxt.edge)
    answered = min(int(r["seq"]) for r in rows if r["edge"] == nxt.edge and r["status"] == "acked")
    # Held back by the window or the stall (the old code: the stall skipped them). Not the pace:
    # a scan skipped on purpose because the last one needs the uplink for more than a period is
    # the policy's rate choice, and the uplink is the robot's own, whichever edge it goes to (on a
    # loaded machine the fake edges answer late, the budget is cut and the pace skips some)
    held = [r["seq"] for r in rows if r["edge"] == nxt.edge and int(r["seq"]) < answered + 5
            and r["status"] in ("source:stall", "source:window")]
    assert not held, (moved, answered, held)
    assert answered - moved <= 2, (moved, answered)
    # no scan of the move went without a pose (the silent edge's were bridged by the robot)
    assert f["max_pose_gap_scans"] <= 1, f
    lost = [r for r in rows if r["status"] == "lost"]
    assert lost and all(r["edge"] == first.edge and r["pose_source"] == "local" for r in lost)


def test_after_a_kill_the_next_edge_gets_the_poses_after_the_checkpoint_and_the_unanswered_ones(
        free_port: int, tmp_path: Path) -> None:
    """An edge dies (its token goes: the robot moves at once) with scans unanswered. The attach to
    the next edge carries the dead edge's last checkpoint and the poses the robot got after it
    (before: only its local odometry's, none here), and the robot's first scans to it carry, as
    their prior, the local pose of the newest unanswered scan (registered once the robot moved,
    after the attach went), so the next edge predicts from the robot's newest pose instead of
    stretching the checkpoint's motion over every scan since. (When the attach is not in place by
    the next scan, the scans between are mapped with no edge and the first scans carry the newest
    of those.) Either is in the frame of the poses the attach handed over (version 11: the edge
    moves it by the correction it finds registering a backfill)."""
    with fleet_hub(free_port) as (edges, stop):
        a = FakeEdge(free_port, "edgeA", checkpoints=1)
        edges.append(a)
        robot, thread = start_robot(free_port, tmp_path, stop, bridge_after=5.0)  # no bridge here
        led = robot.ledger
        state = robot.fleet_state
        assert state is not None

        def past_checkpoint() -> bool:
            cp = state.checkpoint
            with robot._lock:
                return cp is not None and sum(s > cp.seq for s in led.poses) >= 8

        wait_for(past_checkpoint, 30, "edge A acking past a checkpoint")
        b = FakeEdge(free_port, "edgeB")
        edges.append(b)
        def heard_b() -> bool:  # B's status heard: the robot could move to it at once
            with state._lock:
                info = state.assignment.edges.get("edgeB")
                return info is not None and info.heard

        wait_for(heard_b, 30, "the robot hearing edge B's status")
        a.muted = True
        time.sleep(0.15)  # three scans or so unanswered
        a.leave()
        wait_for(lambda: len(b.scans) >= 10, 30, "edge B acking")
        stop_robot(stop, thread)
    att = b.attaches[0]
    cp = wire.decode(att.checkpoint, expect=wire.Checkpoint)
    assert cp.edge == "edgeA"
    acked_after = sorted(s.seq for s in a.scans if s.seq > cp.seq and s.epoch == a.epoch)
    seqs = list(att.local_seqs)
    assert len(acked_after) >= 5 and seqs == sorted(seqs) and all(s > cp.seq for s in seqs)
    # every scan A answered after its checkpoint, with A's pose (x = 1 cm a scan), the newest included
    answered = [s for s in acked_after if s in led.poses]
    assert answered and set(answered) <= set(seqs), (answered, seqs)
    poses = dict(zip(seqs, att.local_poses, strict=True))
    assert all(abs(poses[s][0, 3] - 0.01 * s) < 1e-9 for s in answered)
    # the scans A left unanswered were registered by the robot; B's first scan brings the newest
    unanswered = [s for s, r in led.records.items()
                  if r.get("edge") == "edgeA" and r.get("pose_source") == "local"]
    assert unanswered and robot.poses is not None and robot.poses.bridges == 0
    first = b.scans[0]
    between = [s for s, r in led.records.items()
               if max(unanswered) < s < first.seq and r.get("pose_source") == "local"]
    newest = max(between) if between else max(unanswered)
    # between: the attach to B took longer than a period (a loaded host, CI once), and the scans
    # between were mapped here with no edge (localpose.py)
    assert first.prior is not None and first.prior_seq == newest < first.seq, (between, first.prior_seq)
    assert np.allclose(first.prior[0], led.poses[newest]) and first.prior_frame == 1
    assert b.scans[-1].prior is None  # B answered: the prior ends


@pytest.mark.parametrize("ignore", [False, True], ids=["answered", "unanswered-with-backfill"])
def test_back_to_its_edge_after_an_outage_the_robot_hands_over_its_backfill(
        free_port: int, tmp_path: Path, ignore: bool) -> None:
    """The robot's edge goes and comes back under the same id: the attach back to it carries the
    scans the robot registered itself (codec version 9), at most ``backfill_scans`` spread over the
    outage, at the ring's grid (a quarter of the local odometry's 0.8 m): the loopback was seen to
    carry more than ``backfill_bytes`` in half the attach's timeout; the robot marks them, and the
    grid, in its records. When that attach goes unanswered (a link too slow for its bytes), the
    next carries them within ``backfill_bytes``, at a coarser grid, and when that one goes
    unanswered too the next goes without and is accepted."""
    with fleet_hub(free_port) as (edges, stop):
        a = FakeEdge(free_port, "edgeA")
        a.proc_time = 0.0  # the round trip is the network's (the link's rate is read from it)
        edges.append(a)
        robot, thread = start_robot(free_port, tmp_path, stop, backfill_scans=12, backfill_bytes=40_000)
        led = robot.ledger
        wait_for(lambda: led.counters["acked"] >= 10, 30, "edge A acking")
        a.leave()
        a.close()
        edges.remove(a)
        wait_for(lambda: led.counters["local"] >= 20, 30, "local odometry")
        back = FakeEdge(free_port, "edgeA")
        back.ignore_backfill = ignore
        edges.append(back)
        state = robot.fleet_state
        assert state is not None
        wait_for(lambda: led.counters["acked"] >= 25, 30, "edge A acking again")
        stop_robot(stop, thread)
    first = back.attaches[0]
    assert first.backfill is not None and first.backfill_sizes is not None
    scans = first.backfill_scans()
    assert 4 <= len(scans) <= 12 and all(s.coding == "q16d" and s.voxel == 0.2 for s in scans)
    assert len(first.backfill) > 40_000
    f = robot.metrics()["fleet"]
    assert f["backfill_sent"] >= len(scans)
    rows = list(csv.DictReader(open(tmp_path / "robot_scans.csv")))
    marked = sorted(int(r["seq"]) for r in rows if r.get("backfill") == "1")
    if not ignore:
        assert f["backfill_accepted"] == len(scans) and marked == [s.seq for s in scans]
        assert all(r["status"] != "acked" and float(r["backfill_voxel"]) == 0.2 for r in rows
                   if r.get("backfill") == "1")
    else:  # unanswered: again within backfill_bytes, coarser; unanswered: without; accepted; none marked
        assert len(back.attaches) >= 3
        second, third = back.attaches[1], back.attaches[2]
        assert second.backfill is not None and len(second.backfill) <= 40_000
        assert {s.voxel for s in second.backfill_scans()} <= {0.4, 0.8}
        assert third.backfill is None
        assert f.get("backfill_accepted", 0) == 0 and marked == []
