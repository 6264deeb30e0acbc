"""The messages the edge publishes, built from zoffload's values."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("rosbags")

from zoffload.ros2 import messages  # noqa: E402
from zoffload.ros2.typestore import deserialize, serialize  # noqa: E402


def _rot(q: tuple[float, float, float, float]) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_quaternions_of_any_rotation() -> None:
    rng = np.random.default_rng(0)
    cases = [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]
    for _ in range(200):
        x, y, z, w = rng.normal(size=4) / 2
        n = float(np.sqrt(x * x + y * y + z * z + w * w))
        cases.append(_rot((x / n, y / n, z / n, w / n)))
    for r in cases:
        q = messages.quaternion(r)
        assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0
        np.testing.assert_allclose(_rot(q), r, atol=1e-9)


def test_ros_time() -> None:
    t = messages.ros_time(1700000000.25)
    assert (t.sec, t.nanosec) == (1700000000, 250_000_000)
    assert messages.stamp_seconds(t) == pytest.approx(1700000000.25)
    assert (messages.ros_time(float("nan")).sec, messages.ros_time(-1).sec) == (0, 0)


def test_odometry_and_velocity() -> None:
    prev = np.eye(4)
    cur = np.eye(4)
    cur[:3, :3] = _rot((0.0, 0.0, math.sin(0.05), math.cos(0.05)))  # 0.1 rad of yaw
    cur[:3, 3] = [1.0, 0.0, 0.0]
    lin, ang = messages.velocity(prev, cur, 0.5)
    np.testing.assert_allclose(ang, [0, 0, 0.2], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(lin), 2.0)
    msg = messages.odometry(cur, 1700000000.5, "robot1/odom", "robot1/lidar", lin, ang)
    back = deserialize(serialize(msg, "nav_msgs/msg/Odometry"), "nav_msgs/msg/Odometry")
    assert back.header.frame_id == "robot1/odom" and back.child_frame_id == "robot1/lidar"
    assert back.pose.pose.position.x == 1.0 and back.twist.twist.angular.z == pytest.approx(0.2)
    assert back.header.stamp.nanosec == 500_000_000
    assert messages.velocity(prev, cur, 0.0)[0].tolist() == [0, 0, 0]


def test_detections() -> None:
    boxes = np.array([[10, 20, 30, 60], [0, 0, 5, 5]], np.float32)
    msg = messages.detections(boxes, np.array([0.9, 0.5]), np.array([0, 2]), 3.0, "cam", {0: "person"})
    back = deserialize(serialize(msg, "vision_msgs/msg/Detection2DArray"), "vision_msgs/msg/Detection2DArray")
    d = back.detections[0]
    box = d.bbox
    assert (box.center.position.x, box.center.position.y, box.size_x, box.size_y) == (20, 40, 20, 40)
    hyp = d.results[0].hypothesis
    assert hyp.class_id == "person" and hyp.score == pytest.approx(0.9)
    assert back.detections[1].results[0].hypothesis.class_id == "2"


def test_transform_matches_pose() -> None:
    pose = np.eye(4)
    pose[:3, :3] = _rot(tuple(np.array([0.2, -0.4, 0.1, 0.9]) / np.linalg.norm([0.2, -0.4, 0.1, 0.9])))
    pose[:3, 3] = [1.0, -2.0, 0.5]
    t = messages.transform(pose, 2.0, "odom", "lidar")
    r = t.transform.rotation
    np.testing.assert_allclose(_rot((r.x, r.y, r.z, r.w)), pose[:3, :3], atol=1e-9)
    assert messages.tf_message([t]).transforms[0].child_frame_id == "lidar"
