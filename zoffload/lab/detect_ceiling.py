"""``python -m zoffload.lab.detect_ceiling``: how high asynchronous AP50 can go on a set of clips.

Asynchronous AP50 (lab/eval/detection.py) scores a frame's detections against the ground truth of
the frame current when they arrived, and a frame never processed as a miss. So a strategy whose
answers come ``k`` camera periods after capture scores about what a detector answering *every*
frame at that lag scores, at most: this prints that figure for each model and lag (the real
detectors' outputs on every frame, cached as the simulation caches them, lab/offload_sim.py
``clip_detections``). A reference level, not a proof: AP is not a sum over frames, and answers at
mixed lags and from both models score in between. An answer that needs the edge's inference
(38-65 ms a frame on the development machine, from day to day) plus the link is about one 40 ms
period late; the quarter-core robot's detector (~100 ms and more) two to four. The strategies'
rows are read against it: what a dispatcher could still win over "edge only" is the distance from
edge only's score to the edge model's row at the lag it achieves.

``--runs RUN...`` (detect experiment runs on the same clips) prints each run's score, the frames it
processed and their mean lateness, and a what-if: the frames the edge answered ``dropped`` (it
serves the newest waiting frame) detected by the robot's model some time after that answer came.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from zoffload.lab.eval.ap import average_precision
from zoffload.lab.eval.detection import detection_metrics, load_run, score_frames
from zoffload.lab.offload_sim import CACHE, clip_detections, detections_cache

MODELS = ("picodet-s", "nanodet-m")  # the edge's detector, the robot's

Detections = tuple[np.ndarray, np.ndarray]  # boxes (n, 4), scores (n,)


def late_ap(dets: Sequence[Detections], gt: Callable[[int], np.ndarray], lag: int) -> float:
    """AP50 (%) of ``dets`` (one entry per frame, every frame processed) when each frame's are
    scored against the ground truth ``lag`` frames later (the last frame's for the last ones)."""
    n = len(dets)
    return 100 * average_precision(list(dets), [gt(min(i + lag, n - 1)) for i in range(n)])


def dropped_detected_later(run: Path, dets: Sequence[Detections], after: float,
                           gt: Callable[[int], np.ndarray], n: int | None = None) -> tuple[float, int]:
    """Async AP50 of ``run`` (over its ``n`` frames; None: the frames it recorded) had each frame
    the edge answered ``dropped`` been detected by the model of ``dets`` ``after`` seconds after
    that answer; and how many such frames there were."""
    frames, persons, period = load_run(run)
    if not frames:
        raise ValueError(f"{run}: frames.csv has no frame")
    changed = 0
    for f in frames:
        if f["status"] == "edge_dropped" and isinstance(f["result"], float) and int(f["seq"]) < len(dets):
            f["status"], f["result"] = "local_done", f["result"] + after
            persons[int(f["seq"])] = dets[int(f["seq"])]
            changed += 1
    return score_frames(frames, persons, period, gt, n)["ap50_async"], changed


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m zoffload.lab.detect_ceiling",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--images", default="coco-clips@holdout",
                   help="clips with ground truth: coco-clips[:FOLDER][@tune|@holdout] (default: held-out)")
    p.add_argument("--frames", type=int, default=None, help="first N frames (default: all)")
    p.add_argument("--max-lag", type=int, default=4, help="largest lag in camera periods (default 4)")
    p.add_argument("--models", nargs="+", default=list(MODELS), help="detectors (default: %(default)s)")
    p.add_argument("--runs", type=Path, nargs="*", default=[],
                   help="detect experiment runs on these clips: their scores and the dropped-frames what-if")
    p.add_argument("--after", type=float, nargs="+", default=[0.15, 0.3],
                   help="what-if: seconds from the drop answer to the robot's result (default 0.15 0.3)")
    p.add_argument("--cache", type=Path, default=CACHE,
                   help="folder of the cached detections (shared with the simulation)")
    args = p.parse_args(argv)
    from zoffload.sources.images import CocoClipSource, open_image_source

    source = open_image_source(args.images)
    if not isinstance(source, CocoClipSource):
        p.error(f"{args.images}: needs clips with ground truth (coco-clips)")
    n = len(source) if args.frames is None else min(args.frames, len(source))
    lags = range(args.max_lag + 1)
    print(f"{args.images}: {n} frames, every frame detected, scored k camera periods late (AP50 %)")
    print("| model | " + " | ".join(f"k = {k}" for k in lags) + " |")
    print("| --- | " + " | ".join("---" for _ in lags) + " |")
    loaded: dict[str, list[Detections]] = {}

    def detections(model: str) -> list[Detections]:  # each model's read (or computed) once
        if model not in loaded:
            cache = detections_cache(args.images, model, args.cache)
            loaded[model] = clip_detections(source, model, n, cache)[:n]
        return loaded[model]

    for model in args.models:
        aps = [late_ap(detections(model), source.boxes, k) for k in lags]
        print(f"| {model} | " + " | ".join(f"{ap:.1f}" for ap in aps) + " |")
    if args.runs:
        local = detections(MODELS[1])
        print("\n| run | async AP50 | processed | mean lateness (frames) | edge dropped | "
              + " | ".join(f"dropped ones by {MODELS[1]} {1000 * a:.0f} ms later" for a in args.after) + " |")
        print("| --- | --- | --- | --- | --- | " + " | ".join("---" for _ in args.after) + " |")
        for run in args.runs:
            try:  # each run over its own frames (a run of fewer frames is not scored on the rest)
                m = detection_metrics(run, source.boxes)
                whatif = [dropped_detected_later(run, local, a, source.boxes) for a in args.after]
            except (OSError, ValueError, KeyError) as exc:
                print(f"| {run} | not a detect run of these clips: {exc} |")
                continue
            print(f"| {run} | {m['ap50_async']:.1f} | {m['processed']} | {m['mean_lateness_frames']:.2f} | "
                  f"{whatif[0][1]} | " + " | ".join(f"{ap:.1f}" for ap, _ in whatif) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
