"""The learnt local bias (``perception.learn_bias``, policy/agreement.py) on the real detectors'
answers: what it costs the robot per answer, and what it estimates, against the truth.

Each half of the COCO clips is streamed as a dispatcher would see it: a share of the frames
answered by the robot's detector (NanoDet-m), most of the rest by the edge's (PicoDet-S), a few by
none, in order (the models' real outputs, cached as the simulation caches them). Printed per half:

* CPU time of ``Agreement.observe`` per answer (mean and p99, this thread's);
* the estimate every 10 s of camera time (25 frames/s), blended with the 40 ms prior as the
  dispatcher blends it, in camera periods, for three seeds of which frames go where;
* the estimate on the whole half at once, and the same quantity from the ground truth: where the
  edge's model scored k frames late falls to what the robot's scores at each age the estimate
  compares it at (0 to 4), less the age, averaged; and for a fresh answer alone
  (``python -m zoffload.lab.detect_ceiling`` prints the scores by lag).

Run: python -m benchmarks.bench_agreement [--local-share 0.2]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from benchmarks.common import header
from zoffload.lab.detect_ceiling import late_ap
from zoffload.lab.offload_sim import clip_detections, detections_cache
from zoffload.policy.agreement import EDGE, LOCAL, Agreement, crossing
from zoffload.policy.dispatch import Dispatcher

PERIOD = 0.04  # s: the clips' 25 frames per second


def stream(edge: list, local: list, share: float, seed: int, agreement: Agreement,
           every: int = 250) -> tuple[list[float], list[float]]:
    """Feed the answers; returns the CPU seconds of each call and the blended bias (periods) every
    ``every`` frames."""
    d = Dispatcher(learn_bias=True)
    d.agreement = agreement
    rng = np.random.default_rng(seed)
    cpu, bias = [], []
    for i in range(len(edge)):
        r = rng.random()
        side, dets = (LOCAL, local[i]) if r < share else (EDGE, edge[i]) if r < 0.97 else (None, None)
        if side is not None:
            t0 = time.thread_time()
            d.observe(i, side, *dets)
            cpu.append(time.thread_time() - t0)
        if i % every == every - 1:
            bias.append(d.bias(PERIOD) / PERIOD)
    return cpu, bias


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--local-share", type=float, default=0.2, help="frames answered locally (default 0.2)")
    args = p.parse_args()
    from zoffload.sources.images import CocoClipSource, ImageSourceError, open_image_source

    header("learnt local bias: NanoDet-m (robot) against PicoDet-S (edge), COCO clips")
    for half in ("tune", "holdout"):
        name = f"coco-clips@{half}"
        try:
            source = open_image_source(name)
        except ImageSourceError as exc:
            sys.exit(f"needs the COCO clips (set ZOFFLOAD_DATA): {exc}")
        assert isinstance(source, CocoClipSource)
        n = len(source)
        edge = clip_detections(source, "picodet-s", n, detections_cache(name, "picodet-s"))
        local = clip_detections(source, "nanodet-m", n, detections_cache(name, "nanodet-m"))
        cpus = []
        print(f"\n{name}, {n} frames, {args.local_share:.0%} answered locally")
        for seed in range(3):
            cpu, bias = stream(edge, local, args.local_share, seed, Agreement())
            cpus += cpu
            print(f"  seed {seed}: bias every 10 s (periods) " + " ".join(f"{b:.2f}" for b in bias))
        cpus.sort()
        print(f"  observe(): CPU per answer mean {1e3 * np.mean(cpus):.3f} ms, p99 "
              f"{1e3 * cpus[int(0.99 * len(cpus))]:.3f} ms")
        whole = Agreement(keep=n, min_pairs=30, every=n)
        for i in range(n):  # every frame answered by both: the estimate with all the pairs there are
            whole.observe(i, LOCAL, *local[i])
            whole.observe(i, EDGE, *edge[i])
        whole.offset = whole.estimate()
        # the same quantity from the ground truth: the edge's model scored k frames late, the robot's
        # at the ages the estimate compares it at, crossings less the age, averaged
        lags = np.arange(whole.edge_span + 1.0)
        truth_edge = np.minimum.accumulate(np.array([late_ap(edge, source.boxes, int(k)) for k in lags]))
        truth = np.mean([crossing(lags, truth_edge, late_ap(local, source.boxes, k)) - k
                         for k in range(whole.span + 1)])
        fresh = crossing(lags, truth_edge, late_ap(local, source.boxes, 0))
        print(f"  whole half: estimate {whole.offset:.2f} periods; the truth the same way {truth:.2f} "
              f"(for a fresh answer alone {fresh:.2f})")
        print(f"  observe(): CPU per answer max {1e3 * cpus[-1]:.3f} ms")


if __name__ == "__main__":
    main()
