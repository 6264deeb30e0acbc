"""A robot's own data must not end an edge's mapping worker: a robot the edge admitted attached
with a local pose 50 km out (the attach check bounds poses at 1e7 m) made each registered scan's
checkpoint fail in the voxel grid (26 km at its 2.5 cm cells), outside registration's error
handling, and the exception ended the worker thread: that robot's later scans, and those of every
robot sharing the worker, went unanswered (found by a hostile-input audit of the protocol). Then
(a review): the failing checkpoint was tried on every scan, and a failed final checkpoint left the
robot owed it for good."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from zoffload.edge.mapping import MappingService
from zoffload.edge.recipe import MapperRecipe
from zoffload.protocol import wire
from zoffload.protocol.keys import Keys


class _Pub:
    def __init__(self) -> None:
        self.sent: list[Any] = []

    def put(self, data: bytes) -> None:
        self.sent.append(wire.decode(data))


class _Session:
    """Stands in for a Zenoh session (the fault is the robot's data, not the transport)."""

    def __init__(self) -> None:
        self.pubs: dict[str, _Pub] = {}

    def declare_publisher(self, key: str, **_: Any) -> _Pub:
        return self.pubs.setdefault(key, _Pub())

    def put(self, key: str, data: bytes, **_: Any) -> None:
        self.declare_publisher(key).put(data)


class _Payload:
    def __init__(self, b: bytes) -> None:
        self.b = b

    def to_bytes(self) -> bytes:
        return self.b


class _Sample:
    def __init__(self, key: str, b: bytes) -> None:
        self.key_expr, self.payload = key, _Payload(b)


class _Query(_Sample):
    def reply(self, key: str, data: bytes) -> None:
        self.got = wire.decode(data)


def test_a_checkpoint_that_fails_does_not_end_the_worker() -> None:
    keys = Keys()
    # (a final checkpoint on a grid too, so that it fails as the periodic ones do)
    svc = MappingService(keys, MapperRecipe(), edge_id="e1", workers=1, final_checkpoint_resolution=0.025)
    svc._session = _Session()  # type: ignore[assignment]
    for w in svc._workers:
        w.start()
    try:
        far = np.eye(4)
        far[:3, 3] = [50_000.0, 0.0, 0.0]
        attach = wire.Attach(robot="r1", epoch=1, max_range=5.0, voxel_max=0.0, rate_hz=10.0, reads=6,
                             local_seqs=np.array([0], np.int64), local_poses=far[None])
        query = _Query(keys.attach("r1", "e1"), wire.encode(attach))
        svc._on_attach(query)  # type: ignore[arg-type]
        assert query.got.accepted, query.got.detail
        pts = np.random.default_rng(0).uniform(-4, 4, (3000, 3)).astype(np.float32)
        acks = svc._session.pubs.setdefault(keys.scan_ack("r1", "e1"), _Pub())  # type: ignore[attr-defined]
        for seq in (1, 2, 3):
            scan = wire.Scan(robot="r1", seq=seq, send_stamp=float(seq), capture_stamp=float(seq), voxel=0.0,
                             voxel_max=0.0, max_range=5.0, n_raw=len(pts), points=pts, edge="e1", epoch=1)
            svc._on_scan(_Sample(keys.scan("r1"), wire.encode(scan)))  # type: ignore[arg-type]
            deadline = time.monotonic() + 10
            while len(acks.sent) < seq and time.monotonic() < deadline:
                time.sleep(0.01)
        assert [a.seq for a in acks.sent] == [1, 2, 3]  # the code before answered scan 1 only
        assert svc.status()["workers"] == 1
        # counted, with a warning in the log; tried once, not again on every scan (the code before
        # this: 3, one a scan)
        assert svc.counters["worker_errors"] == 1
        # its final checkpoint fails too, and the robot is owed it no longer (before: "pending" for
        # good, a drain waited for the robot to move by itself and a shed one was never refused)
        svc.begin_drain()
        deadline = time.monotonic() + 10
        while svc.counters["worker_errors"] < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert svc.fleet.attached["r1"].final == "sent"
        assert svc.counters["worker_errors"] == 2
    finally:
        svc._stop.set()
        for w in svc._workers:
            w.join(5)
