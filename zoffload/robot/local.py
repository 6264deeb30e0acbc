"""Mapping on the robot itself, with no network: the scale-optimisation paper's "Local" row.

The same sensor replay (its rate, newest-scan-only semantics) feeds a KISS-ICP mapper in this
process; T is the time between consecutive scans reaching the mapper (robot clock), so a mapper
slower than the sensor shows up as T above the sensor period and as overrun drops.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.mapper import RobotMapper, mapper_voxel_size
from zoffload.mapping.voxel import voxel_downsample
from zoffload.robot.sensor import SensorThread
from zoffload.sources.base import ScanSource


@dataclass
class LocalRun:
    records: list[dict[str, Any]] = field(default_factory=list)
    mapper: RobotMapper | None = None
    overrun: int = 0
    gt: dict[int, np.ndarray] = field(default_factory=dict)
    cpu_s: float = 0.0  # the process's CPU time over the run (KISS-ICP is multithreaded)
    sensor_cpu_s: float = 0.0  # of which the sensor thread's (replay, simulator)


def run_local(source: ScanSource, rate_hz: float, replay: str, max_scans: int | None,
              voxel: float = 0.0, voxel_max: float = 0.07, map_resolution: float = 0.1) -> LocalRun:
    run = LocalRun()
    mapper = RobotMapper(voxel_size=mapper_voxel_size(source.max_range, voxel_max),
                         max_range=source.max_range, map_resolution=map_resolution)
    run.mapper = mapper
    sensor = SensorThread(source, rate_hz, replay, max_scans)
    cpu0 = time.process_time()
    sensor.start()
    last: float | None = None
    try:
        while True:
            reading = sensor.take(timeout=0.05)
            if reading is None:
                if sensor.exhausted:
                    break
                continue
            arrival = time.monotonic()
            pts, _ = drop_non_finite(reading.frame.points)
            sent = voxel_downsample(pts, voxel) if voxel > 0 else pts
            reg = mapper.register(reading.seq, sent)
            if reading.frame.gt_pose is not None:
                run.gt[reading.seq] = reading.frame.gt_pose
            run.records.append({
                "seq": reading.seq, "index": reading.frame.index,
                "capture_stamp": reading.capture_stamp, "voxel": voxel, "n_raw": len(pts),
                "n_sent": len(sent), "bytes": 0, "status": "acked",
                "interarrival": float("nan") if last is None else arrival - last,
                "proc_time": reg.proc_time, "map_points": reg.map_points,
            })
            last = arrival
    finally:
        sensor.stop()
    run.overrun = sensor.overwritten
    run.cpu_s, run.sensor_cpu_s = time.process_time() - cpu0, sensor.cpu_s
    return run
