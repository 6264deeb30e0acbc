"""Seeded generators of the link traces the scan policies were *not* tuned on.

* ``cellular``: an LTE-like uplink. The rate follows a random walk in log space between 2 and
  40 Mbps (one step a second), the one-way delay wanders between 30 and 70 ms and the jitter
  between 5 and 20 ms, and an outage of 1 to 4 seconds comes every 15 to 35 s (handovers, dead
  spots).
  The downlink (acks) has twice the uplink's rate.
* ``wifi-congested``: a shared Wi-Fi cell whose capacity (50-80 Mbps, slowly varying) other
  stations take in bursts: a burst (0.2-2 s, about 40 % of the time) leaves the robot 5-25 % of
  the cell, and while it lasts the access point's queue adds 20-60 ms of delay and 10-25 ms of
  jitter (5-15 ms and 3-8 ms between bursts).

* ``satellite``: a geostationary satellite terminal's return link (VSAT): one-way delay 260-320
  ms (the 36,000 km hop and the modem), jitter 5-20 ms, an uplink of 3-20 Mbps (a random walk in
  log space, one step a second) with a downlink of 20-50 Mbps, and a rain fade every 20-40 s that
  cuts the uplink to 15-40 % for 2-6 s (the modem's adaptive coding) and adds 10-40 ms of delay.
  A round trip of at least 0.52 s: 5-6 scans on the path at 10 Hz with no queue anywhere.
* ``satellite-reroute``: the satellite link whose one-way delay rises by 600 ms for good at 30 s
  (the ground station's backhaul rerouted): a base delay that changes is not a queue.

Each trace is written for two seeds: seed 1 (``cellular``, ``wifi-congested``), which the policy
may be developed against, and seed 2 (``cellular-heldout``, ``wifi-congested-heldout``), which is
for final tables only and must never be used to tune anything; the cellular uplink also for seeds
3-5 (``cellular-3`` ...), more development cases; the satellite link for seeds 1 (``satellite``)
and 2 (``satellite-heldout``, held out likewise). Regenerate (the files are
committed beside this script; the same seeds give the same files):

    python -m zoffload.lab.link.make_traces [--out zoffload/lab/link/traces]
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from zoffload.lab.link.trace import COLUMNS

DURATION = 90.0  # seconds; the experiment adds 10 s of the last row
Row = tuple[float, float, float, float, float, int]


def cellular(seed: int, duration: float = DURATION) -> list[Row]:
    rng = np.random.default_rng(seed)
    lo, hi = math.log(2.0), math.log(40.0)
    log_rate = rng.uniform(math.log(8.0), hi)
    delay, jitter = rng.uniform(30, 70), rng.uniform(5, 20)
    next_outage = rng.uniform(10.0, 30.0)
    rows: list[Row] = []
    t = 0.0
    # an outage always ends in a row of its own: a trace's last row holds for ever, so one that
    # started in the last seconds would otherwise last the run out (it did for seed 2 until
    # 2026-11-29: cellular-heldout's link was dead for its last 11 s)
    while t < duration or rows[-1][5]:
        if t >= next_outage:
            length = float(rng.uniform(1.0, 4.0))
            rows.append((t, 0.0, 0.0, 0.0, 0.0, 1))
            t += length
            next_outage = t + rng.uniform(15.0, 35.0) - length
            continue
        up = math.exp(log_rate)
        rows.append((t, up, min(100.0, 2 * up), delay, jitter, 0))
        log_rate = _reflect(log_rate + rng.normal(0, 0.3), lo, hi)
        delay = _reflect(delay + rng.normal(0, 6), 30, 70)
        jitter = _reflect(jitter + rng.normal(0, 2.5), 5, 20)
        t += 1.0
    return rows


def wifi_congested(seed: int, duration: float = DURATION) -> list[Row]:
    rng = np.random.default_rng(seed)
    cell = rng.uniform(50, 80)
    rows: list[Row] = []
    t = 0.0
    burst = False
    while t < duration:
        if burst:
            length = float(np.clip(rng.exponential(0.7), 0.2, 2.0))
            share = rng.uniform(0.05, 0.25)
            delay, jitter = rng.uniform(20, 60), rng.uniform(10, 25)
        else:
            length = float(np.clip(rng.exponential(1.2), 0.3, 4.0))
            share = 1.0
            delay, jitter = rng.uniform(5, 15), rng.uniform(3, 8)
        up = cell * share
        rows.append((t, up, up, delay, jitter, 0))
        t += round(length, 1)
        cell = _reflect(cell + rng.normal(0, 3), 50, 80)
        burst = not burst
    return rows


def satellite(seed: int, duration: float = DURATION) -> list[Row]:
    rng = np.random.default_rng(seed)
    lo, hi = math.log(3.0), math.log(20.0)
    log_rate = rng.uniform(math.log(6.0), hi)
    delay, jitter = rng.uniform(260, 320), rng.uniform(5, 20)
    next_fade = rng.uniform(10.0, 30.0)
    fade_until, fade_share, fade_delay = -1.0, 1.0, 0.0
    rows: list[Row] = []
    t = 0.0
    while t < duration:
        if t >= next_fade:
            fade_until = t + float(rng.uniform(2.0, 6.0))
            fade_share, fade_delay = float(rng.uniform(0.15, 0.4)), float(rng.uniform(10, 40))
            next_fade = t + rng.uniform(20.0, 40.0)
        fading = t < fade_until
        up = math.exp(log_rate) * (fade_share if fading else 1.0)
        down = float(np.clip(2.5 * math.exp(log_rate), 20.0, 50.0))
        rows.append((t, up, down, delay + (fade_delay if fading else 0.0), jitter, 0))
        log_rate = _reflect(log_rate + rng.normal(0, 0.25), lo, hi)
        delay = _reflect(delay + rng.normal(0, 5), 260, 320)
        jitter = _reflect(jitter + rng.normal(0, 2.5), 5, 20)
        t += 1.0
    return rows


def satellite_reroute(seed: int, duration: float = DURATION, at: float = 30.0,
                      rise_ms: float = 600.0) -> list[Row]:
    return [(t, up, down, delay + (rise_ms if t >= at else 0.0), jitter, outage)
            for t, up, down, delay, jitter, outage in satellite(seed, duration)]


def _reflect(x: float, lo: float, hi: float) -> float:
    """``x`` folded back into [lo, hi] (a random walk that bounces off its limits)."""
    while not lo <= x <= hi:
        x = 2 * lo - x if x < lo else 2 * hi - x
    return float(x)


def to_csv(rows: list[Row], comment: str) -> str:
    lines = [f"# {line}" for line in comment.splitlines()]
    lines.append(", ".join(COLUMNS))
    for t, up, down, delay, jitter, outage in rows:
        lines.append(f"{t:.1f}, {up:.2f}, {down:.2f}, {delay:.1f}, {jitter:.1f}, {outage}")
    return "\n".join(lines) + "\n"


TRACES: dict[str, tuple[Callable[[int], list[Row]], int, str]] = {
    "cellular": (cellular, 1, "cellular uplink, seed 1 (development)"),
    "cellular-heldout": (cellular, 2, "cellular uplink, seed 2: HELD OUT, final tables only, never tuned on"),
    "wifi-congested": (wifi_congested, 1, "congested shared Wi-Fi, seed 1 (development)"),
    "wifi-congested-heldout": (wifi_congested, 2,
                               "congested shared Wi-Fi, seed 2: HELD OUT, final tables only, never tuned on"),
    # more development seeds of the cellular uplink (seed 4 spends half its time below 5 Mbps)
    "cellular-3": (cellular, 3, "cellular uplink, seed 3 (development)"),
    "cellular-4": (cellular, 4, "cellular uplink, seed 4 (development)"),
    "cellular-5": (cellular, 5, "cellular uplink, seed 5 (development)"),
    # a long path: the window of unanswered scans must hold a round trip of half a second
    "satellite": (satellite, 1, "geostationary satellite return link, seed 1 (development)"),
    "satellite-heldout": (satellite, 2,
                          "geostationary satellite return link, seed 2: HELD OUT, final tables only, "
                          "never tuned on"),
    "satellite-reroute": (satellite_reroute, 3, "geostationary satellite return link, seed 3, its delay "
                          "600 ms longer from 30 s on (development)"),
}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="write the generated link traces")
    ap.add_argument("--out", default=str(Path(__file__).parent / "traces"), help="folder for the CSV files")
    a = ap.parse_args(argv)
    for name, (make, seed, what) in TRACES.items():
        path = Path(a.out) / f"{name}.csv"
        path.write_text(to_csv(make(seed), f"{what}.\nGenerated by zoffload/lab/link/make_traces.py"))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
