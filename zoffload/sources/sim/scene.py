"""A warehouse-like scene made of axis-aligned boxes and vertical cylinders over a floor plane.

The layout is deliberately rich in structure at several ranges and heights (shelf rows of mixed
heights with cross aisles, pillars, boxes, pallets, people, a raised loading dock): a ring pattern
over flat ground between plain walls is degenerate for ICP and makes any mapper drift.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Scene:
    """Geometry the ray caster understands. Boxes are (min, max) corners; cylinders are
    ``(cx, cy, radius, z_min, z_max)``; the floor is the plane ``z = floor_z``."""

    box_min: np.ndarray  # (B, 3)
    box_max: np.ndarray  # (B, 3)
    cylinders: np.ndarray  # (C, 5)
    floor_z: float = 0.0
    labels: tuple[str, ...] = ()

    @property
    def extent(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.minimum(self.box_min.min(0), 0)
        hi = self.box_max.max(0)
        return lo, hi


class _Builder:
    def __init__(self) -> None:
        self.boxes: list[tuple[list[float], list[float]]] = []
        self.cyls: list[list[float]] = []
        self.labels: list[str] = []

    def box(self, label: str, x0: float, y0: float, z0: float, x1: float, y1: float, z1: float) -> None:
        self.boxes.append(([min(x0, x1), min(y0, y1), z0], [max(x0, x1), max(y0, y1), z1]))
        self.labels.append(label)

    def cylinder(self, cx: float, cy: float, r: float, z0: float, z1: float) -> None:
        self.cyls.append([cx, cy, r, z0, z1])

    def build(self) -> Scene:
        return Scene(
            box_min=np.array([b[0] for b in self.boxes], np.float64),
            box_max=np.array([b[1] for b in self.boxes], np.float64),
            cylinders=np.array(self.cyls, np.float64).reshape(-1, 5),
            labels=tuple(self.labels),
        )


def _clear_of(path_xy: np.ndarray, x: float, y: float, margin: float) -> bool:
    return bool(np.min(np.hypot(path_xy[:, 0] - x, path_xy[:, 1] - y)) > margin)


def warehouse(
    path_xy: np.ndarray | None = None, seed: int = 0, size: tuple[float, float] = (40.0, 24.0)
) -> Scene:
    """A 40 m x 24 m warehouse. Random clutter is kept 1.2 m away from ``path_xy`` (the robot's
    path, (K, 2)) so the robot never drives through an object."""
    rng = np.random.default_rng(seed)
    w, d = size
    b = _Builder()
    path = path_xy if path_xy is not None else np.array([[-100.0, -100.0]])

    # Walls, 6 m high, with door recesses that break the long planes
    t, h = 0.3, 6.0
    b.box("wall", -t, -t, 0, w + t, 0, h)
    b.box("wall", -t, d, 0, w + t, d + t, h)
    b.box("wall", -t, 0, 0, 0, d, h)
    b.box("wall", w, 0, 0, w + t, 9.0, h)
    b.box("wall", w, 12.0, 0, w + t, d, h)
    b.box("wall", w + 3.0, 9.0, 0, w + t + 3.0, 12.0, h)  # behind the open dock door
    b.box("wall", w, 8.7, 0, w + 3.3, 9.0, h)
    b.box("wall", w, 12.0, 0, w + 3.3, 12.3, h)
    # Loading dock: a raised platform, a floor edge at two heights
    b.box("dock", w - 2.5, 9.0, 0, w, 12.0, 0.6)

    # Shelf rows along x with cross aisles; segment heights vary
    for row_y in (6.0, 10.5, 15.0, 19.5):
        x = 8.0
        while x < 32.0:
            seg = float(rng.uniform(4.0, 7.0))
            x1 = min(x + seg, 32.0)
            height = float(rng.choice([2.2, 3.2, 4.4]))
            if not all(_clear_of(path, sx, row_y, 1.6) for sx in np.linspace(x, x1, 12)):
                x = x1 + float(rng.uniform(1.6, 2.6))
                continue  # the robot's path crosses the row here: leave a cross aisle
            # A rack: uprights, beams and shelf boards at several heights, goods on the boards
            for ux in np.arange(x, x1, 1.8):
                b.box("upright", ux, row_y - 0.55, 0, ux + 0.1, row_y + 0.55, height + 0.3)
            levels = np.arange(0.15, height, 1.1)
            for lz in levels:
                b.box("shelf", x, row_y - 0.5, lz, x1, row_y + 0.5, lz + 0.06)
                gx = x + float(rng.uniform(0.1, 0.6))
                while gx < x1 - 0.5:
                    gw = float(rng.uniform(0.4, 1.1))
                    gh = float(rng.uniform(0.25, 0.8))
                    gd = float(rng.uniform(0.5, 0.95))
                    if rng.random() < 0.7:
                        b.box("goods", gx, row_y - gd / 2, lz + 0.06, min(gx + gw, x1), row_y + gd / 2,
                              min(lz + 0.06 + gh, lz + 1.0))
                    gx += gw + float(rng.uniform(0.1, 0.8))
            b.box("shelf", x, row_y - 0.5, height, x1, row_y + 0.5, height + 0.06)
            x = x1 + float(rng.uniform(1.6, 2.6))

    # Pillars on a grid, where they do not block the path
    for px in np.arange(4.0, w, 8.0):
        for py in (3.8, d - 3.8):
            if _clear_of(path, px, py, 1.0):
                b.box("pillar", px - 0.25, py - 0.25, 0, px + 0.25, py + 0.25, h)

    # Boxes, pallets and people scattered where the robot does not drive
    placed = 0
    while placed < 80:
        x, y = float(rng.uniform(1.5, w - 1.5)), float(rng.uniform(1.5, d - 1.5))
        kind = rng.choice(["box", "pallet", "person"], p=[0.5, 0.3, 0.2])
        sx, sy = (1.2, 0.8) if kind == "pallet" else tuple(rng.uniform(0.4, 1.2, size=2))
        # Centred footprint; keep its far corner 1 m from the path
        if not _clear_of(path, x, y, 1.0 + 0.5 * float(np.hypot(sx, sy))):
            continue
        x0, y0, x1, y1 = x - sx / 2, y - sy / 2, x + sx / 2, y + sy / 2
        if kind == "box":
            b.box("box", x0, y0, 0, x1, y1, float(rng.uniform(0.4, 1.2)))
        elif kind == "pallet":
            b.box("pallet", x0, y0, 0, x1, y1, 0.15)
            b.box("box", x0 + 0.1, y0 + 0.1, 0.15, x1 - 0.1, y1 - 0.1, float(rng.uniform(0.6, 1.6)))
        else:
            b.cylinder(x, y, 0.25, 0.0, float(rng.uniform(1.55, 1.9)))
        placed += 1
    return b.build()
