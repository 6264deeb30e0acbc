"""``python -m zoffload.lab.link.ceiling``: how many scans can be on time for their slot on a trace.

A scan is *on time for its slot* (the scan experiment's ``on_time_slot``) when it reaches the edge
at most 1.1 x the periods the robot meant it to take after the scan received before it: one period,
or k + 1 after k scans skipped on purpose. On the link emulator (``proxy.py``) a scan's arrival is
its last piece's, and every 16 kB piece gets its own Gaussian extra delay (clipped at 0, order
kept): the interarrival is the difference of two scans' delays, whatever their size. So on a
jittery trace some scans are late however small they are.

This measures that limit by running the emulator's own scheduling (``Direction._schedule``, the
code that shapes the experiments' links) on a stream of scans of a given size, one every
``every`` periods, alone on the uplink, with an oracle that skips (and announces) exactly the
scans sent during the trace's outages. A policy sending a scan every period is on time about as
often at best: its scans are bigger (more pieces, each with its own jitter) and share the link
with Zenoh's other traffic; it can only trade scans for timeliness by pacing (``every`` 2, 3: a
longer slot absorbs the same jitter). A limit of this emulator's model, not of real radio links,
whose delays are correlated from one packet to the next.

    python -m zoffload.lab.link.ceiling --trace cellular-heldout wifi-locations [--sizes 1 20000]
        [--every 1 2] [--seeds 5]
    python -m zoffload.lab.link.ceiling --runs results/unseen/sim/cellular-heldout/rate/run*

``--runs``: scan experiment runs, each against the limit on its own link seed (1-byte scans, what
``zoffload experiment scan`` now writes as ``on_time_limit``) and a steady stream of its mean scan
size (``on_time_steady_size``), which a policy sizing each scan for the link may beat; runs made
before them lack both.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import random
import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from zoffload.lab.link.proxy import Direction, LinkStats
from zoffload.lab.link.trace import Trace, TraceError, load_trace

SLOT_SLACK = 1.1  # as the scan experiment's (lab/scan_experiment.py)
QUANTUM = 16 * 1024  # the emulator's piece size (LinkEmulator's default)


@dataclass(frozen=True)
class Ceiling:
    """One stream's timeliness on one trace."""

    sent: int  # scans offered (every ``every`` periods)
    received: int
    skipped: int  # held by an outage: skipped on purpose by the oracle, counted in the next slot
    on_time: int  # received scans with T <= 1.1 x their slot (the first has no T and is not counted)
    late_ms_p95: float  # the 95th percentile of T - slot, ms

    @property
    def on_time_share(self) -> float:
        return self.on_time / max(1, self.received - 1)


def slot_ceiling(trace: Trace, *, period: float = 0.1, size: int = 1, every: int = 1, seed: int = 0,
                 duration: float | None = None, quantum: int = QUANTUM, slack: float = SLOT_SLACK) -> Ceiling:
    """Scans of ``size`` bytes sent every ``every`` x ``period`` seconds for ``duration`` (the
    trace's length plus the 10 s a scan experiment adds), through the emulator's uplink model."""
    if period <= 0 or size < 1 or every < 1 or quantum < 1:
        raise ValueError("period must be > 0, size, every and quantum >= 1")
    span = trace.duration + 10.0 if duration is None else duration
    up = Direction("up", trace, 0.0, LinkStats(), random.Random(seed), quantum, math.inf)
    pieces = [quantum] * (size // quantum) + ([size % quantum] if size % quantum else [])
    slot = every * period
    sent = received = skipped = on_time = 0
    held = 0  # scans skipped since the last one sent
    last: float | None = None
    late: list[float] = []
    k = 0
    while (t := k * slot) < span:
        k += 1
        sent += 1
        if trace.at(t).outage:
            skipped += 1
            held += 1
            continue
        arrival = max(up._schedule(bytes(n), t) for n in pieces)
        received += 1
        if last is not None:
            over = (arrival - last) - (1 + held) * slot
            late.append(over)
            on_time += arrival - last <= slack * (1 + held) * slot
        last, held = arrival, 0
    p95 = statistics.quantiles(late, n=20)[-1] * 1e3 if len(late) >= 2 else math.nan
    return Ceiling(sent, received, skipped, on_time, p95)


def _spread(xs: Sequence[float]) -> str:
    sd = statistics.stdev(xs) if len(xs) > 1 else 0.0
    return f"{100 * statistics.fmean(xs):.1f} ± {100 * sd:.1f} %"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m zoffload.lab.link.ceiling",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--trace", nargs="+", default=[], help="shipped trace names or CSV files")
    p.add_argument("--runs", type=Path, nargs="+", default=[],
                   help="scan experiment runs: each one's on time for slot against its limit")
    p.add_argument("--sizes", type=int, nargs="+", default=[1, 20_000],
                   help="bytes per scan on the wire (default: 1, the limit, and 20,000)")
    p.add_argument("--every", type=int, nargs="+", default=[1, 2],
                   help="a scan every N periods (the policy's pacing; default 1 2)")
    p.add_argument("--period", type=float, default=0.1, help="the sensor's period, s (default 0.1)")
    p.add_argument("--seeds", type=int, default=5, help="emulator seeds 0..N-1 (default 5)")
    args = p.parse_args(argv)
    if args.seeds < 1 or args.period <= 0 or min(args.sizes) < 1 or min(args.every) < 1:
        p.error("--seeds, --sizes and --every must be >= 1, --period > 0")
    if not args.trace and not args.runs:
        p.error("give --trace or --runs")
    if args.runs:
        return _runs(args.runs)
    print(f"on time for the slot (T <= {SLOT_SLACK} x slot), scans alone on the emulated uplink, outages "
          f"skipped by an oracle; mean ± sd over emulator seeds 0-{args.seeds - 1}")
    print("| trace | bytes a scan | a scan every | received / sent | on time for slot | p95 of T - slot |")
    print("| --- | --- | --- | --- | --- | --- |")
    for spec in args.trace:
        try:
            trace = load_trace(spec)
        except TraceError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        for size in args.sizes:
            for every in args.every:
                runs = [slot_ceiling(trace, period=args.period, size=size, every=every, seed=s)
                        for s in range(args.seeds)]
                print(f"| {trace.name} | {size:,} | {every} period{'s' if every > 1 else ''} "
                      f"| {runs[0].received} / {runs[0].sent} | {_spread([r.on_time_share for r in runs])} "
                      f"| {statistics.fmean(r.late_ms_p95 for r in runs):.0f} ms |")
    return 0


