"""Each reproduction of the hardening audit (issue 11) as a regression test against a real
`zoffload-edge` process: the crafted message, then the edge alive, the message counted, its peak
resident memory within the target (+100 MB), and the edge still serving a normal scan.

The peak RSS of each case (``VmHWM`` reset before it) is printed; run with ``-s`` to see them."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
import zstandard

from benchmarks.bench_collisions import crafted_points, random_points
from tests.daemon.edge.acks import Acks
from tests.helpers import KEYS, client, wait_for
from tests.system.edgewatch import EdgeWatch
from tests.system.procs import Proc, edge_args, script, session_args, start_edge
from zoffload.protocol import wire

pytestmark = pytest.mark.system
pytest.importorskip("kiss_icp")

PEAK_MB = 100.0  # the target for any crafted message


def scan(robot: str, seq: int, n: int = 2000, **over: object) -> wire.Scan:
    pts = np.random.default_rng(seq).uniform(-15, 15, (n, 3)).astype(np.float32)
    fields: dict[str, object] = dict(robot=robot, seq=seq, send_stamp=float(seq), capture_stamp=0.0,
                                     voxel=0.05, voxel_max=0.07, max_range=40.0, n_raw=n, points=pts)
    fields.update(over)
    return wire.Scan(**fields)  # type: ignore[arg-type]


def raw(msg: wire.Message, **fields: object) -> bytes:
    """The message encoded, then fields overwritten at the msgpack level (what no encoder sends)."""
    obj = msgpack.unpackb(wire.encode(msg), raw=False)
    obj.update(fields)
    return msgpack.packb(obj, use_bin_type=True)


def q16z_fields(blob: bytes, n_points: int) -> dict[str, object]:
    return {"coding": "q16z", "n_points": n_points, "quant_step": 0.01,
            "points": {"nd": "<f4", "shape": [0, 3], "data": b""},
            "origin": {"nd": "<f8", "shape": [3], "data": b"\x00" * 24},
            "packed": {"nd": "|u1", "shape": [len(blob)], "data": blob}}


class Edge:
    def __init__(self, session: zenoh.Session, proc: Proc, tmp: Path) -> None:
        self.session, self.proc, self.tmp = session, proc, tmp
        self.watch = EdgeWatch(session, proc.p.pid)
        self.peaks: dict[str, float] = {}

    def case(self, name: str, send: list[bytes], robot: str = "robot1", key: str = "scan") -> float:
        """Send ``send`` on the robot's key, wait until the edge accounted for every message, and
        return (and record) the case's peak RSS above the RSS before it, in MB."""
        before_samples = self.watch.value("samples" if key == "scan" else "detector.samples")
        base = self.watch.reset_peak()
        for payload in send:
            self.session.put(KEYS.scan(robot) if key == "scan" else KEYS.frame(robot), payload,
                             congestion_control=zenoh.CongestionControl.BLOCK)
        counter = "samples" if key == "scan" else "detector.samples"
        self.watch.wait(counter, before_samples + len(send))
        self.watch.settle()
        time.sleep(0.5)  # registration (after the count) finishes
        peak = self.watch.peak_mb() - base
        self.peaks[name] = peak
        print(f"{name}: peak RSS +{peak:.1f} MB")
        assert self.watch.alive(), self.proc.text()
        return peak

    def still_serves(self, robot: str = "healthy") -> None:
        acks = Acks(self.session, robot)
        seq = 100 + len(acks.items)
        self.session.put(KEYS.scan(robot), wire.encode(scan(robot, seq)))
        wait_for(lambda: acks.seqs("ok") == [seq], 30, "a normal scan acked")
        acks.sub.undeclare()


@pytest.fixture(scope="module")
def edge(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Edge]:
    from zoffload.runtime.session import free_tcp_port

    tmp = tmp_path_factory.mktemp("edge")
    port = free_tcp_port()
    with client(port) as s:
        proc = start_edge(s, edge_args(port, "--map-dir", str(tmp / "maps")), tmp / "edge.log")
        e = Edge(s, proc, tmp)
        try:
            yield e
            assert "Traceback" not in proc.text()
            # seq >= 2^63 used to break map queries and the shutdown: one SIGINT, maps exported
            t0 = time.monotonic()
            assert proc.sigint(30) == 0, proc.text()
            assert time.monotonic() - t0 < 20
            assert (tmp / "maps" / "healthy_map.ply").exists()
        finally:
            e.watch.close()
            if proc.p.poll() is None:
                proc.p.kill()
    (tmp / "peaks.json").write_text(json.dumps(e.peaks, indent=2))


def test_infinite_and_absurd_max_range_is_refused(edge: Edge) -> None:
    """Was: inf max_range sized KISS-ICP and Sophus aborted the edge on the third such scan."""
    values = [float("inf")] * 3 + [1e200, float("nan")]
    bad = [raw(scan("robot1", i), max_range=v) for i, v in enumerate(values)]
    before = edge.watch.value("drop.malformed")
    assert edge.case("inf max_range", bad) <= PEAK_MB
    assert edge.watch.value("drop.malformed") == before + 5
    edge.still_serves()


