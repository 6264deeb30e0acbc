"""What every scan source yields, and how a source is chosen from a config string."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Protocol

import numpy as np

if TYPE_CHECKING:
    from zoffload.ros2.session import Ros2Link

Replay = Literal["once", "loop", "pingpong"]


class ScanSourceError(Exception):
    """A scan source that cannot be opened or read: missing folder, truncated or empty file."""


@dataclass(frozen=True)
class ScanFrame:
    """One LiDAR scan in the sensor frame."""

    index: int  # position in the source's sequence (repeats when a replay loops)
    points: np.ndarray  # (N, 3) float32, may contain non-finite rows straight from the sensor
    gt_pose: np.ndarray | None = None  # 4x4 sensor-to-world ground truth, if the source has one
    # Per-point time, (N,) float64 seconds with any offset (only order and spacing matter), row
    # for row with ``points`` (sources with times leave non-finite rows out); None without
    times: np.ndarray | None = None
    # When the scan was complete, seconds since the Unix epoch on the sensor's clock: a ROS
    # header stamp (live topics, bags); None for sources without one
    stamp: float | None = None


class ScanSource(Protocol):
    """A finite sequence of scans; replay (pacing, looping) is the sensor's job, not the source's."""

    name: str
    rate_hz: float
    max_range: float  # what the mapper should use as its range limit for this sensor

    def __len__(self) -> int: ...

    def read(self, index: int) -> ScanFrame: ...


def replay_order(n: int, mode: str) -> Iterator[int]:
    """Indices of a replay: ``once``; ``loop`` (0..n-1, 0..n-1, ...); ``pingpong`` (forward then
    back, so a short real sequence plays as one continuous longer drive)."""
    if n <= 0:
        return
    if mode == "once":
        yield from range(n)
    elif mode == "loop":
        while True:
            yield from range(n)
    elif mode == "pingpong":
        yield from range(n)
        while n > 1:
            yield from range(n - 2, -1, -1)
            yield from range(1, n)
    else:
        raise ValueError(f"unknown replay mode {mode!r} (once, loop, pingpong)")


class ReplayClock:
    """When each reading of a replay is due, on the monotonic clock: one ``period`` after the
    previous one, or, for frames that carry their recorded stamps (bags), as far apart as they
    were recorded times ``scale`` (a replay at another rate than the recorded one: ``scale`` =
    recorded rate / replay rate); a step back, as when a loop restarts, or a pause over
    ``max_gap`` seconds counts one period. Frames of a ``live`` source (a ROS topic) are due the
    moment they come: the topic paces itself."""

    def __init__(self, start: float, period: float, live: bool = False, max_gap: float = 10.0,
                 scale: float = 1.0) -> None:
        self.period = period
        self.live = live
        self.max_gap = max_gap
        self.scale = scale
        self._due = start
        self._stamp: float | None = None

    def due(self, stamp: float | None = None) -> float:
        if self.live:
            return -math.inf
        step = self.period
        if stamp is not None and self._stamp is not None and 0 <= stamp - self._stamp <= self.max_gap:
            step = (stamp - self._stamp) * self.scale
        self._stamp = stamp
        self._due += step
        return self._due

    def skip(self) -> None:
        """A reading that could not be read keeps its slot: one period on; after a stamped reading
        (a bag's) nothing, as the next stamp's distance from the last covers the skipped one."""
        if self.live or self._stamp is not None:
            return
        self._due += self.period

    def behind(self, now: float) -> bool:
        """Whether the reading just due is more than a period late at ``now`` (a slow first read,
        the process stalled); then the clock restarts from ``now``: a sensor that was not read
        for a while delivers its next scan, not the missed ones back to back (the simulator's
        start-up otherwise sent a dozen scans 5 ms apart into the robot's window)."""
        if self.live or now - self._due <= self.period:
            return False
        self._due = now
        return True


def _sim_options(text: str) -> dict[str, float | bool]:
    """``speed=4,sweep,laps=0.5`` as the simulator's keyword arguments."""
    out: dict[str, float | bool] = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        key, _, value = item.partition("=")
        if key == "sweep":
            out["sweep"] = value.lower() not in ("0", "false", "no", "off")
        elif key in ("speed", "laps") and value:
            try:
                out[key] = float(value)
            except ValueError:
                raise ScanSourceError(f"sim option {item!r}: {key} is a number") from None
        else:
            raise ScanSourceError(f"unknown sim option {item!r} (speed=M/S, laps=N, sweep)")
    return out


def split_bag_spec(body: str) -> tuple[Path, str | None]:
    """``PATH`` or ``PATH:/TOPIC`` (the topic is fully qualified, so it starts with ``/``)."""
    path, sep, topic = body.rpartition(":/")
    if not sep:
        return Path(body).expanduser(), None
    return Path(path).expanduser(), "/" + topic


def open_scan_source(spec: str, *, sim_seed: int = 0, bin_fields: str | None = None,
                     ros2: Ros2Link | None = None) -> ScanSource:
    """A scan source by its spec:

    * ``sim`` or ``sim:speed=4,sweep,laps=1`` (the simulator; ``sweep``: points fired over the
      rotation with their times, so a moving sensor's scan is skewed as a real one);
    * ``ros2:/TOPIC``: a live sensor_msgs/PointCloud2 topic of an rmw_zenoh graph (``ros2`` says
      how to join it; default: client of ``tcp/localhost:7447``, ``ROS_DOMAIN_ID``);
    * ``bag:PATH[:/TOPIC]``: PointCloud2 messages of a rosbag2 folder (.db3/.mcap) or ROS 1 bag,
      at their recorded pace (the topic may be left out when the bag has one cloud topic);
    * a folder of ``.bin`` (KITTI; ``.pcd.bin`` nuScenes; ``bin_fields`` declares other column
      layouts), ``.pcd`` or ``.ply`` scans.
    """
    if spec == "sim" or spec.startswith("sim:"):
        from zoffload.sources.simulated import SimulatedSource

        return SimulatedSource(seed=sim_seed, **_sim_options(spec[4:]))  # type: ignore[arg-type]
    if spec.startswith("ros2:"):
        from zoffload.ros2.session import Ros2Link
        from zoffload.sources.ros2_topic import Ros2ScanSource

        return Ros2ScanSource(spec[5:], ros2 or Ros2Link(node="zoffload_robot"))
    if spec.startswith("bag:"):
        from zoffload.sources.bag import BagScanSource

        path, topic = split_bag_spec(spec[4:])
        return BagScanSource(path, topic)
    path = Path(spec).expanduser()
    if not path.exists():
        raise ScanSourceError(f"scan folder {path} does not exist")
    if not path.is_dir():
        raise ScanSourceError(f"{path} is not a folder of scans (a bag is given as bag:{path})")
    if any(path.glob("*.bin")):
        from zoffload.sources.kitti import KittiBinSource
        from zoffload.sources.layouts import parse_layout

        try:
            layout = parse_layout(bin_fields) if bin_fields else None
        except ValueError as exc:
            raise ScanSourceError(str(exc)) from exc
        return KittiBinSource(path, layout=layout)
    if any(path.glob("*.pcd")) or any(path.glob("*.ply")):
        from zoffload.sources.pointcloud_files import PointCloudFolderSource

        return PointCloudFolderSource(path)
    raise ScanSourceError(f"no .bin, .pcd or .ply scans in {path}")
