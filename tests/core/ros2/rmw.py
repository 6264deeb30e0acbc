"""A stand-in for an rmw_zenoh ROS 2 node, written from rmw_zenoh_cpp's sources and independently
of ``zoffload.ros2`` (only zenoh-python, struct and rosbags), so zoffload's side is checked against
what a ROS node does rather than against itself:

* tokens ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/%/<ns>/<node>[/<topic>/<type>/<hash>/<qos>]``
  (``liveliness_utils.cpp`` ``Entity::Entity``), QoS strings as ROS writes them (defaults elided);
* publishers put CDR (``00 01 00 00`` header) with the 33-byte attachment
  ``struct.pack('<qqB16s', seq, ns, 16, gid)`` (``attachment_helpers.cpp``, Jazzy >= 0.2.4);
* subscribers drop samples without an attachment (``rmw_subscription_data.cpp``); a
  TRANSIENT_LOCAL subscription is an advanced subscriber with history and late-publisher
  detection, configured as ``SubscriptionData::init`` does.
"""

from __future__ import annotations

import itertools
import os
import struct
import threading
import time
from typing import Any

import zenoh

# rosbags' Jazzy store: the hashes a Jazzy node computes for the bundled types
from rosbags.typesys import Stores, get_typestore
from zenoh import ext

STORE = get_typestore(Stores.ROS2_JAZZY)
_ids = itertools.count(100)


def dds(msgtype: str) -> str:
    pkg, kind, name = msgtype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def session(listen: int | None = None, connect: int | None = None) -> zenoh.Session:
    """A peer session on loopback, timestamping on (as rmw_zenoh's config has it)."""
    conf = zenoh.Config()
    if listen is not None:
        conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{listen}"]')
    if connect is not None:
        conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{connect}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/shared_memory/enabled", "false")
    conf.insert_json5("timestamping/enabled", "true")
    return zenoh.open(conf)


class FakeNode:
    def __init__(self, s: zenoh.Session, name: str = "lidar_driver", domain: int = 0) -> None:
        self.s, self.name, self.domain = s, name, domain
        self.zid = str(s.zid())
        self.nid = next(_ids)
        self.tokens = [s.liveliness().declare_token(
            f"@ros2_lv/{domain}/{self.zid}/{self.nid}/{self.nid}/NN/%/%/{name}")]
        self.entities: list[Any] = []

    def _token(self, kind: str, topic: str, msgtype: str, type_hash: str, qos: str) -> None:
        eid = next(_ids)
        self.tokens.append(self.s.liveliness().declare_token(
            f"@ros2_lv/{self.domain}/{self.zid}/{self.nid}/{eid}/{kind}/%/%/{self.name}/"
            f"{topic.replace('/', '%')}/{dds(msgtype)}/{type_hash}/{qos}"))

    def publisher(self, topic: str, msgtype: str, type_hash: str | None = None,
                  qos: str = "2::,5:,:,:,,") -> FakePublisher:
        type_hash = type_hash or STORE.hash_rihs01(msgtype)
        self._token("MP", topic, msgtype, type_hash, qos)
        pub = FakePublisher(self.s, f"{self.domain}/{topic.strip('/')}/{dds(msgtype)}/{type_hash}", msgtype)
        self.entities.append(pub.pub)
        return pub

    def subscription(self, topic: str, msgtype: str, store: Any, latched: bool = False) -> FakeSubscription:
        type_hash = store.hash_rihs01(msgtype)
        self._token("MS", topic, msgtype, type_hash, ":1:,1:,:,:,," if latched else "::,10:,:,:,,")
        sub = FakeSubscription(self.s, f"{self.domain}/{topic.strip('/')}/{dds(msgtype)}/{type_hash}",
                               msgtype, store, latched)
        self.entities.append(sub.sub)
        return sub

    def close(self) -> None:
        for e in self.entities + self.tokens:
            try:
                e.undeclare()
            except Exception:  # the session is closing
                pass


class FakePublisher:
    def __init__(self, s: zenoh.Session, key: str, msgtype: str) -> None:
        self.key, self.msgtype = key, msgtype
        self.pub = s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        self.gid = os.urandom(16)
        self.seq = 1  # rmw_zenoh's sequence numbers start at 1

    def put_cdr(self, cdr: bytes, attachment: bytes | None | bool = True) -> None:
        if attachment is True:
            attachment = struct.pack("<qqB16s", self.seq, time.time_ns(), 16, self.gid)
        self.seq += 1
        if attachment is None or attachment is False:
            self.pub.put(cdr)
        else:
            self.pub.put(cdr, attachment=attachment)

    def publish(self, msg: Any) -> None:
        self.put_cdr(bytes(STORE.serialize_cdr(msg, self.msgtype)))


class FakeSubscription:
    """Samples as a ROS node receives them: (message, attachment bytes, key)."""

    def __init__(self, s: zenoh.Session, key: str, msgtype: str, store: Any, latched: bool) -> None:
        self.msgtype, self.store = msgtype, store
        self.received: list[tuple[Any, bytes, str]] = []
        self.no_attachment = 0
        self.cond = threading.Condition()
        if latched:  # rmw_zenoh_cpp SubscriptionData::init for TRANSIENT_LOCAL + RELIABLE
            self.sub = ext.declare_advanced_subscriber(
                s, key, self._on, history=ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
                recovery=ext.RecoveryConfig(periodic_queries=None, heartbeat=True), subscriber_detection=True)
        else:
            self.sub = ext.declare_advanced_subscriber(s, key, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        if sample.attachment is None:
            self.no_attachment += 1  # rmw_zenoh logs "Unable to obtain attachment" and drops it
            return
        msg = self.store.deserialize_cdr(sample.payload.to_bytes(), self.msgtype)
        with self.cond:
            self.received.append((msg, sample.attachment.to_bytes(), str(sample.key_expr)))
            self.cond.notify_all()

    def wait(self, n: int = 1, timeout: float = 20.0) -> list[tuple[Any, bytes, str]]:
        with self.cond:
            self.cond.wait_for(lambda: len(self.received) >= n, timeout)
            return list(self.received)


def graph(s: zenoh.Session, domain: int = 0, timeout: float = 2.0) -> list[str]:
    """Every graph token of the domain, as rmw_zenoh's graph cache reads them."""
    return sorted(str(r.ok.key_expr) for r in s.liveliness().get(f"@ros2_lv/{domain}/**", timeout=timeout)
                  if r.ok is not None)


def pointcloud(store: Any, fields: list[tuple[str, int, int]], records: Any, stamp: float,
               frame: str = "lidar", point_step: int | None = None, height: int = 1,
               bigendian: bool = False, row_step: int | None = None, data: Any = None) -> Any:
    """A PointCloud2 from (name, offset, datatype) fields and a numpy structured array."""
    import numpy as np

    T = store.types
    step = point_step or records.dtype.itemsize
    width = len(records) // height
    raw = records.view(np.uint8).reshape(-1) if data is None else data
    sec = int(stamp)
    return T["sensor_msgs/msg/PointCloud2"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=sec, nanosec=int(round((stamp - sec) * 1e9))), frame_id=frame),
        height=height, width=width,
        fields=[T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=1) for n, o, d in fields],
        is_bigendian=bigendian, point_step=step, row_step=row_step or step * width, data=raw,
        is_dense=False)
