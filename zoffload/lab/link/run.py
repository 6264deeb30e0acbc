"""``zoffload link``: run the emulator as its own process, reporting what it let through."""

from __future__ import annotations

import asyncio
import csv
import logging
from pathlib import Path

from zoffload.lab.link.proxy import LinkEmulator
from zoffload.lab.link.trace import Trace
from zoffload.runtime.lifecycle import StopSignal

log = logging.getLogger("zoffload.lab.link")


def write_report(path: Path, emu: LinkEmulator, seconds: int) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["second", "up_mbps", "down_mbps", "trace_up_mbps", "trace_down_mbps", "delay_ms",
                    "outage"])
        for s in range(seconds):
            st = emu.trace.at(s + 0.5)
            w.writerow([s, f"{emu.stats.mbps('up', s):.3f}", f"{emu.stats.mbps('down', s):.3f}",
                        st.up_mbps, st.down_mbps, st.delay_ms, int(st.outage)])


def run(trace: Trace, listen_port: int, target: tuple[str, int], stop: StopSignal,
        report: Path | None = None, seed: int = 0, queue_ms: float = 100.0, quiet: bool = False) -> None:
    async def main() -> None:
        emu = LinkEmulator(trace, listen_port, target, seed=seed, queue_ms=queue_ms)
        emu.on_clock_start.append(lambda wall: print(f"clock wall_start={wall:.6f}", flush=True))
        await emu.start_serving()
        log.info("link emulator on 127.0.0.1:%d -> %s:%d, trace %s", listen_port, *target, trace.name)
        print(f"ready {listen_port}", flush=True)
        second = 0
        while not stop.is_set():
            await asyncio.sleep(0.2)
            elapsed = emu.elapsed()
            if elapsed is None:
                continue
            while second < int(elapsed) - 1:  # report a second once complete (plus delivery slack)
                if not quiet:
                    print(emu.report_line(second), flush=True)
                second += 1
        await emu.close()
        if report is not None:
            write_report(report, emu, second + 1 if emu.start is not None else 0)

    asyncio.run(main())
