"""SE(3) raised to a real power."""

from __future__ import annotations

import numpy as np


def test_se3_power() -> None:
    from zoffload.mapping.se3 import se3_power

    c, s = np.cos(0.05), np.sin(0.05)
    step = np.array([[c, -s, 0, 0.12], [s, c, 0, 0.01], [0, 0, 1, 0], [0, 0, 0, 1]])
    np.testing.assert_allclose(se3_power(step, 3), step @ step @ step, atol=1e-12)
    np.testing.assert_allclose(se3_power(step, 1), step, atol=1e-12)
    root = se3_power(step @ step @ step @ step, 0.25)
    np.testing.assert_allclose(root[:3, :3], step[:3, :3], atol=1e-9)
    np.testing.assert_allclose(root[:3, 3], step[:3, 3], atol=1e-9)
