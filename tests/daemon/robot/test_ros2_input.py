"""The robot fed by a ROS 2 topic: a stand-in rmw_zenoh LiDAR driver (tests/core/ros2/rmw.py)
publishes the simulator's scans as PointCloud2 at 10 Hz; the robot server in-process streams them
to a real edge, whose KISS-ICP trajectory is checked against the simulator's ground truth."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("kiss_icp")

from tests.core.ros2 import rmw  # noqa: E402
from tests.core.sources.bags import T0, cloud  # noqa: E402
from tests.daemon.robot.test_scans import run_robot  # noqa: E402
from tests.helpers import connect_to, listen_on, running_edge, wait_for  # noqa: E402
from zoffload.lab.eval.trajectory import trajectory_error  # noqa: E402
from zoffload.ros2.session import Ros2Link  # noqa: E402
from zoffload.runtime.config import DetectorSettings, EdgeSettings, RobotSettings  # noqa: E402
from zoffload.runtime.session import (
    free_tcp_port,  # noqa: E402
    has_subscribers,  # noqa: E402
)
from zoffload.sources.base import ScanFrame  # noqa: E402
from zoffload.sources.ros2_topic import Ros2ScanSource  # noqa: E402
from zoffload.sources.simulated import SimulatedSource  # noqa: E402

SIM = SimulatedSource(seed=0, sweep=True)


class Recording:
    """The live source, noting which driver scan (by its header stamp) each robot scan was."""

    def __init__(self, inner: Ros2ScanSource) -> None:
        self.inner = inner
        self.name, self.rate_hz, self.max_range, self.live = inner.name, inner.rate_hz, SIM.max_range, True
        self.sim_index: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self.inner)

    def read(self, index: int) -> ScanFrame:
        f = self.inner.read(index)
        assert f.stamp is not None
        self.sim_index[index] = int(round((f.stamp - T0) * SIM.rate_hz))
        return f


def test_robot_maps_a_ros2_lidar_topic(free_port: int) -> None:
    ros_port = free_tcp_port()
    ros = rmw.session(listen=ros_port)
    driver = rmw.FakeNode(ros, "velodyne_driver")
    pub = driver.publisher("/velodyne_points", "sensor_msgs/msg/PointCloud2")
    frames = [SIM.read(i) for i in range(80)]
    stop = threading.Event()

    def drive() -> None:  # a 10 Hz driver, header stamp = when the sweep was complete
        start = time.monotonic()
        for i, f in enumerate(frames):
            if stop.wait(max(0.0, start + i * 0.1 - time.monotonic())):
                return
            pub.publish(cloud(f.points, T0 + i / SIM.rate_hz, f.times))

    source = Recording(Ros2ScanSource("/velodyne_points", Ros2Link(connect=(f"tcp/127.0.0.1:{ros_port}",))))
    try:
        wait_for(lambda: has_subscribers(pub.pub), what="the robot subscribed")
        driving = threading.Thread(target=drive, daemon=True)
        driving.start()
        settings = RobotSettings(zenoh=connect_to(free_port), max_scans=40, scale_policy="fixed",
                                 scan_coding="q16z")
        with running_edge(EdgeSettings(zenoh=listen_on(free_port), detector=DetectorSettings(enabled=False))):
            robot = run_robot(settings, source)
    finally:
        stop.set()
        source.inner.close()
        driver.close()
        ros.close()
    m = robot.metrics()
    assert m["source"] == "ros2:/velodyne_points" and m["balanced"], m
    assert m["balance"]["produced"] == 40 and m["balance"]["acked"] >= 30, m["balance"]
    assert source.inner.drops.snapshot() == {}
    poses = dict(robot.ledger.poses)
    seqs = np.array(sorted(poses))
    idx = [source.sim_index[s] for s in seqs]
    assert len(set(idx)) == len(idx) and idx == sorted(idx)  # each driver scan at most once, in order
    gt = np.array([frames[i].gt_pose for i in idx])
    err = trajectory_error(seqs, np.array([poses[s] for s in seqs]), seqs, gt)
    assert err is not None and err.path_length > 2.0
    assert err.ate_rmse < 0.3, err
