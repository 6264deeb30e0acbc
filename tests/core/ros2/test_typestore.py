"""Type hashes, vision_msgs and CDR with rosbags (what rmw_zenoh puts in a sample's payload)."""

from __future__ import annotations

import random

import numpy as np
import pytest

pytest.importorskip("rosbags")

from zoffload.ros2.typestore import MessageError, deserialize, msg_class, serialize, type_hash  # noqa: E402

# Cross-checked against ROS installs' output (ros2 topic info -v, share/*/msg/*.json, rcl tests)
HASHES = {
    "sensor_msgs/msg/PointCloud2": "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5",
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CompressedImage":
        "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",
    "nav_msgs/msg/Odometry": "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "tf2_msgs/msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    # not checked against a ROS install (vision_msgs 4.1.1 definitions; see README)
    "vision_msgs/msg/Detection2DArray":
        "RIHS01_214274120007f4a683866481336b70310268cfa107aebe9d594a6acf75bda968",
}


@pytest.mark.parametrize("msgtype", sorted(HASHES))
def test_type_hashes(msgtype: str) -> None:
    assert type_hash(msgtype) == HASHES[msgtype]


def test_unknown_type() -> None:
    with pytest.raises(MessageError):
        type_hash("nope_msgs/msg/Nothing")


def test_cdr_bytes_as_rmw_zenoh_writes_them() -> None:
    T = msg_class
    msg = T("sensor_msgs/msg/CompressedImage")(
        header=T("std_msgs/msg/Header")(stamp=T("builtin_interfaces/msg/Time")(sec=1, nanosec=2),
                                        frame_id="cam"),
        format="jpeg", data=np.array([0xFF, 0xD8, 0xFF], np.uint8))
    raw = serialize(msg, "sensor_msgs/msg/CompressedImage")
    assert raw.hex() == "0001000001000000020000000400000063616d00050000006a7065670000000003000000ffd8ff"
    back = deserialize(raw, "sensor_msgs/msg/CompressedImage")
    assert back.format == "jpeg" and back.data.tolist() == [0xFF, 0xD8, 0xFF]


def test_hostile_payloads_raise_message_error_only() -> None:
    T = msg_class
    msg = T("std_msgs/msg/String")(data="hello " * 20)
    good = serialize(msg, "std_msgs/msg/String")
    rng = random.Random(1)
    cases = [b"", b"\x00\x01", b"\x01\x00\x00\x00" + good[4:], good[: len(good) // 2], good[:-6]]
    for _ in range(300):
        b = bytearray(good)
        for _ in range(rng.randint(1, 4)):
            b[rng.randrange(4, len(b))] = rng.randrange(256)
        cases.append(bytes(b[: rng.randint(0, len(b))]))
    for data in cases:
        try:
            deserialize(data, "std_msgs/msg/String")
        except MessageError:
            pass
