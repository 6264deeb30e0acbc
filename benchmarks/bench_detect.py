"""The three detectors on the real COCO person images: person AP50 and latency, with 1 and 2
onnxruntime threads, and the local detector's latency under the robot's CFS quota.

AP50: COCO's 101-point interpolated AP at IoU 0.5 over the 50 dev images (eval/ap.py, which
matches pycocotools on these images). Latency: median wall time of ``Detector.detect`` (resize,
inference, decode, NMS) on a 848x480 frame of the COCO clips.

Run: python -m benchmarks.bench_detect
"""

from __future__ import annotations

import os
import subprocess
import sys

from benchmarks.common import DATA, header, median_ms


def ap50(name: str) -> float:
    from zoffload.detect.detector import Detector
    from zoffload.lab.eval.detection import person_ap50

    return person_ap50(Detector(name), DATA / "coco-person-dev")


def latency(name: str, threads: int) -> float:
    from zoffload.detect.detector import Detector
    from zoffload.sources.images import open_image_source

    frame = open_image_source(f"coco-clips:{DATA / 'coco-person-dev'}").read(10).image
    det = Detector(name, threads=threads)
    return median_ms(lambda: det.detect(frame), repeat=40, warmup=5)


def quota_latency(name: str, cores: float) -> float:
    """Latency in a child process placed under a CFS quota of ``cores``."""
    code = (
        "from zoffload.runtime.quota import apply_cpu_quota; import sys; "
        f"how = apply_cpu_quota({cores}); "
        "from benchmarks.bench_detect import latency; "
        f"print(how, latency({name!r}, 1))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=dict(os.environ, ZOFFLOAD_LOG="WARNING"))
    how, ms = out.stdout.split()
    return float(ms) if how.startswith("cgroup") else float("nan")


def main() -> None:
    if not (DATA / "models").is_dir() or not (DATA / "coco-person-dev").is_dir():
        sys.exit(f"needs the models and COCO images under {DATA} (set ZOFFLOAD_DATA)")
    header("detectors on the COCO person dev images (50 images, 100 persons)")
    print(f"{'model':12} {'AP50':>6} {'1 thread':>10} {'2 threads':>10} {'quota 0.5':>10} {'quota 0.25':>11}")
    for name in ("nanodet-m", "picodet-s", "yolox-nano"):
        a = ap50(name)
        t1, t2 = latency(name, 1), latency(name, 2)
        q5, q25 = quota_latency(name, 0.5), quota_latency(name, 0.25)
        print(f"{name:12} {a:6.3f} {t1:8.1f} ms {t2:8.1f} ms {q5:8.1f} ms {q25:9.1f} ms")
    print("(quota: the process in its own cgroup with that many cores of CFS time; n/a = no cgroup)")


if __name__ == "__main__":
    main()
