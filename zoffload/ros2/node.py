"""A ROS 2 node on a Zenoh session, declared as rmw_zenoh declares one: ``ros2 node list`` sees
the node, ``ros2 topic info -v`` its publishers and subscriptions, ``ros2 topic echo`` and RViz
its messages.

* the node's ``NN`` token, and one ``MP``/``MS`` token per endpoint, all under the node's id;
* a publisher puts CDR with the attachment (sequence from 1, wall-clock ns, the GID); a
  TRANSIENT_LOCAL one is a zenoh-ext advanced publisher with a cache of ``depth`` samples and
  publisher detection, as rmw_zenoh ≥ Jazzy 0.2.2 declares it, so a late-joining ROS subscriber
  (an advanced subscriber querying ``<key>/@adv/**``) gets the last message;
* a subscription listens on the topic's key with any type hash and hands on each sample's CDR
  bytes and attachment; samples without a valid attachment are dropped, as rmw_zenoh drops them.

The GID is 16 bytes of BLAKE2b of the endpoint's token (rmw_zenoh hashes the token with XXH3;
only the uniqueness matters: it names the publisher in ``message_info``).
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import zenoh
from zenoh import ext

from zoffload.ros2.attachment import Attachment, AttachmentError, parse_attachment
from zoffload.ros2.keys import (
    DEFAULT_QOS,
    RELIABLE,
    SENSOR_DATA,
    TRANSIENT_LOCAL,
    Qos,
    Ros2NameError,
    TopicKey,
    endpoint_token,
    namespace_name,
    node_name,
    node_token,
    parse_topic_key,
    topic_key,
    topic_name,
)
from zoffload.ros2.typestore import serialize, type_hash

log = logging.getLogger("zoffload.ros2")

# Node and entity ids: any integers unique within the session (rmw_zenoh draws them from one
# counter per context); one counter per process is unique per session too
_ids = itertools.count()
OnDrop = Callable[[str, str], None]
Handler = Callable[[bytes, Attachment, TopicKey], None]


class Tally:
    """Counted drops with a bounded log: the first ``first`` of each reason, then one in ``every``
    (the core's stand-in for the daemons' ``runtime.drops.Drops``)."""

    def __init__(self, logger: logging.Logger, first: int = 10, every: int = 1000) -> None:
        self.log, self.first, self.every = logger, first, every
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()

    def __call__(self, reason: str, detail: str) -> None:
        with self._lock:
            self.counts[reason] += 1
            n = self.counts[reason]
        if n <= self.first or n % self.every == 0:
            self.log.warning("dropped (%s, %d so far): %s", reason, n, detail[:300])

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counts)


class Ros2Node:
    """A node's identity and its endpoints; ``close`` undeclares them all."""

    def __init__(self, session: zenoh.Session, name: str, namespace: str = "/", domain_id: int = 0,
                 keyed_attachment: bool = False, enclave: str = "/") -> None:
        self.session = session
        self.name = node_name(name)
        self.namespace = namespace_name(namespace)
        self.domain_id = domain_id
        self.enclave = enclave
        self.keyed_attachment = keyed_attachment  # Jazzy 0.2.0-0.2.3 peers read only that format
        self.zid = str(session.zid())
        self.nid = next(_ids)
        self.token_key = node_token(domain_id, self.zid, self.nid, self.namespace, self.name, enclave)
        self._token = session.liveliness().declare_token(self.token_key)
        self._endpoints: list[Ros2Publisher | Ros2Subscription] = []

    def publisher(self, topic: str, msgtype: str, qos: Qos = DEFAULT_QOS,
                  congestion: zenoh.CongestionControl = zenoh.CongestionControl.DROP) -> Ros2Publisher:
        pub = Ros2Publisher(self, topic, msgtype, qos, congestion)
        self._endpoints.append(pub)
        return pub

    def subscription(self, topic: str, msgtype: str, handler: Handler, qos: Qos = SENSOR_DATA,
                     on_drop: OnDrop | None = None) -> Ros2Subscription:
        sub = Ros2Subscription(self, topic, msgtype, handler, qos, on_drop or Tally(log))
        self._endpoints.append(sub)
        return sub

    def close(self) -> None:
        while self._endpoints:
            self._endpoints.pop().close()
        _undeclare(self._token)