def run_limits(folder: Path) -> tuple[float, float]:
    """(on_time_limit, on_time_steady_size) of a scan experiment run (``results.json`` and
    ``experiment.json``): the 1-byte stream and a steady stream of its mean scan size, on its link
    seed. ``OSError``/``ValueError``/``KeyError``/``TypeError`` when the run does not say enough,
    ``TraceError`` when its trace is not found (a path that is gone is looked up by its name)."""
    row = json.loads((folder / "results.json").read_text())
    exp = json.loads((folder / "experiment.json").read_text())
    spec = str(row["trace"])
    trace = load_trace(spec if Path(spec).is_file() else Path(spec).name.removesuffix(".csv"))
    size, seed = float(row["S_kB"]), int(row.get("link_seed", exp.get("seed", 0)))
    period = 1.0 / float(exp.get("rate_hz") or 10.0)
    limit, steady = (slot_ceiling(trace, period=period, size=max(1, round(b)), seed=seed,
                                  duration=int(exp["max_scans"]) * period).on_time_share
                     for b in (1, 1e3 * size))
    return limit, steady


def own_scans_share(folder: Path, seed: int) -> float | None:
    """The on-time share of a run's own scans (their sizes, their send times, the deliberate skips
    their messages announced: ``scans.csv``) alone on its emulated link, or None without the
    link's clock. What the policy's choices allow on this link; the run's own share is lower by
    what the transport and the host add."""
    from zoffload.lab.runner import link_clock_start

    row = json.loads((folder / "results.json").read_text())
    spec = str(row["trace"])
    trace = load_trace(spec if Path(spec).is_file() else Path(spec).name.removesuffix(".csv"))
    wall_start = link_clock_start(folder / "link.log")
    with open(folder / "scans.csv", newline="") as f:
        sent = [r for r in csv.DictReader(f) if r.get("bytes") not in (None, "", "nan")
                and r.get("send_stamp") not in (None, "", "nan")]
    if wall_start is None or not sent:
        return None
    sent.sort(key=lambda r: float(r["send_stamp"]))
    # trace time: the first scan's capture on the link's clock, then the robot's own send times
    t0 = float(sent[0]["capture_stamp"]) - wall_start - float(sent[0]["send_stamp"])
    up = Direction("up", trace, 0.0, LinkStats(), random.Random(seed), QUANTUM, math.inf)
    last: float | None = None
    on_time = late = 0
    exp = json.loads((folder / "experiment.json").read_text())
    period = 1.0 / float(exp.get("rate_hz") or 10.0)
    for r in sent:
        size = max(1, int(float(r["bytes"])))
        pieces = [QUANTUM] * (size // QUANTUM) + ([size % QUANTUM] if size % QUANTUM else [])
        arrival = max(up._schedule(bytes(n), t0 + float(r["send_stamp"])) for n in pieces)
        if last is not None and math.isfinite(arrival):
            slot = period * (1 + int(float(r.get("skipped") or 0)))
            if arrival - last <= SLOT_SLACK * slot:
                on_time += 1
            else:
                late += 1
        last = arrival
    return on_time / max(1, on_time + late)


def _runs(folders: Sequence[Path]) -> int:
    """Each run's on time for slot beside the limit at its mean size (``results.json``)."""
    print("| run | trace | S (kB/scan) | link seed | on time for slot | 1-byte scans (the limit) "
          "| a steady stream of its size | its own scans alone on the link |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    status = 0
    for folder in folders:
        try:
            limit, steady = run_limits(folder)
            row = json.loads((folder / "results.json").read_text())
        except (OSError, ValueError, KeyError, TypeError, TraceError) as exc:
            print(f"error: {folder}: {exc}", file=sys.stderr)
            status = 2
            continue
        try:
            own = own_scans_share(folder, int(row.get("link_seed", 0)))
        except (OSError, ValueError, KeyError, TypeError):
            own = None  # no scans.csv or link clock to replay: unknown
        on_time = row.get("on_time_slot")
        print(f"| {folder} | {Path(str(row['trace'])).name.removesuffix('.csv')} | {float(row['S_kB']):.0f} "
              f"| {row.get('link_seed', '–')} "
              f"| {'–' if on_time is None else f'{100 * on_time:.1f} %'} | {100 * limit:.1f} % "
              f"| {100 * steady:.1f} % | {'–' if own is None else f'{100 * own:.1f} %'} |")
    return status


if __name__ == "__main__":
    sys.exit(main())
