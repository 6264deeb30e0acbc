"""sensor_msgs/PointCloud2 to numpy and back, by the message's own field descriptions.

A cloud is ``height x width`` points of ``point_step`` bytes, rows ``row_step`` apart, each field
at its ``offset`` with its ``datatype`` (offsets may be unaligned: Hesai puts a float64 at 18),
in the byte order ``is_bigendian`` says. Only the fields used here are read (x, y, z and the
per-point time), so a driver's extra fields of any type are no obstacle.

The per-point time of common drivers, normalised to float64 seconds (the offset stays arbitrary;
KISS-ICP ≥ 1.2.2 and the wire only need the order and the span):

=================  ============  ==========================================================
field              type          driver and unit
=================  ============  ==========================================================
``t``              uint32        Ouster (ns since the scan's start)
``time``           float32       Velodyne (s relative to the header stamp, often negative)
``time``           uint32        Newer College and others (ns)
``timestamp``      float64       Hesai, RoboSense (absolute s); Livox (absolute ns)
``offset_time``    uint32        Livox custom layouts (ns from the packet's time base)
=================  ============  ==========================================================

Integer times are nanoseconds; float times are seconds unless a value is beyond 1e11 (an
absolute time in seconds cannot be: that is year 5138), which only nanoseconds since the epoch
reach (Livox).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

# sensor_msgs/PointField datatypes
DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
FLOAT32 = 7
TIME_FIELDS = ("t", "time", "timestamp", "offset_time")
ABSOLUTE_NS = 1e11  # a float time beyond this is nanoseconds since the epoch
MAX_POINTS = 4_000_000  # as wire.Limits.max_points: what one scan may hold


class PointCloudError(ValueError):
    """A PointCloud2 that cannot be read: no x/y/z, an unknown datatype of a needed field, a
    layout that does not fit its data."""


@dataclass(frozen=True)
class Cloud:
    """The points of one PointCloud2, with their times if it has a time field."""

    points: np.ndarray  # (N, 3) float32, finite, no (0, 0, 0) "no return" points
    times: np.ndarray | None  # (N,) float64 seconds, arbitrary offset; None without a time field
    time_field: str | None
    dropped: int  # points left out: non-finite coordinates or time, or exactly (0, 0, 0)


def _fields(msg: Any) -> dict[str, Any]:
    return {str(f.name): f for f in msg.fields}


def time_field(msg: Any) -> str | None:
    """The per-point time field a cloud has, first in the message's field order (as KISS-ICP's
    reader picks it)."""
    for f in msg.fields:
        if str(f.name) in TIME_FIELDS:
            return str(f.name)
    return None


def _dtype(msg: Any, names: list[str]) -> np.dtype:
    fields = _fields(msg)
    order = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for name in names:
        f = fields[name]
        kind = DATATYPES.get(int(f.datatype))
        if kind is None:
            raise PointCloudError(f"field {name!r} has datatype {f.datatype}, not one of "
                                  f"{sorted(DATATYPES)} (sensor_msgs/PointField INT8..FLOAT64)")
        if int(f.count) != 1:
            raise PointCloudError(f"field {name!r} has count {f.count}; one value per point is needed")
        size = int(kind[1])
        if not 0 <= int(f.offset) <= int(msg.point_step) - size:
            raise PointCloudError(f"field {name!r} at offset {f.offset} does not fit a point of "
                                  f"{msg.point_step} bytes")
        formats.append(order + kind)
        offsets.append(int(f.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                     "itemsize": int(msg.point_step)})


def _records(msg: Any, dtype: np.dtype, max_points: int) -> np.ndarray:
    height, width = int(msg.height), int(msg.width)
    step, row_step = int(msg.point_step), int(msg.row_step)
    n = height * width
    if n > max_points:
        raise PointCloudError(f"a cloud of {height}x{width} = {n} points (at most {max_points})")
    if n == 0:
        return np.zeros(0, dtype)
    data = np.frombuffer(msg.data, np.uint8) if not isinstance(msg.data, np.ndarray) else \
        msg.data.view(np.uint8).reshape(-1)
    if row_step < width * step:
        raise PointCloudError(f"row_step {row_step} is less than width {width} x point_step {step}")
    need = (height - 1) * row_step + width * step
    if len(data) < need:
        raise PointCloudError(f"{len(data)} data bytes for {height} rows of {width} points "
                              f"({need} needed: truncated?)")
    if row_step == width * step:
        buf = np.ascontiguousarray(data[: n * step])
    else:  # rows padded: drop each row's padding
        rows = np.lib.stride_tricks.as_strided(data, shape=(height, width * step), strides=(row_step, 1))
        buf = np.ascontiguousarray(rows).reshape(-1)
    return buf.view(dtype)


def seconds(raw: np.ndarray) -> np.ndarray:
    """A time field's values as float64 seconds from the earliest one (see the module table)."""
    if raw.size == 0:
        return np.zeros(0, np.float64)
    if raw.dtype.kind in "iu":
        rel = raw.astype(np.int64) - int(raw.min())
        return rel.astype(np.float64) * 1e-9
    t = raw.astype(np.float64)
    finite = t[np.isfinite(t)]
    if finite.size == 0:
        return t
    scale = 1e-9 if float(np.abs(finite).max()) > ABSOLUTE_NS else 1.0
    return (t - float(finite.min())) * scale


