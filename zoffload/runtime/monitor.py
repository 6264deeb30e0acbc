"""State monitors the offloading strategies read: CPU (psutil), RAPL energy, bandwidth from byte
counters, ping-pong latency, and the simple moving averages the thesis smooths them with.

Nothing here is faked: RAPL is read from ``/sys/class/powercap`` and reported as unavailable where
that does not exist (containers, VMs, non-Intel machines); CPU is psutil's reading of this process
and of the whole machine.
"""

from __future__ import annotations

import csv
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil
import zenoh

from zoffload.policy.smoothing import MovingAverage
from zoffload.protocol import wire

log = logging.getLogger("zoffload.runtime.monitor")


class CpuMonitor:
    """CPU use in percent of the whole machine (all cores = 100) and of this process (one core =
    100, psutil's convention, so a process can read up to 100 x cores)."""

    def __init__(self) -> None:
        self.proc = psutil.Process()
        psutil.cpu_percent(None)
        self.proc.cpu_percent(None)

    def sample(self) -> tuple[float, float]:
        return float(psutil.cpu_percent(None)), float(self.proc.cpu_percent(None))


class RaplMonitor:
    """Package energy from Intel RAPL (``/sys/class/powercap/intel-rapl:N/energy_uj``); average
    power in watts between samples. ``available`` is False where the counters do not exist."""

    def __init__(self, root: Path = Path("/sys/class/powercap")) -> None:
        self.files = sorted(root.glob("intel-rapl:[0-9]*/energy_uj")) if root.is_dir() else []
        self.files = [f for f in self.files if self._read(f) is not None]
        self.available = bool(self.files)
        self._last: tuple[float, float] | None = None

    @staticmethod
    def _read(f: Path) -> float | None:
        try:
            return float(f.read_text())
        except (OSError, ValueError):
            return None

    def sample(self) -> float:
        """Watts since the previous sample; NaN when unavailable or on the first call."""
        if not self.available:
            return float("nan")
        now = time.monotonic()
        energy = sum(v for f in self.files if (v := self._read(f)) is not None) * 1e-6
        last, self._last = self._last, (now, energy)
        if last is None or now <= last[0] or energy < last[1]:  # first sample or counter wrap
            return float("nan")
        return (energy - last[1]) / (now - last[0])


class ByteRate:
    """Mbps from a byte counter: Δbytes / Δt · 8e-6 between samples."""

    def __init__(self, read: Callable[[], float]) -> None:
        self.read = read
        self._last = (time.monotonic(), read())

    def sample(self) -> float:
        now, value = time.monotonic(), self.read()
        t0, v0 = self._last
        self._last = (now, value)
        return (value - v0) / (now - t0) * 8e-6 if now > t0 else float("nan")


def nic_bytes(nic: str, direction: str = "sent") -> Callable[[], float]:
    """A counter of a network interface's bytes (``sent`` or ``recv``), for ``ByteRate``."""
    if nic not in psutil.net_io_counters(pernic=True):
        raise ValueError(f"no network interface {nic!r} (have {sorted(psutil.net_io_counters(pernic=True))})")

    def read() -> float:
        c = psutil.net_io_counters(pernic=True)[nic]
        return float(c.bytes_sent if direction == "sent" else c.bytes_recv)

    return read


class Pinger:
    """Ping-pong over a Zenoh queryable once per ``period``: the round trip in ms, smoothed.
    An unanswered ping counts as ``timeout`` (the link is at least that slow). ``key``: the ping key
    of one edge (``Keys.ping``), or a function giving the current one (the edge a robot's frames go
    to; None: no edge to ping, the period is skipped); a new key starts a new average. A pong must
    name the edge its key does (an edge answers only its own key under the router's ACL)."""

    def __init__(self, session: zenoh.Session, key: str | Callable[[], str | None], period: float = 1.0,
                 timeout: float = 1.0, window: int = 5) -> None:
        self.session, self.period, self.timeout = session, period, timeout
        self._key_of = key if callable(key) else (lambda: key)
        self.key: str | None = None
        self.window = window
        self.rtt = MovingAverage(window)
        self.last_ms = float("nan")
        self.lost = 0
        self.wrong_edge = 0  # pongs naming another edge than their key
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pinger", daemon=True)

    def start(self) -> Pinger:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=self.timeout + 1)

    def ping(self) -> float:
        """One ping of the current key: the round trip in ms, NaN when unanswered."""
        key = self.key if self.key is not None else self._key_of()
        if key is None:
            return float("nan")
        edge = key.rsplit("/", 1)[-1]
        t0 = time.monotonic()
        try:
            # the stamp travels in the selector's parameters (``key?stamp=…``), echoed in the Pong
            for reply in self.session.get(f"{key}?stamp={time.time():.6f}", timeout=self.timeout):
                if reply.ok is None:
                    continue
                try:
                    pong = wire.decode(reply.ok.payload.to_bytes(), expect=wire.Pong)
                except wire.WireError:
                    pong = None
                if pong is None or pong.edge != edge:
                    self.wrong_edge += 1
                    continue
                return (time.monotonic() - t0) * 1e3
        except Exception as exc:  # a closed session while stopping, or a bad key
            if not self._stop.is_set():
                log.warning("ping on %s failed: %s", key, exc)
        return float("nan")

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            try:
                key = self._key_of()
            except Exception as exc:  # the caller's function: logged, the pinger lives on
                log.warning("ping key: %s", exc)
                key = None
            if key != self.key:  # another edge (or none): its round trip is another's
                self.key, self.rtt = key, MovingAverage(self.window)
            if key is None:
                continue
            ms = self.ping()
            if math.isfinite(ms):
                self.last_ms = ms
            else:
                self.lost += 1
                ms = self.timeout * 1e3
            self.rtt.add(ms)


