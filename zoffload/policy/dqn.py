"""DQN training for the scale policy (PyTorch; the ``train`` extra), and ONNX export.

As the paper: 3 linear layers (2 hidden), Adam lr 0.0005, discount 0.98, batch 64, a replay
buffer, a target network, epsilon-greedy exploration; one scan = one episode (so every
transition is terminal and the target is the reward; the discount is kept for generality).
The state is normalised inside the network, so the exported ONNX model takes the raw
``[T, v]`` and the robot needs nothing but onnxruntime.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.policy.env import ScaleEnv
from zoffload.policy.mdp import ACTIONS


@dataclass(frozen=True)
class DQNConfig:
    episodes: int = 300_000
    hidden: int = 64
    lr: float = 0.0005
    gamma: float = 0.98
    batch: int = 64
    buffer: int = 100_000
    target_every: int = 1_000  # episodes between target-network syncs
    eps_start: float = 1.0
    eps_end: float = 0.05
    eps_decay_fraction: float = 0.5  # share of the episodes over which epsilon decays linearly
    level_switch: float = 0.02  # per-scan chance the link level changes (states follow the link)
    seed: int = 0


def _torch() -> Any:
    try:
        import torch
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("training needs torch: pip install 'zoffload[train]'") from exc
    return torch


def make_network(hidden: int) -> Any:
    torch = _torch()
    nn = torch.nn

    class ScaleQNet(nn.Module):  # type: ignore[name-defined]
        def __init__(self) -> None:
            super().__init__()
            self.register_buffer("mean", torch.tensor([0.15, 0.04]))
            self.register_buffer("scale", torch.tensor([0.2, 0.03]))
            self.body = nn.Sequential(
                nn.Linear(2, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                nn.Linear(hidden, len(ACTIONS)),
            )

        def forward(self, state: Any) -> Any:
            return self.body((state - self.mean) / self.scale)

    return ScaleQNet()


@dataclass
class TrainResult:
    rewards: np.ndarray  # per episode
    losses: np.ndarray  # per gradient step
    epsilons: np.ndarray
    seconds: float


def train(env: ScaleEnv, cfg: DQNConfig, progress: bool = True) -> tuple[Any, TrainResult]:
    torch = _torch()
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(1)  # a tiny MLP: one thread is fastest and leaves the other core free
    rng = np.random.default_rng(cfg.seed)
    online, target = make_network(cfg.hidden), make_network(cfg.hidden)
    target.load_state_dict(online.state_dict())
    opt = torch.optim.Adam(online.parameters(), lr=cfg.lr)
    n_levels = len(env.link.levels)
    # Replay buffer: state, action, reward, next state, done
    S = np.zeros((cfg.buffer, 2), np.float32)
    A = np.zeros(cfg.buffer, np.int64)
    R = np.zeros(cfg.buffer, np.float32)
    S2 = np.zeros((cfg.buffer, 2), np.float32)
    D = np.ones(cfg.buffer, np.float32)
    rewards = np.zeros(cfg.episodes, np.float32)
    epsilons = np.zeros(cfg.episodes, np.float32)
    losses: list[float] = []
    state = env.mdp.initial_state()
    level = int(rng.integers(n_levels))
    decay = max(1, int(cfg.episodes * cfg.eps_decay_fraction))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.episodes, unit="ep", mininterval=1.0)
    t0 = time.perf_counter()
    for ep in range(cfg.episodes):
        eps = max(cfg.eps_end, cfg.eps_start - (cfg.eps_start - cfg.eps_end) * ep / decay)
        if rng.random() < cfg.level_switch:
            level = int(rng.integers(n_levels))
        # Act
        if rng.random() < eps:
            action = int(rng.integers(len(ACTIONS)))
        else:
            with torch.no_grad():
                action = int(online(torch.tensor([state], dtype=torch.float32)).argmax(1).item())
        reward, nxt = env.step(state, action, level)
        i = ep % cfg.buffer
        S[i], A[i], R[i], S2[i], D[i] = state, action, reward, nxt, 1.0  # one scan = one episode
        rewards[ep], epsilons[ep] = reward, eps
        state = nxt
        # Learn
        filled = min(ep + 1, cfg.buffer)
        if filled >= cfg.batch:
            idx = rng.integers(0, filled, size=cfg.batch)
            s, a, r = torch.from_numpy(S[idx]), torch.from_numpy(A[idx]), torch.from_numpy(R[idx])
            s2, d = torch.from_numpy(S2[idx]), torch.from_numpy(D[idx])
            with torch.no_grad():
                y = r + cfg.gamma * (1 - d) * target(s2).max(1).values
            q = online(s).gather(1, a[:, None]).squeeze(1)
            loss = torch.nn.functional.smooth_l1_loss(q, y)
            opt.zero_grad()
            loss.backward()
            opt.step()
            if ep % 100 == 0:
                losses.append(float(loss.item()))
        if ep % cfg.target_every == 0:
            target.load_state_dict(online.state_dict())
        if bar is not None and ep % 1000 == 0:
            bar.update(1000 if ep else 1)
            bar.set_postfix(reward=f"{rewards[max(0, ep - 5000):ep + 1].mean():.3f}", eps=f"{eps:.2f}")
    if bar is not None:
        bar.close()
    return online, TrainResult(rewards, np.array(losses), epsilons, time.perf_counter() - t0)


def export_onnx(net: Any, path: Path) -> Path:
    """Export with input ``state`` (N x 2: T [s], v [m]) and output ``q`` (N x 3)."""
    torch = _torch()
    net.eval()
    path.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.tensor([[0.1, 0.05]], dtype=torch.float32)
    from torch.export import Dim

    torch.onnx.export(net, (dummy,), str(path), input_names=["state"], output_names=["q"],
                      dynamic_shapes={"state": {0: Dim("n")}}, dynamo=True, verbose=False,
                      external_data=False)  # one self-contained file for the robot
    return path


def greedy_actions(net: Any, states: np.ndarray) -> np.ndarray:
    torch = _torch()
    with torch.no_grad():
        return net(torch.from_numpy(states.astype(np.float32))).argmax(1).numpy()


def write_metrics(path: Path, cfg: DQNConfig, result: TrainResult, extra: dict[str, Any]) -> Path:
    last = result.rewards[-max(1, len(result.rewards) // 10):]
    data = {"config": asdict(cfg), "seconds": result.seconds,
            "mean_reward_last_10pct": float(last.mean()), **extra}
    path.write_text(json.dumps(data, indent=2))
    return path