def cloud_from_msg(msg: Any, max_points: int = MAX_POINTS) -> Cloud:
    """The finite points of a PointCloud2 (a rosbags message or anything with its fields) and
    their times; ``PointCloudError`` when it cannot be read."""
    fields = _fields(msg)
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        raise PointCloudError(f"a PointCloud2 without {'/'.join(missing)} (fields: "
                              f"{', '.join(fields) or 'none'})")
    if int(msg.point_step) <= 0:
        raise PointCloudError(f"point_step {msg.point_step}")
    tname = time_field(msg)
    names = ["x", "y", "z"] + ([tname] if tname else [])
    try:
        rec = _records(msg, _dtype(msg, names), max_points)
    except PointCloudError:
        raise
    except (ValueError, TypeError) as exc:  # numpy refusing an impossible layout
        raise PointCloudError(f"unreadable cloud layout: {exc}") from exc
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float32)
    keep = np.isfinite(xyz).all(axis=1) & (xyz != 0).any(axis=1)
    times = None
    if tname:
        times = seconds(rec[tname])
        keep &= np.isfinite(times)
    points = xyz[keep]
    if times is not None:
        times = times[keep]
        times = times - times.min() if len(times) else times
    return Cloud(points=points, times=times, time_field=tname, dropped=int(len(xyz) - len(points)))


def cloud_msg(points: np.ndarray, header: Any, extra: dict[str, np.ndarray] | None = None) -> Any:
    """An unorganised, dense, little-endian PointCloud2 of float32 x, y, z and float32 ``extra``
    fields (e.g. ``{"t": seconds}``)."""
    from zoffload.ros2.typestore import msg_class

    pts = np.asarray(points, np.float32).reshape(-1, 3)
    extra = extra or {}
    names = ["x", "y", "z", *extra]
    rec = np.zeros(len(pts), np.dtype([(name, "<f4") for name in names]))
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    for name, values in extra.items():
        rec[name] = np.asarray(values, np.float32)
    PointField = msg_class("sensor_msgs/msg/PointField")
    step = 4 * len(names)
    return msg_class("sensor_msgs/msg/PointCloud2")(
        header=header, height=1, width=len(pts),
        fields=[PointField(name=name, offset=4 * i, datatype=FLOAT32, count=1)
                for i, name in enumerate(names)],
        is_bigendian=False, point_step=step, row_step=step * len(pts),
        data=rec.view(np.uint8).reshape(-1), is_dense=True)