@pytest.mark.parametrize("max_range, voxel_max", [(10_000.0, 10.0), (0.1, 0.0), (10_000.0, 0.0)])
def test_scans_at_the_codec_bounds_are_registered_with_a_clamped_mapper(edge: Edge, max_range: float,
                                                                        voxel_max: float) -> None:
    robot = f"bounds{int(max_range)}-{int(voxel_max)}"
    acks = Acks(edge.session, robot)
    msgs = [wire.encode(scan(robot, i, max_range=max_range, voxel_max=voxel_max)) for i in range(3)]
    assert edge.case(f"max_range {max_range:g} voxel_max {voxel_max:g}", msgs, robot) <= PEAK_MB
    wait_for(lambda: len(acks.items) == 3, 30, "an answer per scan")
    statuses = [a.status for a in acks.items]  # (sent at once: one may be dropped from the queue)
    assert set(statuses) <= {"ok", "error", "dropped"} and statuses.count("dropped") < 3
    edge.still_serves()


def test_q16z_bomb_is_refused_before_decompression(edge: Edge) -> None:
    """Was: a 32 KiB scan whose zstd frame declares 1 GiB: +1 GiB peak RSS."""
    cctx = zstandard.ZstdCompressor(level=19).compressobj(size=1 << 30)
    blob = b"".join([cctx.compress(b"\x00" * (1 << 20)) for _ in range(1024)] + [cctx.flush()])
    assert len(blob) < 40_000 and zstandard.frame_content_size(blob) == 1 << 30
    acks = Acks(edge.session, "bomber")
    msgs = [raw(scan("bomber", 0), **q16z_fields(blob, 1)),  # declared size != 1 point
            raw(scan("bomber", 1), **q16z_fields(blob, (1 << 30) // 6)),  # consistent, beyond max_points
            raw(scan("bomber", 2), **q16z_fields(blob[:1200], 5_000_000))]  # 1.2 KiB claiming 5 M points
    before = edge.watch.value("drop.malformed")
    assert edge.case("q16z bomb", msgs, "bomber") <= PEAK_MB
    assert edge.watch.value("drop.malformed") == before + 2  # refused at intake
    wait_for(lambda: len(acks.items) == 1, 10, "the first scan's answer")
    assert acks.items[0].status == "error" and "declares" in acks.items[0].detail
    edge.still_serves()


def test_a_scan_at_the_point_cap_stays_within_the_memory_target(edge: Edge) -> None:
    """The largest scan the edge accepts by default (limits.max_points, zeros): decoded, mapped."""
    from zoffload.runtime.config import LimitsSettings

    n = LimitsSettings().max_points
    blob = zstandard.ZstdCompressor(level=3).compress(np.zeros(n * 3, "<u2").tobytes())
    acks = Acks(edge.session, "biggest")
    peak = edge.case(f"{n} points at the cap", [raw(scan("biggest", 0), **q16z_fields(blob, n))], "biggest")
    wait_for(lambda: len(acks.items) == 1, 60, "the big scan's answer")
    assert peak <= PEAK_MB, f"a {n}-point scan took +{peak:.0f} MB"
    edge.still_serves()


def test_seq_beyond_2_63_is_refused_and_map_queries_still_work(edge: Edge) -> None:
    """Was: OverflowError in the map queryable and at shutdown (no map exported, two SIGINTs)."""
    before = edge.watch.value("drop.malformed")
    assert edge.case("seq 2^63", [raw(scan("healthy", 0), seq=2**63), raw(scan("healthy", 0), seq=2**64 - 1)],
                     "healthy") <= PEAK_MB
    assert edge.watch.value("drop.malformed") == before + 2
    edge.still_serves()
    reply = list(edge.session.get(KEYS.map("healthy", "edge1"), timeout=10))[0].ok
    assert reply is not None
    m = wire.decode(reply.payload.to_bytes(), expect=wire.MapReply)
    assert m.scans >= 1 and int(m.seqs.max()) < 2**63


def test_a_small_jpeg_claiming_a_huge_image_is_answered_without_decoding(edge: Edge) -> None:
    """Was: an 829-byte frame took 2 GB peak RSS and the detector thread 2.2 s."""
    cv2 = pytest.importorskip("cv2")
    if "detector.samples" not in edge.watch.values and not edge.watch.values.get("detector.infer_ms"):
        time.sleep(2)
    if not any(k.startswith("detector.") for k in edge.watch.values):
        pytest.skip("the edge runs no detector (model files not found: set ZOFFLOAD_MODELS)")
    ok, buf = cv2.imencode(".jpg", np.random.default_rng(0).integers(0, 255, (8, 8, 3), np.uint8))
    b = bytearray(buf.tobytes())
    i = b.index(b"\xff\xc0")
    b[i + 5:i + 9] = (65_500).to_bytes(2, "big") * 2  # the header claims 65,500 x 65,500
    data = np.frombuffer(bytes(b), np.uint8)
    frames = [wire.encode(wire.Frame(robot="camera1", seq=k, send_stamp=1.0, capture_stamp=1.0,
                                     encoding="jpeg", width=w, height=h, data=data))
              for k, (w, h) in enumerate([(8, 8), (65_500, 65_500), (1000, 1000)])]
    got: list[wire.Detections] = []
    sub = edge.session.declare_subscriber(KEYS.detections_to("camera1"), lambda s: got.append(
        wire.decode(s.payload.to_bytes(), expect=wire.Detections)))
    t0 = time.monotonic()
    assert edge.case("829-byte JPEG", frames, "camera1", key="frame") <= PEAK_MB
    wait_for(lambda: len(got) == 3, 10, "an answer per frame")
    assert time.monotonic() - t0 < 10
    assert [d.status for d in got] == ["error"] * 3
    assert all("JPEG header" in d.detail or "pixels" in d.detail for d in got)
    sub.undeclare()


def test_fuzzed_scans_leave_no_traceback_and_every_one_is_counted(edge: Edge) -> None:
    from tests.fuzzing import corpus

    msgs = list(corpus(11, 2000, kinds=("scan_f32", "scan_q16z", "scan_q16z_times")))
    edge.case("2000 fuzzed scans", msgs)
    edge.still_serves()
    assert "Traceback" not in edge.proc.text()
    assert edge.watch.value("drop.callback_error") == 0


def test_collision_flooding_of_the_global_map_costs_what_random_points_cost(tmp_path: Path,
                                                                           free_port: int) -> None:
    """Was: 60k points crafted for one hash slot: 840 ms vs 3.8 ms for random points. The mapper's
    range is set wide so the crafted points (spread over +-60 km at 0.1 m voxels) reach the map."""
    with client(free_port) as s:
        proc = start_edge(s, edge_args(free_port, "--mapper.max-range", "200000",
                                       "--mapper.voxel-size", "50"), tmp_path / "edge.log")
        try:
            times = {}
            cases = (("random", random_points(60_000, 0.1, seed=1)), ("crafted", crafted_points(60_000, 0.1)))
            for name, pts in cases:
                acks = Acks(s, name)
                msg = scan(name, 0, points=pts.astype(np.float32), n_raw=len(pts))
                s.put(KEYS.scan(name), wire.encode(msg))
                wait_for(lambda a=acks: len(a.items) == 1, 60, f"the {name} scan acked")  # type: ignore[misc]
                ack = acks.items[0]
                assert ack.status == "ok", ack.detail
                assert ack.map_points >= 59_000
                times[name] = ack.proc_time - ack.icp_time  # the global map's insert
            print(f"global map insert of 60k points: crafted {times['crafted'] * 1e3:.1f} ms, random "
                  f"{times['random'] * 1e3:.1f} ms")
            assert times["crafted"] < 10 * times["random"] + 0.2, times
        finally:
            assert proc.sigint() == 0, proc.text()


# -m slow: tests/daemon/edge/test_admission.py keeps robots beyond max_robots refused without state
@pytest.mark.slow
def test_5000_fake_robot_ids_cost_no_threads_and_a_real_robot_keeps_its_acks(tmp_path: Path,
                                                                               free_port: int) -> None:
    """Was: 5,000 fake ids in 5.6 s: 5.2 GB RSS, 3,360 threads, and a real robot 0 of 15 scans acked."""
    with client(free_port) as s:
        proc = start_edge(s, edge_args(free_port), tmp_path / "edge.log")
        watch = EdgeWatch(s, proc.p.pid)
        try:
            robot = Proc(script("zoffload-robot") + session_args(connect=free_port)
                         + ["--max-scans", "100", "--out", str(tmp_path / "robot")],
                         tmp_path / "robot.log")
            watch.wait("received", 10, 60)  # the real robot is being served
            threads, base = watch.threads(), watch.reset_peak()
            pts = np.zeros((20, 3), np.float32)
            for i in range(5000):
                fake = f"fake{i}"
                # BLOCK: every hostile message reaches the edge (put's default, DROP, let this
                # session's own Zenoh drop some of the burst: CI once counted fewer than 4985)
                s.put(KEYS.scan(fake), wire.encode(scan(fake, 0, points=pts, n_raw=20)),
                      congestion_control=zenoh.CongestionControl.BLOCK)
            watch.wait("drop.refused", 5000 - 15, 60)
            peak = watch.peak_mb() - base
            print(f"5000 fake ids: threads {threads} -> {watch.threads()}, peak RSS +{peak:.0f} MB")
            assert robot.wait(120) == 0, robot.text()
            assert watch.threads() <= threads + 4  # a fixed pool; Zenoh may start a thread or two
            assert peak <= 200
            assert watch.value("robots") <= 16  # max_robots
            metrics = json.loads((tmp_path / "robot" / "robot_metrics.json").read_text())
            b = metrics["balance"]
            print(f"the real robot: {b['acked']} of {b['published']} published scans acked")
            # (93 of 100 once in CI, with the core tests running on the other core beside it)
            assert metrics["balanced"] and b["acked"] >= 0.9 * b["published"], b
        finally:
            watch.close()
            assert proc.sigint() == 0, proc.text()
