"""The robot daemon in-process against a real edge daemon (own Zenoh sessions, loopback port)."""

from __future__ import annotations

import csv
import json
import math
import queue
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.helpers import KEYS, client, connect_to, listen_on, running_edge
from zoffload.protocol import wire
from zoffload.robot.scans import ScanStreamer, scan_streamer
from zoffload.robot.server import RobotServer
from zoffload.runtime.config import EdgeSettings, RobotFleetSettings, RobotSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import open_session
from zoffload.sources.base import ScanFrame
from zoffload.sources.simulated import SimulatedSource

pytest.importorskip("kiss_icp")


def run_robot(settings: RobotSettings, source: object | None = None) -> ScanStreamer:
    """The robot server with its scan pipeline only, run to the end of the source."""
    stop = StopSignal()
    robot = scan_streamer(settings, stop, source=source)  # type: ignore[arg-type]
    RobotServer(settings, [robot], stop).run()
    return robot


def test_scans_are_acked_and_counters_balance(free_port: int, tmp_path: Path) -> None:
    with running_edge(EdgeSettings(zenoh=listen_on(free_port))):
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=25, rate_hz=20,
                                        scale_policy="fixed", scan_coding="f32", out_dir=str(tmp_path)))
    m = robot.metrics()
    assert m["balanced"] and m["balance"]["produced"] == 25
    # a scan the source replaced before the loop took it (a busy machine: once or twice in a suite
    # run) is counted, not a row
    taken = 25 - m["balance"]["dropped_source"]
    assert m["balance"]["acked"] >= taken - 1 and m["balance"]["in_flight"] == 0, m["balance"]
    s = m["scans"]
    assert s["mean_points_sent"] < s["mean_points_raw"]  # 5 cm voxels really reduce
    assert 0.02 < s["mean_T"] < 0.2 and s["mean_rtt_ms"] > 0
    rows = list(csv.DictReader(open(tmp_path / "robot_scans.csv")))
    assert len(rows) == taken and all(float(r["voxel"]) == 0.05 for r in rows if r["status"] == "acked")
    assert json.loads((tmp_path / "robot_metrics.json").read_text())["balanced"] is True
    assert (tmp_path / "robot_config.yaml").exists()
    poses = np.load(tmp_path / "robot_poses.npz")
    assert len(poses["gt_seqs"]) == taken and len(poses["acked_seqs"]) == m["balance"]["acked"]


def test_without_an_edge_the_robot_keeps_running_and_counts(free_port: int) -> None:
    # With the attach protocol (default) the robot maps its scans itself; without it (legacy)
    # they are dropped as edge_absent
    robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=10, rate_hz=50,
                                    wait_edge=0.2))
    m = robot.metrics()
    assert m["balanced"]
    assert m["balance"]["produced"] == 10 and m["balance"]["published"] == 0
    assert m["balance"]["local"] == 10 and m["dropped_source"] == {}
    legacy = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=10, rate_hz=50,
                                     wait_edge=0.2, fleet=RobotFleetSettings(attach=False)))
    m = legacy.metrics()
    assert m["balanced"] and m["dropped_source"] == {"edge_absent": 10} and "fleet" not in m


class NaNSource:
    """Real geometry (simulator) with the NaN rows a driver emits for beams without return."""

    def __init__(self) -> None:
        self.sim = SimulatedSource()
        self.name, self.rate_hz, self.max_range = "nan-sim", 10.0, 40.0

    def __len__(self) -> int:
        return 6

    def read(self, index: int) -> ScanFrame:
        f = self.sim.read(index)
        pts = np.vstack([f.points, np.full((100, 3), np.nan, np.float32)])
        if index == 3:
            pts = np.full((50, 3), np.nan, np.float32)  # a scan with no valid point at all
        return ScanFrame(index=index, points=pts, gt_pose=f.gt_pose)


