"""Image sources (clips with moving ground truth, folders, video), monitors, offloading strategies,
and the frame/detections messages."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from zoffload.edge.detection import decode_image
from zoffload.policy.offload import EDGE, HOLD, LOCAL, OffloadState, make_strategy
from zoffload.protocol import wire
from zoffload.runtime.monitor import ByteRate, CpuMonitor, MovingAverage, RaplMonitor
from zoffload.sources.images import CocoClipSource, ImageSourceError, open_image_source

cv2 = pytest.importorskip("cv2")


def _still(tmp_path: Path, boxes: list[list[float]], w: int = 640, h: int = 480) -> Path:
    """A synthetic annotated still: white rectangles where the person boxes are."""
    img = np.zeros((h, w, 3), np.uint8)
    for x, y, bw, bh in boxes:
        img[int(y):int(y + bh), int(x):int(x + bw)] = 255
    cv2.imwrite(str(tmp_path / "a.png"), img)
    gt = {"images": [{"id": 1, "file_name": "a.png", "width": w, "height": h}],
          "annotations": [{"image_id": 1, "category_id": 1, "bbox": b} for b in boxes]}
    (tmp_path / "person_gt.json").write_text(json.dumps(gt))
    return tmp_path


def test_clip_boxes_follow_the_pixels(tmp_path: Path) -> None:
    src = CocoClipSource(_still(tmp_path, [[300, 200, 60, 120]]), size=(424, 240), frames_per_image=20)
    first, last = src.read(0), src.read(19)
    for frame in (first, last):
        assert frame.image.shape == (240, 424, 3)
        assert frame.gt_boxes is not None and len(frame.gt_boxes) == 1
        x1, y1, x2, y2 = frame.gt_boxes[0]
        inside = frame.image[int(y1) + 2:int(y2) - 2, int(x1) + 2:int(x2) - 2]
        assert inside.min() > 200  # the box covers the white rectangle ...
        ring = frame.image[int(y1) - 4:int(y2) + 4, int(x2) + 3:int(x2) + 6]
        assert ring.max() < 60  # ... and ends where it ends
    # the camera moved: the box moved and grew (zooming in)
    assert abs(first.gt_boxes[0][0] - last.gt_boxes[0][0]) > 5
    assert (last.gt_boxes[0][2] - last.gt_boxes[0][0]) > (first.gt_boxes[0][2] - first.gt_boxes[0][0])


def test_a_box_mostly_outside_the_crop_is_not_ground_truth(tmp_path: Path) -> None:
    src = CocoClipSource(_still(tmp_path, [[0, 200, 40, 80]]), size=(424, 240), frames_per_image=10,
                         zoom=(0.6, 0.6))
    counts = [len(src.boxes(i)) for i in range(10)]
    assert counts[0] == 1 and counts[-1] == 0  # the pan leaves the box behind


def test_image_folder_and_a_corrupt_image(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "0.png"), np.full((10, 12, 3), 7, np.uint8))
    (tmp_path / "1.png").write_bytes(b"\x89PNG broken")
    src = open_image_source(str(tmp_path))
    assert len(src) == 2 and src.read(0).image.shape == (10, 12, 3)
    with pytest.raises(ImageSourceError, match="not a readable image"):
        src.read(1)
    with pytest.raises(ImageSourceError, match="does not exist"):
        open_image_source(str(tmp_path / "nope"))


def test_video_file_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "v.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 12.0, (64, 48))
    for k in range(5):
        vw.write(np.full((48, 64, 3), 40 * k, np.uint8))
    vw.release()
    src = open_image_source(str(path))
    assert len(src) == 5 and src.rate_hz == pytest.approx(12.0)
    means = [src.read(k).image.mean() for k in range(5)]
    assert means == sorted(means) and means[-1] > 120
    assert src.read(1).image.mean() == pytest.approx(means[1], abs=1)  # seeking back works


@pytest.mark.realdata
def test_shared_coco_clips_have_moving_ground_truth(coco_dir: Path) -> None:
    src = open_image_source(f"coco-clips:{coco_dir}")
    assert isinstance(src, CocoClipSource) and len(src) == 50 * 50
    assert src.read(0).image.shape == (480, 848, 3)
    assert sum(len(src.boxes(i)) for i in range(0, len(src), 50)) >= 60


def test_moving_average_and_byte_rate() -> None:
    ma = MovingAverage(3)
    assert np.isnan(ma.value)
    for v in (1, 2, 3, 4, float("nan")):
        ma.add(v)
    assert ma.value == pytest.approx(3.0)
    counter = [0.0]
    rate = ByteRate(lambda: counter[0])
    time.sleep(0.2)
    counter[0] = 1e6
    mbps = rate.sample()
    assert 8e-6 * 1e6 / 0.5 < mbps < 8e-6 * 1e6 / 0.19  # 1 MB over ~0.2 s = ~40 Mbps


def test_cpu_monitor_sees_this_process_working() -> None:
    cpu = CpuMonitor()
    end = time.process_time() + 0.3
    while time.process_time() < end:
        pass
    system, proc = cpu.sample()
    assert proc > 30 and 0 < system <= 100


def test_rapl_reports_unavailable_rather_than_a_number(tmp_path: Path) -> None:
    missing = RaplMonitor(tmp_path / "no-powercap")
    assert not missing.available and np.isnan(missing.sample())
    # A fake powercap tree (this machine has no RAPL): the arithmetic of Δenergy / Δt
    zone = tmp_path / "intel-rapl:0"
    zone.mkdir()
    (zone / "energy_uj").write_text("1000000")
    fake = RaplMonitor(tmp_path)
    assert fake.available and np.isnan(fake.sample())
    time.sleep(0.1)
    (zone / "energy_uj").write_text("3000000")  # +2 J
    assert 5 < fake.sample() < 21


def _st(**kw: float) -> OffloadState:
    base = {"now": 0.0, "edge_available": True}
    base.update(kw)
    return OffloadState(**base)  # type: ignore[arg-type]


def test_fixed_ratio_is_algorithm_1() -> None:
    s = make_strategy("ratio:0.3")
    sides = [s.decide(_st()) for _ in range(100)]
    assert sides.count(EDGE) == 30
    assert sides[:4] == [EDGE, LOCAL, LOCAL, EDGE]  # offload while offloaded/total < r
    with pytest.raises(ValueError):
        make_strategy("ratio:1.5")
    with pytest.raises(ValueError):
        make_strategy("sometimes")


def test_thesis_rule_constraints_then_rtt() -> None:
    s = make_strategy("thesis", cpu_max=80, bw_max_mbps=100)
    s.on_local_result(0.05)
    s.on_edge_result(0.10)
    assert s.decide(_st()) == LOCAL  # local is faster
    assert s.decide(_st(cpu_percent=85)) == EDGE  # CPU bound first
    s.on_edge_result(0.01)
    s.on_edge_result(0.01)
    assert s.decide(_st()) == EDGE  # edge average 0.04 < 0.05
    assert s.decide(_st(mbps_out=120)) == LOCAL  # bandwidth bound
    assert s.decide(_st(edge_available=False)) == LOCAL  # no edge: local whatever the rule says


def test_frames_that_never_return_count_in_our_rule_but_not_in_the_thesis() -> None:
    """The thesis' failure under a cap: the few edge frames that return look fast."""
    thesis, ours = make_strategy("thesis"), make_strategy("dynamic", max_in_flight=10)
    for s in (thesis, ours):
        s.on_local_result(0.15)
        for _ in range(3):
            s.on_edge_result(0.08)  # the frames that made it
        for _ in range(7):
            s.on_edge_timeout(0.5)  # the ones the link dropped
    assert thesis.decide(_st()) == EDGE
    assert ours.decide(_st()) == LOCAL


