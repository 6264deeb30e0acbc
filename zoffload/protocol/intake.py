"""Intake of messages from the network: decode within the receiver's limits, check the sender
named in the key, and count every message refused as a drop (``runtime.drops.Drops``: counted by
reason, the log rate-limited) instead of a log line each. A robot's scans and frames on the edge;
an edge's answers on the robot; the edges' status and liveliness tokens wherever they are read (the
robot's fleet link and camera, the edge's peers)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, TypeVar

from zoffload.protocol import wire
from zoffload.protocol.keys import ID, Keys

if TYPE_CHECKING:
    import zenoh

M = TypeVar("M", wire.Scan, wire.Frame, wire.MapReply)


class DropCounter(Protocol):
    """What intake needs of ``runtime.drops.Drops`` (protocol/ sits below runtime/)."""

    def drop(self, reason: str, detail: str) -> None: ...


def robot_in_key(sample: zenoh.Sample, keys: Keys, drops: DropCounter, what: str) -> str | None:
    """The robot id a data key names, or None after counting a ``bad_key`` drop."""
    robot = keys.robot_of(str(sample.key_expr))
    if robot is None:
        drops.drop("bad_key", f"{what} on {str(sample.key_expr)[:100]!r}")
    return robot


def decode_from_robot(sample: zenoh.Sample, expect: type[M], robot: str, drops: DropCounter, what: str,
                      limits: wire.Limits = wire.DEFAULT_LIMITS) -> M | None:
    """``robot``'s message from a Zenoh sample, or None after counting it as a drop:
    ``malformed`` (not a valid message of that type within ``limits``) or ``foreign`` (the payload
    names another robot than the key, or than the query asked about)."""
    try:
        msg = wire.decode(sample.payload.to_bytes(), expect=expect, limits=limits)
    except wire.WireError as exc:
        drops.drop("malformed", f"{what} on {str(sample.key_expr)[:100]}: {exc}")
        return None
    if msg.robot != robot:
        drops.drop("foreign", f"{what}: robot {msg.robot!r} in the payload, {robot!r} in the key")
        return None
    return msg


def answer_from(sample: zenoh.Sample, keys: Keys, drops: DropCounter, named: str, what: str) -> bool:
    """Whether an answer (ack, detections, checkpoint) that names edge ``named`` came on that edge's
    key, else False after counting a drop: ``bad_key`` (not an answer key) or ``edge_key_<what>``
    (another edge's key: the router's ACL lets an edge identity put only under its own id, so the
    payload's edge must be the key's). The key before per-edge answers (no edge chunk) passes."""
    key = str(sample.key_expr)
    edge = keys.answering_edge(key)
    if edge is None:
        drops.drop("bad_key", f"{what} on {key[:100]!r}")
        return False
    if edge and edge != named:
        drops.drop(f"edge_key_{what}", f"{what} naming edge {named[:40]!r} on edge {edge!r}'s key")
        return False
    return True


def map_from(sample: zenoh.Sample, keys: Keys, robot: str, edge: str, drops: DropCounter,
             limits: wire.Limits = wire.DEFAULT_LIMITS) -> wire.MapReply | None:
    """``robot``'s map from a reply to the query asking ``edge`` (``keys.map``; ``edge`` "": the key
    before per-edge maps, ``keys.map_before``, an older edge's), or None after counting a drop:
    ``edge_key_map`` (the reply's key or payload names another edge than asked: under the ACL an
    edge answers only its own key), or ``decode_from_robot``'s (``malformed``, ``foreign``)."""
    key = str(sample.key_expr)
    if key != (keys.map(robot, edge) if edge else keys.map_before(robot)):
        drops.drop("edge_key_map", f"map of {robot} asked of edge {edge!r} came on {key[:100]!r}")
        return None
    msg = decode_from_robot(sample, wire.MapReply, robot, drops, f"map from edge {edge!r}", limits)
    if msg is not None and msg.edge != edge:
        drops.drop("edge_key_map", f"map of {robot} asked of edge {edge!r} names edge {msg.edge[:40]!r}")
        return None
    return msg


def edge_status(sample: zenoh.Sample, keys: Keys, drops: DropCounter) -> wire.Status | None:
    """An edge's status from a Zenoh sample on ``keys.edge_status(edge)``, or None after counting it
    as a drop: ``malformed_status`` (not a valid status message) or ``foreign_status`` (not an
    edge's, or naming another edge than the key)."""
    try:
        msg = wire.decode(sample.payload.to_bytes(), expect=wire.Status)
    except wire.WireError as exc:
        drops.drop("malformed_status", f"on {str(sample.key_expr)[:100]}: {exc}")
        return None
    if msg.source != "edge" or msg.id != keys.last_chunk(str(sample.key_expr)):
        drops.drop("foreign_status", f"status of {msg.source} {msg.id!r} on {str(sample.key_expr)[:100]}")
        return None
    return msg


def edge_token(sample: zenoh.Sample, keys: Keys, drops: DropCounter) -> str | None:
    """The edge id a liveliness sample on ``keys.any_edge_alive()`` names, or None after counting a
    ``bad_token`` drop (the sample's kind says whether the token came or went)."""
    edge = keys.last_chunk(str(sample.key_expr))
    if not ID.match(edge):
        drops.drop("bad_token", f"edge token {str(sample.key_expr)[:100]!r}")
        return None
    return edge
