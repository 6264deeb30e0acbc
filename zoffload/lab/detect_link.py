"""The detection experiments' held-out link: a trace no offloading strategy was tuned on until
2026-12-07, when the tuning pairs of the dispatcher's overflow rule used it (README, Experiments).

``mmwave-blockage``: a 5G millimetre-wave uplink as a walking robot sees it. The rate follows a
seeded random walk in log space between 60 and 400 Mbps (the raw 848x480 camera stream needs
244 Mbps, so the link is sometimes ample and sometimes a bottleneck), changing every 0.5-2 s;
one-way delay 5-20 ms with 2-8 ms jitter; and a blockage (a body or a wall in the beam: nothing
passes) of 0.2-0.8 s every 8-15 s. Its character differs from the tuned links: faster changes
than the Wi-Fi walk, a rate above and below the stream's, short total outages.

``python -m zoffload.lab.detect_link --out DIR`` writes the CSV; the shipped file is its output
with the default seed (tests/core/lab/test_detect_link.py checks that).
"""

from __future__ import annotations

import argparse
import math
import random
from pathlib import Path

NAME = "mmwave-blockage"
SEED = 15
DURATION = 70.0  # s: longer than a 1250-frame run (50 s) and its start-up
Row = tuple[float, float, float, float, float, int]


def mmwave_rows(seed: int = SEED, duration: float = DURATION) -> list[Row]:
    """(time_s, up_mbps, down_mbps, delay_ms, jitter_ms, outage) rows of the trace."""
    rng = random.Random(seed)
    rows: list[Row] = []
    t, log_rate = 0.0, math.log(200.0)
    next_block = rng.uniform(8.0, 15.0)
    while t < duration or rows[-1][5]:  # a blockage always ends in a row: the last row holds for ever
        if t >= next_block:
            length = round(rng.uniform(0.2, 0.8), 2)
            rows.append((round(t, 2), 0.0, 0.0, 0.0, 0.0, 1))
            t += length
            next_block = t + rng.uniform(8.0, 15.0)
            continue
        log_rate = min(math.log(400.0), max(math.log(60.0), log_rate + rng.gauss(0.0, 0.35)))
        rate = round(math.exp(log_rate))
        delay = round(rng.uniform(5.0, 20.0), 1)
        jitter = round(rng.uniform(2.0, 8.0), 1)
        rows.append((round(t, 2), float(rate), float(rate), delay, jitter, 0))
        t += rng.uniform(0.5, 2.0)
    return rows


def to_csv(rows: list[Row]) -> str:
    head = [f"# {NAME}: a 5G mmWave uplink, 60-400 Mbps random walk, 5-20 ms delay, blockages.",
            f"# Written by python -m zoffload.lab.detect_link (seed {SEED}); held out until 2026-12-07, "
            "when the tuning pairs of the dispatcher's overflow rule used it.",
            "time_s, up_mbps, down_mbps, delay_ms, jitter_ms, outage"]
    body = [f"{t:g}, {u:g}, {d:g}, {dl:g}, {j:g}, {o}" for t, u, d, dl, j, o in rows]
    return "\n".join([*head, *body]) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=str(Path(__file__).parent / "link" / "traces"), help="folder for the CSV")
    p.add_argument("--seed", type=int, default=SEED)
    a = p.parse_args(argv)
    path = Path(a.out) / f"{NAME}.csv"
    path.write_text(to_csv(mmwave_rows(a.seed)))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
