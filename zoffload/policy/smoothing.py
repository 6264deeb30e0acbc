"""Simple moving averages, as the offloading thesis smooths its monitors and round-trip times."""

from __future__ import annotations

import math
from collections import deque


class MovingAverage:
    """Simple moving average of the last ``n`` values (NaN until the first value)."""

    def __init__(self, n: int = 10) -> None:
        self.values: deque[float] = deque(maxlen=n)

    def add(self, value: float) -> float:
        if math.isfinite(value):
            self.values.append(float(value))
        return self.value

    @property
    def value(self) -> float:
        return sum(self.values) / len(self.values) if self.values else float("nan")

    def __len__(self) -> int:
        return len(self.values)
