"""A daemon's figures written at the end of a run (``vision_metrics.json``, ``robot_metrics.json``,
the edge's ``<robot>_edge.json``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def _plain(value: Any) -> Any:
    """``json.dumps``'s fallback for numpy scalars (``np.bool_``, ``np.float32``...): their value."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")


def write_figures(path: Path, figures: dict[str, Any]) -> None:
    """The run's figures as JSON: a numpy number that slipped into them is written as the number
    (a numpy bool once lost a whole run's ``vision_metrics.json`` at shutdown)."""
    path.write_text(json.dumps(figures, indent=2, default=_plain))
