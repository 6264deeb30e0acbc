"""The scale-optimisation paper's MDP, exactly.

State ``[T_{n-1}, v_{n-1}]``: the last receive time (inter-arrival at the edge, s) and the last
voxel size (m); start ``T0 = 0``, ``v0 = 0.05``. Actions: 0 = ``v - 0.02``, 1 = keep,
2 = ``v + 0.02``, the result clamped to ``[v_min, v_max] = [0.01, 0.07]``. One scan is one episode.

Reward, with ``ratio = S'/S`` the fraction of the scan's points kept, ``T`` the receive time
observed for the scan sent under the action and ``v`` the voxel size after it:

* eq. 7, ``T < T_ref``:  a0 -> +ratio,  a1 -> 0,                           a2 -> -ratio
* eq. 8, ``T >= T_ref``: a0 -> -ratio,  a1 -> (v - v_max) * ratio * 10,    a2 -> 0

``T_ref = 0.11`` s: a 10 Hz sensor received without delay.
"""

from __future__ import annotations

from dataclasses import dataclass

DECREASE, KEEP, INCREASE = 0, 1, 2
ACTIONS = (DECREASE, KEEP, INCREASE)


@dataclass(frozen=True)
class ScaleMDP:
    v_min: float = 0.01
    v_max: float = 0.07
    step: float = 0.02
    v0: float = 0.05
    t0: float = 0.0
    t_ref: float = 0.11

    def __post_init__(self) -> None:
        if not 0 < self.v_min <= self.v0 <= self.v_max:
            raise ValueError(f"need 0 < v_min <= v0 <= v_max, got {self.v_min}, {self.v0}, {self.v_max}")
        if self.step <= 0 or self.t_ref <= 0:
            raise ValueError("step and t_ref must be positive")

    def initial_state(self) -> tuple[float, float]:
        return (self.t0, self.v0)

    def apply(self, v: float, action: int) -> float:
        """The voxel size after ``action``, clamped to the range (rounded to kill float dust)."""
        if action not in ACTIONS:
            raise ValueError(f"action must be 0, 1 or 2, got {action!r}")
        nxt = v + (action - 1) * self.step
        return round(min(self.v_max, max(self.v_min, nxt)), 9)

    def clamp_state(self, t: float, v: float) -> tuple[float, float]:
        """Out-of-range observations (a negative or non-finite T, a v off the range) are clamped,
        never raised: a policy must always get a usable state."""
        t = t if t == t and t >= 0 else 0.0  # NaN or negative -> 0
        t = min(t, 60.0)
        v = v if v == v else self.v0
        return (t, min(self.v_max, max(self.v_min, v)))

    def reward(self, t: float, action: int, v: float, ratio: float) -> float:
        """Eq. 7 / eq. 8 of the paper (see the module docstring)."""
        if action not in ACTIONS:
            raise ValueError(f"action must be 0, 1 or 2, got {action!r}")
        if t < self.t_ref:
            return (ratio, 0.0, -ratio)[action]
        return (-ratio, (v - self.v_max) * ratio * 10.0, 0.0)[action]
