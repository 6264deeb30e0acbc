"""Bags written by the tests themselves with rosbags' writers: rosbag2 (sqlite3 .db3, .mcap) and
ROS 1 .bag, of PointCloud2 scans (x, y, z, intensity float32, optional Ouster-style ``t``) and
images, recorded at ``rate_hz`` with header stamp = recorded time."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_JAZZY)
STORE1 = get_typestore(Stores.ROS1_NOETIC)
T0 = 1_700_000_000.0  # the first message's stamp [s]
PC2 = "sensor_msgs/msg/PointCloud2"


def cloud(points: np.ndarray, stamp: float, times: np.ndarray | None = None, frame: str = "velodyne") -> Any:
    T = STORE.types
    names = ["x", "y", "z", "intensity"] + (["t"] if times is not None else [])
    rec = np.zeros(len(points), [(n, "<u4" if n == "t" else "<f4") for n in names])
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    rec["intensity"] = 1.0
    if times is not None:
        rec["t"] = np.round((times - times.min()) * 1e9).astype(np.uint32)
    sec = int(stamp)
    return T[PC2](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=sec, nanosec=int(round((stamp - sec) * 1e9))), frame_id=frame),
        height=1, width=len(points),
        fields=[T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=6 if n == "t" else 7, count=1)
                for i, n in enumerate(names)],
        is_bigendian=False, point_step=4 * len(names), row_step=4 * len(names) * len(points),
        data=rec.view(np.uint8).reshape(-1), is_dense=True)


def write_bag(path: Path, messages: Iterable[tuple[str, str, Any]], rate_hz: float = 10.0,
              storage: str = "mcap") -> Path:
    """``messages``: (topic, type, message) in order, the i-th recorded at T0 + i / rate_hz.
    ``storage``: mcap, sqlite3 (rosbag2 folders) or ros1 (``path`` gets ``.bag``)."""
    items = list(messages)
    if storage == "ros1":
        path = path.with_suffix(".bag")
        with Writer1(path) as w:
            conns: dict[str, Any] = {}
            for i, (topic, msgtype, msg) in enumerate(items):
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, msgtype, typestore=STORE1)
                cdr = STORE.serialize_cdr(msg, msgtype)
                w.write(conns[topic], int((T0 + i / rate_hz) * 1e9), STORE.cdr_to_ros1(cdr, msgtype))
        return path
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer2(path, version=9, storage_plugin=plugin) as w:
        conns = {}
        for i, (topic, msgtype, msg) in enumerate(items):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=STORE)
            w.write(conns[topic], int((T0 + i / rate_hz) * 1e9), bytes(STORE.serialize_cdr(msg, msgtype)))
    return path


def scan_bag(path: Path, frames: list[tuple[np.ndarray, np.ndarray | None]], topic: str = "/velodyne_points",
             rate_hz: float = 10.0, storage: str = "mcap") -> Path:
    messages = ((topic, PC2, cloud(pts, T0 + i / rate_hz, t)) for i, (pts, t) in enumerate(frames))
    return write_bag(path, messages, rate_hz, storage)
