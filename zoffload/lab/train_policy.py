"""``zoffload train-policy``: recorded runs -> fitted environment -> DQN -> ONNX, with metrics."""

from __future__ import annotations

import json
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.lab.eval.plots import plot_training_curves
from zoffload.policy.dqn import DQNConfig, export_onnx, greedy_actions, train, write_metrics
from zoffload.policy.env import LinkModel, Retention, ScaleEnv, read_records
from zoffload.policy.mdp import ScaleMDP


def rollout(env: ScaleEnv, choose: Any, level: int, steps: int = 2000) -> dict[str, float]:
    """Mean reward, mean T and share of T <= t_ref of a policy on one link level."""
    state = env.mdp.initial_state()
    rewards, times, voxels = [], [], []
    for _ in range(steps):
        action = choose(state)
        r, state = env.step(state, action, level)
        rewards.append(r)
        times.append(state[0])
        voxels.append(state[1])
    t = np.array(times)
    return {"reward": float(np.mean(rewards)), "T_mean": float(t.mean()),
            "T_le_ref": float((t < env.mdp.t_ref).mean()), "v_mean": float(np.mean(voxels))}


def run_training(
    data: list[Path], out: Path, cfg: DQNConfig, voxel_range: tuple[float, float]
) -> dict[str, Any]:
    records = read_records(d / "scans.csv" for d in data)
    retention, link = Retention.fit(records), LinkModel.fit(records)
    lo, hi = voxel_range
    mdp = ScaleMDP(v_min=lo, v_max=hi, v0=min(hi, max(lo, 0.05)))
    env = ScaleEnv(mdp, retention, link, seed=cfg.seed)
    print(f"training on {len(records)} recorded scans from {len(data)} runs; link levels (Mbps): "
          f"{[round(lv.rate_mbps, 1) for lv in link.levels]}; voxel range {voxel_range}", flush=True)
    net, result = train(env, cfg)
    out.mkdir(parents=True, exist_ok=True)
    model = export_onnx(net, out / "dqn_scale.onnx")
    # The exported graph must answer exactly as the trained network
    import onnxruntime as ort

    grid = np.array([(t, v) for t in np.linspace(0, 0.6, 25) for v in np.linspace(lo, hi, 7)], np.float32)
    sess = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    onnx_actions = sess.run(None, {"state": grid})[0].argmax(1)
    assert np.array_equal(onnx_actions, greedy_actions(net, grid)), "ONNX export disagrees with torch"
    # Evaluate: the greedy DQN against fixed voxel sizes on every link level
    eval_env = ScaleEnv(mdp, retention, link, seed=cfg.seed + 1)

    def dqn(state: tuple[float, float]) -> int:
        return int(greedy_actions(net, np.array([state]))[0])

    evaluation: dict[str, Any] = {}
    for level in range(len(link.levels)):
        key = f"level_{level}_{link.levels[level].rate_mbps:.0f}Mbps"
        evaluation[key] = {"dqn": rollout(eval_env, dqn, level)}
        for v in (voxel_range[0], voxel_range[1]):
            fixed_env = ScaleEnv(ScaleMDP(v_min=v, v_max=v, v0=v), retention, link, seed=cfg.seed + 1)
            evaluation[key][f"fixed_{v:g}"] = rollout(fixed_env, lambda s: 1, level)
    plot_training_curves(out / "training_curves.png", result)
    metrics = write_metrics(out / "training_metrics.json", cfg, result, {
        "command": " ".join(sys.argv), "data": [str(d) for d in data], "records": len(records),
        "voxel_range": list(voxel_range),
        "retention": {"voxels": retention.voxels.tolist(), "bytes": retention.bytes.tolist(),
                      "ratios": retention.ratios.tolist()},
        "link_levels": [asdict(lv) for lv in link.levels], "evaluation": evaluation,
        "model_bytes": model.stat().st_size,
    })
    return json.loads(metrics.read_text())