def test_non_finite_points_are_dropped_and_counted(free_port: int) -> None:
    with running_edge(EdgeSettings(zenoh=listen_on(free_port))):
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), rate_hz=20), NaNSource())
    m = robot.metrics()
    assert m["balanced"] and m["dropped_source"] == {"empty": 1}
    recs = robot.ledger.records
    assert recs[0]["n_nonfinite"] == 100 and recs[3]["n_nonfinite"] == 50
    assert recs[3]["status"] == "source:empty"
    assert m["balance"]["acked"] == 5


def test_robot_runs_an_onnx_scale_policy_against_the_edge(free_port: int, tmp_path: Path) -> None:
    pytest.importorskip("onnx")
    from tests.core.policy.test_onnx_scale import threshold_model

    model = threshold_model(tmp_path / "policy.onnx")  # finer when T < 0.1 s, coarser above
    with running_edge(EdgeSettings(zenoh=listen_on(free_port))):
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=30, rate_hz=10,
                                        scale_policy=f"dqn:{model}"))
    assert robot.policy.name == "dqn"
    m = robot.metrics()
    assert m["balanced"] and m["balance"]["acked"] >= 28
    voxels = [r["voxel"] for r in robot.ledger.records.values() if "voxel" in r]
    assert set(voxels) <= {0.01, 0.03, 0.05, 0.07} and len(set(voxels)) > 1
    assert voxels[0] == 0.03  # T0 = 0 < 0.1: the first decision is "finer" from v0 = 0.05


def test_coded_scans_are_decoded_and_registered_on_the_edge(free_port: int, tmp_path: Path) -> None:
    with running_edge(EdgeSettings(zenoh=listen_on(free_port))) as edge:
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=20, rate_hz=20,
                                        scan_coding="q16z", out_dir=str(tmp_path)))
        assert edge.mapping is not None
        registered = edge.mapping.robots["robot1"].counters["registered"]
    m = robot.metrics()
    assert m["balanced"] and m["balance"]["acked"] >= 15 and registered >= m["balance"]["acked"], m["balance"]
    rows = list(csv.DictReader(open(tmp_path / "robot_scans.csv")))
    sent_bytes = np.mean([float(r["bytes"]) for r in rows if r["bytes"]])
    points = np.mean([float(r["n_sent"]) for r in rows if r["n_sent"]])
    assert sent_bytes < 0.45 * points * 12  # a third of the float payload, points all kept


def test_rate_policy_sizes_scans_from_the_acks(free_port: int, tmp_path: Path) -> None:
    from zoffload.policy.rate import LinkAwareScale

    with running_edge(EdgeSettings(zenoh=listen_on(free_port))):
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=30, rate_hz=20,
                                        scale_policy="rate", scan_coding="q16z", out_dir=str(tmp_path)))
    assert isinstance(robot.policy, LinkAwareScale)
    m = robot.metrics()
    assert m["balanced"] and m["balance"]["acked"] >= 22, m["balance"]
    rows = list(csv.DictReader(open(tmp_path / "robot_scans.csv")))
    voxels = [float(r["voxel"]) for r in rows if r["voxel"]]
    # in the range, widened up to twice its end when nothing fits, or 0 (sent as they are) when
    # its finest size would keep nearly every point
    assert voxels[0] == 0.05 and all(v == 0 or 0.01 - 1e-9 <= v <= 0.14 + 1e-9 for v in voxels)
    assert len(set(voxels)) > 1 and robot.policy.budget > 0  # it follows the link, not a constant
    assert all(r["reason"] for r in rows if r["status"] == "acked")  # every choice says why
    m = robot.metrics()
    assert m["cpu"]["per_scan_ms"] > 0 and m["cpu"]["process_s"] > 0


def test_scans_an_edge_refuses_are_booked_apart_and_the_counters_balance(free_port: int) -> None:
    from zoffload.runtime.config import AdmissionSettings

    edge = EdgeSettings(zenoh=listen_on(free_port), admission=AdmissionSettings(robots=["someone_else"]))
    with running_edge(edge):
        # Legacy (no attach): the edge refuses every scan
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=12, rate_hz=20,
                                        max_in_flight=0, fleet=RobotFleetSettings(attach=False)))
        # Attach protocol: the edge refuses the attach; the robot maps itself, sends nothing
        attaching = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=12, rate_hz=20))
    m = robot.metrics()
    assert m["balanced"] and m["balance"]["edge_refused"] >= 8 and m["balance"]["acked"] == 0, m["balance"]
    m = attaching.metrics()
    assert m["balanced"] and m["balance"]["local"] == 12 and m["fleet"]["attach_refused"] >= 1, m


