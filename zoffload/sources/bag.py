"""Replaying recorded bags: rosbag2 folders (``.db3`` or ``.mcap``) and ROS 1 ``.bag`` files,
through rosbags' ``AnyReader`` (no ROS install).

``bag:PATH[:/TOPIC]`` plays one topic's messages in their recorded order. A frame carries its
sensor stamp (the message header's, else the recorded time), so the sensor thread can pace the
replay as it was recorded; ``rate_hz`` is the recorded rate (the median spacing of the first
messages). Reading is sequential, as a replay is; going back (a loop restarting, a ping-pong
replay) seeks to the recorded time of the frame wanted. A message that cannot be read is a
counted, logged drop that yields an empty scan, never the end of the replay.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.ros2.messages import stamp_seconds
from zoffload.ros2.node import Tally
from zoffload.ros2.pointcloud import cloud_from_msg
from zoffload.ros2.typestore import typestore
from zoffload.sources.base import ScanFrame, ScanSourceError

log = logging.getLogger("zoffload.sources.bag")
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"


class BagStream:
    """One topic of a bag, read by index (sequentially fast, backwards by seeking)."""

    def __init__(self, path: Path, topic: str | None, msgtypes: tuple[str, ...]) -> None:
        try:
            from rosbags.highlevel import AnyReader
        except ImportError as exc:
            raise ScanSourceError("reading bags needs rosbags: pip install 'zoffload[ros]'") from exc
        path = Path(path)
        if path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").exists():
            path = path.parent  # a rosbag2 recording is its folder
        if not path.exists():
            raise ScanSourceError(f"bag {path} does not exist")
        if path.is_dir() and not (path / "metadata.yaml").exists():
            raise ScanSourceError(f"{path}: not a rosbag2 folder (no metadata.yaml)")
        if path.is_file() and path.suffix != ".bag":
            raise ScanSourceError(f"{path}: give a rosbag2 folder (with metadata.yaml) or a ROS 1 .bag")
        try:
            self.reader = AnyReader([path], default_typestore=typestore())
            self.reader.open()
        except Exception as exc:  # rosbags raises its own errors for unreadable bags
            raise ScanSourceError(f"{path}: cannot read the bag: {exc}") from exc
        self.path = path
        self.topic, self.msgtype = self._pick(topic, msgtypes)
        self.connections = [c for c in self.reader.connections if c.topic == self.topic]
        self.count = int(self.reader.topics[self.topic].msgcount)
        if self.count == 0:
            raise ScanSourceError(f"{path}: topic {self.topic} has no messages")
        self._times: list[int] = []  # recorded times of the messages read so far, by index
        self._it: Iterator[tuple[Any, int, bytes]] | None = None
        self._next = 0

    def _pick(self, topic: str | None, msgtypes: tuple[str, ...]) -> tuple[str, str]:
        topics = {name: info.msgtype for name, info in self.reader.topics.items()}
        listing = ", ".join(f"{t} ({m})" for t, m in sorted(topics.items())) or "none"
        if topic is not None:
            if topic not in topics:
                raise ScanSourceError(f"{self.path}: no topic {topic} in the bag (topics: {listing})")
            if topics[topic] not in msgtypes:
                raise ScanSourceError(f"{self.path}: {topic} is {topics[topic]}, not {' or '.join(msgtypes)}")
            return topic, str(topics[topic])
        found = sorted(t for t, m in topics.items() if m in msgtypes)
        if len(found) != 1:
            what = "no" if not found else "several"
            raise ScanSourceError(f"{self.path}: {what} {' or '.join(msgtypes)} topics (topics: {listing}); "
                                  "name one as bag:PATH:/TOPIC")
        return found[0], str(topics[found[0]])

    def recorded_rate(self, probe: int = 20) -> float:
        """Messages per second over the first ``probe`` (their median spacing); 10 if unknown."""
        times: list[int] = []
        for _, t, _ in self._iterate(None):
            times.append(t)
            if len(times) >= probe:
                break
        gaps = np.diff(np.asarray(times, np.float64)) * 1e-9
        gaps = gaps[gaps > 0]
        return float(1.0 / np.median(gaps)) if len(gaps) else 10.0

    def _iterate(self, start: int | None) -> Iterator[tuple[Any, int, bytes]]:
        return iter(self.reader.messages(connections=self.connections, start=start))

    def raw(self, index: int) -> tuple[Any, int, bytes]:
        """(connection, recorded time ns, raw bytes) of message ``index``."""
        if not 0 <= index < self.count:
            raise ScanSourceError(f"{self.path}: message {index} of {self.count}")
        if self._it is None or index < self._next:
            self._seek(index)
        assert self._it is not None
        while True:
            try:
                item = next(self._it)
            except StopIteration:
                raise ScanSourceError(f"{self.path}: the bag ended before message {index}") from None
            if self._next == len(self._times):
                self._times.append(int(item[1]))
            self._next += 1
            if self._next - 1 == index:
                return item

    def _seek(self, index: int) -> None:
        if index == 0 or index >= len(self._times):
            self._it, self._next = self._iterate(None), 0
            return
        t = self._times[index]
        first = self._times.index(t)  # messages recorded at the same nanosecond come in order
        self._it, self._next = self._iterate(t), first

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        return self.reader.deserialize(raw, msgtype)

    def close(self) -> None:
        try:
            self.reader.close()
        except Exception as exc:  # already closed
            log.debug("bag not closed: %s", exc)


def header_stamp(msg: Any, recorded_ns: int) -> float:
    """The message's header stamp in seconds, or its recorded time when the header has none."""
    header = getattr(msg, "header", None)
    stamp = stamp_seconds(header.stamp) if header is not None else 0.0
    return stamp if stamp > 0 else recorded_ns * 1e-9


class BagScanSource:
    """The PointCloud2 messages of one bag topic as scans, with their per-point times."""

    def __init__(self, path: Path, topic: str | None = None, max_range: float = 100.0) -> None:
        self.stream = BagStream(path, topic, (POINTCLOUD2,))
        self.topic = self.stream.topic
        self.name = f"bag:{self.stream.path}:{self.topic}"
        self.rate_hz = self.stream.recorded_rate()
        self.max_range = max_range
        self.drops = Tally(log)

    def __len__(self) -> int:
        return self.stream.count

    def read(self, index: int) -> ScanFrame:
        conn, recorded, raw = self.stream.raw(index)
        try:
            msg = self.stream.deserialize(raw, conn.msgtype)
            cloud = cloud_from_msg(msg)
        except Exception as exc:  # PointCloudError, and rosbags' errors (not one class)
            self.drops("bad_cloud", f"{self.name} message {index}: {exc}")
            return ScanFrame(index=index, points=np.zeros((0, 3), np.float32), stamp=recorded * 1e-9)
        return ScanFrame(index=index, points=cloud.points, times=cloud.times,
                         stamp=header_stamp(msg, recorded))

    def close(self) -> None:
        self.stream.close()
