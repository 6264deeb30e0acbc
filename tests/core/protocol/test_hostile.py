"""Hostile input to the codec: anything raises ``WireError`` and nothing else, every field is
checked before anything is sized from it, and no forged length makes it allocate."""

from __future__ import annotations

import dataclasses
import math
import resource
import time

import msgpack
import numpy as np
import pytest
import zstandard

from tests.fuzzing import corpus, valid_messages
from zoffload.protocol import wire
from zoffload.protocol.coding import CodingError, decode_q16z, encode_q16z, times_from_u16, times_to_u16


def tamper(kind: str, **changes: object) -> bytes:
    obj = msgpack.unpackb(valid_messages()[kind], raw=False)
    obj.update(changes)
    return msgpack.packb(obj, use_bin_type=True)


def test_every_valid_message_round_trips() -> None:
    for kind, data in valid_messages().items():
        msg = wire.decode(data)
        assert wire.encode(msg) == data, kind
    scan = wire.decode(valid_messages()["scan_q16z_times"], expect=wire.Scan)
    pts, times = scan.cloud_and_times()
    assert pts.shape == (500, 3) and times is not None and times[0] == 0 and times[-1] == pytest.approx(0.1)


def test_twenty_thousand_mutations_raise_wire_error_only() -> None:
    decoded = rejected = 0
    start = time.monotonic()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for data in corpus(seed=1, n=20_000):
        try:
            msg = wire.decode(data)
        except wire.WireError:
            rejected += 1
            continue
        decoded += 1
        if isinstance(msg, wire.Scan):  # the payload inside must not escape either
            try:
                msg.cloud_and_times()
            except wire.WireError:
                pass
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak) / 1024
    assert rejected > 15_000 and decoded > 100  # most are refused, the harmless ones pass
    assert grown_mb < 100, f"peak RSS grew {grown_mb:.0f} MB"
    assert time.monotonic() - start < 60


@pytest.mark.parametrize("kind, field, value, reason", [
    ("scan_f32", "max_range", math.inf, "max_range"),
    ("scan_f32", "max_range", 1e200, "outside"),
    ("scan_f32", "voxel", math.nan, "NaN"),
    ("scan_f32", "send_stamp", -math.inf, "outside"),
    ("scan_f32", "seq", 2**63, "outside"),
    ("scan_f32", "seq", -1, "outside"),
    ("scan_f32", "robot", "r" * 65, "not an id"),
    ("scan_f32", "robot", "a/b", "not an id"),
    ("scan_f32", "coding", "gzip", "not one of"),
    ("scan_f32", "n_raw", 10**12, "outside"),
    ("ack", "interarrival", math.inf, "outside"),
    ("ack", "status", "pwned", "not one of"),
    ("ack", "detail", "x" * 5000, "longer"),
    ("frame", "width", 0, "outside"),
    ("status", "values", {"x": math.inf}, "numbers"),
    ("status", "values", {str(i): 1.0 for i in range(2000)}, "at most"),
    ("attach_reply", "accepted", 1, "type int"),
])
def test_field_limits(kind: str, field: str, value: object, reason: str) -> None:
    with pytest.raises(wire.WireError, match=reason):
        wire.decode(tamper(kind, **{field: value}))


def test_nan_means_not_measured_only_where_a_field_says_so() -> None:
    ack = wire.decode(tamper("ack", interarrival=math.nan, sigma=math.nan), expect=wire.ScanAck)
    assert math.isnan(ack.interarrival) and math.isnan(ack.sigma)
    nan_pose = {"nd": "<f8", "shape": [4, 4], "data": np.full(16, np.nan).tobytes()}
    assert np.isnan(wire.decode(tamper("ack", pose=nan_pose), expect=wire.ScanAck).pose).all()
    half = np.eye(4)
    half[0, 0] = np.nan
    with pytest.raises(wire.WireError, match="non-finite"):
        wire.decode(tamper("ack", pose={"nd": "<f8", "shape": [4, 4], "data": half.tobytes()}))
    bad_points = np.zeros((2, 3), np.float32)
    bad_points[1, 2] = np.inf
    with pytest.raises(wire.WireError, match="non-finite"):
        wire.decode(tamper("scan_f32", points={"nd": "<f4", "shape": [2, 3], "data": bad_points.tobytes()},
                           times={"nd": "<u2", "shape": [2], "data": b"\x00" * 4}))


