"""Collision flooding of the global map's voxel set: points crafted so that every voxel key lands
in one hash slot of the *unsalted* Fibonacci hash, against random points, with the salt off
(the hash as it was) and on (as shipped).

    python -m benchmarks.bench_collisions [--points 60000] [--voxel 0.1] [--repeat 3]

Prints the insert time of each case (best of ``--repeat``) and the crafted/random ratio.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from zoffload.mapping.voxel import GOLDEN, KEY_BITS, KEY_OFFSET, MAX_INDEX
from zoffload.mapping.voxelset import VoxelSet, warmup

MASK = (1 << 64) - 1
FIELD = (1 << KEY_BITS) - 1


def crafted_points(n: int, voxel: float) -> np.ndarray:
    """``n`` points in distinct voxels whose keys ``k`` all have ``k * GOLDEN < 2^40`` (mod 2^64):
    the top bits, the slot of any table up to 2^24 slots, are 0 for every one of them."""
    ginv = pow(int(GOLDEN) & MASK, -1, 1 << 64)
    reach = int(MAX_INDEX / 1.7321) - 1  # what VoxelSet.add accepts at the identity pose
    out: list[tuple[int, int, int]] = []
    t = 0
    while len(out) < n:
        t += 1
        k = (ginv * t) & MASK
        if k >> 63:
            continue
        idx = (((k >> (2 * KEY_BITS)) & FIELD) - KEY_OFFSET, ((k >> KEY_BITS) & FIELD) - KEY_OFFSET,
               (k & FIELD) - KEY_OFFSET)
        if k >> (3 * KEY_BITS) or max(abs(i) for i in idx) > reach:
            continue
        out.append(idx)
    return (np.asarray(out, np.float64) + 0.5) * voxel


def random_points(n: int, voxel: float, seed: int = 0) -> np.ndarray:
    reach = MAX_INDEX / 1.7321 - 1
    idx = np.random.default_rng(seed).integers(-int(reach), int(reach), (n, 3))
    return (idx + 0.5) * voxel


def insert_time(points: np.ndarray, voxel: float, salted: bool) -> float:
    vs = VoxelSet(voxel)
    if not salted:
        vs._salt = np.int64(0)  # the hash before the salt: key * GOLDEN
    t0 = time.perf_counter()
    vs.add(points)
    elapsed = time.perf_counter() - t0
    assert len(vs) == len(points)
    return elapsed


def measure(n: int, voxel: float, repeat: int = 3) -> dict[str, float]:
    warmup()
    crafted, rand = crafted_points(n, voxel), random_points(n, voxel)
    return {f"{kind}_{'salted' if salted else 'unsalted'}_s": min(insert_time(pts, voxel, salted)
                                                                 for _ in range(repeat))
            for kind, pts in (("crafted", crafted), ("random", rand)) for salted in (False, True)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--points", type=int, default=60_000)
    p.add_argument("--voxel", type=float, default=0.1)
    p.add_argument("--repeat", type=int, default=3)
    a = p.parse_args()
    r = measure(a.points, a.voxel, a.repeat)
    for salted in ("unsalted", "salted"):
        c, rnd = r[f"crafted_{salted}_s"], r[f"random_{salted}_s"]
        print(f"{salted:9s} crafted {c * 1e3:8.1f} ms  random {rnd * 1e3:6.1f} ms  ratio {c / rnd:6.1f}")


if __name__ == "__main__":
    main()
