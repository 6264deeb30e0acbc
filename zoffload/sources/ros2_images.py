"""Camera frames from ROS 2: a live sensor_msgs/Image or CompressedImage topic of an rmw_zenoh
graph (``ros2:/TOPIC``), or one recorded in a bag (``bag:PATH[:/TOPIC]``).

A live topic's type is read from the graph (the publishers' liveliness tokens); when no publisher
is there yet, a topic ending in ``/compressed`` is taken as CompressedImage (image_transport's
naming), any other as Image. Like the live scan source, ``read`` blocks until the next frame and
bad messages are counted, logged drops.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import zenoh

from zoffload.ros2.image import COMPRESSED, IMAGE, ImageMsgError, image_from_msg
from zoffload.ros2.keys import Ros2NameError, topic_name
from zoffload.ros2.messages import stamp_seconds
from zoffload.ros2.node import Tally
from zoffload.ros2.session import Ros2Link
from zoffload.ros2.typestore import MessageError, deserialize
from zoffload.sources.bag import BagStream, header_stamp
from zoffload.sources.base import ScanSourceError
from zoffload.sources.images import ImageFrame, ImageSourceError
from zoffload.sources.ros2_topic import LiveTopic

log = logging.getLogger("zoffload.sources.ros2_images")


def published_types(session: zenoh.Session, domain: int, topic: str, timeout: float = 2.0) -> set[str]:
    """The message types the graph's publishers of ``topic`` advertise (their MP tokens)."""
    from zoffload.ros2.keys import graph_selector, parse_token

    found = set()
    for reply in session.liveliness().get(graph_selector(domain), timeout=timeout):
        if reply.ok is None:
            continue
        try:
            entity = parse_token(str(reply.ok.key_expr))
        except Ros2NameError:
            continue
        if entity.kind == "MP" and entity.topic == topic and entity.msgtype:
            found.add(entity.msgtype)
    return found


class Ros2ImageSource:
    live = True  # read() waits for the topic: no pacing on top

    def __init__(self, topic: str, link: Ros2Link, rate_hz: float = 30.0,
                 session: zenoh.Session | None = None, msgtype: str | None = None) -> None:
        try:
            full = topic_name(topic, link.namespace)
        except Ros2NameError as exc:
            raise ImageSourceError(str(exc)) from exc
        own = session is None
        if session is None:
            try:
                session = link.open()
            except Exception as exc:  # Ros2SessionError: no router
                raise ImageSourceError(str(exc)) from exc
        if msgtype is None:
            types = published_types(session, link.domain(), full) & {IMAGE, COMPRESSED}
            by_name = COMPRESSED if full.endswith("/compressed") else IMAGE
            msgtype = types.pop() if len(types) == 1 else by_name
        self.msgtype = msgtype
        self.feed = LiveTopic(full, msgtype, link, session, owns_session=own)
        self.name = f"ros2:{full}"
        self.rate_hz = rate_hz

    @property
    def drops(self) -> Tally:
        return self.feed.drops

    def __len__(self) -> int:
        return sys.maxsize

    def read(self, index: int) -> ImageFrame:
        while True:
            cdr = self.feed.take()
            try:
                msg = deserialize(cdr, self.msgtype)
                image = image_from_msg(msg, self.msgtype)
            except (MessageError, ImageMsgError) as exc:
                self.feed.drops("bad_image", f"{self.name}: {exc}")
                continue
            stamp = stamp_seconds(msg.header.stamp)
            return ImageFrame(index, image, stamp=stamp if stamp > 0 else None)

    def close(self) -> None:
        self.feed.close()


class BagImageSource:
    """The Image or CompressedImage messages of one bag topic, at their recorded pace."""

    def __init__(self, path: Path, topic: str | None = None) -> None:
        try:
            self.stream = BagStream(path, topic, (IMAGE, COMPRESSED))
        except ScanSourceError as exc:
            raise ImageSourceError(str(exc)) from exc
        self.name = f"bag:{self.stream.path}:{self.stream.topic}"
        self.rate_hz = self.stream.recorded_rate()
        self.drops = Tally(log)

    def __len__(self) -> int:
        return self.stream.count

    def read(self, index: int) -> ImageFrame:
        """Frame ``index``, or the next readable one after it (a bad message is a counted drop)."""
        for k in range(index, self.stream.count):
            conn, recorded, raw = self.stream.raw(k)
            try:
                msg = self.stream.deserialize(raw, conn.msgtype)
                image = image_from_msg(msg, conn.msgtype)
            except Exception as exc:  # ImageMsgError, and rosbags' errors (not one class)
                self.drops("bad_image", f"{self.name} message {k}: {exc}")
                continue
            return ImageFrame(index, image, stamp=header_stamp(msg, recorded))
        raise ImageSourceError(f"{self.name}: no readable image from message {index} on")

    def close(self) -> None:
        self.stream.close()


def open_ros_image_source(spec: str, rate_hz: float | None = None,
                          link: Ros2Link | None = None) -> Ros2ImageSource | BagImageSource:
    """``ros2:/TOPIC`` or ``bag:PATH[:/TOPIC]`` (see ``open_image_source``)."""
    if spec.startswith("ros2:"):
        return Ros2ImageSource(spec[5:], link or Ros2Link(node="zoffload_camera"), rate_hz or 30.0)
    from zoffload.sources.base import split_bag_spec

    path, topic = split_bag_spec(spec[4:])
    source = BagImageSource(path, topic)
    if rate_hz:
        source.rate_hz = rate_hz
    return source
