"""The secure deployment as local processes: a `zoffload router` with TLS, client certificates and
the generated default-deny ACL; `zoffload-edge` and `zoffload-robot` as clients with their own
certificates; the test's sessions as attackers holding a robot's identity, or none."""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import zenoh

from tests.helpers import KEYS, wait_for, wait_token
from tests.system.procs import Proc, script
from tests.system.secure import Deployment, deploy, deploy_linked
from zoffload.lab.runner import StatusWatcher
from zoffload.protocol import wire
from zoffload.runtime.drops import Drops
from zoffload.runtime.errors import ZenohSessionError
from zoffload.runtime.maps import fetch_map
from zoffload.runtime.session import open_session

pytestmark = pytest.mark.system
pytest.importorskip("kiss_icp")
pytest.importorskip("cryptography")


class EdgeStatus:
    """The edge's latest status values, through a monitor session."""

    def __init__(self, session: zenoh.Session) -> None:
        self.values: dict[str, float] = {}
        self.sub = session.declare_subscriber(KEYS.edge_status("edge1"), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        self.values = dict(wire.decode(sample.payload.to_bytes(), expect=wire.Status).values)


def forged_ack(robot: str, seq: int, stamp: float) -> bytes:
    return wire.encode(wire.ScanAck(robot=robot, seq=seq, send_stamp=stamp, status="ok", interarrival=0.1,
                                    queue_time=0.0, proc_time=0.01, icp_time=0.01, map_points=1, keypoints=1,
                                    sigma=0.1, pose=np.eye(4), edge="edge1"))


def robot1_mapped_by_edge1(d: Deployment, tmp_path: Path, monitor: zenoh.Session, procs: list[Proc],
                           edge_port: int | None = None) -> tuple[EdgeStatus, dict]:
    """A real edge1 (on the router at ``edge_port``, default the first) and a real robot1 (on the
    first) sending 30 scans through the secure deployment; returns the edge's status watcher and
    the robot's metrics. Both processes go into ``procs`` as they start, for the caller to stop."""
    procs.append(Proc(script("zoffload-edge") + d.args("edge1", edge_port), tmp_path / "edge.log"))
    wait_token(monitor, KEYS.edge_alive("edge1"), 60)
    status = EdgeStatus(monitor)
    robot = Proc(script("zoffload-robot") + d.args("robot1") + ["--max-scans", "30", "--out",
                                                                 str(tmp_path / "robot")],
                 tmp_path / "robot.log")
    procs.append(robot)
    assert robot.wait(120) == 0, robot.text()
    return status, json.loads((tmp_path / "robot" / "robot_metrics.json").read_text())


def refused(d: Deployment, **over: object) -> bool:
    try:
        open_session(d.settings(**over)).close()  # type: ignore[arg-type]
    except ZenohSessionError:
        return True
    return False


def test_unauthenticated_clients_are_refused(free_port: int, tmp_path: Path) -> None:
    d = deploy(tmp_path, free_port, ["robot1"], ["edge1"])
    try:
        from zoffload.runtime.certs import make_ca, make_leaf, write_pair

        rogue = make_ca("rogue CA")
        write_pair(tmp_path, "rogue", make_leaf(rogue, "robot1"))  # claims robot1, wrong issuer
        assert refused(d, identity=None)  # no client certificate
        assert refused(d, identity=None, tls_ca=None, connect=[f"tcp/127.0.0.1:{free_port}"])  # plain tcp
        assert refused(d, identity="robot1", tls_cert=str(tmp_path / "rogue.pem"),
                       tls_key=str(tmp_path / "rogue.key"))
        assert not refused(d, identity="robot1")
    finally:
        assert d.stop() == 0


# -m slow: the linked-routers test keeps the same forgeries refused through TLS + ACL in the default run
@pytest.mark.slow
def test_a_robot_identity_cannot_publish_for_another_robot_or_answer_as_an_edge(
        free_port: int, tmp_path: Path) -> None:
    d = deploy(tmp_path, free_port, ["robot1", "robot2"], ["edge1"])
    procs: list[Proc] = []
    try:
        monitor = open_session(d.settings("monitor"))
        status, metrics = robot1_mapped_by_edge1(d, tmp_path, monitor, procs)
        assert metrics["balanced"] and metrics["balance"]["acked"] >= 28  # TLS + ACL: the path works

        # robot1's identity, in a session of its own: nothing it forges reaches anyone
        attacker = open_session(d.settings("robot1"))
        victim = open_session(d.settings("robot2"))
        got: list[bytes] = []
        victim.declare_subscriber(KEYS.scan_acks("robot2"), lambda s: got.append(s.payload.to_bytes()))
        # (a session sees its own puts locally: the eavesdropper is a session of its own)
        spy = open_session(d.settings("robot1"))
        stolen: list[str] = []
        spy.declare_subscriber("zoffload/data/**", lambda s: stolen.append(str(s.key_expr)))
        token = attacker.liveliness().declare_token(KEYS.edge_alive("edge9"))
        before = metrics["balance"]["published"]
        wait_for(lambda: status.values.get("samples") == before, 10, "the edge to count robot1's scans")
        scan2 = wire.Scan(robot="robot2", seq=0, send_stamp=1.0, capture_stamp=1.0, voxel=0.05,
                          voxel_max=0.07, max_range=40.0, n_raw=10, points=np.zeros((10, 3), np.float32))
        for seq in range(20):
            attacker.put(KEYS.scan("robot2"), wire.encode(scan2))
            attacker.put(KEYS.scan_ack("robot2", "edge1"), forged_ack("robot2", seq, 1.0))
            attacker.put(KEYS.edge_status("edge1"), b"forged")
        # a genuine robot2 scan in a fresh session shows the path is open for robot2 itself
        victim.put(KEYS.scan("robot2"), wire.encode(scan2))
        wait_for(lambda: len(got) == 1, 20, "the edge's answer to robot2's own scan")
        time.sleep(1.5)  # two more edge status periods
        assert len(got) == 1 and wire.decode(got[0], expect=wire.ScanAck).edge == "edge1"
        assert status.values["samples"] == before + 1  # only robot2's own scan reached the edge
        edges = [str(r.ok.key_expr) for r in victim.liveliness().get(KEYS.any_edge_alive(), timeout=3)
                 if r.ok is not None]
        assert edges == [KEYS.edge_alive("edge1")]  # the forged edge token was not forwarded
        assert stolen == []  # robot1 cannot even listen to other robots' traffic
        replies = list(attacker.get(KEYS.map("robot2", "edge1"), timeout=3))
        assert not [r for r in replies if r.ok is not None]
        token.undeclare()
        for s in (attacker, spy, victim, monitor):
            s.close()
    finally:
        for p in reversed(procs):  # the robot, then the edge
            p.sigint()
        assert d.stop() == 0


def test_forged_edge_token_and_acks_book_nothing_without_an_edge(free_port: int, tmp_path: Path) -> None:
    """The audit's attack: a fake edge token and acks for every scan (echoing what it overhears).
    Without TLS and the ACL the robot booked 50 of 50 scans as acked with no edge running."""
    d = deploy(tmp_path, free_port, ["robot1", "robot2"], ["edge1"])
    robot = None
    sessions: list[zenoh.Session] = []
    stop_blind = threading.Event()
    try:
        attacker = open_session(d.settings("robot1"))
        sessions.append(attacker)
        token = attacker.liveliness().declare_token(KEYS.edge_alive("edge1"))
        echoed = threading.Event()

        def echo(sample: zenoh.Sample) -> None:  # would answer every scan it overhears
            scan = wire.decode(sample.payload.to_bytes(), expect=wire.Scan)
            attacker.put(KEYS.scan_ack(scan.robot, "edge1"),
                         forged_ack(scan.robot, scan.seq, scan.send_stamp))
            echoed.set()

        attacker.declare_subscriber(KEYS.all_scans(), echo)

        def blind() -> None:  # and acks guessed seqs blindly
            seq = 0
            while not stop_blind.is_set():
                attacker.put(KEYS.scan_ack("robot2", "edge1"),
                             forged_ack("robot2", seq % 60, time.monotonic()))
                seq += 1
                time.sleep(0.01)

        blinder = threading.Thread(target=blind, daemon=True)
        blinder.start()
        monitor = open_session(d.settings("monitor"))
        sessions.append(monitor)
        watch = StatusWatcher(monitor, KEYS, "robot2")
        robot = Proc(script("zoffload-robot") + d.args("robot2") + ["--max-scans", "50", "--wait-edge", "2",
                                                                     "--out", str(tmp_path / "robot")],
                     tmp_path / "robot.log")
        assert robot.wait(120) == 0, robot.text()
        metrics = json.loads((tmp_path / "robot" / "robot_metrics.json").read_text())
        b = metrics["balance"]
        assert b["produced"] == 50 and b["acked"] == 0 and b["published"] == 0
        assert b["local"] == 50  # no edge ever mapped it: every scan registered on the robot
        assert not echoed.is_set()
        assert watch.values.get("edges", 0) == 0
        token.undeclare()
    finally:
        # the blind sender stops before its session closes; every session closes, also after a
        # failed assertion (an open session's callback thread would keep pytest from exiting)
        stop_blind.set()
        if "blinder" in locals():
            blinder.join(5)
        for session in sessions:
            session.close()
        if robot is not None:
            robot.sigint()
        assert d.stop() == 0


def test_user_password_binds_to_the_certificate(free_port: int, tmp_path: Path) -> None:
    d = deploy(tmp_path, free_port, ["robot1", "robot2"], ["edge1"], passwords=True)
    try:
        pw = {n: str(d.certs / f"{n}.password") for n in ("robot1", "robot2")}
        assert not refused(d, identity="robot1", user="robot1", password_file=pw["robot1"])
        assert refused(d, identity="robot1")  # no credentials
        wrong = tmp_path / "wrong"
        wrong.write_text("nope\n")
        assert refused(d, identity="robot1", user="robot1", password_file=str(wrong))
        # robot2's valid login on robot1's certificate connects, but the ACL subject wants both to match
        monitor = open_session(d.settings("monitor", user="monitor",
                                          password_file=str(d.certs / "monitor.password")))
        seen: list[str] = []
        monitor.declare_subscriber("zoffload/status/**", lambda s: seen.append(str(s.key_expr)))
        mixed = open_session(d.settings("robot1", user="robot2", password_file=pw["robot2"]))
        good = open_session(d.settings("robot1", user="robot1", password_file=pw["robot1"]))
        time.sleep(0.5)
        for _ in range(5):
            mixed.put(KEYS.robot_status("robot1"), b"mixed")
            good.put(KEYS.robot_status("robot1"), b"good")
        wait_for(lambda: len(seen) >= 5, 10, "robot1's status with its own login")
        time.sleep(0.5)
        assert len(seen) == 5
        for s in (mixed, good, monitor):
            s.close()
    finally:
        assert d.stop() == 0


def test_two_linked_routers_carry_a_robot_and_an_edge_and_keep_forgeries_out(
        free_port: int, tmp_path: Path) -> None:
    """The robots' router and the edges' (rack) router, linked with mTLS, each with the ACL: a
    robot on one is mapped by an edge on the other; what an identity may not send is dropped at
    its own router and does not cross the link."""
    from zoffload.runtime.session import free_tcp_port

    d = deploy_linked(tmp_path, (free_port, free_tcp_port()), ["robot1", "robot2"], ["edge1", "edge2"])
    rack = d.linked[0][0]
    procs: list[Proc] = []
    sessions: list[zenoh.Session] = []
    try:
        monitor = open_session(d.settings("monitor"))  # on the robots' router: edge1's token and
        sessions.append(monitor)  # status come across the link
        status, metrics = robot1_mapped_by_edge1(d, tmp_path, monitor, procs, edge_port=rack)
        assert metrics["balanced"] and metrics["balance"]["acked"] >= 28, metrics["balance"]
        assert metrics["fleet"]["per_edge"] == {"edge1": metrics["balance"]["acked"]}
        before = metrics["balance"]["published"]
        wait_for(lambda: status.values.get("samples") == before, 10, "the edge to count robot1's scans")

        # robot1 on the robots' router forges robot2's scans and edge1's status; edge2 on the
        # rack forges robot2's scans: each is dropped by the router it is connected to
        attacker = open_session(d.settings("robot1"))
        rogue_edge = open_session(d.settings("edge2", connect=[f"tls/localhost:{rack}"]))
        victim = open_session(d.settings("robot2"))
        sessions += [attacker, rogue_edge, victim]
        got: list[bytes] = []
        victim.declare_subscriber(KEYS.scan_acks("robot2"), lambda s: got.append(s.payload.to_bytes()))
        statuses: list[bytes] = []  # edge1's status as it arrives, raw: a forged one would show here
        monitor.declare_subscriber(KEYS.edge_status("edge1"), lambda s: statuses.append(s.payload.to_bytes()))
        scan = wire.Scan(robot="robot2", seq=0, send_stamp=1.0, capture_stamp=1.0, voxel=0.05,
                         voxel_max=0.07, max_range=40.0, n_raw=10, points=np.zeros((10, 3), np.float32))
        for _ in range(10):
            attacker.put(KEYS.scan("robot2"), wire.encode(scan))
            attacker.put(KEYS.edge_status("edge1"), b"forged")
            rogue_edge.put(KEYS.scan("robot2"), wire.encode(scan))
        victim.put(KEYS.scan("robot2"), wire.encode(scan))  # robot2's own scan crosses both routers
        wait_for(lambda: len(got) == 1, 20, "the edge's answer to robot2's own scan")
        time.sleep(1.5)
        assert status.values["samples"] == before + 1  # nothing forged reached the edge
        assert statuses and b"forged" not in statuses  # edge1's own statuses came, no forged one
        assert len(got) == 1 and wire.decode(got[0], expect=wire.ScanAck).edge == "edge1"
        edges = [str(r.ok.key_expr) for r in victim.liveliness().get(KEYS.any_edge_alive(), timeout=3)
                 if r.ok is not None]
        assert edges == [KEYS.edge_alive("edge1")]
    finally:
        for session in sessions:
            session.close()
        for p in reversed(procs):  # the robot, then the edge
            p.sigint()
        assert d.stop() == 0


def test_an_edge_sees_the_other_edges_status_and_liveliness_through_the_acl(free_port: int,
                                                                               tmp_path: Path) -> None:
    """An edge sheds a robot only when another *live* edge announces room: through the secure
    router it must receive the other edges' status and their tokens' going (before, the ACL let
    neither through, so an edge under the ACL never knew of another's room)."""
    d = deploy(tmp_path, free_port, ["robot1"], ["edge1", "edge2"])
    sessions: list[zenoh.Session] = []
    try:
        edge1 = open_session(d.settings("edge1"))
        edge2 = open_session(d.settings("edge2"))
        sessions += [edge1, edge2]
        statuses: list[str] = []
        tokens: list[tuple[str, str]] = []
        edge2.declare_subscriber(KEYS.all_edge_status(), lambda s: statuses.append(str(s.key_expr)))
        edge2.liveliness().declare_subscriber(
            KEYS.any_edge_alive(), lambda s: tokens.append((str(s.key_expr), str(s.kind))), history=True)
        token = edge1.liveliness().declare_token(KEYS.edge_alive("edge1"))
        status = wire.encode(wire.Status(source="edge", id="edge1", stamp=time.time(),
                                         values={"capacity": 4.0}))
        wait_for(lambda: bool(tokens), 10, "edge1's token seen by edge2")
        edge1.put(KEYS.edge_status("edge1"), status)
        wait_for(lambda: bool(statuses), 10, "edge1's status received by edge2")
        token.undeclare()
        wait_for(lambda: any("DELETE" in kind for _, kind in tokens), 10, "edge1's token going seen by edge2")
        assert all(key == KEYS.edge_alive("edge1") for key, _ in tokens)
        # a robot's identity still cannot speak for an edge
        robot = open_session(d.settings("robot1"))
        sessions.append(robot)
        n = len(statuses)
        robot.put(KEYS.edge_status("edge1"), status)
        time.sleep(1.0)
        assert len(statuses) == n
    finally:
        for session in sessions:
            session.close()
        assert d.stop() == 0


def test_an_authorised_edge_cannot_answer_in_another_edges_name(free_port: int, tmp_path: Path) -> None:
    """Was: the ACL let every edge identity put acks and checkpoints for every robot on one key, and
    the robot checked only the fields an edge echoes, so a compromised edge2 that overheard robot1's
    scans fed it poses in edge1's name. Now an edge puts answers only under its own id (the router
    refuses edge1's key to edge2) and the robot drops an answer whose payload names another edge than
    its key (counted ``edge_key_ack`` / ``edge_key_checkpoint``)."""
    d = deploy(tmp_path, free_port, ["robot1"], ["edge1", "edge2"])
    procs: list[Proc] = []
    forged = {"edge1_key": 0, "own_key": 0}
    try:
        attacker = open_session(d.settings("edge2"))  # edge2's real identity, compromised

        def forge(sample: zenoh.Sample) -> None:  # answers every robot1 scan it overhears as edge1
            scan = wire.decode(sample.payload.to_bytes(), expect=wire.Scan)
            ack = wire.encode(dataclasses.replace(
                wire.decode(forged_ack(scan.robot, scan.seq, scan.send_stamp), expect=wire.ScanAck),
                epoch=scan.epoch, map_points=777_777))
            attacker.put(KEYS.scan_ack(scan.robot, "edge1"), ack)  # refused by the router
            forged["edge1_key"] += 1
            attacker.put(KEYS.scan_ack(scan.robot, "edge2"), ack)  # reaches robot1, which drops it
            cp = wire.Checkpoint(robot=scan.robot, edge="edge1", epoch=scan.epoch, seq=scan.seq,
                                 stamp=scan.capture_stamp, voxel_size=0.4, max_range=40.0, min_range=0.0,
                                 max_points_per_voxel=20, pose=np.eye(4), delta=np.eye(4),
                                 points=np.zeros((10, 3), np.float32))
            attacker.put(KEYS.checkpoint(scan.robot, "edge2"), wire.encode(cp))
            forged["own_key"] += 1

        sub = attacker.declare_subscriber(KEYS.all_scans(), forge)
        monitor = open_session(d.settings("monitor"))
        _, metrics = robot1_mapped_by_edge1(d, tmp_path, monitor, procs)
        sub.undeclare()
        assert forged["own_key"] >= 20, forged  # it overheard and answered robot1's scans
        assert metrics["balance"]["acked"] >= 25  # edge1's own answers still count
        rows = list(csv.DictReader((tmp_path / "robot" / "robot_scans.csv").open()))
        assert not [r for r in rows if r["map_points"] == "777777"]  # no forged ack booked
        drops = metrics["drops"]
        assert drops.get("edge_key_ack", 0) >= 20, drops  # those on edge2's key, dropped by the robot
        assert drops.get("edge_key_ack", 0) <= forged["own_key"], drops  # none on edge1's key came through
        for s in (attacker, monitor):
            s.close()
    finally:
        for p in reversed(procs):
            p.sigint()
        assert d.stop() == 0


def test_an_authorised_edge_cannot_answer_a_map_query_in_another_edges_name(free_port: int,
                                                                            tmp_path: Path) -> None:
    """Was: every edge identity declared and answered ``ctrl/*/map``, so a compromised edge2 answered
    map queries for robot1, which edge1 maps, in edge1's name. Now an edge declares and answers only
    its own ``ctrl/*/map/<edge>`` (the router refuses edge2's queryable on edge1's key and never sends
    it edge1's queries), a querier asks each edge by name, and a map naming another edge than asked
    is dropped (``edge_key_map``): the monitor (the lab's runner) still gets edge1's own map."""
    d = deploy(tmp_path, free_port, ["robot1"], ["edge1", "edge2"])
    procs: list[Proc] = []
    sessions: list[zenoh.Session] = []
    asked: dict[str, int] = {"edge1_key": 0, "before_key": 0, "own_key": 0}
    try:
        attacker = open_session(d.settings("edge2"))  # edge2's real identity, compromised
        sessions.append(attacker)
        forged = wire.encode(wire.MapReply(robot="robot1", scans=777, points=np.zeros((10, 3), np.float32),
                                           seqs=np.arange(777), poses=np.repeat(np.eye(4)[None], 777, 0),
                                           edge="edge1"))

        def answer(where: str) -> Callable[[zenoh.Query], None]:
            def on(query: zenoh.Query) -> None:
                asked[where] += 1
                query.reply(query.key_expr, forged)
            return on

        held = [attacker.declare_queryable(KEYS.all_maps("edge1"), answer("edge1_key")),  # refused
                attacker.declare_queryable(KEYS.map_before("robot1"), answer("before_key")),  # refused
                attacker.declare_queryable(KEYS.all_maps("edge2"), answer("own_key"))]  # edge1's name
        monitor = open_session(d.settings("monitor"))
        sessions.append(monitor)
        robot1_mapped_by_edge1(d, tmp_path, monitor, procs)

        # every queryable on edge1's key is asked: only edge1's own answers come back
        replies = [r.ok for r in monitor.get(KEYS.map("robot1", "edge1"), target=zenoh.QueryTarget.ALL,
                                             consolidation=zenoh.ConsolidationMode.NONE, timeout=10)
                   if r.ok is not None]
        maps = [wire.decode(r.payload.to_bytes(), expect=wire.MapReply) for r in replies]
        assert len(maps) == 1 and maps[0].edge == "edge1" and 1 <= maps[0].scans <= 30, maps
        # the runner's query, told to ask edge2 first: its map in edge1's name is dropped, edge1's taken
        drops = Drops(logging.getLogger("test.maps"))
        got = fetch_map(monitor, KEYS, "robot1", ["edge2"], drops, timeout=10)
        assert got is not None and got.edge == "edge1" and got.scans == maps[0].scans
        assert drops.snapshot() == {"edge_key_map": 1} and asked["own_key"] >= 1
        assert asked["edge1_key"] == 0 and asked["before_key"] == 0  # never reached edge2
        for h in held:
            h.undeclare()
    finally:
        for session in sessions:
            session.close()
        for p in reversed(procs):
            p.sigint()
        assert d.stop() == 0
