"""``python -m zoffload.lab.link.ceiling``: how often scans can be on time for their slot on a trace.

A scan is *on time for its slot* (the scan experiment's ``on_time_slot``) when it reaches the edge
at most 1.1 x the periods the robot meant it to take after the scan received before it: one period,
or k + 1 after k scans skipped on purpose. On the link emulator (``proxy.py``) a scan's arrival is
its last piece's, and every 16 kB piece gets its own Gaussian extra delay (clipped at 0, order
kept): the interarrival is the difference of two scans' delays. So on a jittery trace some scans
are late however small they are.

This runs the emulator's own scheduling (``Direction._schedule``, the code that shapes the
experiments' links) on a stream of scans of a given size, one every ``every`` periods, alone on
the uplink, with an oracle that skips (and announces) exactly the scans sent during the trace's
outages, and gives the share on time: for 1-byte scans, what the link's jitter alone leaves of a
scan every period (a reference, not a bound: on a trace whose rate varies a steady stream of bigger
scans can score a point more, and a policy that reacts to each answer can do better than any open
loop); with ``every`` 2, 3 what a longer slot buys. The model's simplifications: pieces are cut at
scan boundaries (the emulator cuts the byte stream as it reads it, Zenoh's framing and other
messages included, and the share moves by a point when a scan crosses a 16 kB boundary); the
backpressure of the emulator's queue is left out (it changes when the emulator reads a piece, not
when the piece departs); and in a run the same random stream also draws the jitter of every other
message in both directions, so a run's seed does not give the jitter its scans met: a run is set
against the mean over seeds. A property of this emulator's model, not of real radio links, whose
delays are correlated from one packet to the next.

    python -m zoffload.lab.link.ceiling --trace cellular-heldout wifi-locations [--sizes 1 20000]
        [--every 1 2] [--seeds 5]
    python -m zoffload.lab.link.ceiling --runs results/unseen/sim/cellular-heldout/rate/run*

``--runs``: scan experiment runs, each beside (over ``RUN_SEEDS`` seeds, from the run's own start on
the trace's clock) a stream of 1-byte scans (what ``zoffload experiment scan`` writes as
``on_time_tiny``), a steady stream of its mean scan size (``on_time_steady_size``), and its own
scans (sizes, send times and announced skips, ``scans.csv``) alone on its emulated link: what the
policy's choices allow there, before the transport and the host add their part.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import random
import statistics
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from zoffload.lab.link.proxy import Direction, LinkStats
from zoffload.lab.link.trace import Trace, TraceError, load_trace

SLOT_SLACK = 1.1  # as the scan experiment's (lab/scan_experiment.py)
QUANTUM = 16 * 1024  # the emulator's piece size (LinkEmulator's default)
RUN_SEEDS = 20  # a run is set against the mean over this many seeds (its own is not its jitter)


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


def _arrival(up: Direction, size: int, t: float) -> float:
    """When a scan of ``size`` bytes put on ``up`` at ``t`` is delivered: its last piece's."""
    q = up.quantum
    pieces = [q] * (size // q) + ([size % q] if size % q else [])
    return max(up._schedule(bytes(n), t) for n in pieces)


def stream_start(captures: Iterable[float], wall_start: float | None) -> float:
    """A run's first scan on the trace's clock (the link's ``wall_start``): 0 without either."""
    first = min(captures, default=None)
    return 0.0 if wall_start is None or first is None else max(0.0, first - wall_start)


def slot_ceiling(trace: Trace, *, period: float = 0.1, size: int = 1, every: int = 1, seed: int = 0,
                 duration: float | None = None, start: float = 0.0, quantum: int = QUANTUM,
                 slack: float = SLOT_SLACK) -> Ceiling:
    """Scans of ``size`` bytes sent every ``every`` x ``period`` seconds from ``start`` on the
    trace's clock for ``duration`` (default: the trace's length plus the 10 s a scan experiment
    adds), through the emulator's uplink model."""
    if period <= 0 or size < 1 or every < 1 or quantum < 1:
        raise ValueError("period must be > 0, size, every and quantum >= 1")
    span = trace.duration + 10.0 if duration is None else duration
    up = Direction("up", trace, 0.0, LinkStats(), random.Random(seed), quantum, math.inf)
    slot = every * period
    sent = received = skipped = on_time = 0
    held = 0  # scans skipped since the last one sent
    last: float | None = None
    late: list[float] = []
    k = 0
    while (t := start + k * slot) < start + span:
        k += 1
        sent += 1
        if trace.at(t).outage:
            skipped += 1
            held += 1
            continue
        arrival = _arrival(up, size, t)
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
                   help="scan experiment runs: each one's on time for slot beside the streams")
    p.add_argument("--sizes", type=int, nargs="+", default=[1, 20_000],
                   help="bytes per scan on the wire (default: 1, the jitter alone, and 20,000)")
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


@dataclass(frozen=True)
class _Run:
    """What a scan experiment run's folder says, read once."""

    row: dict[str, Any]  # results.json
    trace: Trace
    period: float
    start: float  # its first scan on the trace's clock
    scans: int  # the sensor's scans it was run for
    wall_start: float | None  # the link's clock (link.log); None: not known
    records: list[dict[str, str]]  # scans.csv (empty without it)


