"""How the edge makes and bounds a robot's mapper.

``MapperRecipe`` builds a robot's KISS-ICP from its first scan: the robot's sensor range and voxel
bound fill what the edge's settings leave open (``mapping.mapper.mapper_voxel_size``), clamped to
sane values, because the scan that sizes the mapper comes from the network: the codec admits a
``max_range`` up to 10 km and a ``voxel_max`` up to 10 m, and KISS-ICP at such values registers
nothing useful (its voxel would be 100 m) even though it survives them (checked with 10,000 m and
0.1 m ranges, 0.001 m and 100 m voxels).

``BoundedMapper`` wraps ``RobotMapper`` with the edge's memory budget, the policy being:

* **Range.** Points farther than the mapper's ``max_range`` are dropped before registration:
  KISS-ICP ignores them anyway, and the global map would refuse a point too far for its grid
  only after KISS-ICP had already moved on (a pose without its scan).
* **Global map.** At most ``map_budget`` points (``VoxelSet.max_points``): once reached, points in
  new voxels are counted (``map_overflow``) and not stored; the map keeps what it has.
* **Trajectory.** At most ``trajectory_budget`` poses stay in memory (plus one chunk of a tenth of
  that, so trimming is occasional). Older poses are handed to ``spill`` (the mapping service
  writes them to ``map_dir`` and merges them into the exported trajectory) or, without one, only
  counted. Map replies carry the poses in memory; their ``scans`` counts every registered scan.

In a fleet, the mapper also hands out its state as a checkpoint (``checkpoint``: coarse local map,
pose, motion; mapping/checkpoint.py) and continues a robot's trajectory from one
(``continue_from``: the odometry seeded, the robot's own poses appended to the trajectory).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from zoffload.mapping import voxel, voxelset
from zoffload.mapping.checkpoint import take_checkpoint
from zoffload.mapping.mapper import Registration, RobotMapper, load_kiss_icp, mapper_voxel_size
from zoffload.protocol import wire

log = logging.getLogger("zoffload.edge.mapping")

# A mapper sized from a hostile or broken scan still gets values KISS-ICP is meant for
RANGE_BOUNDS = (1.0, 1000.0)  # metres: an indoor sensor to the longest automotive LiDARs
VOXEL_BOUNDS = (0.02, 10.0)  # metres

Spill = Callable[[np.ndarray, np.ndarray], None]  # (seqs, poses) leaving memory


def clamp(value: float, bounds: tuple[float, float]) -> float:
    return float(min(max(value, bounds[0]), bounds[1]))


class BoundedMapper:
    """A robot's ``RobotMapper`` under the edge's budgets (see the module docstring)."""

    def __init__(self, inner: RobotMapper, max_range: float, trajectory_budget: int = 100_000,
                 spill: Spill | None = None) -> None:
        self.inner = inner
        self.max_range = max_range
        self.trajectory_budget = trajectory_budget
        self.spill = spill
        self.trimmed = 0  # poses that left memory

    @property
    def map_points(self) -> int:
        return self.inner.map_points

    @property
    def map_overflow(self) -> int:
        return self.inner.global_map.overflow

    @property
    def scans(self) -> int:
        return self.inner.registered

    @property
    def backfilled(self) -> int:
        return self.inner.backfilled

    @property
    def backfill_unused(self) -> int:
        return self.inner.backfill_unused

    @property
    def backfill_posed(self) -> int:
        return self.inner.backfill_posed

    @property
    def priors_moved(self) -> int:
        return self.inner.priors_moved

    @property
    def backfilled_seqs(self) -> Sequence[int]:
        return self.inner.backfilled_seqs

    def _near(self, points: np.ndarray, times: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray | None]:
        if len(points) and max(float(points.max()), -float(points.min())) > self.max_range:
            near = np.einsum("ij,ij->i", points, points) <= self.max_range**2
            points = points[near]
            times = times[near] if times is not None and len(times) == len(near) else times
        return points, times

    def register(self, seq: int, points: np.ndarray, times: np.ndarray | None = None) -> Registration:
        points, times = self._near(points, times)
        if len(points) == 0:
            raise ValueError(f"no point within the mapper's range of {self.max_range:g} m")
        # Per-point times only when there are some: the mapper deskews with them if made to
        reg = self.inner.register(seq, points) if times is None else self.inner.register(seq, points, times)
        self._trim()
        return reg

    def _trim(self) -> None:
        seqs, poses = self.inner.seqs, self.inner.poses
        if len(seqs) <= self.trajectory_budget + max(1, self.trajectory_budget // 10):
            return
        k = len(seqs) - self.trajectory_budget
        if self.spill is not None:
            self.spill(np.asarray(seqs[:k], np.int64), np.asarray(poses[:k], np.float64).reshape(-1, 4, 4))
        # RobotMapper only reads its last seq (scan gaps) and hands both lists out in trajectory()
        del seqs[:k]
        del poses[:k]
        self.trimmed += k

    def map_cloud(self) -> np.ndarray:
        return self.inner.map_cloud()

    def continue_from(self, checkpoint: wire.Checkpoint | None, local_seqs: np.ndarray,
                      local_poses: np.ndarray, backfill: Sequence[tuple[int, np.ndarray]] = (),
                      backfill_poses: np.ndarray | None = None) -> bool:
        near = [(seq, self._near(points)[0]) for seq, points in backfill]
        ok = [bool(len(points)) for _, points in near]
        kept = [b for b, k in zip(near, ok, strict=True) if k]
        self.inner.backfill_unused += len(near) - len(kept)  # no point within the mapper's range
        poses = (np.asarray(backfill_poses)[np.asarray(ok, bool)]
                 if backfill_poses is not None and len(backfill_poses) == len(near) else None)
        seeded = self.inner.continue_from(checkpoint, local_seqs, local_poses, kept, poses)
        self._trim()
        return seeded

    def predict_from(self, seq: int, prior_seq: int, pose: np.ndarray, delta: np.ndarray,
                     contest: bool = False, frame: int = -1) -> bool:
        return self.inner.predict_from(seq, prior_seq, pose, delta, contest, frame)

    def checkpoint(self, robot: str, edge: str, epoch: int, stamp: float, resolution: float | None = None,
                   final: bool = False, coded: bool = True) -> wire.Checkpoint | None:
        """The odometry's state after its last scan (``coded``: its map as version 6 codes it);
        None before it has one."""
        if self.inner.last_seq is None:
            return None
        cp = take_checkpoint(self.inner.odometry, robot, edge, epoch, self.inner.last_seq, stamp, resolution,
                             coded, self.inner.turn_rate)
        return replace(cp, final=True) if final else cp

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        return self.inner.trajectory()


@dataclass(frozen=True)
class MapperRecipe:
    """Builds a robot's bounded KISS-ICP on its first scan (see the module docstring)."""

    voxel_size: float | None = None
    min_range: float = 0.0
    max_range: float | None = None
    max_points_per_voxel: int = 20
    deskew: bool = False
    map_resolution: float = 0.1
    map_budget: int = 2_000_000
    trajectory_budget: int = 100_000

    def warm_up(self) -> None:
        # Compile the map kernels and load KISS-ICP now, not while the first scans queue up
        voxel.warmup()
        voxelset.warmup()
        load_kiss_icp()

    def mapper(self, max_range: float, voxel_max: float) -> RobotMapper:
        """The KISS-ICP for a robot that says this max range and voxel_max: the edge's own
        settings are taken as they are; what the robot says is clamped (also the offline remap's,
        lab/remap.py)."""
        max_range = self.max_range or clamp(max_range, RANGE_BOUNDS)
        size = self.voxel_size or clamp(mapper_voxel_size(max_range, voxel_max), VOXEL_BOUNDS)
        inner = RobotMapper(voxel_size=size, max_range=max_range, min_range=self.min_range,
                            max_points_per_voxel=self.max_points_per_voxel, deskew=self.deskew,
                            map_resolution=self.map_resolution)
        inner.global_map.set_budget(self.map_budget)
        return inner

    def __call__(self, scan: wire.Scan, spill: Spill | None = None) -> BoundedMapper:
        return self.bounded(scan.robot, scan.max_range, scan.voxel_max, spill)

    def bounded(self, robot: str, max_range: float, voxel_max: float,
                spill: Spill | None = None) -> BoundedMapper:
        """The bounded mapper for ``robot``, sized from what its first scan says."""
        inner = self.mapper(max_range, voxel_max)
        kept_range = inner.config.data.max_range
        log.info("robot %s: KISS-ICP voxel %.3f m, max range %.1f m (robot: max range %.1f m, voxel_max "
                 "%.3f m)", robot, inner.voxel_size, kept_range, max_range, voxel_max)
        return BoundedMapper(inner, kept_range, self.trajectory_budget, spill)
