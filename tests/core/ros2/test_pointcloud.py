"""PointCloud2 to numpy by the message's fields, for the layouts real drivers publish."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")

from tests.core.ros2.rmw import STORE, pointcloud  # noqa: E402
from zoffload.ros2.messages import header  # noqa: E402
from zoffload.ros2.pointcloud import PointCloudError, cloud_from_msg, cloud_msg, seconds  # noqa: E402
from zoffload.ros2.typestore import deserialize, serialize  # noqa: E402

F32, F64, U8, U16, U32 = 7, 8, 2, 4, 6
RNG = np.random.default_rng(0)
XYZ = RNG.uniform(-30, 30, (200, 3)).astype(np.float32)


def _records(dtype: np.dtype, n: int = 200) -> np.ndarray:
    rec = np.zeros(n, dtype)
    rec["x"], rec["y"], rec["z"] = XYZ[:n, 0], XYZ[:n, 1], XYZ[:n, 2]
    return rec


def _roundtrip(msg: Any) -> Any:
    """Through CDR, as it arrives from a ROS node."""
    return deserialize(serialize(msg, "sensor_msgs/msg/PointCloud2"), "sensor_msgs/msg/PointCloud2")


def test_ouster_t_uint32_nanoseconds() -> None:
    # ouster_ros PointOS: x y z pad, intensity @16, t @20, reflectivity @24, ring @26, ambient @28, range @32
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2", "<u2", "<u4"],
                   "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32], "itemsize": 48})
    rec = _records(dt)
    rec["t"] = np.arange(200) * 500_000  # 0 .. 99.5 ms
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 16, F32), ("t", 20, U32),
              ("reflectivity", 24, U16), ("ring", 26, U16), ("ambient", 28, U16), ("range", 32, U32)]
    cloud = cloud_from_msg(_roundtrip(pointcloud(STORE, fields, rec, 5.0)))
    np.testing.assert_array_equal(cloud.points, XYZ)
    assert cloud.time_field == "t" and cloud.times is not None
    np.testing.assert_allclose(cloud.times, np.arange(200) * 5e-4, atol=1e-12)


def test_velodyne_time_float32_seconds_negative() -> None:
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "time"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"], "offsets": [0, 4, 8, 16, 20, 24],
                   "itemsize": 32})
    rec = _records(dt)
    rec["time"] = np.linspace(-0.1, 0.0, 200)
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 16, F32), ("ring", 20, U16),
              ("time", 24, F32)]
    cloud = cloud_from_msg(pointcloud(STORE, fields, rec, 5.0))
    assert cloud.times is not None
    np.testing.assert_allclose(cloud.times, np.linspace(0, 0.1, 200), atol=1e-7)


@pytest.mark.parametrize("scale", [1.0, 1e9], ids=["hesai_seconds", "livox_nanoseconds"])
def test_unaligned_float64_timestamp_absolute(scale: float) -> None:
    # Hesai: x y z intensity, ring u16 @16, timestamp f64 @18, point_step 26 (unaligned float64);
    # Livox: tag u8 @16, line u8 @17, timestamp f64 @18 in absolute nanoseconds
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "timestamp"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f8"], "offsets": [0, 4, 8, 12, 16, 18],
                   "itemsize": 26})
    rec = _records(dt)
    rec["timestamp"] = (1.7e9 + np.arange(200) * 5e-4) * scale
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 12, F32), ("ring", 16, U16),
              ("timestamp", 18, F64)]
    cloud = cloud_from_msg(_roundtrip(pointcloud(STORE, fields, rec, 1.7e9)))
    np.testing.assert_array_equal(cloud.points, XYZ)
    assert cloud.times is not None
    np.testing.assert_allclose(cloud.times, np.arange(200) * 5e-4, atol=1e-6)


def test_big_endian_organized_padded_rows_with_nan_and_zero_points() -> None:
    dt = np.dtype({"names": ["x", "y", "z", "offset_time"], "formats": [">f4", ">f4", ">f4", ">u4"],
                   "offsets": [0, 4, 8, 12], "itemsize": 16})
    rec = _records(dt)
    rec["offset_time"] = np.arange(200) * 1000
    rec["x"][5] = np.nan
    rec["x"][6] = rec["y"][6] = rec["z"][6] = 0.0  # "no return"
    rows = rec.view(np.uint8).reshape(10, 20 * 16)
    padded = np.zeros((10, 20 * 16 + 8), np.uint8)  # 8 bytes of padding per row
    padded[:, : 20 * 16] = rows
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("offset_time", 12, U32)]
    msg = pointcloud(STORE, fields, rec, 5.0, height=10, bigendian=True, row_step=20 * 16 + 8,
                     data=padded.reshape(-1))
    cloud = cloud_from_msg(_roundtrip(msg))
    keep = np.ones(200, bool)
    keep[[5, 6]] = False
    np.testing.assert_array_equal(cloud.points, XYZ[keep])
    assert cloud.dropped == 2 and cloud.times is not None and len(cloud.times) == 198
    np.testing.assert_allclose(cloud.times, (np.arange(200) * 1e-6)[keep])


def test_without_time_field_and_unknown_type_of_an_unused_field() -> None:
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("rgb", 12, 42)]  # 42: not a datatype
    cloud = cloud_from_msg(pointcloud(STORE, fields, _records(dt), 5.0))
    assert cloud.times is None and cloud.time_field is None and len(cloud.points) == 200


@pytest.mark.parametrize("case", ["no_xyz", "unknown_datatype", "truncated", "offset_beyond_step",
                                  "short_row_step", "huge"])
def test_unreadable_clouds_are_clear_errors(case: str) -> None:
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32)]
    rec = _records(dt)
    kwargs: dict[str, object] = {}
    if case == "no_xyz":
        fields = [("a", 0, F32), ("b", 4, F32), ("z", 8, F32)]
    elif case == "unknown_datatype":
        fields = [("x", 0, 9), ("y", 4, F32), ("z", 8, F32)]
    elif case == "truncated":
        kwargs["data"] = rec.view(np.uint8).reshape(-1)[:-5]
    elif case == "offset_beyond_step":
        fields = [("x", 0, F32), ("y", 4, F32), ("z", 10, F32)]
    elif case == "short_row_step":
        kwargs["row_step"] = 100
    msg = pointcloud(STORE, fields, rec, 5.0, **kwargs)  # type: ignore[arg-type]
    if case == "huge":
        msg.height, msg.width = 100_000, 100_000  # claims 1e10 points over 2400 bytes
    with pytest.raises(PointCloudError, match={"no_xyz": "without x/y", "unknown_datatype": "datatype 9",
                                               "truncated": "truncated", "offset_beyond_step": "offset 10",
                                               "short_row_step": "row_step", "huge": "at most"}[case]):
        cloud_from_msg(msg)


def test_cloud_msg_round_trip() -> None:
    msg = cloud_msg(XYZ, header(12.5, "map"), {"t": np.linspace(0, 0.1, 200)})
    back = _roundtrip(msg)
    assert [f.name for f in back.fields] == ["x", "y", "z", "t"] and back.point_step == 16
    assert back.header.frame_id == "map" and back.header.stamp.sec == 12
    cloud = cloud_from_msg(back)
    np.testing.assert_array_equal(cloud.points, XYZ)
    assert cloud.times is not None
    np.testing.assert_allclose(cloud.times, np.linspace(0, 0.1, 200), atol=1e-7)


def test_seconds_rule() -> None:
    assert seconds(np.array([3, 1, 2], np.uint32)).tolist() == [2e-9, 0.0, 1e-9]
    np.testing.assert_allclose(seconds(np.array([-0.1, 0.0])), [0.0, 0.1])
    np.testing.assert_allclose(seconds(np.array([1.7e18, 1.7e18 + 1e8])), [0.0, 0.1])
