"""The ROS 2 messages zoffload publishes, built from plain numpy values.

Stamps are ROS time: seconds since the Unix epoch split into ``sec`` and ``nanosec``. A pose is
zoffload's 4x4 sensor-to-world matrix; ROS wants a position and a unit quaternion (x, y, z, w).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from zoffload.ros2.typestore import msg_class


def ros_time(seconds: float) -> Any:
    """builtin_interfaces/Time of a wall-clock stamp (negative or non-finite: zero)."""
    Time = msg_class("builtin_interfaces/msg/Time")
    if not math.isfinite(seconds) or seconds < 0:
        return Time(sec=0, nanosec=0)
    sec = math.floor(seconds)
    ns = int(round((seconds - sec) * 1e9))  # the fraction alone: seconds * 1e9 would lose bits
    if ns >= 1_000_000_000:
        sec, ns = sec + 1, ns - 1_000_000_000
    return Time(sec=int(sec), nanosec=ns)


def stamp_seconds(stamp: Any) -> float:
    """A builtin_interfaces/Time back to float seconds."""
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def header(stamp: float, frame_id: str) -> Any:
    return msg_class("std_msgs/msg/Header")(stamp=ros_time(stamp), frame_id=frame_id)


def quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a 3x3 rotation matrix, w ≥ 0 (Shepperd's method: the largest of the four
    diagonal combinations is the pivot, so it is stable for every rotation)."""
    r = np.asarray(rotation, np.float64)
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 1e-300))
        q = (0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s)
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(max(1.0 + r[1, 1] - r[0, 0] - r[2, 2], 1e-300))
        q = ((r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s)
    else:
        s = 2.0 * math.sqrt(max(1.0 + r[2, 2] - r[0, 0] - r[1, 1], 1e-300))
        q = ((r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s)
    v = np.asarray(q)
    v = v / np.linalg.norm(v)
    if v[3] < 0:
        v = -v
    return float(v[0]), float(v[1]), float(v[2]), float(v[3])


def _pose(pose: np.ndarray) -> Any:
    T = msg_class
    x, y, z, w = quaternion(pose[:3, :3])
    return T("geometry_msgs/msg/Pose")(
        position=T("geometry_msgs/msg/Point")(x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3])),
        orientation=T("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w))


def _vector(v: np.ndarray) -> Any:
    return msg_class("geometry_msgs/msg/Vector3")(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def odometry(pose: np.ndarray, stamp: float, frame_id: str, child_frame_id: str,
             linear: np.ndarray | None = None, angular: np.ndarray | None = None) -> Any:
    """nav_msgs/Odometry: the pose in ``frame_id``, the twist (if known) in ``child_frame_id``;
    covariances unknown (zeros, as most odometry sources publish)."""
    T = msg_class
    cov = np.zeros(36, np.float64)
    twist = T("geometry_msgs/msg/Twist")(linear=_vector(np.zeros(3) if linear is None else linear),
                                         angular=_vector(np.zeros(3) if angular is None else angular))
    return T("nav_msgs/msg/Odometry")(
        header=header(stamp, frame_id), child_frame_id=child_frame_id,
        pose=T("geometry_msgs/msg/PoseWithCovariance")(pose=_pose(pose), covariance=cov),
        twist=T("geometry_msgs/msg/TwistWithCovariance")(twist=twist, covariance=cov.copy()))


def velocity(prev: np.ndarray, cur: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear and angular velocity between two poses ``dt`` seconds apart, in the later pose's
    frame (a twist's convention); zeros when ``dt`` is not positive."""
    if not dt > 0:
        return np.zeros(3), np.zeros(3)
    delta = np.linalg.inv(cur) @ prev  # the previous pose seen from the current one
    linear = -delta[:3, 3] / dt
    r = delta[:3, :3].T
    angle = math.acos(max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0)))
    if angle < 1e-12:
        return linear, np.zeros(3)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (2.0 * math.sin(angle))
    return linear, axis * angle / dt


def transform(pose: np.ndarray, stamp: float, frame_id: str, child_frame_id: str) -> Any:
    """geometry_msgs/TransformStamped: ``child_frame_id`` placed in ``frame_id`` by ``pose``."""
    T = msg_class
    x, y, z, w = quaternion(pose[:3, :3])
    return T("geometry_msgs/msg/TransformStamped")(
        header=header(stamp, frame_id), child_frame_id=child_frame_id,
        transform=T("geometry_msgs/msg/Transform")(
            translation=_vector(pose[:3, 3]), rotation=T("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w)))


def tf_message(transforms: list[Any]) -> Any:
    return msg_class("tf2_msgs/msg/TFMessage")(transforms=transforms)


def detections(boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, stamp: float, frame_id: str,
               labels: dict[int, str] | None = None) -> Any:
    """vision_msgs/Detection2DArray of boxes (x1, y1, x2, y2 pixels): each box's centre and size,
    one hypothesis (the class's label, or its number as text, and the score)."""
    T = msg_class
    labels = labels or {}
    zero_pose = T("geometry_msgs/msg/PoseWithCovariance")(pose=_pose(np.eye(4)), covariance=np.zeros(36))
    out = []
    for box, score, cls in zip(np.asarray(boxes, np.float64).reshape(-1, 4), np.asarray(scores).ravel(),
                               np.asarray(classes).ravel(), strict=True):
        x1, y1, x2, y2 = (float(v) for v in box)
        bbox = T("vision_msgs/msg/BoundingBox2D")(
            center=T("vision_msgs/msg/Pose2D")(
                position=T("vision_msgs/msg/Point2D")(x=(x1 + x2) / 2, y=(y1 + y2) / 2), theta=0.0),
            size_x=x2 - x1, size_y=y2 - y1)
        hyp = T("vision_msgs/msg/ObjectHypothesisWithPose")(
            hypothesis=T("vision_msgs/msg/ObjectHypothesis")(class_id=labels.get(int(cls), str(int(cls))),
                                                            score=float(score)),
            pose=zero_pose)
        out.append(T("vision_msgs/msg/Detection2D")(header=header(stamp, frame_id), results=[hyp],
                                                     bbox=bbox, id=""))
    return T("vision_msgs/msg/Detection2DArray")(header=header(stamp, frame_id), detections=out)
