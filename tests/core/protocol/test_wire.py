"""The wire codec: round trips, and every malformed input a WireError."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from zoffload.edge.detection import decode_image
from zoffload.protocol import wire


def scan(**over: object) -> wire.Scan:
    fields: dict[str, object] = dict(
        robot="r1", seq=7, send_stamp=12.5, capture_stamp=12.4, voxel=0.05, voxel_max=0.07,
        max_range=40.0, n_raw=100, points=np.arange(30, dtype=np.float32).reshape(10, 3),
    )
    fields.update(over)
    return wire.Scan(**fields)  # type: ignore[arg-type]


def test_scan_round_trip_keeps_every_field_and_array() -> None:
    msg = scan()
    out = wire.decode(wire.encode(msg), expect=wire.Scan)
    assert isinstance(out, wire.Scan)
    assert (out.robot, out.seq, out.send_stamp, out.voxel, out.n_raw) == ("r1", 7, 12.5, 0.05, 100)
    np.testing.assert_array_equal(out.points, msg.points)
    assert out.points.dtype == np.float32


def test_ack_map_pong_status_round_trip() -> None:
    ack = wire.ScanAck(robot="r", seq=1, send_stamp=1.0, status="ok", interarrival=float("nan"),
                       queue_time=0.001, proc_time=0.02, icp_time=0.015, map_points=5, keypoints=3, sigma=0.4,
                       pose=np.eye(4))
    out = wire.decode(wire.encode(ack))
    assert isinstance(out, wire.ScanAck) and np.isnan(out.interarrival)
    np.testing.assert_array_equal(out.pose, np.eye(4))
    m = wire.MapReply(robot="r", scans=2, points=np.zeros((4, 3), np.float32),
                      seqs=np.array([0, 1]), poses=np.stack([np.eye(4)] * 2))
    mo = wire.decode(wire.encode(m))
    assert isinstance(mo, wire.MapReply) and mo.poses.shape == (2, 4, 4)
    st = wire.decode(wire.encode(wire.Status(source="edge", id="e", stamp=3.0, values={"x": 2})))
    assert isinstance(st, wire.Status) and st.values == {"x": 2}
    assert isinstance(wire.decode(wire.encode(wire.Pong(edge="e", stamp=1.5))), wire.Pong)


def test_scan_payload_is_raw_bytes_not_per_element() -> None:
    pts = np.random.default_rng(0).random((50_000, 3), dtype=np.float32)
    data = wire.encode(scan(points=pts))
    assert len(data) < pts.nbytes + 300


def _tamper(**changes: object) -> bytes:
    obj = msgpack.unpackb(wire.encode(scan()), raw=False)
    for k, v in changes.items():
        if v is None:
            del obj[k]
        else:
            obj[k] = v
    return msgpack.packb(obj, use_bin_type=True)


@pytest.mark.parametrize(
    "payload, reason",
    [
        (b"\xc1\xc1garbage", "not msgpack"),
        (msgpack.packb([1, 2, 3]), "not a message map"),
        (_tamper(v=99), "codec version"),
        (_tamper(t="teleport"), "unknown message type"),
        (_tamper(seq=None), "missing field 'seq'"),
        (_tamper(extra=1), "unknown fields"),
        (_tamper(seq="seven"), "field 'seq'"),
        (_tamper(seq=True), "field 'seq'"),
        (_tamper(points={"nd": "<f4", "shape": [10, 3], "data": b"\x00" * 7}), "bytes for shape"),
        (_tamper(points={"nd": "<f8", "shape": [1, 3], "data": b"\x00" * 24}), "dtype"),
        (_tamper(points={"nd": "<f4", "shape": [2, 2], "data": b"\x00" * 16}), "shape"),
        (_tamper(points={"nd": "|O", "shape": [1], "data": b"\x00" * 8}), "object"),
        (_tamper(points={"nd": "nope", "shape": [1], "data": b""}), "unknown dtype"),
        (_tamper(points=[1, 2, 3]), "not an encoded array"),
    ],
)
def test_malformed_payloads_raise_wire_error(payload: bytes, reason: str) -> None:
    with pytest.raises(wire.WireError, match=reason):
        wire.decode(payload)


def test_expect_rejects_other_message_types() -> None:
    with pytest.raises(wire.WireError, match="where 'scan_ack' is expected"):
        wire.decode(wire.encode(scan()), expect=wire.ScanAck)


def test_encode_checks_arrays() -> None:
    with pytest.raises(wire.WireError, match="dtype"):
        wire.encode(scan(points=np.zeros((3, 3), np.float64)))


def test_frame_and_detections_messages_round_trip() -> None:
    img = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    f = wire.Frame(robot="r", seq=3, send_stamp=1.0, capture_stamp=0.9, encoding="bgr8", width=6, height=4,
                   data=img.reshape(-1))
    back = wire.decode(wire.encode(f), expect=wire.Frame)
    assert isinstance(back, wire.Frame)
    np.testing.assert_array_equal(decode_image(back), img)
    d = wire.Detections(robot="r", seq=3, send_stamp=1.0, edge="e", model="m", status="ok",
                           infer_time=0.01, queue_time=0.0, batch=1, boxes=np.ones((2, 4), np.float32),
                           scores=np.ones(2, np.float32), classes=np.zeros(2, np.int32))
    assert wire.decode(wire.encode(d), expect=wire.Detections).classes.tolist() == [0, 0]


def test_peek_fields_reads_some_fields_of_one_message_type_and_nothing_else() -> None:
    scan = wire.Scan(robot="r1", seq=3, send_stamp=0.0, capture_stamp=0.0, voxel=0.1, voxel_max=0.1,
                     max_range=50.0, n_raw=2, points=np.zeros((2, 3), np.float32), epoch=7, edge="e2")
    data = wire.encode(scan)
    assert wire.peek_fields(data, "scan", ("edge", "epoch")) == {"edge": "e2", "epoch": 7}
    assert wire.peek_fields(memoryview(data), "scan", ("seq",)) == {"seq": 3}
    assert wire.peek_fields(data, "scan", ("nothing",)) == {}  # absent: left out
    assert wire.peek_fields(data, "frame", ("edge",)) is None  # another message type
    assert wire.peek_fields(data[: len(data) // 2], "scan", ("edge",)) is None  # broken off
    assert wire.peek_fields(b"\x92\x01\x02", "scan", ("edge",)) is None  # not a map
