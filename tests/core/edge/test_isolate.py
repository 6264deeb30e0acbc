"""Robots' mappers in processes of their own (edge/isolate.py): the same registrations as in the
edge's process, errors and trimmed poses carried back, and a process that dies or hangs costs its
robots their maps (counted, the robot detached to attach again), not the edge."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.core.edge.test_worker_survives import _Pub, _Query, _Sample, _Session
from zoffload.edge.export import RobotFiles
from zoffload.edge.isolate import MapperPool
from zoffload.edge.mapping import MappingService
from zoffload.edge.recipe import MapperRecipe
from zoffload.edge.robots import MapperLost, Queued
from zoffload.protocol import wire
from zoffload.protocol.keys import Keys
from zoffload.runtime.maps import NO_MAP

pytest.importorskip("kiss_icp")


class _MapQuery:
    """A map query: records the edge's error reply."""

    def __init__(self, key: str) -> None:
        self.key_expr, self.err = key, ""

    def reply_err(self, data: bytes) -> None:
        self.err = data.decode()


def header(robot: str = "r1") -> wire.Scan:
    return wire.Scan(robot=robot, seq=0, send_stamp=0.0, capture_stamp=0.0, voxel=0.05, voxel_max=0.05,
                     max_range=30.0, n_raw=0, points=np.zeros((0, 3), np.float32))


def scene(seed: int = 0) -> np.ndarray:
    """A room's walls and floor with clutter, 12 m across: enough structure for ICP."""
    rng = np.random.default_rng(seed)
    n = 4000
    walls = [np.c_[rng.uniform(-6, 6, n), np.full(n, 6.0), rng.uniform(0, 3, n)],
             np.c_[np.full(n, -6.0), rng.uniform(-6, 6, n), rng.uniform(0, 3, n)],
             np.c_[rng.uniform(-6, 6, n), rng.uniform(-6, 6, n), np.zeros(n)],
             rng.uniform([1, -3, 0], [2, -2, 1.5], (n, 3))]
    return np.concatenate(walls)


def scans(count: int) -> list[np.ndarray]:
    """The scene seen from a sensor moving 0.1 m along x per scan."""
    world = scene()
    return [(world - [0.1 * i, 0.0, 1.0]).astype(np.float32) for i in range(count)]


def _along_x(x: float) -> np.ndarray:
    """The sensor's pose after moving ``x`` m along x (``scans``' motion)."""
    pose = np.eye(4)
    pose[0, 3] = x
    return pose


@pytest.fixture
def pool() -> Iterator[MapperPool]:
    p = MapperPool(MapperRecipe(), 1, call_timeout=30.0)
    p.warm_up()
    try:
        yield p
    finally:
        p.close()


def test_a_mapper_in_a_process_registers_as_one_in_the_edge_process(pool: MapperPool) -> None:
    here, there = MapperRecipe()(header()), pool(header())
    for seq, pts in enumerate(scans(6)):
        a, b = here.register(seq, pts), there.register(seq, pts)
        np.testing.assert_allclose(b.pose, a.pose, atol=1e-9)
        assert b.map_points == a.map_points
    assert there.scans == here.scans == 6 and there.map_points == here.map_points
    assert there.pid != os.getpid()
    np.testing.assert_allclose(there.trajectory()[1], here.trajectory()[1], atol=1e-9)
    assert len(there.map_cloud()) == len(here.map_cloud())
    cp = there.checkpoint("r1", "e1", 1, 0.0)
    assert cp is not None and cp.seq == 5
    assert there.predict_from(9, 5, np.eye(4), np.eye(4)) == here.predict_from(9, 5, np.eye(4), np.eye(4))
    assert there.backfilled_seqs == []


