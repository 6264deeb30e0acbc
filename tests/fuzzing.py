"""A seeded generator of hostile messages: valid zoffload messages of every type, mutated at the
byte level and at the msgpack level (fields replaced by values of the wrong type or absurd size,
array headers that lie, compressed payloads whose declared size lies). The same seed gives the
same corpus, so a failure found once is found again."""

from __future__ import annotations

import dataclasses
import math
import random
from collections.abc import Iterator
from typing import Any

import msgpack
import numpy as np
import zstandard

from zoffload.protocol import wire
from zoffload.protocol.coding import encode_q16z, times_to_u16

_RNG = np.random.default_rng(0)
_PTS = _RNG.uniform(-20, 20, (500, 3)).astype(np.float32)


def valid_messages(robot: str = "robot1", edge: str = "edge1") -> dict[str, bytes]:
    """One valid encoded message per type (the scan in both codings)."""
    origin, step, blob = encode_q16z(_PTS, 0.01)
    q, span = times_to_u16(np.linspace(0, 0.1, len(_PTS)))
    origin_t, step_t, blob_t = encode_q16z(_PTS, 0.01, times=q)
    cp = wire.Checkpoint(robot=robot, edge=edge, epoch=1, seq=10, stamp=1.0, voxel_size=1.0, max_range=50.0,
                         min_range=0.0, max_points_per_voxel=20, pose=np.eye(4), delta=np.eye(4),
                         points=_PTS[:50])
    coarse = [wire.encode(wire.Scan(robot=robot, seq=seq, send_stamp=1.0, capture_stamp=2.0, voxel=0.8,
                                    voxel_max=0.8, max_range=50.0, n_raw=500,
                                    points=np.zeros((0, 3), np.float32),
                                    coding="q16z", quant_step=step, n_points=len(_PTS), origin=origin,
                                    packed=np.frombuffer(blob, np.uint8), epoch=2)) for seq in (11, 12)]
    backfill = b"".join(coarse)
    assert len(coarse[0]) == len(coarse[1])
    msgs: dict[str, wire.Message] = {
        "scan_f32": wire.Scan(robot=robot, seq=3, send_stamp=1.0, capture_stamp=2.0, voxel=0.05,
                              voxel_max=0.07, max_range=50.0, n_raw=500, points=_PTS, time_span=span,
                              times=q),
        "scan_q16z": wire.Scan(robot=robot, seq=4, send_stamp=1.0, capture_stamp=2.0, voxel=0.05,
                               voxel_max=0.07, max_range=50.0, n_raw=500,
                               points=np.zeros((0, 3), np.float32), coding="q16z",
                               quant_step=step, n_points=len(_PTS), origin=origin,
                               packed=np.frombuffer(blob, np.uint8)),
        "scan_q16z_times": wire.Scan(robot=robot, seq=5, send_stamp=1.0, capture_stamp=2.0, voxel=0.05,
                                     voxel_max=0.07, max_range=50.0, n_raw=500,
                                     points=np.zeros((0, 3), np.float32), coding="q16z", quant_step=step_t,
                                     n_points=len(_PTS), origin=origin_t,
                                     packed=np.frombuffer(blob_t, np.uint8), time_span=span),
        "scan_prior": wire.Scan(robot=robot, seq=9, send_stamp=1.0, capture_stamp=2.0, voxel=0.05,
                                voxel_max=0.07, max_range=50.0, n_raw=500, points=_PTS[:20], edge=edge,
                                epoch=2, prior_seq=9, prior=np.stack([np.eye(4), np.eye(4)])),
        "ack": wire.ScanAck(robot=robot, seq=3, send_stamp=1.0, status="ok", interarrival=0.1,
                            queue_time=0.0, proc_time=0.01, icp_time=0.01, map_points=10, keypoints=5,
                            sigma=0.2, pose=np.eye(4), epoch=1, edge=edge),
        "frame": wire.Frame(robot=robot, seq=1, send_stamp=1.0, capture_stamp=1.0, encoding="bgr8", width=8,
                            height=6, data=np.zeros(8 * 6 * 3, np.uint8)),
        "detections": wire.Detections(robot=robot, seq=1, send_stamp=1.0, edge=edge, model="m", status="ok",
                                      infer_time=0.01, queue_time=0.0, batch=1,
                                      boxes=np.zeros((2, 4), np.float32), scores=np.ones(2, np.float32),
                                      classes=np.zeros(2, np.int32)),
        # Version 4: a frame whose robot reads 4 (and was shrunk, version 3), the answer stamped
        "frame_v4": wire.Frame(robot=robot, seq=2, send_stamp=1.0, capture_stamp=1.0, encoding="bgr8",
                               width=8, height=6, data=np.zeros(8 * 6 * 3, np.uint8), edge=edge,
                               camera_width=16, camera_height=12, reads=4),
        "detections_v4": wire.Detections(robot=robot, seq=2, send_stamp=1.0, edge=edge, model="m",
                                         status="ok", infer_time=0.01, queue_time=0.0, batch=1,
                                         boxes=np.zeros((1, 4), np.float32), scores=np.ones(1, np.float32),
                                         classes=np.zeros(1, np.int32), arrival=12_345.678),
        "status": wire.Status(source="edge", id=edge, stamp=1.0, values={"a": 1.0, "b": float("nan")}),
        "pong": wire.Pong(edge=edge, stamp=1.0),
        "map": wire.MapReply(robot=robot, scans=1, points=_PTS[:10], seqs=np.array([0]),
                             poses=np.eye(4)[None]),
        "map_v7": wire.MapReply(robot=robot, scans=1, points=_PTS[:10], seqs=np.array([0]),
                                poses=np.eye(4)[None], edge=edge),
        "checkpoint": cp,
        "checkpoint_v8": dataclasses.replace(cp, turn_rate=0.05),  # the turn rate said (version 8)
        "attach": wire.Attach(robot=robot, epoch=2, max_range=50.0, voxel_max=0.07, rate_hz=10.0,
                              checkpoint=wire.encode(cp), local_seqs=np.array([11, 12]),
                              local_poses=np.stack([np.eye(4)] * 2)),
        # Version 9: the attach's backfill, two coded scans (robot/fleet.py ``backfill_payload``)
        "attach_v9": wire.Attach(robot=robot, epoch=2, max_range=50.0, voxel_max=0.07, rate_hz=10.0,
                                 checkpoint=wire.encode(cp), local_seqs=np.array([11, 12]),
                                 local_poses=np.stack([np.eye(4)] * 2), reads=9,
                                 backfill=np.frombuffer(backfill, np.uint8),
                                 backfill_sizes=np.array([len(backfill) // 2] * 2, np.int64)),
        # Version 10: and the robot's pose of each backfilled scan
        "attach_v10": wire.Attach(robot=robot, epoch=2, max_range=50.0, voxel_max=0.07, rate_hz=10.0,
                                  checkpoint=wire.encode(cp), local_seqs=np.array([11, 12]),
                                  local_poses=np.stack([np.eye(4)] * 2), reads=10,
                                  backfill=np.frombuffer(backfill, np.uint8),
                                  backfill_sizes=np.array([len(backfill) // 2] * 2, np.int64),
                                  backfill_poses=np.stack([np.eye(4)] * 2)),
        "attach_reply": wire.AttachReply(robot=robot, edge=edge, epoch=2, accepted=True, robots=1,
                                         capacity=4),
    }
    return {k: wire.encode(m) for k, m in msgs.items()}


def _odd_value(rng: random.Random) -> Any:
    choices: list[Any] = [
        None, True, False, -1, 0, 2**63, 2**64 - 1, -(2**63), 10**30, math.nan, math.inf, -math.inf, 1e308,
        -1e-300, "", "x" * rng.choice([65, 1000, 100_000]), "a/b", "*", "$*", "..", "\x00",
        b"", b"\xff" * rng.choice([1, 100, 10_000]), [], [1, 2, 3], [[[[[]]]]], {}, {"nd": "<f4"},
        {"nd": "<f4", "shape": [2**40, 3], "data": b""},
        {"nd": "<f4", "shape": [10**6, 3], "data": b"\x00" * 12},
        {"nd": "<f4", "shape": [-1, 3], "data": b""}, {"nd": "|O", "shape": [1], "data": b"\x00" * 8},
        {"nd": "<f4", "shape": [1, 3], "data": np.array([math.nan, 0, 0], "<f4").tobytes()},
        {"nd": "<f4", "shape": [1, 3], "data": np.array([math.inf, 0, 0], "<f4").tobytes()},
        {"nd": "<f8", "shape": [4, 4], "data": np.full(16, np.inf).tobytes()},
        {"nd": "V8", "shape": [1], "data": b"\x00" * 8}, {"nd": "U100000", "shape": [1], "data": b""},
        {"nd": ">f4", "shape": [1, 3], "data": b"\x00" * 12},
        {str(i): float(i) for i in range(rng.choice([10, 5000]))},
    ]
    return rng.choice(choices)


def _lying_q16z(obj: dict[str, Any], rng: random.Random) -> dict[str, Any]:
    """A q16z scan whose compressed frame claims far more (or other) bytes than its point count."""
    n = rng.choice([1, 10, 10**6, 10**9, 2**31])
    content = b"\x00" * rng.choice([0, 6, 600, 6 * 10**5])
    blob = zstandard.ZstdCompressor(level=1, write_content_size=rng.random() < 0.8).compress(content)
    if rng.random() < 0.3:  # a frame header declaring ~1 GiB of zeros
        blob = zstandard.ZstdCompressor(level=19).compress(b"\x00" * (1 << 20))
    obj.update(coding="q16z", n_points=n, quant_step=0.01,
               origin={"nd": "<f8", "shape": [3], "data": b"\x00" * 24},
               packed={"nd": "|u1", "shape": [len(blob)], "data": blob})
    return obj


def mutate(data: bytes, rng: random.Random) -> bytes:
    """One hostile variant of a valid message."""
    how = rng.random()
    if how < 0.35:  # bytes: flips, cuts, insertions
        b = bytearray(data)
        for _ in range(rng.randint(1, 8)):
            op = rng.random()
            if op < 0.5 and b:
                b[rng.randrange(len(b))] = rng.randrange(256)
            elif op < 0.75 and b:
                del b[rng.randrange(len(b)):]
            else:
                b[rng.randrange(len(b) + 1):0] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
        return bytes(b)
    obj = msgpack.unpackb(data, raw=False)
    keys = list(obj)
    if how < 0.85:  # fields: replaced, removed, added
        for _ in range(rng.randint(1, 3)):
            op = rng.random()
            if op < 0.7:
                obj[rng.choice(keys)] = _odd_value(rng)
            elif op < 0.85:
                obj.pop(rng.choice(keys), None)
            else:
                obj[rng.choice(["extra", "v2", "\x00", "a" * 1000])] = _odd_value(rng)
    elif how < 0.95 and obj.get("t") == "scan":
        obj = _lying_q16z(obj, rng)
    else:  # the container itself
        return msgpack.packb(rng.choice([[obj], obj["t"] if "t" in obj else 1, {"v": 2, "t": obj.get("t")},
                                         [[[[[[[[[[[]]]]]]]]]]] * 50]), use_bin_type=True)
    try:
        return msgpack.packb(obj, use_bin_type=True)
    except Exception:  # a value msgpack cannot pack (an int too large): its bytes instead
        return data[: len(data) // 2]


def corpus(seed: int, n: int, robot: str = "robot1", kinds: tuple[str, ...] | None = None) -> Iterator[bytes]:
    """``n`` hostile messages from ``seed``, cycling over the message kinds."""
    rng = random.Random(seed)
    valid = valid_messages(robot)
    names = [k for k in valid if kinds is None or k in kinds]
    for i in range(n):
        yield mutate(valid[names[i % len(names)]], rng)
