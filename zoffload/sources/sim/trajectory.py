"""Ground-truth trajectories for the simulator: a smooth closed path sampled at the sensor rate."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Trajectory:
    """A closed planar path, arc-length parametrised, driven at a constant speed."""

    xy: np.ndarray  # (K, 2) densely sampled closed path
    s: np.ndarray  # (K,) arc length at each sample
    speed: float
    height: float  # sensor height above the floor
    accel_time: float = 2.0  # starts from standstill, reaches ``speed`` after this many seconds
    bounce: float = 0.02  # sensor height oscillation amplitude [m] (suspension, uneven floor)

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def distance_at(self, t: float) -> float:
        """Distance driven after ``t`` seconds: constant acceleration, then constant speed."""
        ta = self.accel_time
        if ta > 0 and t < ta:
            return 0.5 * self.speed * t * t / ta
        return self.speed * (t - 0.5 * ta)

    def pose_at(self, t: float) -> np.ndarray:
        """4x4 sensor-to-world pose at time ``t`` seconds (loops around the path)."""
        s = self.distance_at(t) % self.length
        x = float(np.interp(s, self.s, self.xy[:, 0]))
        y = float(np.interp(s, self.s, self.xy[:, 1]))
        ds = 0.25
        x2 = float(np.interp((s + ds) % self.length, self.s, self.xy[:, 0]))
        y2 = float(np.interp((s + ds) % self.length, self.s, self.xy[:, 1]))
        yaw = float(np.arctan2(y2 - y, x2 - x))
        c, sn = np.cos(yaw), np.sin(yaw)
        pose = np.eye(4)
        pose[:2, :2] = [[c, -sn], [sn, c]]
        # The sensor bobs on its mount: without it, a level LiDAR's floor rings land on the same
        # sensor-frame points every scan and pull ICP towards zero motion.
        wave = 0.6 * np.sin(2 * np.pi * 1.7 * t) + 0.4 * np.sin(2 * np.pi * 0.37 * t + 1.0)
        z = self.height + self.bounce * wave
        pose[:3, 3] = [x, y, z]
        return pose


    def poses_at(self, times: np.ndarray) -> np.ndarray:
        """``pose_at`` of many times at once, (n, 4, 4) (a sweep's column poses); times before
        the start are the start."""
        return np.stack([self.pose_at(max(0.0, float(t))) for t in np.asarray(times, np.float64)])


def _chaikin(points: np.ndarray, rounds: int) -> np.ndarray:
    """Corner-cutting on a closed polygon: rounds the corners so yaw changes smoothly."""
    for _ in range(rounds):
        nxt = np.roll(points, -1, axis=0)
        q = 0.75 * points + 0.25 * nxt
        r = 0.25 * points + 0.75 * nxt
        points = np.stack([q, r], axis=1).reshape(-1, 2)
    return points


def closed_path(waypoints: np.ndarray, speed: float, height: float, step: float = 0.05) -> Trajectory:
    smooth = _chaikin(np.asarray(waypoints, np.float64), 5)
    closed = np.vstack([smooth, smooth[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    dense_s = np.arange(0.0, s[-1], step)
    xy = np.stack([np.interp(dense_s, s, closed[:, 0]), np.interp(dense_s, s, closed[:, 1])], 1)
    xy = np.vstack([xy, xy[:1]])
    dense_s = np.append(dense_s, s[-1])
    return Trajectory(xy=xy, s=dense_s, speed=speed, height=height)


def warehouse_loop(speed: float = 1.2, height: float = 0.8) -> Trajectory:
    """A loop through the warehouse: the outer aisle, then down a middle aisle and back."""
    wp = np.array(
        [[3.0, 2.2], [36.5, 2.2], [36.5, 12.8], [20.0, 12.8], [20.0, 8.3], [5.0, 8.3], [5.0, 21.8],
         [36.5, 21.8], [36.5, 17.2], [3.0, 17.2], [3.0, 6.0]]
    )
    return closed_path(wp, speed=speed, height=height)
