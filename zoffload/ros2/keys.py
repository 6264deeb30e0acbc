"""The key expressions of a ROS 2 graph on rmw_zenoh: topic data keys and liveliness tokens.

Data: ``<domain>/<topic without its leading slash>/<pkg>::msg::dds_::<Type>_/<RIHS01_hash>``
(rmw_zenoh_cpp ``liveliness::TopicInfo``: inner slashes stay key separators; ROS subscribers
declare the exact key, so a wrong hash or type name is never routed, silently).

Graph: liveliness tokens (``Entity::Entity()``, ``liveliness_utils.cpp``)::

    @ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>
    @ros2_lv/<domain>/<zid>/<nid>/<eid>/MP|MS/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>

where every name part has ``/`` written ``%`` (``mangle_name``), the root namespace and the default
enclave ``/`` become ``%``, and ``<qos>`` is ``qos_to_keyexpr``'s
``<rel>:<dur>:<hist>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<lease s>,<ns>``
(an empty field is rmw_zenoh's default). ``@ros2_lv`` is a verbatim chunk: ``**`` never matches
it, a graph reader asks for ``@ros2_lv/<domain>/**``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")  # a node name, one token of a topic name
_TOKEN = re.compile(r"^[A-Za-z0-9_]+$")  # topic tokens: ROS forbids a leading digit; be lenient
_PKG_TYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(msg|srv)/([A-Za-z][A-Za-z0-9_]*)$")
_DDS_TYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)::(msg|srv)::dds_::([A-Za-z][A-Za-z0-9_]*)_$")
_HASH = re.compile(r"^(RIHS01_[0-9a-f]{64}|TypeHashNotSupported)$")

# rmw enum values (rmw/types.h); rosbags' Qos enums have the same numbers
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2


class Ros2NameError(ValueError):
    """A topic, node, namespace, type or key that is not a valid ROS 2 / rmw_zenoh name."""


def topic_name(topic: str, namespace: str = "/") -> str:
    """The fully-qualified topic name: ``points`` in namespace ``/robot1`` is ``/robot1/points``;
    ``Ros2NameError`` for anything ROS would refuse (empty tokens, wildcards, a trailing slash)."""
    topic = topic.strip()
    full = topic if topic.startswith("/") else f"{namespace_name(namespace).rstrip('/')}/{topic}"
    tokens = full.split("/")[1:]
    if not tokens or not all(_TOKEN.match(t) for t in tokens):
        raise Ros2NameError(f"invalid ROS 2 topic name {topic!r} (tokens of letters, digits and '_' "
                            "separated by '/', e.g. /velodyne_points)")
    return full


def namespace_name(namespace: str) -> str:
    if namespace == "/":
        return namespace
    tokens = namespace.split("/")
    if not namespace.startswith("/") or not all(_TOKEN.match(t) for t in tokens[1:]):
        raise Ros2NameError(f"invalid ROS 2 namespace {namespace!r} (/ or /a/b)")
    return namespace


def node_name(name: str) -> str:
    if not _NAME.match(name):
        raise Ros2NameError(f"invalid ROS 2 node name {name!r} (letters, digits, '_')")
    return name


def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/PointCloud2`` → ``sensor_msgs::msg::dds_::PointCloud2_``."""
    m = _PKG_TYPE.match(msgtype)
    if not m:
        raise Ros2NameError(f"invalid ROS 2 type {msgtype!r} (pkg/msg/Name)")
    return f"{m[1]}::{m[2]}::dds_::{m[3]}_"


def ros_type_name(dds_type: str) -> str:
    """``sensor_msgs::msg::dds_::PointCloud2_`` → ``sensor_msgs/msg/PointCloud2``."""
    m = _DDS_TYPE.match(dds_type)
    if not m:
        raise Ros2NameError(f"not an rmw_zenoh type name: {dds_type[:100]!r}")
    return f"{m[1]}/{m[2]}/{m[3]}"


def mangle(name: str) -> str:
    """A name as one token chunk: every ``/`` written ``%`` (rmw_zenoh ``mangle_name``)."""
    return name.replace("/", "%")


def topic_key(domain: int, topic: str, msgtype: str, type_hash: str | None) -> str:
    """The data key of ``topic``; ``type_hash`` None gives a subscriber's key for any hash."""
    if type_hash is not None and not _HASH.match(type_hash):
        raise Ros2NameError(f"invalid type hash {type_hash!r} (RIHS01_ + 64 hex digits)")
    return f"{_domain(domain)}/{topic_name(topic)[1:]}/{dds_type_name(msgtype)}/{type_hash or '*'}"


@dataclass(frozen=True)
class TopicKey:
    domain: int
    topic: str  # fully qualified, e.g. /robot1/points
    msgtype: str  # pkg/msg/Name
    type_hash: str


def parse_topic_key(key: str) -> TopicKey:
    """Split a received data key from the right (the topic itself may hold ``/``)."""
    parts = str(key).split("/")
    if len(parts) < 4 or not parts[0].isdigit() or not _HASH.match(parts[-1]):
        raise Ros2NameError(f"not an rmw_zenoh topic key: {str(key)[:200]!r}")
    return TopicKey(int(parts[0]), topic_name("/" + "/".join(parts[1:-2])), ros_type_name(parts[-2]),
                    parts[-1])


