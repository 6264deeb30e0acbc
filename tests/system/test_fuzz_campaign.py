"""The fuzz campaign: the seeded hostile-message corpus (tests/fuzzing.py) against a real edge
process and a real robot process, on every key each subscribes to or answers. Each daemon must stay
up with no traceback, account for every message (the edge's status: ``samples`` = ``received`` +
drops by reason; the robot's results: its ack buckets + drops by reason), and still serve a normal
message afterwards.

The default run sends ``QUICK`` messages per key; ``-m slow`` runs the campaign's full size
(``FULL`` per key, the issue's >= 10,000)."""

from __future__ import annotations

import json
import random
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from tests.daemon.edge.acks import Acks
from tests.fuzzing import corpus
from tests.helpers import KEYS, client, listen_on, wait_for
from tests.system.edgewatch import EdgeWatch
from tests.system.procs import Proc, edge_args, script, session_args, start_edge
from zoffload.protocol import wire
from zoffload.runtime.session import open_session

pytestmark = pytest.mark.system
pytest.importorskip("kiss_icp")

QUICK, FULL = 1_000, 10_000
SCANS = ("scan_f32", "scan_q16z", "scan_q16z_times")


def odd_parameters(rng: random.Random) -> str:
    value = rng.choice(["nan", "inf", "-inf", "1e309", "", "x" * 5000, "1.5", "-0", "0x10", "1_0", "\x00",
                        "1e300", str(rng.random()), "%zz", "a=b", "stamp"])
    return rng.choice([f"stamp={value}", f"{value}", f"stamp={value};stamp=1", f"x={value}"])


def odd_chunk(rng: random.Random) -> str:
    return rng.choice(["robot1", "nobody", "r" * 200, "a.b-c_d", "**", "*", "robot1/map", "%41", "é"])


def fuzz_queries(s: zenoh.Session, n: int, seed: int) -> tuple[int, int]:
    """``n`` map queries and ``n`` pings with hostile keys, parameters and payloads; returns the
    (queries sent, replies received)."""
    rng = random.Random(seed)
    payloads = corpus(seed, n)
    replies = 0
    lock = threading.Lock()

    def on_reply(_reply: zenoh.Reply) -> None:
        nonlocal replies
        with lock:
            replies += 1

    sent = 0
    for i, payload in zip(range(2 * n), payloads, strict=False):
        kind = "map" if i % 2 == 0 else "ping"
        key = f"zoffload/ctrl/{odd_chunk(rng)}/{kind}"
        try:
            selector = f"{key}?{odd_parameters(rng)}" if kind == "ping" else key
            s.get(selector, on_reply, payload=payload, timeout=10)
        except Exception:  # a key expression Zenoh itself refuses never reaches the edge
            continue
        sent += 1
        if sent % 200 == 0:
            time.sleep(0.05)  # let replies drain: the point is the edge, not Zenoh's query table
    return sent, replies


def run_edge_campaign(tmp: Path, port: int, n: int) -> None:
    with client(port) as s:
        edge = start_edge(s, edge_args(port), tmp / "edge.log")
        watch = EdgeWatch(s, edge.p.pid)
        try:
            block = zenoh.CongestionControl.BLOCK  # every message reaches the edge: each must be counted
            scan_pub = s.declare_publisher(KEYS.scan("robot1"), congestion_control=block)
            frame_pub = s.declare_publisher(KEYS.frame("robot1"), congestion_control=block)
            for payload in corpus(1, n, kinds=SCANS):
                scan_pub.put(payload)
            for payload in corpus(2, n, kinds=("frame",)):
                frame_pub.put(payload)
            sent, _ = fuzz_queries(s, n, 3)
            assert sent >= n  # the hostile keys Zenoh accepted
            watch.wait("samples", n, 120)
            watch.settle(120)
            v = watch.values
            assert v["samples"] == n and v["samples"] == (v.get("received", 0) + v["drops"]
                                                          + v.get("other_edge", 0))
            assert v.get("drop.callback_error", 0) == 0
            if "detector.samples" in v:
                wait_for(lambda: watch.value("detector.samples") == n, 120, "every frame counted")
                d = watch.values
                assert d["detector.samples"] == (d.get("detector.received", 0) + d["detector.drops"]
                                                 + d.get("detector.other_edge", 0))  # mutated Frame.edge
                assert d.get("detector.drop.callback_error", 0) == 0
            # (without a detector model on this machine, no edge subscriber takes the frames)
            assert v.get("ping.drop.callback_error", 0) == 0
            # still serving, still sane
            acks = Acks(s, "after")
            pts = np.random.default_rng(0).uniform(-10, 10, (500, 3)).astype(np.float32)
            s.put(KEYS.scan("after"), wire.encode(wire.Scan(
                robot="after", seq=1, send_stamp=1.0, capture_stamp=1.0, voxel=0.05, voxel_max=0.07,
                max_range=40.0, n_raw=500, points=pts)))
            wait_for(lambda: acks.seqs("ok") == [1], 60, "a normal scan acked after the campaign")
            assert watch.alive()
        finally:
            watch.close()
            code = edge.sigint(60)
        text = edge.text()
        assert code == 0, text
        assert "Traceback" not in text