@dataclass(frozen=True)
class TimedFrame:
    """A scan frame with per-point times (``ScanFrame.times`` as the sources give it)."""

    index: int
    points: np.ndarray
    gt_pose: np.ndarray | None
    times: np.ndarray


class TimedSource(NaNSource):
    def read(self, index: int) -> TimedFrame:  # type: ignore[override]
        f = self.sim.read(index)
        pts = f.points[np.isfinite(f.points).all(axis=1)]
        return TimedFrame(index, pts, f.gt_pose, 1.7e9 + index * 0.1 + np.linspace(0, 0.1, len(pts)))


def test_point_times_reach_the_edge(free_port: int) -> None:
    seen: list[wire.Scan] = []
    with running_edge(EdgeSettings(zenoh=listen_on(free_port))), client(free_port) as s:
        s.declare_subscriber(KEYS.scan("robot1"), lambda x: seen.append(
            wire.decode(x.payload.to_bytes(), expect=wire.Scan)))
        run_robot(RobotSettings(zenoh=connect_to(free_port), rate_hz=20), TimedSource())
    assert seen and all(0.09 < m.time_span <= 0.1 for m in seen)
    pts, times = seen[-1].cloud_and_times()
    assert times is not None and len(times) == len(pts) and times.max() <= 0.1 + 1e-6


@contextmanager
def slow_edge(port: int, answer_after: float, edge_time: float,
              mute_from: int = -1, mute: float = 0.0,
              subscribe_after: float = 0.0) -> Iterator[list[tuple[int, int]]]:
    """A stand-in for an edge whose registration takes ``edge_time`` (a busy edge computer; a real
    one's time drifts with the machine's load, the assertions need it fixed): it answers every
    scan ``answer_after`` seconds after it came, reporting ``edge_time`` as its queue and
    registration time; from scan ``mute_from`` on, no answer leaves it for ``mute`` seconds (an
    outage on the way back). Its scan subscriber is declared ``subscribe_after`` seconds after its
    liveliness token (0: before it, as the real edge does). Yields the (seq, skipped) of the scans
    it received."""
    seen: list[tuple[int, int]] = []
    muted_until = [0.0]
    due: queue.Queue[tuple[float, wire.Scan, float] | None] = queue.Queue()
    session = open_session(listen_on(port))
    pub = session.declare_publisher(KEYS.scan_ack("robot1", "slow"))

    def on_scan(sample: Any) -> None:
        msg = wire.decode(sample.payload.to_bytes(), expect=wire.Scan)
        seen.append((msg.seq, msg.skipped))
        if msg.seq == mute_from:
            muted_until[0] = time.monotonic() + mute
        due.put((max(time.monotonic() + answer_after, muted_until[0]), msg, time.monotonic()))

    def answer() -> None:
        last = math.nan
        while (item := due.get()) is not None:
            at, msg, came = item
            time.sleep(max(0.0, at - time.monotonic()))
            pub.put(wire.encode(wire.ScanAck(
                robot="robot1", seq=msg.seq, send_stamp=msg.send_stamp, status="ok",
                interarrival=came - last if math.isfinite(last) else math.nan, queue_time=edge_time * 0.8,
                proc_time=edge_time * 0.2, icp_time=edge_time * 0.2, map_points=1, keypoints=1, sigma=0.3,
                pose=np.eye(4), edge="slow")))
            last = came

    subs: list[Any] = []
    if subscribe_after <= 0:
        subs.append(session.declare_subscriber(KEYS.scan("robot1"), on_scan))
    token = session.liveliness().declare_token(KEYS.edge_alive("slow"))
    late = threading.Timer(subscribe_after, lambda: subs.append(
        session.declare_subscriber(KEYS.scan("robot1"), on_scan)))
    if subscribe_after > 0:
        late.start()
    worker = threading.Thread(target=answer, daemon=True)
    worker.start()
    try:
        yield seen
    finally:
        late.cancel()
        if subscribe_after > 0:
            late.join()  # (one firing as the body ends declares before the undeclares below)
        due.put(None)
        worker.join(5)
        for sub in subs:
            sub.undeclare()
        token.undeclare()
        session.close()


