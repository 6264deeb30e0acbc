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


def test_as_rigid_projects_float_noise_and_replaces_what_is_not_finite() -> None:
    from zoffload.mapping.se3 import as_rigid

    c, s = np.cos(0.3), np.sin(0.3)
    pose = np.array([[c, -s, 0, 1.0], [s, c, 0, 2.0], [0, 0, 1, 3.0], [0, 0, 0, 1]])
    noisy = pose.copy()
    noisy[:3, :3] += 1e-7
    noisy[3] = [1e-9, 0, 0, 1]
    out = as_rigid(noisy)
    np.testing.assert_allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3), atol=1e-14)
    assert abs(np.linalg.det(out[:3, :3]) - 1) < 1e-14 and list(out[3]) == [0, 0, 0, 1]
    np.testing.assert_allclose(out, pose, atol=1e-6)
    np.testing.assert_array_equal(as_rigid(np.full((4, 4), np.nan)), np.eye(4))
    np.testing.assert_array_equal(as_rigid(np.full((4, 4), np.inf), fallback=pose), pose)
    assert np.linalg.det(as_rigid(np.diag([-1.0, 1, 1, 1]))[:3, :3]) > 0  # a reflection is not a motion