def test_caps_are_checked_before_allocation() -> None:
    limits = wire.Limits(max_points=100, max_detections=1, max_pixels=16)
    with pytest.raises(wire.WireError, match="rows"):
        wire.decode(valid_messages()["scan_f32"], limits=limits)
    with pytest.raises(wire.WireError, match="rows"):
        wire.decode(valid_messages()["detections"], limits=limits)
    # the packed blob is small, but its declared 500 points are not
    scan = wire.decode(valid_messages()["scan_q16z"], expect=wire.Scan, limits=limits)
    with pytest.raises(wire.WireError, match="at most 100"):
        scan.cloud(limits)
    frame = wire.decode(valid_messages()["frame"], expect=wire.Frame)
    with pytest.raises(wire.WireError, match="pixels"):
        frame.check_size(limits)
    with pytest.raises(wire.WireError, match="bytes"):
        wire.decode(b"\x00" * 2000, limits=wire.Limits(max_bytes=1000))


def test_q16z_declared_size_is_checked_before_decompressing() -> None:
    bomb = zstandard.ZstdCompressor(level=19).compress(b"\x00" * (64 << 20))  # 64 MiB of zeros, ~2 kB
    assert len(bomb) < 10_000
    with pytest.raises(CodingError, match="declares"):
        decode_q16z(bomb, 10, np.zeros(3), 0.01)
    no_size = zstandard.ZstdCompressor(write_content_size=False).compress(b"\x00" * 60)
    with pytest.raises(CodingError, match="declares"):
        decode_q16z(no_size, 10, np.zeros(3), 0.01)
    origin, step, blob = encode_q16z(np.zeros((10, 3)), 0.01)
    with pytest.raises(CodingError, match="declares"):
        decode_q16z(blob, 11, origin, step)
    assert decode_q16z(blob, 10, origin, step)[0].shape == (10, 3)


def test_detections_arrays_of_unequal_length_are_refused() -> None:
    with pytest.raises(wire.WireError, match="2 boxes, 1 scores"):
        wire.decode(tamper("detections", scores={"nd": "<f4", "shape": [1], "data": b"\x00" * 4}))


def test_version_1_messages_are_still_read() -> None:
    obj = msgpack.unpackb(valid_messages()["ack"], raw=False)
    for new in ("epoch", "edge"):
        del obj[new]
    obj["v"] = 1
    ack = wire.decode(msgpack.packb(obj, use_bin_type=True), expect=wire.ScanAck)
    assert ack.epoch == 0 and ack.edge == ""
    with pytest.raises(wire.WireError, match="codec version"):
        wire.decode(tamper("ack", v=max(wire.READS) + 1))


def test_a_frame_goes_as_version_2_unless_it_was_shrunk() -> None:
    """A version-2 reader (which refuses unknown fields and version 3) still reads every frame a
    robot sends before an edge has said what its detector takes; a shrunk frame is version 3."""
    whole = wire.Frame(robot="r1", seq=1, send_stamp=1.0, capture_stamp=1.0, encoding="bgr8", width=2,
                       height=1, data=np.zeros(6, np.uint8))
    obj = msgpack.unpackb(wire.encode(whole), raw=False)
    assert obj["v"] == 2 and "camera_width" not in obj and "camera_height" not in obj
    shrunk = dataclasses.replace(whole, camera_width=848, camera_height=480)
    obj = msgpack.unpackb(wire.encode(shrunk), raw=False)
    assert obj["v"] == 3 and (obj["camera_width"], obj["camera_height"]) == (848, 480)
    back = wire.decode(wire.encode(shrunk), expect=wire.Frame)
    assert back.camera_size() == (848, 480) and whole.camera_size() == (2, 1)
    one_side = msgpack.unpackb(wire.encode(shrunk), raw=False)
    del one_side["camera_height"]
    with pytest.raises(wire.WireError, match="both or neither"):
        wire.decode(msgpack.packb(one_side, use_bin_type=True), expect=wire.Frame).check_size()
    below = {**msgpack.unpackb(wire.encode(shrunk), raw=False), "camera_width": 1}  # below the frame's 2
    with pytest.raises(wire.WireError, match="only ever shrunk"):
        wire.decode(msgpack.packb(below, use_bin_type=True), expect=wire.Frame).check_size()
    for bad in ({"camera_width": 70_000}, {"camera_width": -1}, {"camera_height": 8.5}):
        obj = {**msgpack.unpackb(wire.encode(shrunk), raw=False), **bad}
        with pytest.raises(wire.WireError, match="camera_"):
            wire.decode(msgpack.packb(obj, use_bin_type=True), expect=wire.Frame)


