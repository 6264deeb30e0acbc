"""The scale-policy interface: choose each scan's voxel size from the last receive time and size.

State as in the scale-optimisation paper: ``[T_{n-1}, v_{n-1}]`` where T is the last inter-arrival
time the edge reported (seconds, edge clock; 0 before the first ack) and v the last voxel size.
Policies are pure: plain numbers in, a voxel size out.
"""

from __future__ import annotations

from typing import Protocol


class ScalePolicy(Protocol):
    name: str

    def reset(self) -> float:
        """Start of a run; returns the first voxel size."""
        ...

    def choose(self, last_t: float, last_v: float) -> float:
        """The voxel size for the next scan (0 = send the scan raw)."""
        ...


class FixedScale:
    """Always the same voxel size; 0 means no downsampling (the paper's "raw" offload)."""

    def __init__(self, voxel: float) -> None:
        if voxel < 0:
            raise ValueError(f"voxel size must be >= 0, got {voxel}")
        self.voxel = float(voxel)
        self.name = "raw" if voxel == 0 else f"fixed:{voxel:g}"

    def reset(self) -> float:
        return self.voxel

    def choose(self, last_t: float, last_v: float) -> float:
        return self.voxel
