"""The edge's ROS 2 output, read by stand-ins of rmw_zenoh nodes (tests/core/ros2/rmw.py) and
decoded with rosbags: pose, stamps, frames, field layout, tokens, attachments, the latched map."""

from __future__ import annotations

import struct
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import msgpack
import numpy as np
import pytest

pytest.importorskip("rosbags")

from tests.core.ros2 import rmw  # noqa: E402
from tests.daemon.edge.test_server import scan_msg  # noqa: E402
from tests.helpers import KEYS, client, listen_on, running_edge, wait_for, wait_token  # noqa: E402
from zoffload.edge.ros2 import Ros2Names, Ros2Service  # noqa: E402
from zoffload.protocol import wire  # noqa: E402
from zoffload.ros2.keys import LATCHED, parse_token  # noqa: E402
from zoffload.ros2.session import Ros2Link  # noqa: E402
from zoffload.ros2.typestore import typestore  # noqa: E402
from zoffload.runtime.config import DetectorSettings, EdgeSettings  # noqa: E402
from zoffload.runtime.session import free_tcp_port, open_session  # noqa: E402

STORE = typestore()  # rosbags' Jazzy store plus vision_msgs (which rosbags does not bundle)
MAP = np.random.default_rng(0).uniform(-10, 10, (5000, 3)).astype(np.float32)


