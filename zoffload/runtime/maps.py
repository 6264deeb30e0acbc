"""Map queries: a robot's registered map and trajectory (``wire.MapReply``), asked of one edge by name.

Under the router's ACL an edge declares and answers only its own map key
(``<ns>/ctrl/<robot>/map/<edge>``), and the ACL checks a query's key against the rule's: a wildcard
query (``.../map/*``) would reach no edge, so a querier asks each edge by its id. Which edges: those
the caller knows map the robot (the edge of its acks, the querier's own edge), else every live edge
(``alive/edge/*``) and the key before per-edge maps (an older edge, ``keys.map_before``). A reply
whose key or payload names another edge than asked is dropped and counted (``edge_key_map``,
``protocol/intake.map_from``), as a malformed one or another robot's.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence

import zenoh

from zoffload.protocol import wire
from zoffload.protocol.intake import DropCounter, edge_token, map_from
from zoffload.protocol.keys import Keys
from zoffload.runtime.drops import Drops

log = logging.getLogger("zoffload.maps")

BUSY = "busy:"  # how an edge's error reply begins when it is building another querier's map reply
BUSY_TRIES = 4
BUSY_WAIT_S = 0.25
NO_MAP = "no map for robot"  # how an edge's error reply begins when it does not map the robot


def no_map_reply(robot: str | None, why: str = "") -> str:
    """An edge's error reply when it does not map ``robot``; ``why`` when it had a map and lost it.
    The edge answers with it and ``ask_map`` recognises the plain one by it."""
    return f"{NO_MAP} {robot!r}: {why}" if why else f"{NO_MAP} {robot!r}"


def live_edges(session: zenoh.Session, keys: Keys, drops: DropCounter, timeout: float = 5.0) -> list[str]:
    """The edges whose liveliness token is up, by id."""
    edges = {edge for reply in session.liveliness().get(keys.any_edge_alive(), timeout=timeout)
             if reply.ok is not None and (edge := edge_token(reply.ok, keys, drops)) is not None}
    return sorted(edges)


def ask_map(session: zenoh.Session, keys: Keys, robot: str, edges: Sequence[str], drops: DropCounter,
            timeout: float = 10.0, before: bool = False, guessed: bool = True) -> wire.MapReply | None:
    """Ask each of ``edges`` for ``robot``'s map, all at once, and with ``before`` the key before
    per-edge maps too; the first valid reply in that order, None when none came. An edge building
    another querier's reply answers ``BUSY`` (it builds one at a time): its key is asked again, up
    to ``BUSY_TRIES`` times ``BUSY_WAIT_S`` apart, before its answer counts as none. An edge's
    plain answer that it does not map the robot is logged at debug when ``guessed`` (the edges
    were asked in case), at info when the caller knew them to map it; any other error at info."""
    ask = [(edge, keys.map(robot, edge)) for edge in edges]
    if before:
        ask.append(("", keys.map_before(robot)))
    for attempt in range(BUSY_TRIES):
        if attempt:
            time.sleep(BUSY_WAIT_S)
        asked = [(edge, key, session.get(key, timeout=timeout)) for edge, key in ask]
        busy: dict[tuple[str, str], None] = {}  # (edge, key), once each, in order
        for edge, key, replies in asked:
            for reply in replies:
                if reply.ok is None:  # that edge has no map of the robot, or is building another's
                    why = reply.err.payload.to_bytes()[:200].decode(errors="replace") if reply.err else "?"
                    if why.startswith(BUSY):
                        busy[(edge, key)] = None
                    elif guessed and why == no_map_reply(robot):  # an edge asked in case: as usual
                        log.debug("no map of %s from edge %r", robot, edge)
                    else:
                        log.info("no map of %s from edge %r: %s", robot, edge, why)
                    continue
                msg = map_from(reply.ok, keys, robot, edge, drops)
                if msg is not None:
                    return msg
        if not busy:
            return None
        ask = list(busy)
    log.warning("no map of %s: %s still busy after %d tries", robot, [e or "(older edge)" for e, _ in ask],
                BUSY_TRIES)
    return None


def fetch_map(session: zenoh.Session, keys: Keys, robot: str, edges: Sequence[str] = (),
              drops: DropCounter | None = None, timeout: float = 10.0) -> wire.MapReply | None:
    """``robot``'s map from ``edges`` (those the caller knows map it, in order), else from every
    other live edge, or an older edge on the key before per-edge maps."""
    drops = drops if drops is not None else Drops(log)
    msg = ask_map(session, keys, robot, edges, drops, timeout, guessed=False) if edges else None
    if msg is None:
        others = [e for e in live_edges(session, keys, drops, timeout) if e not in edges]
        msg = ask_map(session, keys, robot, others, drops, timeout, before=True)
    return msg
