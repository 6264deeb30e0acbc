"""The edge daemon: a KISS-ICP mapper per robot, acks, map queryable, liveliness."""

from __future__ import annotations

import logging
from collections import Counter
from typing import Any, TypeVar

from zoffload.protocol import wire
from zoffload.protocol.keys import Keys

M = TypeVar("M", wire.Scan, wire.Frame)


def decode_from_robot(sample: Any, expect: type[M], keys: Keys, counters: Counter[str],
                      log: logging.Logger, what: str) -> M | None:
    """A robot's message from a Zenoh sample, or None after counting it as ``malformed`` and
    logging why: undecodable, or sent under another robot's key."""
    robot_in_key = keys.robot_of(str(sample.key_expr))
    try:
        msg = wire.decode(sample.payload.to_bytes(), expect=expect)
    except wire.WireError as exc:
        counters["malformed"] += 1
        log.warning("dropped malformed %s on %s: %s (%d so far)", what, sample.key_expr, exc,
                    counters["malformed"])
        return None
    assert isinstance(msg, expect)
    if msg.robot != robot_in_key:
        counters["malformed"] += 1
        log.warning("dropped %s: robot %r in payload, %r in key", what, msg.robot, robot_in_key)
        return None
    return msg
