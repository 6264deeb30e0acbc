"""The robot's edge-presence watcher over real Zenoh sessions: a "gone" that arrives late (after the
"present" of the same edge's new link) is undone by the re-check, a real "gone" stays."""

from __future__ import annotations

import threading
import time

import zenoh

from tests.helpers import KEYS, connect_to, listen_on, wait_for
from zoffload.robot import presence as presence_mod
from zoffload.robot.presence import EdgePresence
from zoffload.runtime.session import open_session


class LateGone:
    """A fake of a fault that cannot be caused at will: the old link's token DELETE handed to the
    watcher after the new link's PUT (two Zenoh callback threads a few ms apart)."""

    def __init__(self, key_expr: str) -> None:
        self.key_expr = key_expr
        self.kind = zenoh.SampleKind.DELETE


def test_a_late_gone_is_undone_by_the_recheck_and_a_real_gone_stays(free_port: int) -> None:
    edge = open_session(listen_on(free_port))
    robot = open_session(connect_to(free_port))
    watcher = EdgePresence(KEYS)
    events: list[tuple[str, bool, frozenset[str]]] = []
    lock = threading.Lock()

    def listener(e: str, present: bool, now: frozenset[str]) -> None:
        with lock:
            events.append((e, present, now))

    watcher.subscribe(listener)
    try:
        token = edge.liveliness().declare_token(KEYS.edge_alive("edge1"))
        watcher.start(robot)
        wait_for(lambda: watcher.edges == {"edge1"}, 10, "edge1 present")

        # The late "gone": the robot has no edge at once, and the listeners are told so ...
        watcher._on_token(LateGone(KEYS.edge_alive("edge1")))  # type: ignore[arg-type]
        assert watcher.edges == frozenset()
        assert events[-1] == ("edge1", False, frozenset())
        # ... and the first re-check (0.25 s later) finds the token: present again, told in order
        wait_for(lambda: watcher.edges == {"edge1"}, 3, "the re-check to find edge1's token")
        assert watcher.rechecked == 1
        assert events[-1] == ("edge1", True, frozenset({"edge1"}))

        # A "gone" of an edge that never was here is no reason to ask (the set of checks is bounded)
        watcher._on_token(LateGone(KEYS.edge_alive("stranger")))  # type: ignore[arg-type]
        assert "stranger" not in watcher._due

        # A real "gone": every re-check (0.25, 1, 3 s) finds nothing, the edge stays gone
        token.undeclare()
        wait_for(lambda: watcher.edges == frozenset(), 10, "edge1 gone")
        time.sleep(presence_mod.RECHECK_AFTER[-1] + presence_mod.RECHECK_TIMEOUT + 0.5)
        assert watcher.edges == frozenset() and watcher.rechecked == 1
        assert not watcher._due, watcher._due
        assert events[-1] == ("edge1", False, frozenset())

        # The edge back with a new token: present through the subscriber, as always
        token = edge.liveliness().declare_token(KEYS.edge_alive("edge1"))
        wait_for(lambda: watcher.edges == {"edge1"}, 10, "edge1 back")
        assert watcher.rechecked == 1
    finally:
        checker = watcher._checker
        watcher.stop()
        robot.close()
        edge.close()
    assert checker is not None and not checker.is_alive()  # stop() ends the re-check thread
