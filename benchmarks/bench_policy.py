"""Scale-policy decision time on the robot: the packaged DQN through onnxruntime.

Run: python -m benchmarks.bench_policy
"""

from __future__ import annotations

import statistics
import time

from benchmarks.common import header
from zoffload.policy.mdp import ScaleMDP
from zoffload.policy.onnx_scale import OnnxScalePolicy, packaged_model


def main() -> None:
    header("scale-policy decision (ONNX DQN, onnxruntime, 1 thread)")
    path = packaged_model()
    policy = OnnxScalePolicy(path, ScaleMDP())
    for _ in range(200):
        policy.choose(0.1, 0.05)
    times = []
    for i in range(5000):
        t0 = time.perf_counter()
        policy.choose(0.05 + (i % 30) * 0.01, 0.05)
        times.append(time.perf_counter() - t0)
    times.sort()
    print(f"model {path.name}: {path.stat().st_size / 1e3:.1f} kB")
    median, p99 = statistics.median(times) * 1e6, times[int(0.99 * len(times))] * 1e6
    print(f"decision: median {median:.1f} us, p99 {p99:.1f} us (target <= 50 us)")


if __name__ == "__main__":
    main()
