"""The 1 Hz ping-pong monitor against a real edge daemon's ping queryable (own Zenoh sessions)."""

from __future__ import annotations

import math
import time

import pytest

from tests.helpers import KEYS, client, listen_on, running_edge, wait_for, wait_token
from zoffload.protocol import wire
from zoffload.runtime.config import DetectorSettings, EdgeSettings, MapperSettings
from zoffload.runtime.monitor import Pinger

pytestmark = pytest.mark.system


def test_pinger_measures_the_edge_and_counts_a_silent_one(free_port: int) -> None:
    settings = EdgeSettings(mapper=MapperSettings(enabled=False), detector=DetectorSettings(enabled=False),
                            zenoh=listen_on(free_port))
    with client(free_port) as s:
        with running_edge(settings):
            wait_token(s, KEYS.edge_alive("edge1"))
            # the edge echoes the stamp it got in the selector's parameters
            stamp = time.time()
            pongs = [wire.decode(r.ok.payload.to_bytes(), expect=wire.Pong)
                     for r in s.get(f"{KEYS.ping('robot1')}?stamp={stamp:.6f}", timeout=2.0) if r.ok]
            assert len(pongs) == 1 and abs(pongs[0].stamp - stamp) < 1e-5
            pinger = Pinger(s, KEYS.ping("robot1"), period=0.1, timeout=0.5).start()
            wait_for(lambda: len(pinger.rtt) >= 3, 5, "three pings")
            pinger.stop()
            assert pinger.lost == 0 and 0 < pinger.rtt.value < 100 and math.isfinite(pinger.last_ms)
        # no edge any more: a ping is unanswered, returns NaN, and the running pinger books a timeout
        assert math.isnan(Pinger(s, KEYS.ping("robot1"), timeout=0.3).ping())
        pinger = Pinger(s, KEYS.ping("robot1"), period=0.1, timeout=0.3).start()
        wait_for(lambda: pinger.lost >= 2, 5, "two lost pings")
        pinger.stop()
        assert pinger.rtt.value >= 0.3e3 - 1e-6
