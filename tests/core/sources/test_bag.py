"""Bags as scan and image sources: rosbag2 (mcap, sqlite3) and ROS 1, written here with rosbags."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from tests.core.sources.bags import PC2, STORE, T0, cloud, scan_bag, write_bag  # noqa: E402
from zoffload.sources import ScanSourceError, open_scan_source  # noqa: E402
from zoffload.sources.bag import BagScanSource  # noqa: E402
from zoffload.sources.base import ReplayClock, replay_order, split_bag_spec  # noqa: E402
from zoffload.sources.simulated import SimulatedSource  # noqa: E402

SIM = SimulatedSource(seed=0, sweep=True)
FRAMES = [SIM.read(i) for i in range(6)]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3", "ros1"])
def test_scans_times_stamps_and_rate_round_trip(tmp_path: Path, storage: str) -> None:
    path = scan_bag(tmp_path / "run", [(f.points, f.times) for f in FRAMES], storage=storage)
    src = open_scan_source(f"bag:{path}")
    assert isinstance(src, BagScanSource) and len(src) == 6 and src.rate_hz == pytest.approx(10.0)
    for i in (0, 1, 5, 2, 0):  # forwards, then back (a ping-pong replay or a loop restarting)
        f = src.read(i)
        np.testing.assert_array_equal(f.points, FRAMES[i].points)
        want = FRAMES[i].times
        assert f.times is not None and want is not None
        np.testing.assert_allclose(f.times, want - want.min(), atol=1e-9)
        assert f.stamp == pytest.approx(T0 + i / 10.0)
    src.close()


def test_topic_choice_and_clear_errors(tmp_path: Path) -> None:
    pts = FRAMES[0].points
    T = STORE.types
    text = T["std_msgs/msg/String"](data="hi")
    path = write_bag(tmp_path / "two", [("/a", PC2, cloud(pts, T0)), ("/b", PC2, cloud(pts, T0)),
                                        ("/chatter", "std_msgs/msg/String", text)])
    with pytest.raises(ScanSourceError, match="several .*PointCloud2 topics.*bag:PATH:/TOPIC"):
        open_scan_source(f"bag:{path}")
    assert BagScanSource(path, "/b").topic == "/b"
    with pytest.raises(ScanSourceError, match="no topic /c in the bag.*/a \\(sensor_msgs/msg/PointCloud2\\)"):
        open_scan_source(f"bag:{path}:/c")
    with pytest.raises(ScanSourceError, match="/chatter is std_msgs/msg/String"):
        open_scan_source(f"bag:{path}:/chatter")
    only_text = write_bag(tmp_path / "text", [("/chatter", "std_msgs/msg/String", text)])
    with pytest.raises(ScanSourceError, match="no sensor_msgs/msg/PointCloud2 topics"):
        open_scan_source(f"bag:{only_text}")
    with pytest.raises(ScanSourceError, match="does not exist"):
        open_scan_source(f"bag:{tmp_path / 'nope'}")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ScanSourceError, match="metadata.yaml"):
        open_scan_source(f"bag:{tmp_path / 'empty'}")
    # the .mcap file inside a rosbag2 folder names the folder
    assert len(open_scan_source(f"bag:{next(path.glob('*.mcap'))}:/a")) == 1


def test_unreadable_messages_are_counted_drops(tmp_path: Path) -> None:
    bad = cloud(FRAMES[0].points, T0)
    bad.fields = bad.fields[1:]  # no x
    path = write_bag(tmp_path / "bad", [("/p", PC2, cloud(FRAMES[0].points, T0)), ("/p", PC2, bad),
                                        ("/p", PC2, cloud(FRAMES[2].points, T0))])
    src = BagScanSource(path)
    assert len(src.read(1).points) == 0 and src.drops.snapshot() == {"bad_cloud": 1}
    np.testing.assert_array_equal(src.read(2).points, FRAMES[2].points)


def test_replay_clock_follows_recorded_stamps() -> None:
    clock = ReplayClock(start=100.0, period=0.1)
    dues = [clock.due(s) for s in (5.0, 5.1, 5.35, 5.45, 5.0, 60.0, None)]
    # one period first; then the recorded gaps; a step back or a gap over 10 s: one period
    np.testing.assert_allclose(dues, [100.1, 100.2, 100.45, 100.55, 100.65, 100.75, 100.85])
    assert ReplayClock(0.0, 0.1, live=True).due(5.0) == -np.inf
    slow = ReplayClock(start=0.0, period=0.5, scale=5.0)  # a 10 Hz recording replayed at 2 Hz
    np.testing.assert_allclose([slow.due(s) for s in (5.0, 5.1, 5.3)], [0.5, 1.0, 2.0])
    # a reading that could not be read keeps its slot: a bag's next one as far as recorded, a
    # file's one period on
    slow = ReplayClock(start=0.0, period=0.5, scale=5.0)
    dues = [slow.due(5.0), slow.skip(), slow.due(5.2)]  # 5.1 unreadable
    assert dues[0] == 0.5 and dues[2] == pytest.approx(1.5)
    files = ReplayClock(start=0.0, period=0.1)
    assert [files.due(), files.skip(), files.due()] == [pytest.approx(0.1), None, pytest.approx(0.3)]


def test_bag_spec() -> None:
    assert split_bag_spec("/data/run") == (Path("/data/run"), None)
    assert split_bag_spec("/data/run.bag:/velodyne_points") == (Path("/data/run.bag"), "/velodyne_points")
    assert split_bag_spec("rel/run:/ns/points") == (Path("rel/run"), "/ns/points")


def test_pingpong_over_a_bag(tmp_path: Path) -> None:
    path = scan_bag(tmp_path / "run", [(f.points, None) for f in FRAMES[:4]])
    src = open_scan_source(f"bag:{path}")
    order = list(itertools.islice(replay_order(len(src), "pingpong"), 10))
    for i in order:
        np.testing.assert_array_equal(src.read(i).points, FRAMES[i].points)


def test_images_from_a_bag(tmp_path: Path) -> None:
    cv2 = pytest.importorskip("cv2")
    from zoffload.sources.images import open_image_source
    from zoffload.sources.ros2_images import BagImageSource

    T = STORE.types
    rng = np.random.default_rng(0)
    imgs = [rng.integers(0, 256, (8, 10, 3), dtype=np.uint8) for _ in range(3)]
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="cam")
    raw = [("/cam/image_raw", "sensor_msgs/msg/Image",
            T["sensor_msgs/msg/Image"](header=hdr, height=8, width=10, encoding="bgr8", is_bigendian=0,
                                       step=30, data=im.reshape(-1))) for im in imgs]
    png = [("/cam/image_raw/compressed", "sensor_msgs/msg/CompressedImage",
            T["sensor_msgs/msg/CompressedImage"](header=hdr, format="png",
                                                 data=cv2.imencode(".png", im)[1].reshape(-1)))
           for im in imgs]
    bad = T["sensor_msgs/msg/Image"](header=hdr, height=8, width=10, encoding="weird", is_bigendian=0,
                                     step=30, data=imgs[0].reshape(-1))
    bad_msg = ("/cam/image_raw", "sensor_msgs/msg/Image", bad)
    path = write_bag(tmp_path / "cams", raw[:1] + [bad_msg] + raw[1:] + png, rate_hz=30.0)
    with pytest.raises(Exception, match="several"):
        open_image_source(f"bag:{path}")
    src = open_image_source(f"bag:{path}:/cam/image_raw")
    assert isinstance(src, BagImageSource) and len(src) == 4 and src.rate_hz == pytest.approx(30.0, rel=1e-3)
    np.testing.assert_array_equal(src.read(0).image, imgs[0])
    np.testing.assert_array_equal(src.read(1).image, imgs[1])  # the bad one is skipped, and counted
    assert src.drops.snapshot() == {"bad_image": 1}
    comp = open_image_source(f"bag:{path}:/cam/image_raw/compressed")
    np.testing.assert_array_equal(comp.read(2).image, imgs[2])
    assert comp.read(2).stamp == pytest.approx(1.0)


def test_a_clock_more_than_a_period_behind_restarts() -> None:
    clock = ReplayClock(start=0.0, period=0.1)
    assert clock.due() == pytest.approx(0.1)
    assert not clock.behind(0.15)  # half a period late: kept
    assert clock.due() == pytest.approx(0.2)
    assert clock.behind(0.75)  # more than a period late: restarts there
    assert clock.due() == pytest.approx(0.85)
    assert not ReplayClock(0.0, 0.1, live=True).behind(100.0)
