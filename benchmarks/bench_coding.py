"""Scan payload size per voxel size, float32 vs q16z vs q16d, on the simulator's VLP-16 and the
real KITTI-360 HDL-64 scans (mean of scans 0, 10, 20), with the codings' encode/decode CPU times
(median): q16z encoded from a point array (level 3), q16d as the robot makes it (the layout filled
from the grid pass's sums: "pack"; then Zstandard level 1; "raw kB": q16d uncompressed, what the
robot sends where the link has room).

Run: python -m benchmarks.bench_coding
"""

from __future__ import annotations

import time

import numpy as np

from benchmarks.common import header, kitti_dir
from zoffload.mapping.cloud import drop_non_finite
from zoffload.mapping.voxel import VoxelGrid, voxel_downsample
from zoffload.protocol.coding import (
    LAYOUT,
    ZSTD,
    bounds,
    compress,
    decode_q16d,
    decode_q16z,
    encode_q16z,
    pack_q16,
    payload_size,
    quant_step,
)
from zoffload.sources.kitti import KittiBinSource
from zoffload.sources.simulated import SimulatedSource

SIZES = (0.0, 0.01, 0.03, 0.05, 0.07, 0.1, 0.2, 0.3, 0.5)
NO_T = np.empty(0)
NO_C = np.empty(0, np.int32)


def table(name: str, scans: list[np.ndarray]) -> None:
    print(f"\n{name}: {np.mean([len(p) for p in scans]):,.0f} points per scan")
    print(f"{'voxel':>7} {'kept':>5} {'f32 kB':>7} | {'q16z kB':>7} {'enc ms':>6} {'dec ms':>6} | "
          f"{'q16d kB':>7} {'raw kB':>6} {'pack ms':>7} {'zstd ms':>7} {'dec ms':>6}")
    grid = VoxelGrid()
    for v in SIZES:
        downs = [voxel_downsample(p, v).astype(np.float32) if v > 0 else p.astype(np.float32) for p in scans]
        z_enc, z_dec, z_size, d_pack, d_zstd, d_dec, d_size = [], [], [], [], [], [], []
        for p, d in zip(scans, downs, strict=True):
            t0 = time.thread_time()
            origin, step, blob = encode_q16z(d, quant_step(v), widen=True)
            t1 = time.thread_time()
            decode_q16z(blob, len(d), origin, step)
            z_enc.append(t1 - t0)
            z_dec.append(time.thread_time() - t1)
            z_size.append(len(blob))
            # q16d as the robot makes it: the layout filled from the grid pass's sums, then Zstandard
            g = grid.run(p, v, skip_invalid=True) if v > 0 else None
            out = np.empty(payload_size(len(d), False), np.uint8)
            t0 = time.thread_time()
            if g is not None:
                ox, oy, oz, step, _, _ = pack_q16(g.sums, g.counts, NO_T, g.box, quant_step(v), True,
                                                  LAYOUT["q16d"], out)
            else:
                ox, oy, oz, step, _, _ = pack_q16(p, NO_C, NO_T, bounds(p, NO_T), quant_step(v), True,
                                                  LAYOUT["q16d"], out)
            t1 = time.thread_time()
            packed = bytes([ZSTD]) + compress(out, 1)
            t2 = time.thread_time()
            decode_q16d(packed, len(d), np.array([ox, oy, oz]), step)
            d_pack.append(t1 - t0)
            d_zstd.append(t2 - t1)
            d_dec.append(time.thread_time() - t2)
            d_size.append(len(packed))
        kept = np.mean([len(d) / len(p) for d, p in zip(downs, scans, strict=True)])
        f32 = np.mean([d.nbytes for d in downs]) / 1e3
        label = "raw" if v == 0 else f"{v:g} m"
        ms = lambda xs: 1e3 * np.median(xs)  # noqa: E731
        print(f"{label:>7} {100 * kept:4.0f}% {f32:7.0f} | {np.mean(z_size) / 1e3:7.0f} {ms(z_enc):6.1f} "
              f"{ms(z_dec):6.1f} | {np.mean(d_size) / 1e3:7.0f} {f32 / 2:6.0f} {ms(d_pack):7.2f} "
              f"{ms(d_zstd):7.2f} {ms(d_dec):6.1f}")


def main() -> None:
    header("scan payload: float32 vs q16z vs q16d (quantised to max(5 mm, voxel/10))")
    sim = SimulatedSource(seed=0)
    table("simulator VLP-16 (indoors)", [drop_non_finite(sim.read(i).points)[0] for i in (0, 10, 20)])
    kitti = KittiBinSource(kitti_dir())
    table("KITTI-360 HDL-64 (outdoors)", [drop_non_finite(kitti.read(i).points)[0] for i in (0, 10, 20)])


if __name__ == "__main__":
    main()
