"""A throughput probe: ``sink`` counts bytes per second, ``send`` saturates a TCP connection.

    python -m zoffload.lab.link.probe sink PORT SECONDS [HOST]   # prints one JSON line at the end
    python -m zoffload.lab.link.probe send HOST PORT SECONDS

Used to measure a link (the emulator, or a kernel-shaped veth pair) with plain sockets.
"""

from __future__ import annotations

import json
import socket
import sys
import time
from collections import Counter


def listening(port: int, host: str = "127.0.0.1") -> socket.socket:
    """A TCP socket listening on ``host:port`` (reusable address), for one connection."""
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind((host, port))
    srv.listen()
    return srv


def sink(port: int, seconds: float, host: str = "127.0.0.1") -> dict[str, object]:
    per_second: Counter[int] = Counter()
    with listening(port, host) as srv:
        print("listening", flush=True)
        srv.settimeout(seconds + 10)
        conn, _ = srv.accept()
        start = time.time()
        conn.settimeout(1.0)
        with conn:
            while time.time() - start < seconds:
                try:
                    data = conn.recv(65536)
                except TimeoutError:
                    continue
                if not data:
                    break
                per_second[int(time.time() - start)] += len(data)
    return {"mbps": [per_second[s] * 8 / 1e6 for s in range(int(seconds))]}


def send(host: str, port: int, seconds: float) -> None:
    buf = b"\x00" * 65536
    with socket.create_connection((host, port), timeout=10) as c:
        end = time.time() + seconds
        try:
            while time.time() < end:
                c.sendall(buf)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the sink measured its seconds and closed first


def main(argv: list[str]) -> None:
    if argv[0] == "sink":
        host = argv[3] if len(argv) > 3 else "127.0.0.1"
        print(json.dumps(sink(int(argv[1]), float(argv[2]), host)), flush=True)
    elif argv[0] == "send":
        send(argv[1], int(argv[2]), float(argv[3]))
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