@pytest.mark.parametrize("edge_time_window", [False, True])
def test_the_window_leaves_the_scans_the_edge_holds_off_the_link(free_port: int,
                                                                  edge_time_window: bool) -> None:
    # answered 0.45 s after sending at 10 Hz: ~4.5 scans unanswered, of which the edge reports
    # holding 0.4 s (4 periods; the window grows by at most its base, to 6)
    with slow_edge(free_port, answer_after=0.45, edge_time=0.4):
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=40, rate_hz=10,
                                        scale_policy="fixed", scan_coding="f32",
                                        window_edge_time=edge_time_window, window_path=False,
                                        window_hold=False,
                                        fleet=RobotFleetSettings(attach=False)))
    m = robot.metrics()
    window = m["dropped_source"].get("window", 0)
    assert m["balanced"], m["balance"]
    if edge_time_window:
        assert window <= 4, m["dropped_source"]  # the first ones only, before an ack came
        assert m["balance"]["acked"] >= 34, m["balance"]
        held = [r for r in robot.ledger.records.values() if r.get("status") == "source:window"]
        assert all("3 + 0 for the edge" in r["reason"] for r in held)  # ... with nothing measured
    else:
        assert window >= 8, m["dropped_source"]  # the window of 3, full with scans on the edge


@pytest.mark.parametrize("path_window", [False, True])
def test_a_long_path_gets_a_window_of_its_round_trip(free_port: int, path_window: bool) -> None:
    # a quick edge (10 ms) answering 0.55 s after each scan, as over 250 ms each way: 5-6 scans
    # are on the path at 10 Hz with no queue anywhere, and a window of 3 held back 43 % of them
    with slow_edge(free_port, answer_after=0.55, edge_time=0.01):
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=50, rate_hz=10,
                                        scale_policy="fixed", scan_coding="f32", window_path=path_window,
                                        window_hold=False,
                                        fleet=RobotFleetSettings(attach=False)))
    m = robot.metrics()
    window = m["dropped_source"].get("window", 0)
    assert m["balanced"], m["balance"]
    if path_window:
        assert window <= 9, m["dropped_source"]  # the first second only, before 5 acks measured it
        assert m["balance"]["acked"] >= 40, m["balance"]
        held = [r for r in robot.ledger.records.values() if r.get("status") == "source:window"]
        assert all(r["seq"] < 15 for r in held), [r["seq"] for r in held]
        assert m["window"]["max"] >= 7 and m["window"]["route_rtt_min_s"] >= 0.55, m["window"]
    else:
        assert window >= 15, m["dropped_source"]
        assert m["window"]["max"] == 3, m["window"]


@pytest.mark.parametrize("hold", [False, True])
def test_a_scan_the_window_holds_back_goes_when_an_ack_frees_a_slot(free_port: int, hold: bool) -> None:
    # answered 0.33 s after sending at 10 Hz, a window of 3 (its widening off): every fourth scan
    # finds the window full, 30 ms before the ack that frees a slot; dropped without the hold
    # (one in four), sent 30 ms late with it
    with slow_edge(free_port, answer_after=0.33, edge_time=0.01):
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=40, rate_hz=10,
                                        scale_policy="fixed", scan_coding="f32", window_edge_time=False,
                                        window_path=False, window_hold=hold,
                                        fleet=RobotFleetSettings(attach=False)))
    m = robot.metrics()
    assert m["balanced"], m["balance"]
    window = m["dropped_source"].get("window", 0)
    assert m["window"]["max"] == 3, m["window"]
    if hold:
        # (a held scan goes ~30 ms late, and its answer with it: about every tenth waits a period
        # in vain)
        assert window <= 6 and m["window"]["released"] >= 20, (m["dropped_source"], m["window"])
        # every scan sent is answered (a slower host: 5 of 40 waited in vain, 2026-12-06)
        assert m["balance"]["acked"] == m["balance"]["published"], (m["balance"], [
            (seq, r.get("status"), r.get("reason")) for seq, r in robot.ledger.records.items()
            if r.get("status") not in ("acked", "source:window")])
        released = [r for r in robot.ledger.records.values() if "in a freed slot" in str(r.get("reason"))]
        assert len(released) == m["window"]["released"]
        assert all(r["status"] == "acked" and r["bytes"] > 0 for r in released)
    else:
        assert window >= 8 and m["window"]["released"] == 0, (m["dropped_source"], m["window"])
    assert m["window"]["held"] == window + m["window"]["released"]