def test_a_version_2_reader_reads_whole_frames_and_refuses_shrunk_ones(
        monkeypatch: pytest.MonkeyPatch) -> None:
    whole = wire.Frame(robot="r1", seq=1, send_stamp=1.0, capture_stamp=1.0, encoding="bgr8", width=2,
                       height=1, data=np.zeros(6, np.uint8))
    shrunk = dataclasses.replace(whole, camera_width=4, camera_height=2)
    data_whole, data_shrunk = wire.encode(whole), wire.encode(shrunk)
    monkeypatch.setattr(wire, "READS", (1, 2))  # an older build, as far as versions go
    got = wire.decode(data_whole, expect=wire.Frame)
    assert got.camera_size() == (2, 1) and got.data.tolist() == whole.data.tolist()
    with pytest.raises(wire.WireError, match="codec version 3"):
        wire.decode(data_shrunk, expect=wire.Frame)


def test_a_frame_says_it_reads_version_4_and_only_its_answer_carries_the_arrival(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Version 4: a frame that says its robot reads 4 (only sent to an edge that said it reads 4),
    and the arrival stamp in the answer to such a frame; a version-3 build reads everything sent
    to a peer that did not say so."""
    frame = wire.Frame(robot="r1", seq=1, send_stamp=1.0, capture_stamp=1.0, encoding="bgr8", width=2,
                       height=1, data=np.zeros(6, np.uint8))
    assert msgpack.unpackb(wire.encode(frame), raw=False)["v"] == 2 and frame.reads == 3
    says = dataclasses.replace(frame, reads=4)
    obj = msgpack.unpackb(wire.encode(says), raw=False)
    assert obj["v"] == 4 and obj["reads"] == 4
    assert wire.decode(wire.encode(says), expect=wire.Frame).reads == 4
    answer = wire.Detections(robot="r1", seq=1, send_stamp=1.0, edge="e1", model="m", status="ok",
                             infer_time=0.05, queue_time=0.0, batch=1, boxes=np.zeros((0, 4), np.float32),
                             scores=np.zeros(0, np.float32), classes=np.zeros(0, np.int32))
    plain = msgpack.unpackb(wire.encode(answer), raw=False)  # NaN, the default: not sent
    assert plain["v"] == 2 and "arrival" not in plain
    assert math.isnan(wire.decode(wire.encode(answer), expect=wire.Detections).arrival)
    stamped = dataclasses.replace(answer, arrival=1234.5)
    assert msgpack.unpackb(wire.encode(stamped), raw=False)["v"] == 4
    assert wire.decode(wire.encode(stamped), expect=wire.Detections).arrival == 1234.5
    for bad in (float("inf"), 2e12, "x"):
        obj = {**msgpack.unpackb(wire.encode(stamped), raw=False), "arrival": bad}
        with pytest.raises(wire.WireError, match="arrival"):
            wire.decode(msgpack.packb(obj, use_bin_type=True), expect=wire.Detections)
    for bad_reads in (0, 2_000, 3.5):
        obj = {**msgpack.unpackb(wire.encode(says), raw=False), "reads": bad_reads}
        with pytest.raises(wire.WireError, match="reads"):
            wire.decode(msgpack.packb(obj, use_bin_type=True), expect=wire.Frame)
    monkeypatch.setattr(wire, "READS", (1, 2, 3))  # a version-3 build
    assert wire.decode(wire.encode(frame), expect=wire.Frame).seq == 1
    assert wire.decode(wire.encode(answer), expect=wire.Detections).seq == 1
    for newer in (says, stamped):
        with pytest.raises(wire.WireError, match="codec version 4"):
            wire.decode(wire.encode(newer))


def test_times_survive_the_u16_coding() -> None:
    t = np.sort(np.random.default_rng(1).uniform(5.0, 5.1, 1000))
    q, span = times_to_u16(t)
    back = times_from_u16(q, span) + t.min()
    assert np.abs(back - t).max() <= span / 65535 / 2 + 1e-12
    assert times_to_u16(np.full(5, 3.0))[1] == 0.0  # no spread: no times


def _mat(m: np.ndarray) -> dict[str, object]:
    m = np.asarray(m, np.float64)
    return {"nd": "<f8", "shape": list(m.shape), "data": m.tobytes()}


@pytest.mark.parametrize("kind, field", [("ack", "pose"), ("checkpoint", "pose"), ("checkpoint", "delta")])
def test_a_pose_that_is_not_a_rigid_motion_is_refused(kind: str, field: str) -> None:
    """KISS-ICP's Sophus aborts the process on a rotation off by more than 1e-10 or a last row
    other than 0 0 0 1: such a pose must not get past the codec (float noise within 1e-6 may)."""
    for off in (np.diag([1.5, 1.0, 1.0, 1.0]), np.diag([1.0, 1.0, 1.0, 2.0]), np.diag([-1.0, 1.0, 1.0, 1.0])):
        with pytest.raises(wire.WireError, match="not a rigid motion"):
            wire.decode(tamper(kind, **{field: _mat(off)}))
    bottom = np.eye(4)
    bottom[3, 0] = 0.5
    with pytest.raises(wire.WireError, match="not a rigid motion"):
        wire.decode(tamper(kind, **{field: _mat(bottom)}))
    noisy = np.eye(4)
    noisy[0, 0] += 1e-9
    assert getattr(wire.decode(tamper(kind, **{field: _mat(noisy)})), field)[0, 0] == noisy[0, 0]


def test_attach_and_map_poses_are_rigid_motions_too() -> None:
    scaled = np.tile(np.eye(4), (3, 1, 1))
    scaled[1, :3, :3] *= 2
    with pytest.raises(wire.WireError, match="not a rigid motion"):
        wire.decode(tamper("attach", local_seqs={"nd": "<i8", "shape": [3], "data": np.arange(3).tobytes()},
                           local_poses=_mat(scaled)))
    with pytest.raises(wire.WireError, match="not a rigid motion"):
        wire.decode(tamper("map", seqs={"nd": "<i8", "shape": [3], "data": np.arange(3).tobytes()},
                           poses=_mat(scaled)))


def test_a_scan_carries_the_robots_prior_as_version_5_and_only_whole(monkeypatch: pytest.MonkeyPatch) -> None:
    """Version 5: a scan with the robot's own pose and motion (sent only to an edge that said it
    reads 5); a scan without one still goes as version 2, and a prior that is partial, from a
    later scan or not rigid is refused. Version 11: the prior's frame, only with a prior."""
    plain = wire.decode(valid_messages()["scan_f32"], expect=wire.Scan)
    obj = msgpack.unpackb(wire.encode(plain), raw=False)
    assert obj["v"] == 2 and "prior" not in obj and "prior_seq" not in obj and plain.prior is None
    turn = np.eye(4)
    turn[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    turn[:3, 3] = [1.0, 2.0, 0.0]
    prior = np.stack([turn, np.eye(4)])
    with_prior = dataclasses.replace(plain, prior_seq=2, prior=prior)
    obj = msgpack.unpackb(wire.encode(with_prior), raw=False)
    assert obj["v"] == 5 and obj["prior_seq"] == 2
    back = wire.decode(wire.encode(with_prior), expect=wire.Scan)
    assert back.prior_seq == 2 and back.prior is not None and np.array_equal(back.prior, prior)
    with pytest.raises(wire.WireError, match="both"):
        dataclasses.replace(plain, prior_seq=2)
    for bad, match in (({"prior_seq": 4}, "later scan"), ({"prior": None}, "both"),
                       ({"prior_seq": -2}, "prior_seq")):
        obj = {**msgpack.unpackb(wire.encode(with_prior), raw=False), **bad}
        if obj["prior"] is None:
            del obj["prior"]
        with pytest.raises(wire.WireError, match=match):
            wire.decode(msgpack.packb(obj, use_bin_type=True), expect=wire.Scan)
    skewed = prior.copy()
    skewed[0, 0, 0] = 1.5
    obj = msgpack.unpackb(wire.encode(with_prior), raw=False)
    obj["prior"]["data"] = skewed.tobytes()
    with pytest.raises(wire.WireError, match="rigid"):
        wire.decode(msgpack.packb(obj, use_bin_type=True), expect=wire.Scan)
    # Version 11: the prior's frame (1: the poses the robot's attach handed over); only with a prior
    framed = dataclasses.replace(with_prior, prior_frame=1)
    obj = msgpack.unpackb(wire.encode(framed), raw=False)
    assert obj["v"] == 11 and obj["prior_frame"] == 1
    assert wire.decode(wire.encode(framed), expect=wire.Scan).prior_frame == 1
    assert wire.decode(wire.encode(with_prior), expect=wire.Scan).prior_frame == -1  # not said
    with pytest.raises(wire.WireError, match="frame of a prior"):
        dataclasses.replace(plain, prior_frame=0)
    for bad, match in (({"prior_frame": 2}, "prior_frame"), ({"prior_frame": True}, "type"),
                       ({"prior_seq": -1, "prior": None}, "frame of a prior")):
        obj = {**msgpack.unpackb(wire.encode(framed), raw=False), **bad}
        if obj["prior"] is None:
            del obj["prior"]
        with pytest.raises(wire.WireError, match=match):
            wire.decode(msgpack.packb(obj, use_bin_type=True), expect=wire.Scan)
    monkeypatch.setattr(wire, "READS", tuple(range(1, 11)))  # a version-10 build
    with pytest.raises(wire.WireError, match="codec version 11"):
        wire.decode(wire.encode(framed), expect=wire.Scan)
    assert wire.decode(wire.encode(with_prior), expect=wire.Scan).prior_seq == 2
    monkeypatch.setattr(wire, "READS", (1, 2, 3, 4))  # a version-4 build
    assert wire.decode(wire.encode(plain), expect=wire.Scan).seq == 3
    with pytest.raises(wire.WireError, match="codec version 5"):
        wire.decode(wire.encode(with_prior), expect=wire.Scan)


def _zero_checkpoint(n: int) -> wire.Checkpoint:
    """A checkpoint declaring ``n`` points whose coded map is compressed zeros (~1 kB for 2M)."""
    blob = bytes([1]) + zstandard.ZstdCompressor(level=19, write_content_size=True).compress(b"\0" * (6 * n))
    eye = np.eye(4)
    return wire.Checkpoint(robot="r1", edge="e1", epoch=1, seq=5, stamp=0.0, voxel_size=0.5, max_range=100.0,
                           min_range=0.0, max_points_per_voxel=20, pose=eye, delta=eye,
                           points=np.zeros((0, 3), np.float32), quant_step=0.01, n_points=n,
                           origin=np.zeros(3), packed=np.frombuffer(blob, np.uint8))


def test_a_checkpoint_cannot_declare_more_points_than_its_bytes_can_hold() -> None:
    """Was: a 1 kB checkpoint declaring 2M points decoded into +113 MB (100M allowed: ~6 GB);
    a receiver decodes every checkpoint (the robot, the edge on an attach)."""
    bomb = wire.decode(wire.encode(_zero_checkpoint(2_000_000)), expect=wire.Checkpoint)
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(wire.WireError, match="points a byte"):
        bomb.cloud()
    with pytest.raises(wire.WireError, match="points a byte"):
        bomb.plain()  # what an edge reads an attach's checkpoint with
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - r0 < 20_000  # kB: nothing allocated
    over = dataclasses.replace(_zero_checkpoint(100), n_points=wire.DEFAULT_LIMITS.max_checkpoint_points + 1)
    with pytest.raises(wire.WireError, match="at most"):
        over.cloud()
    # a flat synthetic floor on an exact grid, the most compressible map there is, still decodes
    from zoffload.protocol.coding import encode_q16d

    cells = np.stack(np.meshgrid(np.arange(200), np.arange(200), indexing="ij"), -1).reshape(-1, 2) * 0.25
    floor = np.c_[cells, np.zeros(len(cells))].astype(np.float32)
    origin, step, packed = encode_q16d(floor, 0.01, level=1, widen=True)
    flat = dataclasses.replace(_zero_checkpoint(1), quant_step=step, n_points=len(floor), origin=origin,
                               packed=np.frombuffer(packed, np.uint8))
    assert np.allclose(wire.decode(wire.encode(flat), expect=wire.Checkpoint).cloud(), floor, atol=step)


def test_a_key_repeated_in_a_message_is_refused() -> None:
    """Was: msgpack kept the last of a repeated key, the edge's cheap route peek the first: a scan
    peeked as (e1, 7) decoded as (e2, 99) and was mapped under an epoch it was not routed by."""
    scan = wire.Scan(robot="r1", seq=1, send_stamp=1.0, capture_stamp=1.0, voxel=0.1, voxel_max=0.1,
                     max_range=50.0, n_raw=1, points=np.zeros((1, 3), np.float32), edge="e1", epoch=7)
    fields = list(msgpack.unpackb(wire.encode(scan), raw=False).items())
    packer = msgpack.Packer(use_bin_type=True)
    for extra in ([("robot", "r1")] * 64 + [("edge", "e2"), ("epoch", 99)], [("seq", 2)]):
        items = fields + extra
        raw = packer.pack_map_header(len(items)) + b"".join(packer.pack(k) + packer.pack(v) for k, v in items)
        with pytest.raises(wire.WireError, match="repeated"):
            wire.decode(raw, expect=wire.Scan)
    # msgpack's pure-Python fallback (PyPy, MSGPACK_PUREPYTHON) hands the hook a generator, not a
    # list (len() of it raised TypeError: every message refused)
    assert wire._unique_keys(iter([("a", 1), ("b", 2)])) == {"a": 1, "b": 2}
    with pytest.raises(ValueError, match="repeated"):
        wire._unique_keys(iter([("a", 1), ("a", 2)]))


def test_a_checkpoints_turn_rate_is_version_8_and_bounded() -> None:
    """Version 8: the turn rate goes only when it is said (a checkpoint without it stays the
    version it was), and a receiver refuses one that is negative, not finite or past half a turn
    a period."""
    cp = dataclasses.replace(_zero_checkpoint(1), n_points=-1, packed=None, origin=None, quant_step=0.0)
    assert msgpack.unpackb(wire.encode(cp))["v"] == 2 and "turn_rate" not in msgpack.unpackb(wire.encode(cp))
    turning = dataclasses.replace(cp, turn_rate=0.1)
    raw = msgpack.unpackb(wire.encode(turning))
    assert raw["v"] == 8 and wire.decode(wire.encode(turning), expect=wire.Checkpoint).turn_rate == 0.1
    for bad in (-0.1, float("nan"), float("inf"), 4.0, "0.1"):
        with pytest.raises(wire.WireError, match="turn_rate"):
            wire.decode(msgpack.packb({**raw, "turn_rate": bad}, use_bin_type=True), expect=wire.Checkpoint)


def test_an_attachs_backfill_is_version_9_and_checked_scan_by_scan() -> None:
    """Version 9: an attach carries its backfill (coded scans, concatenated, and their sizes) only
    when there is one; each scan is decoded and checked as any scan, and sizes that do not cut the
    bytes into whole scans, a scan of another robot, seqs that do not ascend or more scans than
    the limit are refused with a ``WireError``, nothing else."""
    raw = msgpack.unpackb(valid_messages()["attach_v9"])
    assert raw["v"] == 9
    attach = wire.decode(valid_messages()["attach_v9"], expect=wire.Attach)
    scans = attach.backfill_scans()
    assert [s.seq for s in scans] == [11, 12] and all(len(s.cloud_and_times()[0]) == 500 for s in scans)
    plain = dataclasses.replace(attach, backfill=None, backfill_sizes=None)
    assert msgpack.unpackb(wire.encode(plain))["v"] == 6 and plain.backfill_scans() == []
    data, sizes = attach.backfill, attach.backfill_sizes
    assert data is not None and sizes is not None
    half = int(sizes[0])
    bad_fields = [
        {"backfill_sizes": sizes[:1]},  # the sizes do not cover the bytes
        {"backfill_sizes": np.array([half - 1, half + 1])},  # ... cover them, but not whole scans
        {"backfill_sizes": np.array([0, 2 * half])},
        {"backfill_sizes": None},
    ]
    for change in bad_fields:
        fields = {**raw}
        for k, v in change.items():
            if v is None:
                fields.pop(k)
            else:
                fields[k] = {"nd": "<i8", "shape": [len(v)], "data": np.asarray(v, "<i8").tobytes()}
        with pytest.raises(wire.WireError):
            wire.decode(msgpack.packb(fields, use_bin_type=True), expect=wire.Attach).backfill_scans()
    scan = wire.decode(bytes(data[:half]), expect=wire.Scan)
    for second in (wire.encode(dataclasses.replace(scan, robot="robot2")),
                   wire.encode(dataclasses.replace(scan, seq=11)), wire.encode(scan)[:-7]):
        odd = dataclasses.replace(attach, backfill=np.frombuffer(bytes(data[:half]) + second, np.uint8),
                                  backfill_sizes=np.array([half, len(second)]))
        with pytest.raises(wire.WireError):
            odd.backfill_scans()  # another robot's; not after the first; cut short
    many = dataclasses.replace(attach, backfill=np.frombuffer(bytes(data[:half]) * 3, np.uint8),
                               backfill_sizes=np.array([half] * 3))
    with pytest.raises(wire.WireError, match="at most 2"):
        many.backfill_scans(wire.Limits(max_backfill_scans=2))


def test_an_attachs_backfill_poses_are_version_10_one_rigid_pose_a_scan() -> None:
    """Version 10: the robot's pose of each backfilled scan, sent with a backfill only; as many as
    the backfill's scans, each a rigid transform, else the attach is refused with a ``WireError``."""
    attach = wire.decode(valid_messages()["attach_v9"], expect=wire.Attach)
    poses = np.repeat(np.eye(4)[None], 2, axis=0)
    posed = dataclasses.replace(attach, backfill_poses=poses)
    assert msgpack.unpackb(wire.encode(posed))["v"] == 10
    np.testing.assert_array_equal(wire.decode(wire.encode(posed), expect=wire.Attach).backfill_poses, poses)
    raw = msgpack.unpackb(wire.encode(posed))
    for bad in (poses[:1], np.repeat(np.eye(4)[None], 3, axis=0), poses * 2.0):
        fields = dict(raw, backfill_poses={"nd": "<f8", "shape": list(bad.shape), "data": bad.tobytes()})
        with pytest.raises(wire.WireError):
            wire.decode(msgpack.packb(fields, use_bin_type=True), expect=wire.Attach)
    fields = {k: v for k, v in raw.items() if k not in ("backfill", "backfill_sizes")}
    with pytest.raises(wire.WireError):  # poses without a backfill
        wire.decode(msgpack.packb(fields, use_bin_type=True), expect=wire.Attach)


def test_an_attachs_backfill_cannot_declare_more_points_than_a_scan() -> None:
    """A receiver decodes a backfill's points before registering them: a coded scan declaring
    more than ``CODED_POINTS_PER_BYTE`` points a byte, or scans declaring more than one scan's
    ``max_points`` together, are refused; so are sizes whose sum wraps a 64-bit integer."""
    attach = wire.decode(valid_messages()["attach_v9"], expect=wire.Attach)
    assert attach.backfill is not None and attach.backfill_sizes is not None
    half = int(attach.backfill_sizes[0])
    scan = wire.decode(bytes(attach.backfill[:half]), expect=wire.Scan)
    assert scan.packed is not None

    def with_second(other: wire.Scan) -> wire.Attach:
        second = wire.encode(other)
        data = np.frombuffer(bytes(attach.backfill[:half]) + second, np.uint8)
        return dataclasses.replace(attach, backfill=data, backfill_sizes=np.array([half, len(second)]))

    bomb = dataclasses.replace(scan, seq=12, n_points=wire.CODED_POINTS_PER_BYTE * len(scan.packed) + 1)
    with pytest.raises(wire.WireError, match="points in"):
        with_second(bomb).backfill_scans()
    with pytest.raises(wire.WireError, match="more than 900 points"):
        with_second(dataclasses.replace(scan, seq=12)).backfill_scans(wire.Limits(max_points=900))
    two = with_second(dataclasses.replace(scan, seq=12))
    assert len(two.backfill_scans(wire.Limits(max_points=1000))) == 2
    raw = msgpack.unpackb(valid_messages()["attach_v9"])
    wrap = np.array([2**62, 2**62, 2**62, 2**62 + len(attach.backfill)], "<i8")  # sums to len mod 2**64
    raw["backfill_sizes"] = {"nd": "<i8", "shape": [4], "data": wrap.tobytes()}
    with pytest.raises(wire.WireError, match="sizes"):
        wire.decode(msgpack.packb(raw, use_bin_type=True), expect=wire.Attach)