@dataclass(frozen=True)
class Qos:
    """The QoS an endpoint advertises in its token. Only graph introspection reads it (``ros2
    topic info -v``, RViz choosing a compatible profile); data routing ignores it."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10

    def keyexpr(self) -> str:
        """Reliability, durability, history and depth written out (an empty field means the
        reader's default, which changed in Jazzy 0.2.3: TRANSIENT_LOCAL before, VOLATILE after);
        deadline, lifespan and liveliness left at the defaults every version shares."""
        return f"{self.reliability}:{self.durability}:{self.history},{self.depth}:,:,:,,"


SENSOR_DATA = Qos(BEST_EFFORT, VOLATILE, KEEP_LAST, 5)  # rclcpp SensorDataQoS
DEFAULT_QOS = Qos(RELIABLE, VOLATILE, KEEP_LAST, 10)
LATCHED = Qos(RELIABLE, TRANSIENT_LOCAL, KEEP_LAST, 1)  # map_server style, for late joiners


def parse_qos(text: str) -> Qos:
    """A token's QoS string; empty fields read as rmw_zenoh ≥ 0.2.3's defaults (reliable,
    volatile, keep last 42)."""
    parts = text.split(":")
    if len(parts) != 6 or len(parts[2].split(",")) != 2:
        raise Ros2NameError(f"not an rmw_zenoh QoS string: {text[:100]!r}")
    hist, depth = parts[2].split(",")
    try:
        return Qos(int(parts[0] or RELIABLE), int(parts[1] or VOLATILE), int(hist or KEEP_LAST),
                   int(depth or 42))
    except ValueError as exc:
        raise Ros2NameError(f"not an rmw_zenoh QoS string: {text[:100]!r}") from exc


def node_token(domain: int, zid: str, nid: int, namespace: str, node: str, enclave: str = "/") -> str:
    """A node's liveliness token (kind ``NN``: the node id is also the entity id)."""
    return "/".join([ADMIN_SPACE, _domain(domain), zid, str(nid), str(nid), "NN", mangle(enclave),
                     mangle(namespace_name(namespace)), node_name(node)])


def endpoint_token(domain: int, zid: str, nid: int, eid: int, kind: str, namespace: str, node: str,
                   topic: str, msgtype: str, type_hash: str, qos: Qos, enclave: str = "/") -> str:
    """A publisher's (``MP``) or subscription's (``MS``) liveliness token."""
    if kind not in ("MP", "MS"):
        raise Ros2NameError(f"endpoint kind {kind!r} (MP, MS)")
    if not _HASH.match(type_hash):
        raise Ros2NameError(f"invalid type hash {type_hash!r}")
    return "/".join([ADMIN_SPACE, _domain(domain), zid, str(nid), str(eid), kind, mangle(enclave),
                     mangle(namespace_name(namespace)), node_name(node),
                     mangle(topic_name(topic, namespace)), dds_type_name(msgtype), type_hash,
                     qos.keyexpr()])


@dataclass(frozen=True)
class Entity:
    """A parsed graph token."""

    domain: int
    zid: str
    nid: int
    eid: int
    kind: str  # NN, MP, MS, SS, SC
    enclave: str
    namespace: str
    node: str
    topic: str | None = None
    msgtype: str | None = None
    type_hash: str | None = None
    qos: Qos | None = None


def parse_token(key: str) -> Entity:
    """A graph token back into its parts (``Ros2NameError`` if it is not one): what a ROS
    graph cache reads from ours, and what tests check ours against."""
    parts = str(key).split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or not all(parts):
        raise Ros2NameError(f"not an rmw_zenoh graph token: {str(key)[:200]!r}")
    try:
        domain, nid, eid = int(parts[1]), int(parts[3]), int(parts[4])
    except ValueError as exc:
        raise Ros2NameError(f"not an rmw_zenoh graph token: {str(key)[:200]!r}") from exc
    unmangle = lambda s: s.replace("%", "/")  # noqa: E731
    common = (domain, parts[2], nid, eid, parts[5], unmangle(parts[6]), unmangle(parts[7]), parts[8])
    if parts[5] == "NN":
        return Entity(*common)
    if len(parts) < 13:
        raise Ros2NameError(f"graph token of kind {parts[5]!r} with {len(parts)} of 13 parts")
    return Entity(*common, topic=unmangle(parts[9]), msgtype=ros_type_name(parts[10]),
                  type_hash=parts[11], qos=parse_qos(parts[12]))


def graph_selector(domain: int) -> str:
    """Every graph token of a domain (what rmw_zenoh's graph cache subscribes to)."""
    return f"{ADMIN_SPACE}/{_domain(domain)}/**"


def _domain(domain: int) -> str:
    if not 0 <= int(domain) <= 232:  # the largest ROS_DOMAIN_ID ROS 2 documents
        raise Ros2NameError(f"ROS domain id {domain} outside 0-232")
    return str(int(domain))
