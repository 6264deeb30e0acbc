"""ROS 2 in and out through the real daemons, as processes: the robot fed by a ROS 2 topic (a
stand-in rmw_zenoh driver) and by a bag of the real KITTI-360 scans; the edge publishing to ROS 2."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("kiss_icp")

from tests.core.ros2 import rmw  # noqa: E402
from tests.core.sources.bags import T0, cloud, scan_bag  # noqa: E402
from tests.helpers import KEYS, client, wait_for, wait_token  # noqa: E402
from tests.system.procs import Proc, edge_args, script, session_args, start_edge  # noqa: E402
from zoffload.mapping.mapper import RobotMapper, mapper_voxel_size  # noqa: E402
from zoffload.ros2.keys import parse_token  # noqa: E402
from zoffload.ros2.typestore import typestore  # noqa: E402
from zoffload.runtime.session import free_tcp_port  # noqa: E402
from zoffload.sources import open_scan_source  # noqa: E402
from zoffload.sources.simulated import SimulatedSource  # noqa: E402

pytestmark = pytest.mark.system
EDGE_SERVER = Path(__file__).resolve().parents[2] / "zoffload" / "edge" / "server.py"


def ros_config(tmp_path: Path, port: int) -> Path:
    """A Zenoh session config for the ROS side, given as rmw_zenoh takes one
    (``ZENOH_SESSION_CONFIG_URI``): a client of the "ROS machine" on ``port``."""
    path = tmp_path / "ros_session.json5"
    path.write_text(f'{{mode: "client", connect: {{endpoints: ["tcp/127.0.0.1:{port}"]}}, '
                    "scouting: {multicast: {enabled: false}}, transport: {shared_memory: {enabled: false}}}")
    return path


def test_robot_process_from_a_ros2_topic(free_port: int, tmp_path: Path,
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    ros_port = free_tcp_port()
    ros = rmw.session(listen=ros_port)
    driver = rmw.FakeNode(ros, "velodyne_driver")
    pub = driver.publisher("/velodyne_points", "sensor_msgs/msg/PointCloud2")
    sim = SimulatedSource(seed=0)
    stop = threading.Event()

    def drive() -> None:
        k = 0
        while not stop.wait(0.1):
            f = sim.read(k % len(sim))
            pub.publish(cloud(f.points, T0 + k * 0.1))
            k += 1

    monkeypatch.setenv("ZENOH_SESSION_CONFIG_URI", str(ros_config(tmp_path, ros_port)))
    monkeypatch.setenv("ROS_DOMAIN_ID", "0")
    driving = threading.Thread(target=drive, daemon=True)
    try:
        with client(free_port) as s:
            edge = start_edge(s, edge_args(free_port), tmp_path / "edge.log")
            try:
                robot = Proc(script("zoffload-robot") + session_args(connect=free_port)
                             + ["--scans", "ros2:/velodyne_points", "--max-scans", "25", "--out",
                                str(tmp_path / "robot")], tmp_path / "robot.log")
                # the robot appears in the ROS graph as a node subscribing to the topic
                wait_for(lambda: any(parse_token(t).kind == "MS" and parse_token(t).node == "zoffload_robot"
                                     for t in rmw.graph(ros, 0, 0.5)), 60, "the robot's subscription token")
                driving.start()
                assert robot.wait(120) == 0, robot.text()
            finally:
                assert edge.sigint() == 0, edge.text()
    finally:
        stop.set()
        if driving.is_alive():
            driving.join(5)
        driver.close()
        ros.close()
    metrics = json.loads((tmp_path / "robot" / "robot_metrics.json").read_text())
    assert metrics["source"] == "ros2:/velodyne_points"
    assert metrics["balanced"] and metrics["balance"]["produced"] == 25 and metrics["balance"]["acked"] >= 20
    # the driver publishes every 0.1 s plus its own work: the policy judges lateness by that real
    # period (at the nominal 0.1 s every scan read as late and the robot cut and paced its scans)
    assert metrics["sensor_period_s"]["used"] >= 0.1


@pytest.mark.realdata
def test_kitti360_bag_through_the_daemons_maps_as_the_folder(kitti_dir: Path, free_port: int,
                                                              tmp_path: Path) -> None:
    n = 15
    folder = open_scan_source(str(kitti_dir))
    scans = [folder.read(i).points for i in range(n)]
    bag = scan_bag(tmp_path / "kitti360_bag", [(p, None) for p in scans], storage="mcap")
    with client(free_port) as s:
        edge = start_edge(s, edge_args(free_port, "--no-detector"), tmp_path / "edge.log")
        try:
            # raw float32 points, every scan, slow enough for the edge: the edge gets the bag's bits
            robot = Proc(script("zoffload-robot") + session_args(connect=free_port)
                         + ["--scans", f"bag:{bag}", "--scale-policy", "fixed", "--voxel", "0",
                            "--scan-coding", "f32", "--rate", "2", "--out", str(tmp_path / "robot")],
                         tmp_path / "robot.log")
            assert robot.wait(180) == 0, robot.text()
        finally:
            assert edge.sigint() == 0, edge.text()
    metrics = json.loads((tmp_path / "robot" / "robot_metrics.json").read_text())
    assert metrics["source"].startswith("bag:") and metrics["balance"]["produced"] == n
    poses = np.load(tmp_path / "robot" / "robot_poses.npz")
    seqs, edge_poses = poses["acked_seqs"], poses["acked_poses"]
    assert len(seqs) >= n - 2, metrics["balance"]
    # the folder's scans registered directly, the same scans in the same order
    mapper = RobotMapper(voxel_size=mapper_voxel_size(100.0, 0.07), max_range=100.0)
    for seq in seqs:
        mapper.register(int(seq), scans[int(seq)])
    np.testing.assert_allclose(edge_poses, mapper.trajectory()[1], atol=1e-4)
    assert np.linalg.norm(edge_poses[-1][:3, 3]) > 3.0


@pytest.mark.skipif("ros2_service" not in EDGE_SERVER.read_text(),
                    reason="edge/server.py does not start the ROS 2 output (zoffload.edge.ros2) yet")
def test_edge_process_publishes_to_ros2(free_port: int, tmp_path: Path) -> None:
    store = typestore()
    ros_port = free_tcp_port()
    ros = rmw.session(listen=ros_port)
    viewer = rmw.FakeNode(ros, "rviz")
    odom = viewer.subscription("/robot1/odom", "nav_msgs/msg/Odometry", store)
    try:
        with client(free_port) as s:
            edge = start_edge(s, edge_args(free_port, "--ros2.enabled", "--ros2.connect",
                                           f"tcp/127.0.0.1:{ros_port}", "--ros2.map-period", "0.5"),
                              tmp_path / "edge.log")
            try:
                wait_for(lambda: any(parse_token(t).node == "zoffload_edge" for t in rmw.graph(ros, 0, 0.5)),
                         60, "the edge's node in the ROS graph")
                robot = Proc(script("zoffload-robot") + session_args(connect=free_port)
                             + ["--max-scans", "30"], tmp_path / "robot.log")
                wait_token(s, KEYS.robot_alive("robot1"))
                assert robot.wait(120) == 0, robot.text()
                got = odom.wait(20)
                time.sleep(1.0)  # a map period
                late = rmw.FakeNode(ros, "rviz_late").subscription(
                    "/robot1/map", "sensor_msgs/msg/PointCloud2", store, latched=True)
                m = late.wait(1)[0][0]
            finally:
                assert edge.sigint() == 0, edge.text()
    finally:
        viewer.close()
        ros.close()
    assert len(got) >= 20 and got[-1][0].header.frame_id == "robot1/odom"
    assert got[-1][0].pose.pose.position.x != 0.0
    assert m.header.frame_id == "robot1/odom" and m.width > 1000
