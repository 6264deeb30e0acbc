"""The DQN scale policy at run time: an ONNX model through onnxruntime (the robot never imports
torch). Input ``state`` (1 x 2: last receive time T [s], last voxel size v [m]), output ``q``
(1 x 3: one value per action of the paper's MDP)."""

from __future__ import annotations

import logging
from importlib import resources
from pathlib import Path

import numpy as np

from zoffload.policy.mdp import ScaleMDP
from zoffload.policy.scale import FixedScale, ScalePolicy

log = logging.getLogger("zoffload.policy")


class PolicyLoadError(Exception):
    pass


def packaged_model() -> Path:
    return Path(str(resources.files("zoffload.policy") / "models" / "dqn_scale.onnx"))


class OnnxScalePolicy:
    def __init__(self, path: Path, mdp: ScaleMDP) -> None:
        try:
            import onnxruntime as ort
        except ImportError as exc:
            raise PolicyLoadError("the DQN policy needs onnxruntime: pip install 'zoffload[robot]'") from exc
        if not path.is_file():
            raise PolicyLoadError(f"policy model {path} does not exist")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1  # a 3-layer MLP: threads cost more than they save
        opts.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for bad files
            raise PolicyLoadError(f"policy model {path} is not a usable ONNX model: {exc}") from exc
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if [i.name for i in inputs] != ["state"] or [o.name for o in outputs] != ["q"]:
            raise PolicyLoadError(f"policy model {path}: expected input 'state' and output 'q'")
        q = self.session.run(None, {"state": np.zeros((1, 2), np.float32)})[0]
        if q.shape != (1, 3):
            raise PolicyLoadError(f"policy model {path}: q has shape {q.shape}, expected (1, 3)")
        self.mdp = mdp
        self.path = path
        self.name = "dqn"
        self._buf = np.zeros((1, 2), np.float32)

    def reset(self) -> float:
        return self.mdp.v0

    def action(self, last_t: float, last_v: float) -> int:
        self._buf[0] = self.mdp.clamp_state(last_t, last_v)
        q = self.session.run(None, {"state": self._buf})[0]
        return int(np.argmax(q[0]))

    def choose(self, last_t: float, last_v: float) -> float:
        _, v = self.mdp.clamp_state(last_t, last_v)
        return self.mdp.apply(v, self.action(last_t, last_v))


def load_scale_policy(spec: str, voxel: float, voxel_range: tuple[float, float], widen: float = 2.0,
                      max_skip: int = 2, stall_after: float = 0.5, jitter_pace: int = 1) -> ScalePolicy:
    """``fixed`` (the robot's ``voxel``), ``dqn`` (the packaged model), ``dqn:PATH`` or ``rate`` (ours,
    policy/rate.py, over ``voxel_range``, widened up to ``widen`` times its upper end, skipping up
    to ``max_skip`` scans in a row, pausing after ``stall_after`` seconds without an ack, taking up
    to ``jitter_pace`` periods per scan on a jittery link). A DQN
    model that cannot be loaded is logged and replaced by the fixed voxel size, named in the log."""
    if spec == "fixed":
        return FixedScale(voxel)
    if spec == "dqn" or spec.startswith("dqn:"):
        path = packaged_model() if spec == "dqn" else Path(spec.split(":", 1)[1])
        lo, hi = voxel_range
        mdp = ScaleMDP(v_min=lo, v_max=hi, v0=min(hi, max(lo, 0.05)))
        try:
            return OnnxScalePolicy(path, mdp)
        except PolicyLoadError as exc:
            fallback = FixedScale(voxel)
            log.error("%s; falling back to a fixed voxel size of %g m", exc, voxel)
            fallback.name = f"{fallback.name} (fallback from dqn)"
            return fallback
    if spec == "rate":
        from zoffload.policy.rate import LinkAwareScale

        return LinkAwareScale(voxel_range, start=voxel if voxel > 0 else 0.05, widen=widen, max_skip=max_skip,
                              stall_after=stall_after, jitter_pace=jitter_pace)
    raise ValueError(f"unknown scale policy {spec!r} (fixed, dqn, dqn:PATH, rate)")