def pose(x: float, yaw: float) -> np.ndarray:
    p = np.eye(4)
    p[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    p[0, 3] = x
    return p


def ack(robot: str, seq: int, p: np.ndarray, status: str = "ok") -> bytes:
    return wire.encode(wire.ScanAck(robot=robot, seq=seq, send_stamp=1.0, status=status, interarrival=0.1,
                                    queue_time=0.0, proc_time=0.01, icp_time=0.01, map_points=len(MAP),
                                    keypoints=100, sigma=0.1, pose=p, edge="edge1"))


def scan(robot: str, seq: int, capture: float) -> bytes:
    return wire.encode(wire.Scan(robot=robot, seq=seq, send_stamp=1.0, capture_stamp=capture, voxel=0.05,
                                 voxel_max=0.07, max_range=40.0, n_raw=3, points=MAP[:3]))


@contextmanager
def ros_machine() -> Iterator[tuple[Any, int]]:
    port = free_tcp_port()
    s = rmw.session(listen=port)
    try:
        yield s, port
    finally:
        s.close()


@pytest.fixture
def service(free_port: int) -> Iterator[tuple[Any, Any, Ros2Service]]:
    """The service on an edge session (listening on ``free_port``), joined to a separate "ROS
    machine" as a client."""
    with ros_machine() as (ros, port):
        edge = open_session(listen_on(free_port))
        svc = Ros2Service(KEYS, Ros2Link(connect=(f"tcp/127.0.0.1:{port}",), node="zoffload_edge"),
                          Ros2Names(), map_period=0.3,
                          map_source=lambda robot: MAP if robot == "robot1" else None)
        svc.start(edge)
        try:
            yield ros, edge, svc
        finally:
            svc.stop()
            edge.close()


def test_odometry_tf_detections_and_latched_map(service: tuple) -> None:
    ros, edge, svc = service
    viewer = rmw.FakeNode(ros, "rviz")
    odom = viewer.subscription("/robot1/odom", "nav_msgs/msg/Odometry", STORE)
    tf = viewer.subscription("/tf", "tf2_msgs/msg/TFMessage", STORE)
    dets = viewer.subscription("/robot1/detections", "vision_msgs/msg/Detection2DArray", STORE)
    time.sleep(0.5)  # the subscriptions reach the publishers, which are declared on the first ack
    captures = [1700000000.0 + 0.1 * k for k in range(3)]
    for k in range(3):  # the robot's scan (its capture stamp), then this edge's ack
        edge.put(KEYS.scan("robot1"), scan("robot1", k, captures[k]))
        # as on a real edge, the scan is in before its ack (registration takes milliseconds)
        wait_for(lambda k=k: ("robot1", "scan", k) in svc._stamps, what=f"scan {k}'s stamp")  # type: ignore[misc]
        edge.put(KEYS.scan_ack("robot1", "edge1"), ack("robot1", k, pose(0.5 * k, 0.1 * k)))
        if k == 0:
            wait_for(lambda: "robot1" in svc.robots, what="robot1's publishers")
            time.sleep(0.5)
    def newest_stamp() -> float:
        got = odom.received
        return got[-1][0].header.stamp.sec + got[-1][0].header.stamp.nanosec * 1e-9 if got else 0.0

    wait_for(lambda: newest_stamp() > captures[2] - 1e-3, what="the last scan's odometry")
    last, att, key = odom.received[-1]
    # which scan: the stamp is that scan's capture stamp
    k = int(round((last.header.stamp.sec + last.header.stamp.nanosec * 1e-9 - captures[0]) / 0.1))
    assert k == 2
    assert last.header.frame_id == "robot1/odom" and last.child_frame_id == "robot1/lidar"
    assert abs(last.header.stamp.sec + last.header.stamp.nanosec * 1e-9 - captures[k]) < 1e-6
    p = last.pose.pose
    assert (p.position.x, p.position.y) == pytest.approx((0.5 * k, 0.0))
    assert (p.orientation.z, p.orientation.w) == pytest.approx((np.sin(0.05 * k), np.cos(0.05 * k)))
    # 0.5 m along world x in 0.1 s, seen from the sensor (yawed 0.2 rad): the twist is in its frame
    assert last.twist.twist.linear.x == pytest.approx(5.0 * np.cos(0.2), rel=1e-5)
    assert last.twist.twist.angular.z == pytest.approx(1.0, rel=1e-5)
    seq, stamp_ns, n, gid = struct.unpack("<qqB16s", att)
    assert len(att) == 33 and n == 16 and seq == k + 1 and abs(stamp_ns / 1e9 - time.time()) < 60
    assert key.startswith("0/robot1/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_3cc97dc7")
    t = tf.wait(1)[-1][0].transforms[0]
    assert (t.header.frame_id, t.child_frame_id) == ("robot1/odom", "robot1/lidar")
    # detections, stamped with the frame's capture stamp
    edge.put(KEYS.frame("robot1"), wire.encode(wire.Frame(
        robot="robot1", seq=9, send_stamp=1.0, capture_stamp=1700000001.25, encoding="bgr8", width=2,
        height=1, data=np.zeros(6, np.uint8))))
    # as on a real edge, the frame is in before its detections (inference takes milliseconds)
    wait_for(lambda: ("robot1", "frame", 9) in svc._stamps, what="frame 9's stamp")
    edge.put(KEYS.detections("robot1", "edge1"), wire.encode(wire.Detections(
        robot="robot1", seq=9, send_stamp=1.0, edge="edge1", model="picodet-s", status="ok", infer_time=0.01,
        queue_time=0.0, batch=1, boxes=np.array([[10, 20, 30, 60]], np.float32),
        scores=np.array([0.8], np.float32), classes=np.array([0], np.int32))))
    d = dets.wait(1)[-1][0]
    assert d.header.frame_id == "robot1/camera" and d.header.stamp.nanosec == 250_000_000
    box = d.detections[0]
    assert (box.bbox.center.position.x, box.bbox.size_y) == (20.0, 40.0)
    assert box.results[0].hypothesis.class_id == "person"
    # the map, latched: a subscriber joining now still gets the last one
    wait_for(lambda: svc.counts["maps"] >= 1, what="a map published")
    late = rmw.FakeNode(ros, "rviz_late").subscription("/robot1/map", "sensor_msgs/msg/PointCloud2", STORE,
                                                       latched=True)
    m, m_att, _ = late.wait(1)[0]
    assert m.header.frame_id == "robot1/odom" and (m.height, m.width) == (1, len(MAP))
    assert [(f.name, f.offset, f.datatype, f.count) for f in m.fields] == \
        [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)]
    assert m.point_step == 12 and not m.is_bigendian and len(m_att) == 33
    np.testing.assert_array_equal(m.data.view("<f4").reshape(-1, 3), MAP)
    # the graph a ROS machine sees: one node, its publishers with their types and QoS
    assert svc._node is not None
    mine = [parse_token(tok) for tok in rmw.graph(ros) if f"/{svc._node.zid}/" in tok]
    assert [e.node for e in mine if e.kind == "NN"] == ["zoffload_edge"]
    pubs = {e.topic: e for e in mine if e.kind == "MP"}
    assert {t: e.msgtype for t, e in pubs.items()} == {
        "/tf": "tf2_msgs/msg/TFMessage", "/robot1/odom": "nav_msgs/msg/Odometry",
        "/robot1/map": "sensor_msgs/msg/PointCloud2",
        "/robot1/detections": "vision_msgs/msg/Detection2DArray"}
    assert pubs["/robot1/map"].qos == LATCHED
    assert all(e.nid == mine[0].nid for e in mine)


