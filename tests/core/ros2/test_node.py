"""A zoffload ROS 2 node against stand-ins of rmw_zenoh nodes (tests/core/ros2/rmw.py), over Zenoh on
loopback: tokens, attachments, CDR, late joiners of a latched topic, any type hash."""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")

from tests.core.ros2 import rmw  # noqa: E402
from tests.helpers import wait_for  # noqa: E402
from zoffload.ros2.attachment import Attachment  # noqa: E402
from zoffload.ros2.keys import LATCHED, parse_token  # noqa: E402
from zoffload.ros2.node import Ros2Node, Tally  # noqa: E402
from zoffload.ros2.session import open_ros_session  # noqa: E402
from zoffload.ros2.typestore import msg_class, typestore  # noqa: E402
from zoffload.runtime.session import has_subscribers  # noqa: E402


@pytest.fixture
def ros_graph(free_port: int) -> Iterator[tuple[object, object]]:
    """The "ROS machine" (a peer listening, like a router) and zoffload's client session."""
    ros = rmw.session(listen=free_port)
    ours = open_ros_session("client", [f"tcp/127.0.0.1:{free_port}"])
    try:
        yield ros, ours
    finally:
        ours.close()
        ros.close()


def _string(text: str) -> object:
    return msg_class("std_msgs/msg/String")(data=text)


def test_publisher_tokens_attachment_and_cdr(ros_graph: tuple) -> None:
    ros, ours = ros_graph
    node = Ros2Node(ours, "zoffload_edge", domain_id=7)
    pub = node.publisher("/robot1/chatter", "std_msgs/msg/String")
    listener = rmw.FakeNode(ros, "listener", domain=7)
    sub = listener.subscription("/robot1/chatter", "std_msgs/msg/String", rmw.STORE)
    # the graph as a ROS node reads it: our node and our publisher, grouped by (zid, nid)
    wait_for(lambda: any("/MP/" in t for t in rmw.graph(ros, 7, 0.5)), what="our MP token")
    tokens = [parse_token(t) for t in rmw.graph(ros, 7) if f"/{ours.zid()}/" in t]
    nn = next(e for e in tokens if e.kind == "NN")
    mp = next(e for e in tokens if e.kind == "MP")
    assert (nn.node, nn.namespace, nn.nid, nn.eid) == ("zoffload_edge", "/", node.nid, node.nid)
    assert (mp.nid, mp.topic, mp.msgtype) == (node.nid, "/robot1/chatter", "std_msgs/msg/String")
    assert mp.type_hash == rmw.STORE.hash_rihs01("std_msgs/msg/String")
    wait_for(lambda: has_subscribers(pub._pub), what="the ROS subscriber matched")
    t0 = time.time_ns()
    for i in range(3):
        pub.publish(_string(f"hello {i}"))
    got = sub.wait(3)
    assert [m.data for m, _, _ in got] == ["hello 0", "hello 1", "hello 2"]
    for i, (_, att, key) in enumerate(got):
        seq, stamp, n, gid = struct.unpack("<qqB16s", att)
        assert len(att) == 33 and n == 16 and seq == i + 1 and gid == pub.gid
        assert t0 <= stamp <= time.time_ns()
        assert key == pub.key
    node.close()
    wait_for(lambda: not any(f"/{ours.zid()}/" in t for t in rmw.graph(ros, 7, 0.5)), what="tokens gone")


def test_latched_topic_reaches_a_late_joining_ros_subscriber(ros_graph: tuple) -> None:
    ros, ours = ros_graph
    node = Ros2Node(ours, "zoffload_edge")
    pub = node.publisher("/map_text", "std_msgs/msg/String", LATCHED)
    pub.publish(_string("old"))
    pub.publish(_string("the map"))
    time.sleep(0.3)
    # a subscriber that joins afterwards, configured as rmw_zenoh's TRANSIENT_LOCAL subscriptions
    late = rmw.FakeNode(ros, "rviz").subscription("/map_text", "std_msgs/msg/String", rmw.STORE, latched=True)
    got = late.wait(1)
    assert [m.data for m, _, _ in got] == ["the map"]
    seq, _, _, gid = struct.unpack("<qqB16s", got[0][1])
    assert seq == 2 and gid == pub.gid
    token = next(parse_token(t) for t in rmw.graph(ros) if "/MP/" in t and f"/{ours.zid()}/" in t)
    assert token.qos == LATCHED
    node.close()


def test_subscription_any_hash_and_drops(ros_graph: tuple) -> None:
    ros, ours = ros_graph
    got: list[tuple[bytes, Attachment, str]] = []
    drops = Tally(__import__("logging").getLogger("test"))
    node = Ros2Node(ours, "zoffload_robot")
    node.subscription("/chatter", "std_msgs/msg/String",
                      lambda cdr, att, key: got.append((cdr, att, key.type_hash)), on_drop=drops)
    driver = rmw.FakeNode(ros, "talker")
    other_hash = "RIHS01_" + "ab" * 32  # a newer revision of the type
    pubs = [driver.publisher("/chatter", "std_msgs/msg/String"),
            driver.publisher("/chatter", "std_msgs/msg/String", type_hash=other_hash)]
    wait_for(lambda: any("/MS/" in t and f"/{ours.zid()}/" in t for t in rmw.graph(ros, 0, 0.5)),
             what="our MS token")
    wait_for(lambda: all(has_subscribers(p.pub) for p in pubs), what="matched")
    raw = bytes(rmw.STORE.serialize_cdr(_string("x"), "std_msgs/msg/String"))
    pubs[0].put_cdr(raw)
    pubs[1].put_cdr(raw)
    pubs[0].put_cdr(raw, attachment=None)  # as zenoh-pico or a bridge might: rmw_zenoh drops it
    pubs[0].put_cdr(raw, attachment=b"\x01\x02")
    wait_for(lambda: len(got) == 2 and sum(drops.counts.values()) == 2, what="two samples, two drops")
    assert {h for _, _, h in got} == {rmw.STORE.hash_rihs01("std_msgs/msg/String"), other_hash}
    assert drops.snapshot() == {"no_attachment": 1, "bad_attachment": 1}
    assert got[0][1].seq == 1 and got[0][0] == raw
    node.close()


def test_typestore_is_shared_and_thread_safe() -> None:
    stores: list[Any] = []
    threads = [threading.Thread(target=lambda: stores.append(typestore())) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len({id(s) for s in stores}) == 1
    assert "vision_msgs/msg/Detection2DArray" in stores[0].types
    assert np.dtype("u1")  # numpy present for the messages' arrays