def test_a_backfill_and_the_priors_it_moves_count_alike_across_the_process_boundary(pool: MapperPool) -> None:
    # the robot's poses of a backfill 1 m off this mapper's frame: the handover's correction moves
    # an estimate said to be in that frame (frame=1), not one said in this mapper's (frame=0); the
    # edge reads the counts off the mapper (prior_moved_by_attach), so they must cross the pipe
    here, there = MapperRecipe()(header()), pool(header())
    pts = scans(14)
    drift = np.eye(4)
    drift[1, 3] = 1.0
    seqs = np.arange(6, 10)
    robot_poses = np.stack([drift @ _along_x(0.1 * i) for i in seqs])
    backfill = [(int(i), pts[i]) for i in seqs]
    for m in (here, there):
        for seq in range(6):
            m.register(seq, pts[seq])
        m.continue_from(None, seqs, robot_poses, backfill, robot_poses)
        assert m.backfilled == 4 and m.backfill_unused == 0
        step = _along_x(0.1)
        assert m.predict_from(12, 11, drift @ _along_x(1.1), step, contest=True, frame=1)
        assert m.priors_moved == 1
        assert m.predict_from(12, 11, _along_x(1.1), step, contest=True, frame=0)
        assert m.priors_moved == 1
        assert m.register(12, pts[12]).map_points > 0
    np.testing.assert_allclose(there.trajectory()[1], here.trajectory()[1], atol=1e-6)
    assert there.backfilled_seqs == list(here.backfilled_seqs) == [6, 7, 8, 9]


def test_errors_come_back_as_what_they_were_and_leave_the_mapper(pool: MapperPool) -> None:
    m = pool(header())
    m.register(0, scans(1)[0])
    with pytest.raises(ValueError, match="no point within"):
        m.register(1, np.full((10, 3), 1e6, np.float32))
    assert m.scans == 1
    assert m.register(1, scans(2)[1]).map_points > 0 and m.scans == 2


def test_poses_trimmed_in_the_process_reach_the_robots_spill(tmp_path: Path) -> None:
    files = RobotFiles(tmp_path, "r1")
    p = MapperPool(MapperRecipe(trajectory_budget=3), 1)
    try:
        m = p(header(), spill=files.spill)
        for seq, pts in enumerate(scans(8)):
            m.register(seq, pts)
        assert files.parts, "no trimmed poses reached the edge's spill"
        files.export(m, {})
    finally:
        p.close()
    seqs = np.load(tmp_path / "r1_trajectory.npz")["seqs"]
    assert list(seqs) == list(range(8))  # the whole trajectory: spilled parts and those in memory


def test_a_killed_process_costs_its_robots_their_maps_not_the_edge(pool: MapperPool) -> None:
    m, other = pool(header()), pool(header("r2"))
    m.register(0, scans(1)[0])
    pid = m.pid
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    with pytest.raises(MapperLost):
        m.register(1, scans(2)[1])
    with pytest.raises(MapperLost):  # the other robot in that process lost its map too
        other.register(0, scans(1)[0])
    assert pool.status()["mapper_restarts"] == 1
    fresh = pool(header())
    assert fresh.pid != pid and fresh.register(0, scans(1)[0]).map_points > 0
    m.close()  # a lost mapper closes without asking its old process
    assert pool.hosts[0].hosted == 1


def test_a_hung_process_is_killed_after_the_call_timeout() -> None:
    """A registration gets ``register_timeout``, any other call ``call_timeout``; the process is
    killed, not left stopped, and the next robot gets a new one."""
    p = MapperPool(MapperRecipe(), 1, call_timeout=2.0, register_timeout=0.5)
    try:
        for call, limit in ((lambda m: m.register(0, scans(1)[0]), "0.5"), (lambda m: m.map_cloud(), "2")):
            m = p(header())
            pid = m.pid
            assert pid is not None
            os.kill(pid, signal.SIGSTOP)
            t0 = time.monotonic()
            with pytest.raises(MapperLost, match=f"no answer in {limit} s"):
                call(m)
            assert time.monotonic() - t0 < 10
            with pytest.raises(ProcessLookupError):  # killed, not left stopped
                for _ in range(50):
                    os.kill(pid, 0)
                    time.sleep(0.1)
        assert p(header()).register(0, scans(1)[0]).map_points > 0
    finally:
        p.close()


def big_scans(count: int, dense: int) -> list[np.ndarray]:
    """``scans`` ``dense`` times as dense (16k points each time: 100 times, ~0.5 s to send and
    register a scan)."""
    noise = np.random.default_rng(1).normal(0, 0.02, (dense, 1, 3)).astype(np.float32)
    return [(s[None] + noise).reshape(-1, 3) for s in scans(count)]


