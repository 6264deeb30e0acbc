"""A short DQN training on recorded-looking data: it must learn the paper's trade-off and export
an ONNX model that decides exactly as the trained network."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.core.policy.test_mdp import recordings
from zoffload.policy.env import LinkModel, Retention, ScaleEnv
from zoffload.policy.mdp import DECREASE, INCREASE, ScaleMDP

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")


pytest.importorskip("onnxscript", reason="ONNX export needs onnxscript (train extra)")


def test_dqn_learns_finer_on_a_fast_link_coarser_on_a_slow_one(tmp_path: Path) -> None:
    from zoffload.policy.dqn import DQNConfig, export_onnx, greedy_actions, train
    from zoffload.policy.onnx_scale import OnnxScalePolicy

    rows = recordings()
    env = ScaleEnv(ScaleMDP(), Retention.fit(rows), LinkModel.fit(rows), seed=0)
    net, result = train(env, DQNConfig(episodes=6000, seed=0), progress=False)
    assert np.isfinite(result.losses).all() and result.rewards[-1000:].mean() > result.rewards[:1000].mean()
    states = np.array([[0.10, 0.05], [0.10, 0.03], [0.30, 0.05], [0.30, 0.03]], np.float32)
    actions = greedy_actions(net, states)
    assert actions[0] == DECREASE and actions[1] == DECREASE  # on time: keep more points
    assert actions[2] == INCREASE and actions[3] == INCREASE  # late: fewer points
    model = export_onnx(net, tmp_path / "dqn.onnx")
    assert model.stat().st_size < 100_000  # tens of kB
    assert list(tmp_path.iterdir()) == [model]  # one self-contained file, no external weights
    runtime = OnnxScalePolicy(model, ScaleMDP())
    for s, a in zip(states, actions, strict=True):
        assert runtime.action(float(s[0]), float(s[1])) == a