class SampleLog:
    """The monitor's samples, bounded for a daemon that runs for days: the newest ``keep`` in
    memory, running means of every field over all of them (finite values only), and, with a
    ``path``, every sample appended to a CSV file as it comes (nothing dropped, nothing held)."""

    def __init__(self, fields: tuple[str, ...], keep: int = 3600, path: Path | None = None) -> None:
        self.fields = fields
        self.recent: deque[dict[str, float]] = deque(maxlen=keep)
        self.count = 0
        self._sums = dict.fromkeys(fields, 0.0)
        self._ns = dict.fromkeys(fields, 0)
        self.path = path
        self._file: Any = None
        self._writer: Any = None
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(path, "w", newline="")  # noqa: SIM115 (closed by close())
            self._writer = csv.DictWriter(self._file, fieldnames=fields)
            self._writer.writeheader()

    def add(self, sample: dict[str, float]) -> None:
        self.recent.append(sample)
        self.count += 1
        for k in self.fields:
            v = sample.get(k)
            if v is not None and math.isfinite(v):
                self._sums[k] += v
                self._ns[k] += 1
        if self._writer is not None:
            self._writer.writerow(sample)
            self._file.flush()

    def means(self) -> dict[str, float | None]:
        """Each field's mean over every sample so far (None when no finite value came)."""
        return {k: self._sums[k] / self._ns[k] if self._ns[k] else None for k in self.fields}

    def write(self, path: Path) -> None:
        """All samples as CSV at ``path``: the spool file itself when it is that path, else the
        samples kept in memory (the newest ``keep``)."""
        if self.path is not None and path.resolve() == self.path.resolve():
            if self._file is not None:
                self._file.flush()
            return
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=self.fields)
            w.writeheader()
            w.writerows(self.recent)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = self._writer = None


class ResourceMonitor:
    """Once a second: this process's and the machine's CPU, outgoing Mbps from a byte counter, RAPL
    power, and the ping-pong RTT to the edge; 3-sample moving averages of CPU and Mbps (what the
    offloading rules read) and a bounded ``SampleLog`` of the samples (the newest ``keep`` in
    memory, running means, all of them in ``spool`` when given)."""

    FIELDS = ("t", "cpu_system", "cpu_process", "mbps_out", "power_w", "ping_ms")

    def __init__(self, session: zenoh.Session, ping_key: str | Callable[[], str | None],
                 bytes_out: Callable[[], float],
                 ping_timeout: float = 0.5, period: float = 1.0, keep: int = 3600,
                 spool: Path | None = None) -> None:
        self.session, self.ping_key, self.bytes_out = session, ping_key, bytes_out
        self.ping_timeout, self.period = ping_timeout, period
        self.cpu = MovingAverage(3)
        self.mbps = MovingAverage(3)
        self.log = SampleLog(self.FIELDS, keep=keep, path=spool)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="monitor", daemon=True)

    def start(self) -> ResourceMonitor:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=self.ping_timeout + 2)

    def _run(self) -> None:
        cpu, rapl, rate = CpuMonitor(), RaplMonitor(), ByteRate(self.bytes_out)
        # ping-pong over the edge's ping queryable: the network's share of the edge RTT
        pinger = Pinger(self.session, self.ping_key, period=self.period, timeout=self.ping_timeout).start()
        try:
            while not self._stop.wait(self.period):
                system, proc = cpu.sample()
                mbps, watts = rate.sample(), rapl.sample()
                with self._lock:
                    self.cpu.add(proc)
                    self.mbps.add(mbps)
                    self.log.add({"t": time.time(), "cpu_system": system, "cpu_process": proc,
                                  "mbps_out": mbps, "power_w": watts, "ping_ms": pinger.rtt.value})
        finally:
            pinger.stop()

    def smoothed(self) -> tuple[float, float]:
        """(process CPU %, outgoing Mbps), 3-sample moving averages (NaN before the first)."""
        with self._lock:
            return self.cpu.value, self.mbps.value

    def latest(self) -> dict[str, float] | None:
        with self._lock:
            return dict(self.log.recent[-1]) if self.log.recent else None

    def means(self) -> dict[str, float | None]:
        with self._lock:
            return self.log.means()

    def write_csv(self, path: Path) -> None:
        with self._lock:
            self.log.write(path)

    def close(self) -> None:
        with self._lock:
            self.log.close()
