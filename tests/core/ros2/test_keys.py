"""rmw_zenoh key expressions and graph tokens, checked against the examples and grammar of
rmw_zenoh_cpp's liveliness_utils.cpp (Jazzy 0.2.10 / Kilted 0.6.7)."""

from __future__ import annotations

import pytest

from zoffload.ros2.keys import (
    DEFAULT_QOS,
    LATCHED,
    SENSOR_DATA,
    Qos,
    Ros2NameError,
    dds_type_name,
    endpoint_token,
    graph_selector,
    node_token,
    parse_qos,
    parse_token,
    parse_topic_key,
    ros_type_name,
    topic_key,
    topic_name,
)

PC2_HASH = "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
ZID = "aac3178e146ba6f1fc6e6a4085e77f21"


def test_topic_keys_as_rmw_zenoh_builds_them() -> None:
    pc2 = "sensor_msgs/msg/PointCloud2"
    assert topic_key(0, "/points", pc2, PC2_HASH) == \
        f"0/points/sensor_msgs::msg::dds_::PointCloud2_/{PC2_HASH}"
    # inner slashes stay key separators; a relative name joins the namespace
    assert topic_key(3, topic_name("points", "/robot1"), pc2, PC2_HASH) == \
        f"3/robot1/points/sensor_msgs::msg::dds_::PointCloud2_/{PC2_HASH}"
    assert topic_key(0, "/points", pc2, None).endswith("PointCloud2_/*")  # any hash
    k = parse_topic_key(f"0/robot1/points/sensor_msgs::msg::dds_::PointCloud2_/{PC2_HASH}")
    assert (k.domain, k.topic, k.msgtype, k.type_hash) == (0, "/robot1/points", pc2, PC2_HASH)
    assert parse_topic_key("0/chatter/std_msgs::msg::dds_::String_/TypeHashNotSupported").topic == "/chatter"


def test_type_names() -> None:
    assert dds_type_name("tf2_msgs/msg/TFMessage") == "tf2_msgs::msg::dds_::TFMessage_"
    assert ros_type_name("vision_msgs::msg::dds_::Detection2DArray_") == "vision_msgs/msg/Detection2DArray"
    for bad in ("PointCloud2", "sensor_msgs/PointCloud2", "a/msg/b/c"):
        with pytest.raises(Ros2NameError):
            dds_type_name(bad)


@pytest.mark.parametrize("bad", ["", "/", "/a//b", "/a/", "/a b", "/a/*", "/a/$b", "/a/#", "/**"])
def test_names_ros_would_refuse_are_errors(bad: str) -> None:
    with pytest.raises(Ros2NameError):
        topic_name(bad)


def test_bad_keys_and_hashes() -> None:
    for key in ("points", "x/points/T_/RIHS01_ab", "0/sensor_msgs::msg::dds_::PointCloud2_/RIHS01_ab"):
        with pytest.raises(Ros2NameError):
            parse_topic_key(key)
    with pytest.raises(Ros2NameError):
        topic_key(0, "/points", "sensor_msgs/msg/PointCloud2", "RIHS01_xyz")
    with pytest.raises(Ros2NameError):
        topic_key(300, "/points", "sensor_msgs/msg/PointCloud2", PC2_HASH)


def test_tokens_match_the_documented_examples() -> None:
    assert node_token(0, ZID, 0, "/", "lidar_bridge") == f"@ros2_lv/0/{ZID}/0/0/NN/%/%/lidar_bridge"
    assert node_token(0, ZID, 4, "/robot1", "lidar_bridge") == \
        f"@ros2_lv/0/{ZID}/4/4/NN/%/%robot1/lidar_bridge"
    mp = endpoint_token(0, ZID, 4, 5, "MP", "/robot1", "lidar_bridge", "points",
                        "sensor_msgs/msg/PointCloud2", PC2_HASH, DEFAULT_QOS)
    # ROS writes "::,10:,:,:,," (defaults elided); we write the numbers out: same QoS
    assert mp == (f"@ros2_lv/0/{ZID}/4/5/MP/%/%robot1/lidar_bridge/%robot1%points/"
                  f"sensor_msgs::msg::dds_::PointCloud2_/{PC2_HASH}/1:2:1,10:,:,:,,")
    e = parse_token(mp)
    assert (e.kind, e.nid, e.eid, e.namespace, e.topic, e.qos) == ("MP", 4, 5, "/robot1", "/robot1/points",
                                                                    DEFAULT_QOS)
    assert graph_selector(0) == "@ros2_lv/0/**"


def _rmw_keyexpr_to_qos(text: str) -> tuple[str, ...]:
    """rmw_zenoh's parser (``keyexpr_to_qos``): 6 ':' parts, history 2, deadline 2, lifespan 2 and
    liveliness 3 ',' parts; each field empty or a number."""
    parts = text.split(":")
    assert len(parts) == 6
    assert [len(p.split(",")) for p in parts[2:]] == [2, 2, 2, 3]
    fields = [parts[0], parts[1], *parts[2].split(","), *parts[3].split(","), *parts[4].split(","),
              *parts[5].split(",")]
    assert all(f == "" or f.isdigit() for f in fields)
    return tuple(fields)


@pytest.mark.parametrize("qos", [DEFAULT_QOS, SENSOR_DATA, LATCHED, Qos(1, 1, 2, 1000)])
def test_our_qos_strings_parse_as_rmw_zenoh_parses_them(qos: Qos) -> None:
    fields = _rmw_keyexpr_to_qos(qos.keyexpr())
    assert fields[:4] == (str(qos.reliability), str(qos.durability), str(qos.history), str(qos.depth))
    assert parse_qos(qos.keyexpr()) == qos


def test_qos_strings_ros_writes() -> None:
    assert parse_qos("::,10:,:,:,,") == DEFAULT_QOS  # rclcpp default, rmw_zenoh >= 0.2.3
    assert parse_qos(":1:,1:,:,:,,") == LATCHED
    assert parse_qos("2::,5:,:,:,,") == SENSOR_DATA
    explicit = "1:2:1,10:9223372036,854775807:9223372036,854775807:1,9223372036,854775807"
    assert parse_qos(explicit) == DEFAULT_QOS
    for bad in ("", "1:2", "a:b:c,d:,:,:,,", "1:2:1:,:,:,,"):
        with pytest.raises(Ros2NameError):
            parse_qos(bad)


def test_malformed_tokens() -> None:
    for key in ("@ros2_lv/0/z/0/0/NN/%/%", "@other/0/z/0/0/NN/%/%/n", "@ros2_lv/x/z/0/0/NN/%/%/n",
                f"@ros2_lv/0/{ZID}/0/1/MP/%/%/n/%points/sensor_msgs::msg::dds_::PointCloud2_/{PC2_HASH}"):
        with pytest.raises(Ros2NameError):
            parse_token(key)
