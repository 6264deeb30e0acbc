"""Every Zenoh key expression zoffload uses, built in one place.

Layout (``<ns>`` defaults to ``zoffload``; ids are single chunks, no ``/``, ``*``, ``$``, ``#``, ``?``):

====================================  ==========  =====================================================
key                                   primitive   payload
====================================  ==========  =====================================================
``<ns>/data/<robot>/scan``            pub/sub     ``wire.Scan``  robot → edge, congestion control BLOCK_FIRST
``<ns>/data/<robot>/scan_ack/<edge>``  pub/sub     ``wire.ScanAck`` edge → robot, one per scan
``<ns>/data/<robot>/frame``           pub/sub     ``wire.Frame`` robot → edge detector
``<ns>/data/<robot>/detections/<e>``  pub/sub     ``wire.Detections`` edge → robot, one per frame
``<ns>/data/<robot>/checkpoint/<e>``  pub/sub     ``wire.Checkpoint`` edge → robot, every few scans
``<ns>/ctrl/<robot>/attach/<edge>``   queryable   ``wire.Attach`` → ``wire.AttachReply`` (edge)
``<ns>/view/<robot>/preview``         pub/sub     ``wire.Preview`` robot → viewers, while one listens
``<ns>/ctrl/<robot>/map/<edge>``      queryable   ``wire.MapReply`` answered by that edge (map + trajectory)
``<ns>/ctrl/<robot>/ping/<edge>``     queryable   ``wire.Pong`` answered by that edge (liveness RTT)
``<ns>/status/<robot>``               pub/sub     ``wire.Status`` robot counters, 1 Hz
``<ns>/status/edge/<edge>``           pub/sub     ``wire.Status`` edge counters, 1 Hz
``<ns>/alive/edge/<edge>``            liveliness  token held while the edge daemon runs
``<ns>/alive/robot/<robot>``          liveliness  token held while a robot daemon runs
====================================  ==========  =====================================================

Data, control, status and liveliness live under separate prefixes so a router ACL or a recorder
can select one class of traffic with a single wildcard.

**Answers** (acks, detections, checkpoints) go under the answering edge's id (``<e>``), so the
router's ACL can hold each edge to its own (``runtime/acl.py``), and a robot drops an answer whose
payload names another edge than its key (``protocol/intake.answer_from``): an edge identity cannot
answer in another edge's name. Before 2026-11-29 they went on ``<ns>/data/<robot>/<answer>``, with
no edge chunk; a robot still reads that key (an older edge's answers; a router with the ACL refuses
puts on it), an older robot does not read the new ones: upgrade robots first.

**Map queries** go to one edge by name (``<ns>/ctrl/<robot>/map/<edge>``), as pings and attaches:
the ACL lets an edge declare and answer only its own, a reply names its edge (``MapReply.edge``)
and a querier drops one naming another edge than it asked (``runtime/maps.py``: it asks the edge
that maps the robot, else every live edge). Before 2026-11-29 any edge answered ``<ns>/ctrl/<robot>/map``
(``map_before``) for any robot; a querier still asks it when no edge answered on its own key (an
older edge), an older querier does not ask the new ones: upgrade queriers (viewer, monitors) first.
"""

from __future__ import annotations

import re

DEFAULT_NAMESPACE = "zoffload"
ID = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")  # one key chunk; at most 64 characters


def check_id(value: str, what: str = "id") -> str:
    """Return ``value`` if it is a valid single key chunk, else raise ``ValueError``."""
    if not ID.match(value):
        raise ValueError(
            f"invalid {what} {value!r}: use letters, digits, '_', '-' or '.' (it becomes one "
            "Zenoh key chunk)"
        )
    return value


def _id_or_any(value: str, what: str) -> str:
    """A valid id, or ``*`` (one chunk: any id) for subscriptions and ACL rules."""
    return value if value == "*" else check_id(value, what)


