"""runtime/maps.py on loopback sessions: a querier asks each edge for a robot's map by name (the
one it knows maps it, else every live edge, then the key before per-edge maps), and takes a reply
only from the edge it asked."""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from tests.helpers import KEYS, served, wait_for
from zoffload.protocol import wire
from zoffload.runtime.maps import NO_MAP, fetch_map, live_edges


class _Drops:
    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()

    def drop(self, reason: str, detail: str) -> None:
        self.counts[reason] += 1


def reply(robot: str, edge: str, scans: int) -> bytes:
    return wire.encode(wire.MapReply(robot=robot, scans=scans, points=np.zeros((2, 3), np.float32),
                                     seqs=np.arange(scans), poses=np.repeat(np.eye(4)[None], scans, 0),
                                     edge=edge))


class Fleet:
    """Edges on one session: each holds a token and answers its own map key with ``maps[edge]``
    (an error reply for robots it does not map), so each query asked is recorded."""

    def __init__(self, session: Any, maps: dict[str, dict[str, bytes]]) -> None:
        self.asked: list[str] = []
        self.held: list[Any] = []
        for edge, robots in maps.items():
            self.held.append(session.liveliness().declare_token(KEYS.edge_alive(edge)))
            self.held.append(session.declare_queryable(KEYS.all_maps(edge), self._answer(edge, robots)))

    def _answer(self, edge: str, robots: dict[str, bytes]) -> Any:
        def on(query: Any) -> None:
            key = str(query.key_expr)
            self.asked.append(key)
            robot = KEYS.robot_of(key)
            if robot in robots:
                query.reply(KEYS.map(robot, edge), robots[robot])
            else:
                query.reply_err(f"{NO_MAP} {robot!r}".encode())  # as the edge's mapping service
        return on

    def wait_routed(self, querier: Any, edges: list[str]) -> None:
        """Until the querier reaches each edge's queryable (declarations take a moment to arrive)."""
        for edge in edges:
            wait_for(lambda: any(r.err is not None for r in querier.get(KEYS.map("probe", edge), timeout=2)),  # noqa: B023
                     10, f"edge {edge}'s queryable")
        self.asked.clear()

    def close(self) -> None:
        for h in self.held:
            h.undeclare()


@pytest.fixture
def sessions(free_port: int) -> Iterator[tuple[Any, Any]]:
    """(the edges' side, the querier's side) on one loopback link."""
    with served(free_port) as pair:
        yield pair


def test_the_edge_that_maps_the_robot_is_asked_by_name_and_no_other(sessions: tuple[Any, Any]) -> None:
    side, querier = sessions
    fleet = Fleet(side, {"e1": {"r1": reply("r1", "e1", 3)}, "e2": {}})
    drops = _Drops()
    try:
        wait_for(lambda: live_edges(querier, KEYS, drops) == ["e1", "e2"], 10, "the edges' tokens")
        fleet.wait_routed(querier, ["e1", "e2"])
        got = fetch_map(querier, KEYS, "r1", ["e1"], drops, timeout=5)
        assert got is not None and got.edge == "e1" and got.scans == 3
        assert fleet.asked == [KEYS.map("r1", "e1")] and not drops.counts
    finally:
        fleet.close()


def test_without_a_hint_every_live_edge_is_asked_by_name_and_a_reply_in_another_edges_name_is_dropped(
        sessions: tuple[Any, Any]) -> None:
    """Edge a0 answers robot r1's query on its own key with a map naming e1 (as a compromised edge
    would, when the ACL keeps it to its own key): dropped and counted; e1's own map is taken. A hint
    of an edge without the map falls back to the others."""
    side, querier = sessions
    fleet = Fleet(side, {"a0": {"r1": reply("r1", "e1", 99)}, "e1": {"r1": reply("r1", "e1", 3)}, "e2": {}})
    drops = _Drops()
    try:
        wait_for(lambda: live_edges(querier, KEYS, drops) == ["a0", "e1", "e2"], 10, "the edges' tokens")
        fleet.wait_routed(querier, ["a0", "e1", "e2"])
        got = fetch_map(querier, KEYS, "r1", ["e2"], drops, timeout=5)
        assert got is not None and got.edge == "e1" and got.scans == 3
        assert drops.counts == {"edge_key_map": 1}
        # every query named one edge, each edge was asked on its own key only
        wait_for(lambda: len(fleet.asked) == 3, 5, "the queries' arrival")
        assert sorted(fleet.asked) == sorted(KEYS.map("r1", e) for e in ("a0", "e1", "e2"))
        assert fetch_map(querier, KEYS, "nobody", [], drops, timeout=5) is None
    finally:
        fleet.close()


