"""Live ROS 2 topics as sources, fed by a stand-in rmw_zenoh node (tests/core/ros2/rmw.py)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")

from tests.core.ros2 import rmw  # noqa: E402
from tests.helpers import wait_for  # noqa: E402
from zoffload.ros2.keys import SENSOR_DATA, parse_token  # noqa: E402
from zoffload.ros2.session import Ros2Link  # noqa: E402
from zoffload.runtime.session import has_subscribers  # noqa: E402
from zoffload.sources import ScanFrame, ScanSourceError, open_scan_source  # noqa: E402
from zoffload.sources.ros2_topic import Ros2ScanSource  # noqa: E402

F32, U32 = 7, 6
PTS = np.random.default_rng(0).uniform(-20, 20, (300, 3)).astype(np.float32)


def ouster(stamp: float, fields: list[tuple[str, int, int]] | None = None) -> object:
    rec = np.zeros(300, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<u4")])
    rec["x"], rec["y"], rec["z"], rec["t"] = PTS[:, 0], PTS[:, 1], PTS[:, 2], np.arange(300) * 300_000
    return rmw.pointcloud(rmw.STORE, fields or [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("t", 12, U32)],
                          rec, stamp, frame="os_lidar")


@pytest.fixture
def ros(free_port: int) -> Iterator[tuple[object, Ros2Link]]:
    s = rmw.session(listen=free_port)
    try:
        yield s, Ros2Link(connect=(f"tcp/127.0.0.1:{free_port}",), node="zoffload_robot", domain_id=0)
    finally:
        s.close()


def _subscribed(ros_session: Any, topic: str) -> bool:
    return any(parse_token(t).topic == topic for t in rmw.graph(ros_session, 0, 0.5) if "/MS/" in t)


def test_clouds_with_times_and_the_bad_ones_dropped(ros: tuple) -> None:
    s, link = ros
    src = open_scan_source("ros2:/ouster/points", ros2=link)
    assert isinstance(src, Ros2ScanSource) and src.live and len(src) > 10**12
    driver = rmw.FakeNode(s, "os_driver")
    pub = driver.publisher("/ouster/points", "sensor_msgs/msg/PointCloud2")
    wait_for(lambda: _subscribed(s, "/ouster/points"), what="the robot's subscription in the graph")
    ms = next(parse_token(t) for t in rmw.graph(s) if "/MS/" in t)
    assert (ms.node, ms.qos, ms.msgtype) == ("zoffload_robot", SENSOR_DATA, "sensor_msgs/msg/PointCloud2")
    wait_for(lambda: has_subscribers(pub.pub), what="matched")

    def cdr(msg: object) -> bytes:
        return bytes(rmw.STORE.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))

    frames: list[ScanFrame] = []

    def reader() -> None:  # the sensor thread: reads until the source closes
        try:
            while True:
                frames.append(src.read(len(frames)))
        except ScanSourceError:
            pass

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    try:
        # each bad sample on its own (a newer one would replace it before read() meets it)
        pub.publish(ouster(1.0, [("a", 0, F32), ("b", 4, F32), ("c", 8, F32)]))  # no x/y/z
        wait_for(lambda: sum(src.drops.snapshot().values()) == 1, what="no x/y/z dropped")
        pub.publish(ouster(1.0, [("x", 0, 11), ("y", 4, F32), ("z", 8, F32)]))  # datatype 11
        wait_for(lambda: sum(src.drops.snapshot().values()) == 2, what="unknown datatype dropped")
        pub.put_cdr(cdr(ouster(1.0))[:-100])  # truncated CDR
        wait_for(lambda: sum(src.drops.snapshot().values()) == 3, what="truncated CDR dropped")
        pub.put_cdr(cdr(ouster(1.0)), attachment=None)  # what rmw_zenoh itself drops
        wait_for(lambda: sum(src.drops.snapshot().values()) == 4, what="no attachment dropped")
        assert frames == []
        pub.publish(ouster(1700000000.5))
        wait_for(lambda: len(frames) >= 1, what="the good cloud")
    finally:
        src.close()
        driver.close()
        th.join(5)
    f = frames[0]
    np.testing.assert_array_equal(f.points, PTS)
    assert f.times is not None
    np.testing.assert_allclose(f.times, np.arange(300) * 3e-4)
    assert f.stamp == pytest.approx(1700000000.5)
    assert src.drops.snapshot() == {"bad_cloud": 3, "no_attachment": 1}


def test_newest_cloud_wins_and_close_wakes_the_reader(ros: tuple) -> None:
    s, link = ros
    src = Ros2ScanSource("/points", link)
    pub = rmw.FakeNode(s).publisher("/points", "sensor_msgs/msg/PointCloud2")
    wait_for(lambda: has_subscribers(pub.pub), what="matched")
    for k in range(3):
        pub.publish(ouster(100.0 + k))
    wait_for(lambda: src.feed.received == 3, what="three clouds")
    assert src.read(0).stamp == pytest.approx(102.0) and src.feed.overwritten == 2
    errors: list[Exception] = []

    def reader() -> None:
        try:
            src.read(1)
        except ScanSourceError as exc:
            errors.append(exc)

    th = threading.Thread(target=reader)
    th.start()
    time.sleep(0.2)
    src.close()
    th.join(5)
    assert not th.is_alive() and "closed" in str(errors[0])


def test_no_ros_router_is_a_clear_error(free_port: int) -> None:
    with pytest.raises(ScanSourceError, match="rmw_zenohd"):
        open_scan_source("ros2:/points", ros2=Ros2Link(connect=(f"tcp/127.0.0.1:{free_port}",)))
    with pytest.raises(ScanSourceError, match="topic name"):
        open_scan_source("ros2:/bad//name", ros2=Ros2Link(connect=(f"tcp/127.0.0.1:{free_port}",)))


def test_live_images_type_from_the_graph(ros: tuple) -> None:
    cv2 = pytest.importorskip("cv2")
    from zoffload.sources.ros2_images import Ros2ImageSource

    s, link = ros
    T = rmw.STORE.types
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=0), frame_id="cam")
    img = np.random.default_rng(0).integers(0, 256, (12, 16, 3), dtype=np.uint8)
    driver = rmw.FakeNode(s, "camera")
    jpeg = driver.publisher("/cam/jpeg", "sensor_msgs/msg/CompressedImage", qos="::,10:,:,:,,")
    raw = driver.publisher("/cam/raw", "sensor_msgs/msg/Image")
    src_c = Ros2ImageSource("/cam/jpeg", link)
    src_r = Ros2ImageSource("/cam/raw", link)
    assert (src_c.msgtype, src_r.msgtype) == ("sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Image")
    wait_for(lambda: has_subscribers(jpeg.pub) and has_subscribers(raw.pub), what="matched")
    jpeg.publish(T["sensor_msgs/msg/CompressedImage"](header=hdr, format="png",
                                                      data=cv2.imencode(".png", img)[1].reshape(-1)))
    raw.publish(T["sensor_msgs/msg/Image"](header=hdr, height=12, width=16, encoding="rgb8", is_bigendian=0,
                                           step=48, data=img[:, :, ::-1].copy().reshape(-1)))
    for src in (src_c, src_r):
        frame = src.read(0)
        np.testing.assert_array_equal(frame.image, img)
        assert frame.stamp == 5.0
        src.close()
    driver.close()
