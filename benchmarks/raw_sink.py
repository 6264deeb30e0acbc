"""A bare Zenoh subscriber that counts what arrives (the raw-Zenoh side of bench_stream).

Run by bench_stream: python -m benchmarks.raw_sink PORT SECONDS
"""

from __future__ import annotations

import json
import sys
import threading
import time

from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.session import loopback_endpoint, open_session


def main() -> None:
    port, seconds = int(sys.argv[1]), float(sys.argv[2])
    session = open_session(ZenohSettings(listen=[loopback_endpoint(port)], multicast_scouting=False,
                                         shared_memory=False))
    stats = {"n": 0, "bytes": 0, "first": 0.0, "last": 0.0}
    lock = threading.Lock()

    def on(sample: object) -> None:
        data = sample.payload.to_bytes()  # type: ignore[attr-defined]
        now = time.monotonic()
        with lock:
            if stats["n"] == 0:
                stats["first"] = now
            stats["n"] += 1
            stats["bytes"] += len(data)
            stats["last"] = now

    session.declare_subscriber("bench/raw", on)
    token = session.liveliness().declare_token("bench/sink")
    print("ready", flush=True)
    time.sleep(seconds)
    del token
    print(json.dumps(stats), flush=True)
    session.close()


if __name__ == "__main__":
    main()