def test_our_rule_sees_an_edge_that_stopped_answering() -> None:
    ours = make_strategy("dynamic", max_in_flight=5)
    ours.on_local_result(0.15)
    ours.on_edge_result(0.08)
    assert ours.decide(_st()) == EDGE
    assert ours.decide(_st(in_flight=1, oldest_in_flight_age=0.3)) == LOCAL  # already slower than local
    # window full: held back while local is the slower side ...
    assert ours.decide(_st(in_flight=5, oldest_in_flight_age=0.01)) == HOLD
    # ... detected locally when only the CPU bound sent it to the edge and local is faster
    cpu_bound = make_strategy("dynamic", cpu_max=90, max_in_flight=5)
    cpu_bound.on_local_result(0.03)
    cpu_bound.on_edge_result(0.04)
    assert cpu_bound.decide(_st(cpu_percent=95)) == EDGE
    assert cpu_bound.decide(_st(cpu_percent=95, in_flight=5, oldest_in_flight_age=0.01)) == LOCAL
    # while local, one frame in probe_every goes to the edge once nothing is in flight
    ours.on_edge_timeout(0.5)
    sides = [ours.decide(_st()) for _ in range(20)]
    assert sides.count(EDGE) == 2


def test_frame_and_detections_messages_round_trip() -> None:
    img = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    f = wire.Frame(robot="r", seq=3, send_stamp=1.0, capture_stamp=0.9, encoding="bgr8", width=6, height=4,
                   data=img.reshape(-1))
    back = wire.decode(wire.encode(f), expect=wire.Frame)
    assert isinstance(back, wire.Frame)
    np.testing.assert_array_equal(decode_image(back), img)
    d = wire.DetectionsMsg(robot="r", seq=3, send_stamp=1.0, edge="e", model="m", status="ok",
                           infer_time=0.01, queue_time=0.0, batch=1, boxes=np.ones((2, 4), np.float32),
                           scores=np.ones(2, np.float32), classes=np.zeros(2, np.int32))
    assert wire.decode(wire.encode(d), expect=wire.DetectionsMsg).classes.tolist() == [0, 0]  # type: ignore


