"""The link emulator: a TCP proxy that shapes each direction by a trace.

Each direction is modelled as a serial link with a bounded queue:

* a chunk read from one side is cut into pieces of at most ``quantum`` bytes;
* a piece finishes transmission at ``max(link free, now) + size / rate(t)`` (rate of the trace
  row in force, per direction), so over any window the link passes ``rate`` bytes per second;
* it is delivered ``delay + jitter`` later (jitter is Gaussian, clipped at 0; delivery order is
  kept, as TCP would);
* while more than ``queue_ms`` of transmission is waiting, the proxy stops reading from that side,
  so TCP backpressure reaches the sender (where Zenoh's congestion control acts: BLOCK_FIRST for scans);
* during an outage nothing departs: data waits until the link is back.

A small SO_RCVBUF/SO_SNDBUF on the proxy's sockets keeps the kernel from hiding megabytes of
buffering on either side of the emulated link.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import socket
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field

from zoffload.lab.link.trace import Trace

log = logging.getLogger("zoffload.lab.link")

SOCKET_BUFFER = 64 * 1024


@dataclass
class LinkStats:
    """Bytes delivered per whole second since the emulator started, per direction."""

    delivered: dict[str, defaultdict[int, int]] = field(
        default_factory=lambda: {"up": defaultdict(int), "down": defaultdict(int)}
    )
    connections: int = 0

    def add(self, direction: str, second: int, n: int) -> None:
        self.delivered[direction][second] += n

    def mbps(self, direction: str, second: int) -> float:
        return self.delivered[direction].get(second, 0) * 8 / 1e6


class Direction:
    """One direction of one proxied connection."""

    def __init__(self, name: str, trace: Trace, start: float, stats: LinkStats, rng: random.Random,
                 quantum: int, queue_ms: float) -> None:
        self.name = name
        self.trace = trace
        self.start = start
        self.stats = stats
        self.rng = rng
        self.quantum = quantum
        self.queue_s = queue_ms / 1000
        self.free_at = 0.0  # when the emulated link finishes its current backlog
        self.last_delivery = 0.0
        self.line: asyncio.Queue[tuple[float, bytes] | None] = asyncio.Queue()

    def _schedule(self, piece: bytes, now: float) -> float:
        """Departure and delivery time of ``piece``; returns its delivery time."""
        t = max(self.free_at, now)
        # Wait out an outage: nothing departs until the trace says the link is back
        state = self.trace.at(t - self.start)
        while state.outage:
            nxt = self.trace.next_change(t - self.start)
            if nxt is None:
                return float("inf")
            t += nxt + 1e-6
            state = self.trace.at(t - self.start)
        finish = t + len(piece) / state.rate_bps(self.name)
        self.free_at = finish
        jitter = max(0.0, self.rng.gauss(0.0, state.jitter_ms / 1000)) if state.jitter_ms else 0.0
        deliver = max(self.last_delivery, finish + state.delay_ms / 1000 + jitter)
        self.last_delivery = deliver
        return deliver

    async def read_side(self, reader: asyncio.StreamReader) -> None:
        loop = asyncio.get_running_loop()
        try:
            while True:
                chunk = await reader.read(self.quantum)
                if not chunk:
                    break
                for i in range(0, len(chunk), self.quantum):
                    piece = chunk[i : i + self.quantum]
                    self.line.put_nowait((self._schedule(piece, loop.time()), piece))
                # Backpressure: stop reading while the emulated queue is full
                while self.free_at - loop.time() > self.queue_s:
                    await asyncio.sleep(min(0.005, self.free_at - loop.time() - self.queue_s + 1e-4))
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            self.line.put_nowait(None)

    async def write_side(self, writer: asyncio.StreamWriter) -> None:
        loop = asyncio.get_running_loop()
        try:
            while True:
                item = await self.line.get()
                if item is None:
                    break
                deliver, piece = item
                while deliver == float("inf"):  # a permanent outage: hold until cancelled
                    await asyncio.sleep(3600)
                delay = deliver - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                writer.write(piece)
                await writer.drain()
                self.stats.add(self.name, int(loop.time() - self.start), len(piece))
        except ConnectionError:
            pass
        finally:
            writer.close()


def _small_buffers(sock: socket.socket) -> None:
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class LinkEmulator:
    """Listens on ``listen_port`` and forwards each connection to ``target``, shaped by ``trace``.
    ``up`` is client -> target (the robot connects through the proxy to the edge)."""

    def __init__(self, trace: Trace, listen_port: int, target: tuple[str, int], host: str = "127.0.0.1",
                 seed: int = 0, quantum: int = 16 * 1024, queue_ms: float = 100.0) -> None:
        self.trace = trace
        self.listen = (host, listen_port)
        self.target = target
        self.rng = random.Random(seed)
        self.quantum = quantum
        self.queue_ms = queue_ms
        self.stats = LinkStats()
        # The trace's clock starts with the first connection (the robot's), not with this process
        self.start: float | None = None
        self.wall_start: float | None = None
        self.on_clock_start: list[Callable[[float], None]] = []
        self._server: asyncio.base_events.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    async def start_serving(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        _small_buffers(sock)
        sock.bind(self.listen)
        self._server = await asyncio.start_server(self._handle, sock=sock)

    async def _handle(self, c_reader: asyncio.StreamReader, c_writer: asyncio.StreamWriter) -> None:
        self.stats.connections += 1
        if self.start is None:
            self.start = asyncio.get_running_loop().time()
            self.wall_start = time.time()
            for callback in self.on_clock_start:
                callback(self.wall_start)
        try:
            up_sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            _small_buffers(up_sock)
            up_sock.setblocking(False)
            await asyncio.get_running_loop().sock_connect(up_sock, self.target)
            t_reader, t_writer = await asyncio.open_connection(sock=up_sock)
        except OSError as exc:
            log.warning("cannot reach %s:%d: %s", *self.target, exc)
            c_writer.close()
            return
        s = self.start
        assert s is not None
        up = Direction("up", self.trace, s, self.stats, self.rng, self.quantum, self.queue_ms)
        down = Direction("down", self.trace, s, self.stats, self.rng, self.quantum, self.queue_ms)
        tasks = [asyncio.ensure_future(x) for x in (up.read_side(c_reader), up.write_side(t_writer),
                                                      down.read_side(t_reader), down.write_side(c_writer))]
        self._tasks.update(tasks)
        try:
            await asyncio.gather(*tasks, return_exceptions=True)
        finally:
            self._tasks.difference_update(tasks)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
        for t in list(self._tasks):
            t.cancel()
        with contextlib.suppress(Exception):
            await asyncio.gather(*self._tasks, return_exceptions=True)

    def elapsed(self) -> float | None:
        """Seconds on the trace clock, or None before the first connection."""
        return None if self.start is None else asyncio.get_running_loop().time() - self.start

    def report_line(self, second: int) -> str:
        st = self.trace.at(second + 0.5)
        state = "OUTAGE" if st.outage else f"trace up {st.up_mbps:g} / down {st.down_mbps:g} Mbps"
        return (f"[link {second:4d} s] up {self.stats.mbps('up', second):7.2f} Mbps, "
                f"down {self.stats.mbps('down', second):7.2f} Mbps ({state}, delay {st.delay_ms:g} ms)")
