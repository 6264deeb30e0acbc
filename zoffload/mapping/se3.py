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


def as_rigid(T: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray:
    """The rigid motion nearest ``T`` (rotation through an SVD, determinant +1; last row exactly
    0 0 0 1), as a new float64 4x4 array, or ``fallback`` (identity by default) when ``T`` is not a
    finite 4x4 matrix. KISS-ICP's Sophus aborts the whole process on a rotation off by more than
    1e-10, so every pose that came from outside (an ack, a checkpoint, an attach) or from long
    products of our own goes through this before it is handed to an odometry."""
    m = np.asarray(T, np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        return np.eye(4) if fallback is None else np.array(fallback, np.float64)
    u, _, vt = np.linalg.svd(m[:3, :3])
    if np.linalg.det(u @ vt) < 0:
        u[:, -1] = -u[:, -1]
    out = np.eye(4)
    out[:3, :3] = u @ vt
    out[:3, 3] = m[:3, 3]
    return out