def run_robot_campaign(tmp: Path, port: int, n: int, camera: bool) -> None:
    """A robot process connected to this test's session, which plays a present edge (its token)
    that answers every real scan correctly and floods the robot's answer keys with the corpus."""
    s = open_session(listen_on(port))
    try:
        token = s.liveliness().declare_token(KEYS.edge_alive("edge1"))
        real_acks = 0

        def answer(sample: zenoh.Sample) -> None:  # the honest edge: one ok ack per real scan
            nonlocal real_acks
            scan = wire.decode(sample.payload.to_bytes(), expect=wire.Scan)
            s.put(KEYS.scan_ack(scan.robot, "edge1"), wire.encode(wire.ScanAck(
                robot=scan.robot, seq=scan.seq, send_stamp=scan.send_stamp, status="ok", interarrival=0.1,
                queue_time=0.0, proc_time=0.001, icp_time=0.001, map_points=1, keypoints=1, sigma=0.1,
                pose=np.eye(4), edge="edge1")), congestion_control=zenoh.CongestionControl.BLOCK)
            real_acks += 1

        sub = s.declare_subscriber(KEYS.scan("robot1"), answer)
        extra = (["--images", "coco-clips", "--perception.strategy", "robot", "--perception.fps", "5"]
                 if camera else [])
        robot = Proc(script("zoffload-robot") + session_args(connect=port)
                     # the stand-in edge answers scans, not attach queries: the robot streams as
                     # it does without the fleet protocol
                     + ["--rate", "10", "--replay", "loop", "--fleet.no-attach", "--out", str(tmp / "robot"),
                        *extra],
                     tmp / "robot.log")
        wait_for(lambda: real_acks >= 5, 60, "the robot streaming")
        block = zenoh.CongestionControl.BLOCK
        ack_pub = s.declare_publisher(KEYS.scan_ack("robot1", "edge1"), congestion_control=block)
        det_pub = s.declare_publisher(KEYS.detections("robot1", "edge1"), congestion_control=block)
        status_pub = s.declare_publisher(KEYS.edge_status("edge1"), congestion_control=block)
        for payload in corpus(4, n, kinds=("ack",)):
            ack_pub.put(payload)
        n_status = n // 10  # an edge's status: read once for the robot (EdgePresence)
        for payload in corpus(6, n_status, kinds=("status",)):
            status_pub.put(payload)
        if camera:
            for payload in corpus(5, n, kinds=("detections",)):
                det_pub.put(payload)
        time.sleep(2)
        assert robot.p.poll() is None, robot.text()
        code = robot.sigint(60)
        sub.undeclare()
        token.undeclare()
        text = robot.text()
        assert code == 0, text
        assert "Traceback" not in text
        m = json.loads((tmp / "robot" / "robot_metrics.json").read_text())
        b, other, drops = m["balance"], m["other"], m["drops"]
        booked = b["acked"] + b["edge_dropped"] + b["edge_error"] + b["late"]
        accounted = (booked + other.get("unknown_acks", 0) + other.get("duplicate_acks", 0)
                     + sum(drops.values()))
        assert accounted == real_acks + n, (m, real_acks)
        assert drops.get("callback_error", 0) == 0
        assert m["balanced"]
        presence = json.loads((tmp / "robot" / "presence_drops.json").read_text())
        # every hostile status refused and counted (a mutation may leave a valid one: it is read)
        assert 0 < sum(presence.values()) <= n_status and presence.get("callback_error", 0) == 0, presence
        if camera:
            v = json.loads((tmp / "robot" / "vision_metrics.json").read_text())
            counted = sum(v["other"].get(k, 0) for k in ("malformed_results", "late_or_unknown_results"))
            assert 0 < counted <= n  # (detections for another robot id are dropped but not in these results)
    finally:
        s.close()


def _camera_available() -> bool:
    from zoffload.lab.soak import _camera_available as available

    return available()


def test_fuzz_campaign_against_a_real_edge(tmp_path: Path, free_port: int) -> None:
    run_edge_campaign(tmp_path, free_port, QUICK)


def test_fuzz_campaign_against_a_real_robot(tmp_path: Path, free_port: int) -> None:
    run_robot_campaign(tmp_path, free_port, QUICK, camera=False)


@pytest.mark.slow
def test_full_fuzz_campaign_against_a_real_edge(tmp_path: Path, free_port: int) -> None:
    run_edge_campaign(tmp_path, free_port, FULL)


@pytest.mark.slow
def test_full_fuzz_campaign_against_a_real_robot_with_its_camera(tmp_path: Path, free_port: int) -> None:
    run_robot_campaign(tmp_path, free_port, FULL, camera=_camera_available())
