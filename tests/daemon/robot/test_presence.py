"""The robot's edge-presence watcher over real Zenoh sessions: a "gone" that arrives late (after the
"present" of the same edge's new link) is undone by the re-check, a real "gone" stays."""

from __future__ import annotations

import threading
from typing import Any

import zenoh

from tests.helpers import KEYS, connect_to, listen_on, wait_for
from zoffload.robot import presence as presence_mod
from zoffload.robot.presence import EdgePresence
from zoffload.runtime.session import open_session


class FakeTokenSample:
    """A fake of Zenoh's token sample, for orderings that cannot be caused at will: e.g. the old
    link's DELETE handed to the watcher after the new link's PUT."""

    def __init__(self, key_expr: str, kind: Any = zenoh.SampleKind.DELETE) -> None:
        self.key_expr = key_expr
        self.kind = kind


def news(watcher: EdgePresence, edge: str, present: bool) -> None:
    watcher._on_token(FakeTokenSample(KEYS.edge_alive(edge), zenoh.SampleKind.PUT if present  # type: ignore[arg-type]
                               else zenoh.SampleKind.DELETE))


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
        watcher._on_token(FakeTokenSample(KEYS.edge_alive("edge1")))  # type: ignore[arg-type]
        assert watcher.edges == frozenset()
        assert events[-1] == ("edge1", False, frozenset())
        # ... and the first re-check (0.25 s later) finds the token: present again, told in order
        wait_for(lambda: watcher.edges == {"edge1"}, 3, "the re-check to find edge1's token")
        assert watcher.rechecked == 1
        # (the set changes first, the listeners are told right after, outside the state's lock)
        wait_for(lambda: events[-1] == ("edge1", True, frozenset({"edge1"})), 3, "the listeners told")
        assert events[-2] == ("edge1", False, frozenset())

        # A "gone" of an edge that never was here is no reason to ask (the set of checks is bounded)
        watcher._on_token(FakeTokenSample(KEYS.edge_alive("stranger")))  # type: ignore[arg-type]
        assert "stranger" not in watcher._due

        # A real "gone": every re-check (0.25, 1, 3 s) finds nothing, the edge stays gone
        token.undeclare()
        wait_for(lambda: watcher.edges == frozenset(), 10, "edge1 gone")
        checks_done = presence_mod.RECHECK_AFTER[-1] + 3 * presence_mod.RECHECK_TIMEOUT + 2
        wait_for(lambda: not watcher._due, checks_done, "the three re-checks to be done")
        assert watcher.edges == frozenset() and watcher.rechecked == 1
        assert events[-1] == ("edge1", False, frozenset())

        assert watcher.drops.snapshot().get("recheck_error", 0) == 0

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


def test_a_recheck_answer_older_than_a_token_event_is_not_applied_and_rechecks_are_bounded(
        monkeypatch: Any) -> None:
    """The re-check's bookkeeping without a session or its thread: answers are handed in directly
    (``_rechecked``, with the token-event count the check saw when it asked)."""
    watcher = EdgePresence(KEYS)
    told: list[tuple[str, bool]] = []
    watcher.subscribe(lambda e, present, _now: told.append((e, present)))
    news(watcher, "edge1", True)
    news(watcher, "edge1", False)
    assert watcher._due["edge1"].events == 0 and not watcher.edges
    watcher._rechecked("edge1", True, events=0, last=False)  # the token is there after all
    assert watcher.edges == {"edge1"} and watcher.rechecked == 1 and told[-1] == ("edge1", True)
    watcher._rechecked("edge1", False, events=0, last=False)  # ... and not at the next check: gone
    assert not watcher.edges and told[-1] == ("edge1", False)
    watcher._rechecked("edge1", None, events=0, last=False)  # a failed query changes nothing
    assert not watcher.edges and len(told) == 4
    watcher._rechecked("edge1", True, events=0, last=False)
    news(watcher, "edge1", False)  # a real "gone" while a check was asking: the checks start over
    assert watcher._due["edge1"].events == 1 and watcher._due["edge1"].step == 0
    watcher._rechecked("edge1", True, events=0, last=True)  # asked before that "gone": stale
    assert not watcher.edges and "edge1" in watcher._due and told[-1] == ("edge1", False)
    news(watcher, "edge1", True)  # the subscriber's "present" ends the checks
    assert "edge1" not in watcher._due and watcher.edges == {"edge1"}

    # Tokens declared and withdrawn under ever new names (no ACL): at most MAX_EDGES re-checks
    monkeypatch.setattr(presence_mod, "MAX_EDGES", 4)
    for i in range(10):
        news(watcher, f"flood{i}", True)
        news(watcher, f"flood{i}", False)
    assert len(watcher._due) == 4 and watcher.drops.snapshot()["too_many_rechecks"] == 6
