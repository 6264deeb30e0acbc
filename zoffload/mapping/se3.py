"""Rigid motions: SE(3) raised to a real power (a constant screw motion stretched or shrunk)."""

from __future__ import annotations

import numpy as np


def _skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def _so3_exp_v(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation exp(w^) and the SE(3) left Jacobian V(w) (maps the twist's translation part)."""
    th = float(np.linalg.norm(w))
    W = _skew(w)
    if th < 1e-9:
        return np.eye(3) + W, np.eye(3) + 0.5 * W
    R = np.eye(3) + np.sin(th) / th * W + (1 - np.cos(th)) / th**2 * W @ W
    V = np.eye(3) + (1 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * W @ W
    return R, V


def se3_power(T: np.ndarray, a: float) -> np.ndarray:
    """``T`` raised to a real power: the same constant screw motion ``a`` times over
    (``exp(a log T)``)."""
    R, t = T[:3, :3], T[:3, 3]
    angle = float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
    if angle < 1e-9:
        w = np.zeros(3)
    else:
        w = angle / (2 * np.sin(angle)) * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    _, V = _so3_exp_v(w)
    rho = np.linalg.solve(V, t)
    Ra, Va = _so3_exp_v(a * w)
    out = np.eye(4)
    out[:3, :3] = Ra
    out[:3, 3] = Va @ (a * rho)
    return out
