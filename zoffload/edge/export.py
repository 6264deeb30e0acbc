"""What the edge writes of one robot's map session to ``map_dir``.

Files of a robot's first session in this process: ``<robot>_map.<fmt>``, ``<robot>_trajectory.npz``
(``seqs``, ``poses``), ``<robot>_edge.json`` (its counters, and the seqs of the outage scans its
backfills registered, ``backfilled_seqs``). A robot evicted for idleness and back
later starts a new map in a new frame (KISS-ICP starts at the identity again): session ``g`` writes
``<robot>_map.<g>.<fmt>`` and so on, so no export overwrites another. Poses trimmed from memory
during a session go to ``<robot>_trajectory[.<g>].part<k>.npz`` and are merged into the exported
trajectory (the part files are then removed).
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from zoffload.mapping.export import write_point_cloud
from zoffload.runtime.results import write_figures


def registered_backfill(summary: object) -> set[int] | None:
    """The seqs in a ``<robot>_edge.json`` summary's ``backfilled_seqs`` (what ``RobotFiles.export``
    writes: the outage scans the edge registered from backfills); None when it does not list them."""
    seqs = summary.get("backfilled_seqs") if isinstance(summary, dict) else None
    return {int(s) for s in seqs if isinstance(s, int)} if isinstance(seqs, list) else None


class MapSource(Protocol):
    @property
    def map_points(self) -> int: ...

    def map_cloud(self) -> np.ndarray: ...

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]: ...


class RobotFiles:
    def __init__(self, folder: Path | None, robot: str, generation: int = 0, fmt: str = "ply") -> None:
        self.folder = folder
        self.robot = robot
        self.fmt = fmt
        self.generation = generation
        self.suffix = f".{generation}" if generation else ""
        self.parts: list[Path] = []
        self.spilled = 0  # poses written to part files

    def path(self, kind: str, ext: str) -> Path:
        assert self.folder is not None, "no map_dir"
        return self.folder / f"{self.robot}_{kind}{self.suffix}.{ext}"

    def spill(self, seqs: np.ndarray, poses: np.ndarray) -> None:
        """Keep poses leaving memory on disk (without a folder they are only counted)."""
        self.spilled += len(seqs)
        if self.folder is None:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        part = self.folder / f"{self.robot}_trajectory{self.suffix}.part{len(self.parts)}.npz"
        np.savez(part, seqs=seqs, poses=poses)
        self.parts.append(part)

    def export(self, mapper: MapSource, counters: dict[str, int]) -> Path | None:
        """Write the map, the whole trajectory and the counters; the map's path (None: no folder,
        or an empty map)."""
        if self.folder is None:
            return None
        self.folder.mkdir(parents=True, exist_ok=True)
        seqs, poses = mapper.trajectory()
        if self.parts:
            loaded = [np.load(p) for p in self.parts]
            seqs = np.concatenate([p["seqs"] for p in loaded] + [seqs])
            poses = np.concatenate([p["poses"] for p in loaded] + [poses])
        np.savez(self.path("trajectory", "npz"), seqs=seqs, poses=poses)
        for p in self.parts:
            p.unlink(missing_ok=True)
        self.parts = []
        summary: dict[str, object] = dict(counters, map_points=mapper.map_points)
        backfilled = getattr(mapper, "backfilled_seqs", None)
        if backfilled is not None:  # which outage scans its backfills registered (the newest 100,000)
            summary["backfilled_seqs"] = [int(s) for s in backfilled]
        write_figures(self.path("edge", "json"), summary)
        cloud = mapper.map_cloud()
        if len(cloud) == 0:  # nothing registered (every scan refused): no map file to write
            return None
        return write_point_cloud(self.path("map", self.fmt), cloud)