def test_without_attach_the_first_scan_waits_for_the_edges_subscriber(free_port: int) -> None:
    # the edge's liveliness token is there 1 s before its scan subscriber: without the attach
    # protocol the robot started on the token, and its first scans reached no one and were booked
    # lost a second later (here 3 lost, and the window they filled dropped the other 7; suspected,
    # not shown, in CI 112's flake of the held-scan test above: 34 of 35 acked); it now waits for
    # the match (up to 1.5 s)
    with slow_edge(free_port, answer_after=0.02, edge_time=0.01, subscribe_after=1.0) as seen:
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=10, rate_hz=10,
                                        scale_policy="fixed", scan_coding="f32",
                                        fleet=RobotFleetSettings(attach=False)))
    m = robot.metrics()
    assert m["balanced"], m["balance"]
    assert m["balance"]["lost"] == 0 and m["balance"]["acked"] == m["balance"]["published"], m["balance"]
    assert [seq for seq, _ in seen][:1] == [0], seen


def test_the_window_holds_a_scan_only_when_an_answer_is_due_within_the_period(free_port: int) -> None:
    # answered 0.55 s after sending, a window of 3: the window fills 0.3 s after the oldest scan
    # left, 0.25 s before its answer; a scan that finds it full more than a period before an
    # answer is due is dropped at once, never sized, and only the next is held (and goes)
    with slow_edge(free_port, answer_after=0.55, edge_time=0.01):
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=40, rate_hz=10,
                                        scale_policy="fixed", scan_coding="f32", window_edge_time=False,
                                        window_path=False, fleet=RobotFleetSettings(attach=False)))
    m = robot.metrics()
    assert m["balanced"], m["balance"]
    dropped = [r for r in robot.ledger.records.values() if r.get("status") == "source:window"]
    at_once = [r for r in dropped if "no slot" not in r["reason"]]
    assert len(at_once) >= 8, [r["reason"] for r in dropped]
    assert all("n_sent" not in r for r in at_once)  # not sized
    assert m["window"]["released"] >= 5, m["window"]


def test_scans_the_window_holds_back_in_a_stall_are_skipped_and_announced(free_port: int) -> None:
    # a quick edge whose answers stop for 0.9 s from scan 15 on: the window fills with 3 scans,
    # and once no ack came for stall_after (0.5 s) the scans it holds back are stall skips, which
    # the next scan sent announces (before: window drops, unannounced)
    with slow_edge(free_port, answer_after=0.02, edge_time=0.01, mute_from=15, mute=0.9) as seen:
        robot = run_robot(RobotSettings(zenoh=connect_to(free_port), max_scans=40, rate_hz=10,
                                        scale_policy="rate", fleet=RobotFleetSettings(attach=False)))
    m = robot.metrics()
    assert m["balanced"], m["balance"]
    stalls = m["dropped_source"].get("stall", 0)
    assert stalls >= 2, m["dropped_source"]
    held = [r for r in robot.ledger.records.values() if r.get("status") == "source:stall"]
    assert all("window full" in r["reason"] for r in held)
    announced = sum(skipped for seq, skipped in seen if seq > 15)
    assert announced >= stalls, seen