def test_only_this_edges_answers_count_and_bad_ones_are_drops(service: tuple, free_port: int) -> None:
    ros, edge, svc = service
    with client(free_port) as other:  # another edge, or a forger, on the edge's network
        other.put(KEYS.scan("intruder"), scan("intruder", 0, 1700000000.0))
        wait_for(lambda: ("intruder", "scan", 0) in svc._stamps, what="the other session connected")
        # a scan on robot1's key naming robot2 (was: set robot2's odometry stamp), and garbage
        other.put(KEYS.scan("robot1"), scan("robot2", 5, 9.9e11))
        other.put(KEYS.scan("robot1"), b"\x93garbage")
        # stamps the decode would refuse: a bool (an int to Python) and one past wire.STAMP
        for seq, bad in ((6, True), (7, 1e13)):
            fields = msgpack.unpackb(scan("robot1", seq, 1.0), raw=False)
            fields["capture_stamp"] = bad
            other.put(KEYS.scan("robot1"), msgpack.packb(fields, use_bin_type=True))
        wait_for(lambda: svc.status().get("ros2.drop.foreign") == 1.0
                 and svc.status().get("ros2.drop.malformed") == 3.0, what="forged, broken scans dropped")
        assert ("robot2", "scan", 5) not in svc._stamps
        assert not any(k[0] == "robot1" and k[2] in (6, 7) for k in svc._stamps)
        other.put(KEYS.scan_ack("intruder", "edge9"), ack("intruder", 0, np.eye(4)))  # not this edge's
        edge.put(KEYS.scan_ack("robot2", "edge1"), b"\x93garbage")
        edge.put(KEYS.scan_ack("robot3", "edge1"), ack("robot3", 0, np.full((4, 4), np.nan), status="error"))
        wait_for(lambda: svc.drops.total() >= 1, what="the malformed ack dropped")
        time.sleep(0.3)
    assert not svc.robots and svc.counts["odom"] == 0
    assert svc.status()["ros2.drop.callback_error"] == 1.0


def test_with_the_real_mapping_service_and_map_queries(free_port: int) -> None:
    pytest.importorskip("kiss_icp")
    settings = EdgeSettings(zenoh=listen_on(free_port), detector=DetectorSettings(enabled=False))
    with ros_machine() as (ros, ros_port), running_edge(settings) as server, client(free_port) as robot:
        svc = Ros2Service(KEYS, Ros2Link(connect=(f"tcp/127.0.0.1:{ros_port}",), node="zoffload_edge"),
                          Ros2Names(world_frame="odom", sensor_frame="velodyne"), map_period=0.3)
        svc.start(server.session)  # type: ignore[arg-type]
        try:
            wait_token(robot, KEYS.edge_alive("edge1"))
            pub = robot.declare_publisher(KEYS.scan("r1"))
            for seq in range(8):
                pub.put(scan_msg("r1", seq))
                wait_for(lambda: svc.counts["odom"] >= seq + 1, what=f"odometry {seq}")  # noqa: B023
            wait_for(lambda: svc.counts["maps"] >= 1, what="the map from the mapping service's queryable")
            late = rmw.FakeNode(ros, "rviz").subscription("/r1/map", "sensor_msgs/msg/PointCloud2", STORE,
                                                          latched=True)
            m = late.wait(1)[0][0]
            assert m.header.frame_id == "odom" and m.width > 1000
        finally:
            svc.stop()


def test_no_ros_router_is_a_session_error(free_port: int) -> None:
    from zoffload.runtime.errors import ZenohSessionError

    edge = open_session(listen_on(free_port))
    try:
        svc = Ros2Service(KEYS, Ros2Link(connect=(f"tcp/127.0.0.1:{free_tcp_port()}",)))
        with pytest.raises(ZenohSessionError, match="rmw_zenohd"):
            svc.start(edge)
    finally:
        edge.close()
