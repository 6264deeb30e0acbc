"""A live sensor_msgs/PointCloud2 topic of an rmw_zenoh ROS 2 graph as a scan source.

The source joins the graph as a node (``zoffload_robot`` by default) with a best-effort
subscription (SensorDataQoS, as LiDAR drivers publish), so ``ros2 node list`` and ``ros2 topic
info`` on the ROS machine show it. It takes the topic's samples with any type hash; the Zenoh
callback only keeps the newest sample (an older one not yet read is counted ``overwritten``), and
``read`` turns it into numpy on the reader's thread.

A live topic paces itself: ``read`` blocks until the next message comes (``live`` tells the
sensor thread not to wait on top of that); ``len`` is unbounded; ``rate_hz`` is the nominal rate
the robot's policies plan with (10 Hz unless given). Bad messages (no x/y/z, an unknown datatype,
truncated CDR, no attachment) are counted, logged drops, and ``read`` waits for the next one.
"""

from __future__ import annotations

import atexit
import logging
import sys
import threading
import weakref

import zenoh

from zoffload.ros2.keys import SENSOR_DATA, Ros2NameError, topic_name
from zoffload.ros2.messages import stamp_seconds
from zoffload.ros2.node import Ros2Node, Tally
from zoffload.ros2.pointcloud import PointCloudError, cloud_from_msg
from zoffload.ros2.session import Ros2Link, Ros2SessionError
from zoffload.ros2.typestore import MessageError, deserialize
from zoffload.sources.base import ScanFrame, ScanSourceError

log = logging.getLogger("zoffload.sources.ros2")
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"


class LiveTopic:
    """The newest sample of one topic, for a reader that blocks until a new one comes."""

    def __init__(self, topic: str, msgtype: str, link: Ros2Link, session: zenoh.Session | None = None,
                 owns_session: bool | None = None) -> None:
        """``session`` None: open one from ``link`` (and close it with the feed); ``owns_session``
        hands a given session's closing to the feed."""
        try:
            self.topic = topic_name(topic, link.namespace)
            self.session = session or link.open()
        except (Ros2NameError, Ros2SessionError) as exc:
            raise ScanSourceError(str(exc)) from exc
        self._owns_session = session is None if owns_session is None else owns_session
        self.msgtype = msgtype
        self.drops = Tally(log)
        self.received = 0
        self.overwritten = 0
        self._slot: bytes | None = None
        self._closed = False
        self._cond = threading.Condition()
        self.node = Ros2Node(self.session, link.node, link.namespace, link.domain(), link.keyed_attachment)
        self.node.subscription(self.topic, msgtype, self._on_message, SENSOR_DATA, on_drop=self.drops)
        # A session left open with a Python callback can hang the interpreter's exit: close it
        # then at the latest, if the owner did not
        atexit.register(_close_at_exit, weakref.ref(self))
        log.info("subscribed to %s (%s) on ROS domain %d as node %s", self.topic, msgtype,
                 self.node.domain_id, link.node)

    def _on_message(self, cdr: bytes, *_: object) -> None:
        with self._cond:
            if self._slot is not None:
                self.overwritten += 1
            self._slot = cdr
            self.received += 1
            self._cond.notify()

    def take(self) -> bytes:
        """The newest sample not yet taken, waiting for one; ``ScanSourceError`` once closed."""
        with self._cond:
            while self._slot is None and not self._closed:
                self._cond.wait(0.5)
            cdr, self._slot = self._slot, None
            if self._closed or cdr is None:
                raise ScanSourceError(f"ros2:{self.topic} closed")
            return cdr

    def close(self) -> None:
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        self.node.close()
        if self._owns_session:
            self.session.close()


def _close_at_exit(ref: weakref.ReferenceType[LiveTopic]) -> None:
    feed = ref()
    if feed is not None:
        feed.close()


class Ros2ScanSource:
    live = True  # read() waits for the topic: no pacing on top

    def __init__(self, topic: str, link: Ros2Link, rate_hz: float = 10.0, max_range: float = 100.0,
                 session: zenoh.Session | None = None) -> None:
        self.feed = LiveTopic(topic, POINTCLOUD2, link, session)
        self.name = f"ros2:{self.feed.topic}"
        self.rate_hz = rate_hz
        self.max_range = max_range

    @property
    def drops(self) -> Tally:
        return self.feed.drops

    def __len__(self) -> int:
        return sys.maxsize

    def read(self, index: int) -> ScanFrame:
        """The next cloud to arrive (the newest, if several came since the last read)."""
        while True:
            cdr = self.feed.take()
            try:
                msg = deserialize(cdr, POINTCLOUD2)
                cloud = cloud_from_msg(msg)
            except (MessageError, PointCloudError) as exc:
                self.feed.drops("bad_cloud", f"{self.name}: {exc}")
                continue
            stamp = stamp_seconds(msg.header.stamp)
            return ScanFrame(index=index, points=cloud.points, times=cloud.times,
                             stamp=stamp if stamp > 0 else None)

    def close(self) -> None:
        self.feed.close()
