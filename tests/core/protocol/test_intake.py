"""protocol/intake.py: an edge's status read once, the same way by every reader (the robot's
fleet link and camera, the edge's peers), refusals counted."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from zoffload.protocol import wire
from zoffload.protocol.intake import edge_status
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

