"""Every scan ack one robot receives, collected from a Zenoh subscriber."""

from __future__ import annotations

import zenoh

from tests.helpers import KEYS, wait_for
from zoffload.protocol import wire


class Acks:
    def __init__(self, session: zenoh.Session, robot: str) -> None:
        self.items: list[wire.ScanAck] = []
        self.sub = session.declare_subscriber(KEYS.scan_acks(robot), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        msg = wire.decode(sample.payload.to_bytes(), expect=wire.ScanAck)
        assert isinstance(msg, wire.ScanAck)
        self.items.append(msg)

    def seqs(self, status: str) -> list[int]:
        return sorted(a.seq for a in self.items if a.status == status)

    def wait(self, n: int, timeout: float = 10.0) -> None:
        """Until at least ``n`` acks are in."""
        wait_for(lambda: len(self.items) >= n, timeout, f"{n} acks")