class Ros2Publisher:
    def __init__(self, node: Ros2Node, topic: str, msgtype: str, qos: Qos,
                 congestion: zenoh.CongestionControl) -> None:
        self.node = node
        self.topic = topic_name(topic, node.namespace)
        self.msgtype = msgtype
        self.type_hash = type_hash(msgtype)
        self.qos = qos
        self.key = topic_key(node.domain_id, self.topic, msgtype, self.type_hash)
        self.token_key = endpoint_token(node.domain_id, node.zid, node.nid, next(_ids), "MP", node.namespace,
                                        node.name, self.topic, msgtype, self.type_hash, qos, node.enclave)
        self.gid = hashlib.blake2b(self.token_key.encode(), digest_size=16).digest()
        self.seq = 0
        self._lock = threading.Lock()
        session = node.session
        reliability = (zenoh.Reliability.RELIABLE if qos.reliability == RELIABLE
                       else zenoh.Reliability.BEST_EFFORT)
        self._pub: Any
        if qos.durability == TRANSIENT_LOCAL:
            # rmw_zenoh_cpp PublisherData::make: cache of depth samples, publisher detection, and
            # a sporadic heartbeat (which also makes the cache sequence-numbered)
            self._pub = ext.declare_advanced_publisher(
                session, self.key, reliability=reliability, congestion_control=congestion,
                cache=ext.CacheConfig(max_samples=max(1, qos.depth)), publisher_detection=True,
                sample_miss_detection=ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=0.5))
        else:
            self._pub = session.declare_publisher(self.key, reliability=reliability,
                                                  congestion_control=congestion)
        self._token = session.liveliness().declare_token(self.token_key)

    def publish(self, msg: Any) -> None:
        self.publish_cdr(serialize(msg, self.msgtype))

    def publish_cdr(self, cdr: bytes) -> None:
        with self._lock:  # sequence numbers in publication order
            self.seq += 1
            att = Attachment(self.seq, time.time_ns(), self.gid).pack(self.node.keyed_attachment)
            self._pub.put(cdr, attachment=att)

    def close(self) -> None:
        _undeclare(self._token, self._pub)


class Ros2Subscription:
    def __init__(self, node: Ros2Node, topic: str, msgtype: str, handler: Handler, qos: Qos,
                 on_drop: OnDrop) -> None:
        self.topic = topic_name(topic, node.namespace)
        self.msgtype = msgtype
        self.handler = handler
        self.on_drop = on_drop
        own_hash = type_hash(msgtype)
        # Any hash: a publisher's type may be a newer or older revision of the same message
        self.key = topic_key(node.domain_id, self.topic, msgtype, None)
        self.token_key = endpoint_token(node.domain_id, node.zid, node.nid, next(_ids), "MS", node.namespace,
                                        node.name, self.topic, msgtype, own_hash, qos, node.enclave)
        self.hashes_seen: set[str] = set()
        # Called on Zenoh's own thread (``indirect=False``): the handler only parses the attachment
        # and hands the bytes on, and no Python thread is left to hold the process open at exit
        # when an owner forgets to close the session
        self._sub = node.session.declare_subscriber(
            self.key, zenoh.handlers.Callback(self._on_sample, indirect=False))
        self._token = node.session.liveliness().declare_token(self.token_key)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            key = parse_topic_key(str(sample.key_expr))
        except Ros2NameError as exc:
            self.on_drop("bad_key", str(exc))
            return
        if sample.attachment is None:
            self.on_drop("no_attachment", f"{self.topic}: a sample without the rmw_zenoh attachment")
            return
        try:
            att = parse_attachment(sample.attachment.to_bytes())
        except AttachmentError as exc:
            self.on_drop("bad_attachment", f"{self.topic}: {exc}")
            return
        if key.type_hash not in self.hashes_seen and len(self.hashes_seen) < 16:
            self.hashes_seen.add(key.type_hash)
            log.info("%s: %s from a publisher with type hash %s", self.topic, key.msgtype, key.type_hash)
        try:
            self.handler(sample.payload.to_bytes(), att, key)
        except Exception as exc:  # a handler bug must not surface in Zenoh's thread
            self.on_drop("handler_error", f"{self.topic}: {exc.__class__.__name__}: {exc}")

    def close(self) -> None:
        _undeclare(self._token, self._sub)


def _undeclare(*entities: Any) -> None:
    for entity in entities:
        try:
            entity.undeclare()
        except Exception as exc:  # the session is closing: nothing left to undeclare
            log.debug("%s not undeclared: %s", type(entity).__name__, exc)
