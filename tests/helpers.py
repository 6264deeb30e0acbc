"""Test helpers: Zenoh settings on free loopback ports, waiting on conditions and tokens."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from zoffload.edge.server import EdgeServer
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
def running_edge(settings: EdgeSettings) -> Iterator[EdgeServer]:
    """An edge server in this process (its own Zenoh session), shut down on exit."""
    server = EdgeServer(settings)
    loop = threading.Thread(target=server.main_loop, daemon=True)
    try:
        server.startup()
        loop.start()
        yield server
    finally:
        server.stop.set()
        if loop.is_alive():
            loop.join(5)
        server.shutdown()


@contextmanager
def client(port: int) -> Iterator[Any]:
    session = open_session(connect_to(port))
    try:
        yield session
    finally:
        session.close()


@contextmanager
def served(port: int) -> Iterator[tuple[Any, Any]]:
    """(a session listening on ``port``, a client of it): two sides of one loopback link."""
    side = open_session(listen_on(port))
    try:
        with client(port) as other:
            yield side, other
    finally:
        side.close()


KEYS = Keys()
