"""Intake of a robot's messages on the edge: decode, check the sender named in the key, count and
log what is dropped."""

from __future__ import annotations

import logging
from collections import Counter
from typing import TYPE_CHECKING, TypeVar

from zoffload.protocol import wire
from zoffload.protocol.keys import Keys

if TYPE_CHECKING:
    import zenoh

M = TypeVar("M", wire.Scan, wire.Frame)


def decode_from_robot(sample: zenoh.Sample, expect: type[M], keys: Keys, counters: Counter[str],
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
    if msg.robot != robot_in_key:
        counters["malformed"] += 1
        log.warning("dropped %s: robot %r in payload, %r in key", what, msg.robot, robot_in_key)
        return None
    return msg