def test_an_older_edge_answers_on_the_key_before_per_edge_maps(sessions: tuple[Any, Any]) -> None:
    side, querier = sessions
    fleet = Fleet(side, {"e1": {}})
    older = side.declare_queryable(KEYS.map_before("r1"),
                                   lambda q: q.reply(KEYS.map_before("r1"), reply("r1", "", 4)))
    drops = _Drops()
    try:
        wait_for(lambda: live_edges(querier, KEYS, drops) == ["e1"], 10, "the edge's token")
        fleet.wait_routed(querier, ["e1"])
        wait_for(lambda: any(r.ok is not None for r in querier.get(KEYS.map_before("r1"), timeout=2)), 10,
                 "the older edge's queryable")
        got = fetch_map(querier, KEYS, "r1", [], drops, timeout=5)
        assert got is not None and got.edge == "" and got.scans == 4 and not drops.counts
    finally:
        older.undeclare()
        fleet.close()


@pytest.mark.parametrize("busy_for", [2, 10])
def test_an_edge_building_another_reply_is_asked_again(sessions: tuple[Any, Any], busy_for: int) -> None:
    """An edge builds one map reply at a time and answers another querier meanwhile with ``BUSY``
    (the live view and the lab's runner may ask at once): it is asked again, a few times, and its
    map taken when it comes; one busy for longer counts as no map, after ``BUSY_TRIES`` queries."""
    from zoffload.runtime import maps

    side, querier = sessions
    asked: list[str] = []

    def on(query: Any) -> None:
        asked.append(str(query.key_expr))
        if len(asked) <= busy_for:
            query.reply_err(f"{maps.BUSY} another map reply is being built; ask again".encode())
        else:
            query.reply(KEYS.map("r1", "e1"), reply("r1", "e1", 5))

    queryable = side.declare_queryable(KEYS.all_maps("e1"), on)
    drops = _Drops()
    try:
        wait_for(lambda: any(r.err is not None for r in querier.get(KEYS.map("probe", "e1"), timeout=2)), 10,
                 "the edge's queryable")
        asked.clear()
        got = maps.ask_map(querier, KEYS, "r1", ["e1"], drops, timeout=5)
        if busy_for < maps.BUSY_TRIES:
            assert got is not None and got.scans == 5 and len(asked) == busy_for + 1
        else:
            assert got is None and len(asked) == maps.BUSY_TRIES
        assert not drops.counts
    finally:
        queryable.undeclare()


def test_an_older_edge_answering_busy_is_asked_again_on_its_own_key_once_a_round(
        sessions: tuple[Any, Any]) -> None:
    """An edge from before per-edge map keys answers on ``map_before``, and busy as well (from the
    review: its key was rebuilt as an edge's, ``keys.map(robot, "")``, which raised; and a key
    answered busy twice was asked twice as often each round)."""
    from zoffload.runtime import maps

    side, querier = sessions
    asked: list[str] = []

    def on(query: Any) -> None:
        asked.append(str(query.key_expr))
        if len(asked) <= 3:
            for _ in range(2):  # two busy replies to one query
                query.reply_err(f"{maps.BUSY} another map reply is being built; ask again".encode())
        else:
            query.reply(KEYS.map_before("r1"), reply("r1", "", 4))

    older = side.declare_queryable(KEYS.map_before("r1"), on)
    drops = _Drops()
    try:
        wait_for(lambda: any(r.err is not None for r in querier.get(KEYS.map_before("r1"), timeout=2)), 10,
                 "the older edge's queryable")
        asked.clear()
        got = maps.ask_map(querier, KEYS, "r1", [], drops, timeout=5, before=True)
        assert got is not None and got.edge == "" and got.scans == 4
        assert asked == [KEYS.map_before("r1")] * 4 and not drops.counts  # one query a round
    finally:
        older.undeclare()


def test_an_edge_that_does_not_map_the_robot_is_logged_at_debug_and_one_that_lost_it_at_info(
        sessions: tuple[Any, Any], caplog: pytest.LogCaptureFixture) -> None:
    """The live view asks every live edge until an ack names the robot's: the usual answer of an
    edge asked in case that does not map it is not worth a line each poll (an edge the caller
    knew to map the robot is: ``guessed=False``); an edge that lost its map says why."""
    from zoffload.runtime import maps

    side, querier = sessions
    fleet = Fleet(side, {"e1": {}})

    def lost(query: Any) -> None:
        query.reply_err(f"{NO_MAP} 'r1': its mapper was lost".encode())

    held = side.declare_queryable(KEYS.map("r1", "e2"), lost)
    try:
        fleet.wait_routed(querier, ["e1"])
        wait_for(lambda: any(r.err is not None for r in querier.get(KEYS.map("r1", "e2"), timeout=2)), 10,
                 "e2's queryable")
        for guessed, plain in ((True, logging.DEBUG), (False, logging.INFO)):
            caplog.clear()
            with caplog.at_level(logging.DEBUG, "zoffload.maps"):
                assert maps.ask_map(querier, KEYS, "r1", ["e1", "e2"], _Drops(), timeout=5,
                                    guessed=guessed) is None
            by_edge = {r.getMessage().split("edge ")[1][:4]: r.levelno for r in caplog.records
                       if r.name == "zoffload.maps"}
            assert by_edge == {"'e1'": plain, "'e2'": logging.INFO}, caplog.text
    finally:
        held.undeclare()
        fleet.close()
