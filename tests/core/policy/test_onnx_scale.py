"""The DQN scale policy at run time: onnxruntime only, with a named fallback on any load failure."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from onnx import TensorProto, helper  # noqa: E402

from zoffload.policy.mdp import ScaleMDP
from zoffload.policy.onnx_scale import OnnxScalePolicy, load_scale_policy
from zoffload.policy.scale import FixedScale

onnx = pytest.importorskip("onnx")


def threshold_model(path: Path, names: tuple[str, str] = ("state", "q")) -> Path:
    """q = state @ W + b with q0 = 1 - 10 T, q1 = 0, q2 = 10 T - 1: decrease below T = 0.1,
    increase above."""
    W = helper.make_tensor("W", TensorProto.FLOAT, [2, 3], [-10.0, 0.0, 10.0, 0.0, 0.0, 0.0])
    b = helper.make_tensor("b", TensorProto.FLOAT, [3], [1.0, 0.0, -1.0])
    nodes = [helper.make_node("MatMul", [names[0], "W"], ["mm"]),
             helper.make_node("Add", ["mm", "b"], [names[1]])]
    graph = helper.make_graph(
        nodes,
        "threshold",
        [helper.make_tensor_value_info(names[0], TensorProto.FLOAT, ["n", 2])],
        [helper.make_tensor_value_info(names[1], TensorProto.FLOAT, ["n", 3])],
        initializer=[W, b],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


def test_onnx_policy_follows_its_q_values_and_clamps(tmp_path: Path) -> None:
    policy = OnnxScalePolicy(threshold_model(tmp_path / "p.onnx"), ScaleMDP())
    assert policy.reset() == 0.05
    assert policy.choose(0.05, 0.05) == 0.03  # fast link: finer
    assert policy.choose(0.30, 0.05) == 0.07  # slow link: coarser
    assert policy.choose(0.30, 0.07) == 0.07  # clamped at the top
    assert policy.choose(0.05, 0.01) == 0.01  # and the bottom
    assert policy.choose(float("nan"), 0.05) == 0.03  # NaN T is clamped to 0, not raised
    assert policy.choose(5.0, 9.9) == 0.07  # v off the range is clamped


@pytest.mark.parametrize("case", ["missing", "corrupt", "wrong_names"])
def test_a_bad_model_falls_back_to_a_named_fixed_voxel(case: str, tmp_path: Path,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "m.onnx"
    if case == "corrupt":
        path.write_bytes(np.random.default_rng(0).bytes(500))
    elif case == "wrong_names":
        threshold_model(path, names=("input", "output"))
    with caplog.at_level(logging.ERROR, logger="zoffload.policy"):
        policy = load_scale_policy(f"dqn:{path}", 0.04, (0.01, 0.07))
    assert isinstance(policy, FixedScale) and policy.voxel == 0.04 and "fallback" in policy.name
    assert "falling back to a fixed voxel size of 0.04 m" in caplog.text


def test_policy_specs(tmp_path: Path) -> None:
    assert isinstance(load_scale_policy("fixed", 0.05, (0.01, 0.07)), FixedScale)
    p = load_scale_policy(f"dqn:{threshold_model(tmp_path / 'x.onnx')}", 0.05, (0.02, 0.2))
    assert isinstance(p, OnnxScalePolicy) and p.mdp.v_max == 0.2  # the configured, sensor-aware range
    with pytest.raises(ValueError, match="unknown scale policy"):
        load_scale_policy("magic", 0.05, (0.01, 0.07))
