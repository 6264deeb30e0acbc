"""PNG figures of a run (matplotlib, headless)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from zoffload.policy.dqn import TrainResult


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_trajectory_and_map(path: Path, est_xyz: np.ndarray, ref_xyz: np.ndarray | None,
                            map_xyz: np.ndarray | None, title: str, ref_label: str = "ground truth") -> Path:
    """Top view: the map (grey), the reference and the edge's estimate."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 7))
    if map_xyz is not None and len(map_xyz):
        pts = map_xyz[:: max(1, len(map_xyz) // 150_000)]
        ax.scatter(pts[:, 0], pts[:, 1], s=0.2, c="0.6", linewidths=0, label="edge map (top view)")
    if ref_xyz is not None and len(ref_xyz):
        ax.plot(ref_xyz[:, 0], ref_xyz[:, 1], "k-", lw=2, label=ref_label)
    ax.plot(est_xyz[:, 0], est_xyz[:, 1], "r--", lw=1.5, label="edge KISS-ICP estimate")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    ax.legend(loc="best", markerscale=20)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_training_curves(path: Path, result: TrainResult) -> Path:
    """Reward (smoothed), loss and exploration rate over a DQN training run."""
    plt = _plt()
    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=False)
    w = max(1, len(result.rewards) // 300)
    smooth = np.convolve(result.rewards, np.ones(w) / w, mode="valid")
    axes[0].plot(smooth)
    axes[0].set_ylabel(f"reward (mean of {w})")
    axes[1].plot(result.losses)
    axes[1].set_ylabel("loss (every 100 eps)")
    axes[1].set_yscale("log")
    axes[2].plot(result.epsilons)
    axes[2].set_ylabel("epsilon")
    axes[2].set_xlabel("episode")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
