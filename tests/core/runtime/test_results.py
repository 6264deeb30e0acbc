"""A daemon's figures written at the end of a run (runtime/results.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from zoffload.runtime.results import write_figures


def test_numpy_numbers_in_the_figures_are_written_as_numbers(tmp_path: Path) -> None:
    # what the robot's and the edge's results are written with
    figures = {"a": np.bool_(True), "b": {"c": np.float32(1.5)}, "d": [np.int64(3)]}
    write_figures(tmp_path / "m.json", figures)
    assert json.loads((tmp_path / "m.json").read_text()) == {"a": True, "b": {"c": 1.5}, "d": [3]}
    with pytest.raises(TypeError, match="object"):  # a value that is no number is still refused
        write_figures(tmp_path / "x.json", {"x": object()})