class Keys:
    """Key expressions of one namespace."""

    def __init__(self, namespace: str = DEFAULT_NAMESPACE) -> None:
        self.ns = check_id(namespace, "namespace")

    # Data streams
    def scan(self, robot: str) -> str:
        return f"{self.ns}/data/{check_id(robot, 'robot id')}/scan"

    def all_scans(self) -> str:
        return f"{self.ns}/data/*/scan"

    def frame(self, robot: str) -> str:
        return f"{self.ns}/data/{check_id(robot, 'robot id')}/frame"

    def all_frames(self) -> str:
        return f"{self.ns}/data/*/frame"

    # Answers, edge → robot, under the answering edge's id (the module's docstring)
    ANSWERS = ("scan_ack", "detections", "checkpoint")

    def answer(self, kind: str, robot: str, edge: str) -> str:
        """The key of ``edge``'s answers of ``kind`` (one of ``ANSWERS``) to ``robot``. Either id may
        be ``*``: one chunk (every robot's, every edge's), so never the key before per-edge answers,
        which has no edge chunk (the ACL's rules)."""
        robot, edge = _id_or_any(robot, "robot id"), _id_or_any(edge, "edge id")
        return f"{self.ns}/data/{robot}/{self._kind(kind)}/{edge}"

    def answers(self, kind: str, robot: str = "*") -> str:
        """What a subscriber to ``robot``'s answers of ``kind`` declares (``*``: every robot's): every
        edge's, and (``**``) the key before per-edge answers, an older edge's."""
        return f"{self.ns}/data/{_id_or_any(robot, 'robot id')}/{self._kind(kind)}/**"

    def _kind(self, kind: str) -> str:
        if kind not in self.ANSWERS:
            raise ValueError(f"{kind!r} is not an answer ({', '.join(self.ANSWERS)})")
        return kind

    def _one(self, kind: str, robot: str, edge: str) -> str:
        """``answer`` of one robot and one edge: a key to put on, so ``*`` is refused."""
        return self.answer(kind, check_id(robot, "robot id"), check_id(edge, "edge id"))

    # The answers by name: one robot's from one edge, and a robot's subscription
    def scan_ack(self, robot: str, edge: str) -> str:
        return self._one("scan_ack", robot, edge)

    def scan_acks(self, robot: str) -> str:
        return self.answers("scan_ack", robot)

    def detections(self, robot: str, edge: str) -> str:
        return self._one("detections", robot, edge)

    def detections_to(self, robot: str) -> str:
        return self.answers("detections", robot)

    def checkpoint(self, robot: str, edge: str) -> str:
        return self._one("checkpoint", robot, edge)

    def checkpoints(self, robot: str) -> str:
        return self.answers("checkpoint", robot)

    def answering_edge(self, key: str) -> str | None:
        """The edge id in an answer's key: "" on the key before per-edge answers, None when ``key``
        is not an answer key of this namespace (one deeper than the edge's chunk, say)."""
        parts = str(key).split("/")
        if len(parts) < 4 or parts[0] != self.ns or parts[1] != "data" or parts[3] not in self.ANSWERS:
            return None
        if len(parts) == 4:
            return ""
        return parts[4] if len(parts) == 5 and ID.match(parts[4]) else None

    # Queries to one edge by name (map, ping, attach): edge E's queryable holds ``ctrl/*/<kind>/E``
    # and answers only its own key (under the ACL, whose rule names its id, a wildcard query would
    # not reach it)
    def _ask(self, kind: str, robot: str, edge: str) -> str:
        """Robot ``robot``'s query of ``kind`` to ``edge``; ``robot`` may be ``*`` (E's queryable)."""
        return f"{self.ns}/ctrl/{_id_or_any(robot, 'robot id')}/{kind}/{check_id(edge, 'edge id')}"

    # Map: a querier asks edge E for robot N's map
    def map(self, robot: str, edge: str) -> str:
        return self._ask("map", check_id(robot, "robot id"), edge)

    def all_maps(self, edge: str) -> str:
        return self._ask("map", "*", edge)

    def map_before(self, robot: str) -> str:
        """The map key before per-edge map keys, which an older edge still answers (any edge's)."""
        return f"{self.ns}/ctrl/{check_id(robot, 'robot id')}/map"

    # Ping: robot N asks edge E for a pong (the round trip to the edge its frames go to); E's
    # queryable answers only its own key, as it answers only its own attaches
    def ping(self, robot: str, edge: str) -> str:
        return self._ask("ping", check_id(robot, "robot id"), edge)

    def all_pings(self, edge: str) -> str:
        return self._ask("ping", "*", edge)

    # Attach: robot N asks edge E to map it (queryable held by E for every robot)
    def attach(self, robot: str, edge: str) -> str:
        return self._ask("attach", check_id(robot, "robot id"), edge)

    def all_attaches(self, edge: str) -> str:
        return self._ask("attach", "*", edge)

    # Viewers
    def preview(self, robot: str) -> str:
        return f"{self.ns}/view/{check_id(robot, 'robot id')}/preview"

    def all_previews(self) -> str:
        return f"{self.ns}/view/*/preview"

    # Status
    def robot_status(self, robot: str) -> str:
        return f"{self.ns}/status/{check_id(robot, 'robot id')}"

    def edge_status(self, edge: str) -> str:
        return f"{self.ns}/status/edge/{check_id(edge, 'edge id')}"

    def all_robot_status(self) -> str:
        return f"{self.ns}/status/*"  # one chunk: not the edges' status/edge/<edge>

    def all_edge_status(self) -> str:
        return f"{self.ns}/status/edge/*"

    # Liveliness
    def edge_alive(self, edge: str) -> str:
        return f"{self.ns}/alive/edge/{check_id(edge, 'edge id')}"

    def any_edge_alive(self) -> str:
        return f"{self.ns}/alive/edge/*"

    def robot_alive(self, robot: str) -> str:
        return f"{self.ns}/alive/robot/{check_id(robot, 'robot id')}"

    def any_robot_alive(self) -> str:
        return f"{self.ns}/alive/robot/*"

    # Parsing
    def robot_of(self, key: str) -> str | None:
        """The robot id in a data or control key of this namespace, or None if it is not one."""
        parts = str(key).split("/")
        if len(parts) in (4, 5) and parts[0] == self.ns and parts[1] in ("data", "ctrl", "view"):
            return parts[2] if ID.match(parts[2]) else None
        return None

    def last_chunk(self, key: str) -> str:
        return str(key).rsplit("/", 1)[-1]