@contextlib.contextmanager
def starved(pid: int, running: float = 0.1, cycle: float = 0.1) -> Iterator[None]:
    """A stand-in for a host too busy to give the process more than ``running`` of a core: it is
    stopped and continued every ``cycle`` seconds (a fake: real contention would take the cores
    from the tests running beside this one)."""
    done = threading.Event()

    def duty() -> None:
        with contextlib.suppress(ProcessLookupError):  # (it died: the test says so)
            while not done.is_set():
                os.kill(pid, signal.SIGSTOP)
                time.sleep(cycle * (1 - running))
                os.kill(pid, signal.SIGCONT)
                time.sleep(cycle * running)

    t = threading.Thread(target=duty, daemon=True)
    t.start()
    try:
        yield
    finally:
        done.set()
        t.join()
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)


def test_a_busy_process_is_waited_for_past_the_register_timeout() -> None:
    """A registration that outlasts ``register_timeout`` while its process uses the CPU (a busy
    host, not a hang) and stays within as many seconds of CPU is waited for, up to
    ``call_timeout``, and counted: no map lost."""
    p = MapperPool(MapperRecipe(), 1, call_timeout=60.0, register_timeout=1.0)
    try:
        m = p(header())
        assert m.pid is not None
        with starved(m.pid):  # a tenth of a core: ~0.3 s of CPU a scan (640k points) takes ~3 s
            for i, points in enumerate(big_scans(2, 40)):
                assert m.register(i, points).map_points > 0
        st = p.status()
        assert st["mapper_slow_calls"] >= 1 and st["mapper_restarts"] == 0, st
    finally:
        p.close()


def test_a_registration_that_runs_away_with_the_cpu_is_lost_at_its_timeout() -> None:
    """A registration still working at ``register_timeout`` that has used that much CPU is not
    slowed by a busy host but running away (here: 1.6M points, ~0.6 s of CPU, against a 0.1 s
    timeout): the process is given up then, not at ``call_timeout``, and started again. (With a
    0.3 s timeout, CI once saw the scan answered between the first look, under its budget of CPU
    then, and the second: the budget is a sixth of the work so that several looks fall within it.)"""
    p = MapperPool(MapperRecipe(), 1, call_timeout=60.0, register_timeout=0.1)
    try:
        m = p(header())
        t0 = time.monotonic()
        with pytest.raises(MapperLost, match=r"s of CPU used \(its budget 0.1 s\)"):
            m.register(0, big_scans(1, 100)[0])
        assert time.monotonic() - t0 < 10
        st = p.status()
        assert st["mapper_restarts"] == 1 and st["mapper_slow_calls"] == 0, st
        assert p(header()).register(0, scans(1)[0]).map_points > 0
    finally:
        p.close()


def test_a_request_that_cannot_be_written_loses_the_process(monkeypatch: pytest.MonkeyPatch) -> None:
    """A process stopped with a request larger than its socket's buffer: the write times out
    (``SEND_TIMEOUT_S``) instead of holding the edge's worker, and the process is started again."""
    from zoffload.edge import isolate

    monkeypatch.setattr(isolate, "SEND_TIMEOUT_S", 1)
    p = MapperPool(MapperRecipe(), 1, call_timeout=60.0, register_timeout=60.0)
    try:
        m = p(header())
        pid = m.pid
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        t0 = time.monotonic()
        with pytest.raises(MapperLost):
            m.register(0, big_scans(1, 20)[0])  # 3.8 MB
        assert time.monotonic() - t0 < 10
        assert p.status()["mapper_restarts"] == 1
        assert p(header()).register(0, scans(1)[0]).map_points > 0
    finally:
        p.close()


