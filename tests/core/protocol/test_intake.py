"""protocol/intake.py: an edge's status read once, the same way by every reader (the robot's
fleet link and camera, the edge's peers), and a map reply only from the edge asked; refusals
counted."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import msgpack
import numpy as np

from zoffload.protocol import wire
from zoffload.protocol.intake import edge_status, map_from
from zoffload.protocol.keys import Keys

KEYS = Keys()


@dataclass
class _Payload:  # the part of a zenoh.ZBytes intake reads
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class _Sample:  # the part of a zenoh.Sample intake reads (a Sample cannot be built by hand)
    key_expr: str
    payload: _Payload


class _Drops:
    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()

    def drop(self, reason: str, detail: str) -> None:
        self.counts[reason] += 1


def status(source: str, sid: str) -> bytes:
    return wire.encode(wire.Status(source=source, id=sid, stamp=1.0, values={"capacity": 3.0}))


def test_an_edge_status_is_read_only_from_that_edge_key() -> None:
    drops = _Drops()
    ok = edge_status(_Sample(KEYS.edge_status("e1"), _Payload(status("edge", "e1"))), KEYS, drops)  # type: ignore[arg-type]
    assert ok is not None and ok.id == "e1" and ok.values == {"capacity": 3.0} and not drops.counts
    for key, payload in ((KEYS.edge_status("e1"), status("edge", "e2")),  # names another edge
                         (KEYS.edge_status("r1"), status("robot", "r1")),  # a robot's, on an edge key
                         (KEYS.edge_status("e1"), b"\x00garbage")):
        assert edge_status(_Sample(key, _Payload(payload)), KEYS, drops) is None  # type: ignore[arg-type]
    assert drops.counts == {"foreign_status": 2, "malformed_status": 1}


def map_reply(robot: str, edge: str) -> bytes:
    return wire.encode(wire.MapReply(robot=robot, scans=1, points=np.zeros((2, 3), np.float32),
                                     seqs=np.array([0]), poses=np.eye(4)[None], edge=edge))


def test_a_map_reply_is_taken_only_from_the_edge_asked() -> None:
    drops = _Drops()
    got = map_from(_Sample(KEYS.map("r1", "e1"), _Payload(map_reply("r1", "e1"))), KEYS, "r1", "e1", drops)  # type: ignore[arg-type]
    assert got is not None and got.edge == "e1" and got.robot == "r1" and not drops.counts
    # an older edge on the key before per-edge maps: no edge in its reply (codec version 2)
    old = map_reply("r1", "")
    assert msgpack.unpackb(old)["v"] == 2
    assert map_from(_Sample(KEYS.map_before("r1"), _Payload(old)), KEYS, "r1", "", drops) is not None  # type: ignore[arg-type]
    assert msgpack.unpackb(map_reply("r1", "e1"))["v"] == 7  # a reader of 6 refuses it whole
    for key, payload, asked in (
            (KEYS.map("r1", "e1"), map_reply("r1", "e2"), "e1"),  # e2's map on e1's key
            (KEYS.map("r1", "e2"), map_reply("r1", "e2"), "e1"),  # on another edge's key than asked
            (KEYS.map("r1", "e1"), map_reply("r1", ""), "e1"),  # naming no edge on a per-edge key
            (KEYS.map_before("r1"), map_reply("r1", "e2"), ""),  # a new edge never answers there
            (KEYS.map("r1", "e1"), map_reply("r2", "e1"), "e1"),  # another robot's
            (KEYS.map("r1", "e1"), b"\x00garbage", "e1")):
        assert map_from(_Sample(key, _Payload(payload)), KEYS, "r1", asked, drops) is None  # type: ignore[arg-type]
    assert drops.counts == {"edge_key_map": 4, "foreign": 1, "malformed": 1}
