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
                     for r in s.get(f"{KEYS.ping('robot1', 'edge1')}?stamp={stamp:.6f}", timeout=2.0) if r.ok]
            assert len(pongs) == 1 and abs(pongs[0].stamp - stamp) < 1e-5
            pinger = Pinger(s, KEYS.ping("robot1", "edge1"), period=0.1, timeout=0.5).start()
            wait_for(lambda: len(pinger.rtt) >= 3, 5, "three pings")
            pinger.stop()
            assert pinger.lost == 0 and 0 < pinger.rtt.value < 100 and math.isfinite(pinger.last_ms)
        # no edge any more: a ping is unanswered, returns NaN, and the running pinger books a timeout
        assert math.isnan(Pinger(s, KEYS.ping("robot1", "edge1"), timeout=0.3).ping())
        pinger = Pinger(s, KEYS.ping("robot1", "edge1"), period=0.1, timeout=0.3).start()
        wait_for(lambda: pinger.lost >= 2, 5, "two lost pings")
        pinger.stop()
        assert pinger.rtt.value >= 0.3e3 - 1e-6


def test_a_pinger_asks_the_edge_it_is_given_and_takes_only_that_edges_pong(free_port: int) -> None:
    """The camera pings the edge its frames go to (in a fleet another edge's link says nothing of
    it): a pinger with no edge to ask does not ping, and a pong naming another edge than its key
    (without the router's ACL anyone may answer) is not a round trip."""
    with client(free_port) as s:
        forger = s.declare_queryable(
            KEYS.all_pings("edge7"),
            lambda q: q.reply(q.key_expr, wire.encode(wire.Pong(edge="edge1", stamp=float("nan")))))
        pinger = Pinger(s, KEYS.ping("robot1", "edge7"), timeout=0.3)
        assert math.isnan(pinger.ping()) and pinger.wrong_edge == 1
        target: list[str | None] = [None]
        pinger = Pinger(s, lambda: target[0], period=0.05, timeout=0.3).start()
        time.sleep(0.3)
        assert pinger.lost == 0 and len(pinger.rtt) == 0  # no edge: nothing asked, nothing booked
        target[0] = KEYS.ping("robot1", "edge7")
        wait_for(lambda: pinger.lost >= 1, 5, "a ping of edge7 answered in edge1's name")
        pinger.stop()
        assert pinger.wrong_edge >= 1 and pinger.key == KEYS.ping("robot1", "edge7")
        forger.undeclare()