def test_closing_the_pool_ends_its_processes() -> None:
    p = MapperPool(MapperRecipe(), 2)
    p.warm_up()
    pids = [h.pid for h in p.hosts]
    assert len(set(pids)) == 2 and None not in pids
    p.close()
    for pid in pids:
        assert pid is not None
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_the_service_detaches_a_robot_whose_mapper_was_lost_so_it_attaches_again() -> None:
    keys = Keys()
    pool = MapperPool(MapperRecipe(), 1)
    svc = MappingService(keys, pool, edge_id="e1", workers=1)
    svc._session = _Session()  # type: ignore[assignment]
    pool.warm_up()
    for w in svc._workers:
        w.start()
    acks = svc._session.pubs.setdefault(keys.scan_ack("r1", "e1"), _Pub())  # type: ignore[attr-defined]
    pts = scans(6)

    def send(seq: int, answers: int, epoch: int = 1) -> None:
        scan = wire.Scan(robot="r1", seq=seq, send_stamp=float(seq), capture_stamp=float(seq), voxel=0.0,
                         voxel_max=0.05, max_range=30.0, n_raw=len(pts[seq]), points=pts[seq], edge="e1",
                         epoch=epoch)
        svc._on_scan(_Sample(keys.scan("r1"), wire.encode(scan)))  # type: ignore[arg-type]
        deadline = time.monotonic() + 20
        while len(acks.sent) < answers and time.monotonic() < deadline:
            time.sleep(0.01)

    def attach(epoch: int, checkpoint: wire.Checkpoint | None = None) -> wire.AttachReply:
        a = wire.Attach(robot="r1", epoch=epoch, max_range=30.0, voxel_max=0.05, rate_hz=10.0, reads=6,
                        local_seqs=np.zeros(0, np.int64), local_poses=np.zeros((0, 4, 4)),
                        checkpoint=wire.encode(checkpoint) if checkpoint is not None else b"")
        query = _Query(keys.attach("r1", "e1"), wire.encode(a))
        svc._on_attach(query)  # type: ignore[arg-type]
        reply: wire.AttachReply = query.got
        return reply

    try:
        assert attach(1).accepted
        send(0, 1)
        send(1, 2)
        assert [a.status for a in acks.sent] == ["ok", "ok"]
        os.kill(pool.hosts[0].pid or 0, signal.SIGKILL)
        send(2, 3)
        assert acks.sent[2].status == "error" and "lost" in acks.sent[2].detail
        assert svc.counters["mapper_lost"] == 1 and "r1" not in svc.fleet.attached
        send(3, 4)  # refused, as by an edge that lost the robot's state: the robot attaches again
        assert acks.sent[3].status == "refused"
        # a scan of that epoch queued before the loss is refused too, not mapped into a new map
        rs = svc.robots["r1"]
        assert rs.lost_epoch == 1 and rs.mapper is None
        asked = _MapQuery(keys.map("r1", "e1"))  # a map query says why there is none
        svc._on_map_query(asked)  # type: ignore[arg-type]
        assert asked.err.startswith(f"{NO_MAP} 'r1': its mapper was lost (1 so far)"), asked.err
        queued = wire.Scan(robot="r1", seq=3, send_stamp=3.0, capture_stamp=3.0, voxel=0.0, voxel_max=0.05,
                           max_range=30.0, n_raw=len(pts[3]), points=pts[3], edge="e1", epoch=1)
        svc._register(rs, Queued(queued, time.monotonic(), 0.1))
        assert acks.sent[4].status == "refused" and rs.mapper is None and svc.counters["refused_lost"] == 1
        del acks.sent[4]
        # with the checkpoint the edge sent after its first scan (the robot keeps the latest)
        cps = svc._session.pubs[keys.checkpoint("r1", "e1")].sent  # type: ignore[attr-defined]
        assert cps and cps[0].seq == 0
        assert attach(2, cps[0]).accepted
        send(4, 5, epoch=2)
        assert acks.sent[4].status == "ok"
        # the new mapper continued the checkpoint's trajectory: scan 4 is 0.4 m from scan 0
        assert abs(acks.sent[4].pose[0, 3] - 0.4) < 0.05, acks.sent[4].pose
        status = svc.status()
        assert status["mapper_restarts"] == 1 and status["mapper_processes"] == 1
        assert status["workers"] == 1
    finally:
        svc._stop.set()
        for w in svc._workers:
            w.join(5)
        pool.close()


def test_a_process_that_died_idle_is_started_again_for_a_new_robot_without_a_loss(pool: MapperPool) -> None:
    pid = pool.hosts[0].pid
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    time.sleep(0.2)
    m = pool(header())  # no MapperLost: nothing of this robot's was in the dead process
    assert m.pid != pid and m.register(0, scans(1)[0]).map_points > 0
    assert pool.status()["mapper_restarts"] == 1


def test_a_closed_pool_starts_no_process() -> None:
    p = MapperPool(MapperRecipe(), 1)
    m = p(header())
    p.close()
    with pytest.raises(MapperLost, match="closed"):
        m.register(0, scans(1)[0])
    assert p.hosts[0].pid is not None and p.status()["mapper_restarts"] == 0
    with pytest.raises(MapperLost, match="closed"):
        p(header())
