"""Scan payload size per voxel size, float32 vs q16z, on the simulator's VLP-16 and the real
KITTI-360 HDL-64 scans (mean of scans 0, 10, 20), with the coding's encode/decode times.

Run: python -m benchmarks.bench_coding
"""

from __future__ import annotations

import time

import numpy as np

from benchmarks.common import header, kitti_dir
from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.voxel import voxel_downsample
from zoffload.protocol.coding import decode_q16z, encode_q16z, quant_step
from zoffload.sources.kitti import KittiBinSource
from zoffload.sources.simulated import SimulatedSource

SIZES = (0.0, 0.01, 0.03, 0.05, 0.07, 0.1, 0.2, 0.3, 0.5)


def table(name: str, scans: list[np.ndarray]) -> None:
    print(f"\n{name}: {np.mean([len(p) for p in scans]):,.0f} points per scan")
    print(f"{'voxel':>7} {'kept':>6} {'f32 kB':>8} {'q16z kB':>8} {'ratio':>6} {'encode':>9} {'decode':>9}")
    for v in SIZES:
        downs = [voxel_downsample(p, v).astype(np.float32) if v > 0 else p.astype(np.float32) for p in scans]
        enc, dec, sizes = [], [], []
        for d in downs:
            t0 = time.perf_counter()
            origin, step, blob = encode_q16z(d, quant_step(v), widen=True)
            t1 = time.perf_counter()
            decode_q16z(blob, len(d), origin, step)
            enc.append(t1 - t0)
            dec.append(time.perf_counter() - t1)
            sizes.append(len(blob))
        kept = np.mean([len(d) / len(p) for d, p in zip(downs, scans, strict=True)])
        f32 = np.mean([d.nbytes for d in downs]) / 1e3
        q = np.mean(sizes) / 1e3
        label = "raw" if v == 0 else f"{v:g} m"
        print(f"{label:>7} {100 * kept:5.0f} % {f32:8.0f} {q:8.0f} {q / f32:6.2f} "
              f"{1e3 * np.median(enc):6.1f} ms {1e3 * np.median(dec):6.1f} ms")


def main() -> None:
    header("scan payload: float32 vs q16z (quantised to max(5 mm, voxel/10), zstd level 3)")
    sim = SimulatedSource(seed=0)
    table("simulator VLP-16 (indoors)", [drop_non_finite(sim.read(i).points)[0] for i in (0, 10, 20)])
    kitti = KittiBinSource(kitti_dir())
    table("KITTI-360 HDL-64 (outdoors)", [drop_non_finite(kitti.read(i).points)[0] for i in (0, 10, 20)])


if __name__ == "__main__":
    main()