def test_bad_frames_are_value_errors_not_crashes() -> None:
    def frame(**kw: object) -> wire.Frame:
        base = dict(robot="r", seq=0, send_stamp=0.0, capture_stamp=0.0, encoding="bgr8", width=6, height=4,
                    data=np.zeros(4 * 6 * 3, np.uint8))
        base.update(kw)
        return wire.Frame(**base)  # type: ignore[arg-type]

    with pytest.raises(ValueError, match="expected"):
        decode_image(frame(width=7))
    with pytest.raises(ValueError, match="undecodable JPEG"):
        decode_image(frame(encoding="jpeg", data=np.frombuffer(b"\xff\xd8garbage", np.uint8)))
    with pytest.raises(ValueError, match="unknown encoding"):
        decode_image(frame(encoding="png"))
    ok, buf = cv2.imencode(".jpg", np.zeros((4, 6, 3), np.uint8))
    assert decode_image(frame(encoding="jpeg", data=buf.ravel())).shape == (4, 6, 3)


def test_our_window_halves_on_losses_and_grows_back() -> None:
    ours = make_strategy("dynamic", max_in_flight=4)
    assert ours.flight_window == 4  # type: ignore[attr-defined]
    ours.on_local_result(0.5, service=0.5)
    ours.on_edge_result(0.1)
    ours.on_edge_timeout(0.5)
    assert ours.flight_window == 2  # type: ignore[attr-defined]
    ours.on_edge_timeout(0.5)
    assert ours.flight_window == 2  # type: ignore[attr-defined]  # never below two
    assert ours.decide(_st(in_flight=2, oldest_in_flight_age=0.05)) == HOLD  # local is slower
    for _ in range(8):
        ours.on_edge_result(0.1)
    assert ours.flight_window == 4  # type: ignore[attr-defined]
