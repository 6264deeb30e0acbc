"""Test helpers: Zenoh settings on free loopback ports, waiting on conditions and tokens."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from zoffload.edge.server import EdgeDaemon
from zoffload.lab import runner
from zoffload.protocol.keys import Keys
from zoffload.runtime.config import EdgeSettings, ZenohSettings
from zoffload.runtime.session import loopback_endpoint, open_session


def listen_on(port: int) -> ZenohSettings:
    return ZenohSettings(listen=[loopback_endpoint(port)], multicast_scouting=False,
                         shared_memory=False)


def connect_to(port: int) -> ZenohSettings:
    return ZenohSettings(connect=[loopback_endpoint(port)], multicast_scouting=False,
                         shared_memory=False)


def wait_for(cond: Callable[[], bool], timeout: float = 10.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def wait_token(session: Any, key: str, timeout: float = 20.0) -> None:
    """Block until a liveliness token matching ``key`` exists (no sleeping on guesses)."""
    if not runner.wait_token(session, key, timeout):
        raise AssertionError(f"no liveliness token {key} after {timeout} s")


@contextmanager
def running_edge(settings: EdgeSettings) -> Iterator[EdgeDaemon]:
    """An edge daemon in this process (its own Zenoh session), stopped on exit."""
    daemon = EdgeDaemon(settings)
    daemon.start()
    thread = threading.Thread(target=daemon.run, daemon=True)
    thread.start()
    try:
        yield daemon
    finally:
        daemon.stop.set()
        thread.join(5)
        daemon.shutdown()


@contextmanager
def client(port: int) -> Iterator[Any]:
    session = open_session(connect_to(port))
    try:
        yield session
    finally:
        session.close()


KEYS = Keys()