def _read_run(folder: Path) -> _Run:
    from zoffload.lab.runner import link_clock_start

    row = json.loads((folder / "results.json").read_text())
    exp = json.loads((folder / "experiment.json").read_text())
    spec = str(row["trace"])  # a path that is gone (a run made from another tree): by its name
    trace = load_trace(spec if Path(spec).is_file() else Path(spec).name.removesuffix(".csv"))
    period = 1.0 / float(exp.get("rate") or exp.get("rate_hz") or 10.0)  # "rate": written since 2026-12-06
    wall_start = link_clock_start(folder / "link.log")
    records: list[dict[str, str]] = []
    if (folder / "scans.csv").exists():
        with open(folder / "scans.csv", newline="") as f:
            records = list(csv.DictReader(f))
    start = stream_start((float(r["capture_stamp"]) for r in records if r.get("capture_stamp")), wall_start)
    return _Run(row, trace, period, start, int(exp["max_scans"]), wall_start, records)


def stream_shares(trace: Trace, *, period: float, size: float, start: float, duration: float,
                  seeds: int = RUN_SEEDS) -> tuple[float, float]:
    """(1-byte scans, a steady stream of ``size`` bytes): their on-time shares over a run's stretch
    of the trace, the mean over ``seeds`` seeds."""
    def share(b: float) -> float:
        return statistics.fmean(slot_ceiling(trace, period=period, size=max(1, round(b)), seed=s, start=start,
                                             duration=duration).on_time_share for s in range(seeds))
    return share(1), share(size)


def _streams(run: _Run, seeds: int) -> tuple[float, float]:
    return stream_shares(run.trace, period=run.period, size=1e3 * float(run.row["S_kB"]), start=run.start,
                         duration=run.scans * run.period, seeds=seeds)


def run_streams(folder: Path, seeds: int = RUN_SEEDS) -> tuple[float, float]:
    """``stream_shares`` of a scan experiment run (``results.json``, ``experiment.json``; its start
    on the trace's clock from ``link.log`` and ``scans.csv`` when they are there) at its mean scan
    size. ``OSError``/``ValueError``/``KeyError``/``TypeError`` when the run does not say enough,
    ``TraceError`` when its trace is not found."""
    return _streams(_read_run(folder), seeds)


def _own_share(run: _Run, seeds: int) -> float | None:
    sent = [r for r in run.records if r.get("bytes") not in (None, "", "nan")
            and r.get("send_stamp") not in (None, "", "nan") and r.get("capture_stamp")]
    if run.wall_start is None or not sent:
        return None
    sent.sort(key=lambda r: float(r["send_stamp"]))
    # on the trace's clock: the first scan's capture, then the robot's own send times
    t0 = float(sent[0]["capture_stamp"]) - run.wall_start - float(sent[0]["send_stamp"])
    shares = []
    for seed in range(seeds):
        up = Direction("up", run.trace, 0.0, LinkStats(), random.Random(seed), QUANTUM, math.inf)
        last: float | None = None
        on_time = late = 0
        for r in sent:
            arrival = _arrival(up, max(1, int(float(r["bytes"]))), t0 + float(r["send_stamp"]))
            if last is not None:
                if arrival - last <= SLOT_SLACK * run.period * (1 + int(float(r.get("skipped") or 0))):
                    on_time += 1
                else:
                    late += 1
            last = arrival
        shares.append(on_time / max(1, on_time + late))
    return statistics.fmean(shares)


def own_scans_share(folder: Path, seeds: int = RUN_SEEDS) -> float | None:
    """The on-time share of a run's own scans (their sizes, their send times, the deliberate skips
    their messages announced: ``scans.csv``) alone on its emulated link, the mean over ``seeds``
    seeds; None without the link's clock (``link.log``) or a scan sent. What the policy's choices
    allow on this link; the run's own share is lower by what the transport and the host add."""
    return _own_share(_read_run(folder), seeds)


def _runs(folders: Sequence[Path]) -> int:
    """Each run's on time for slot beside the streams it is set against."""
    print(f"on time for the slot; the streams: the emulator's model alone, the mean over {RUN_SEEDS} seeds")
    print("| run | trace | S (kB/scan) | on time for slot | 1-byte scans | a steady stream of its size "
          "| its own scans alone on the link |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    status = 0
    for folder in folders:
        try:
            run = _read_run(folder)
            tiny, steady = _streams(run, RUN_SEEDS)
        except (OSError, ValueError, KeyError, TypeError, TraceError) as exc:
            print(f"error: {folder}: {exc}", file=sys.stderr)
            status = 2
            continue
        try:
            own = _own_share(run, RUN_SEEDS)
        except (ValueError, KeyError, TypeError):
            own = None  # records that do not replay: unknown
        row = run.row
        on_time = row.get("on_time_slot")
        print(f"| {folder} | {Path(str(row['trace'])).name.removesuffix('.csv')} | {float(row['S_kB']):.0f} "
              f"| {'–' if on_time is None else f'{100 * on_time:.1f} %'} | {100 * tiny:.1f} % "
              f"| {100 * steady:.1f} % | {'–' if own is None else f'{100 * own:.1f} %'} |")
    return status


if __name__ == "__main__":
    sys.exit(main())
