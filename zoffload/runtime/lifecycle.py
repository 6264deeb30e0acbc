"""Process lifecycle shared by the daemons: logging set-up and signal handling.

The first SIGINT/SIGTERM asks the daemon to stop gracefully (finish, flush results, close the
session); a second one forces the exit with ``ExitCode.INTERRUPTED``. A graceful stop that has not
finished ``shutdown_limit`` seconds after the signal (or after the shutdown began, when the daemon
ends on its own) writes every thread's stack to stderr (the log) and exits with
``ExitCode.FAILURE``: a daemon asked to stop stops, and says where it was stuck. (Once in CI an
edge hung in its shutdown after its robot had finished, at a point that left no log line; a
supervisor's SIGKILL would have ended it without saying where.)
"""

from __future__ import annotations

import contextlib
import faulthandler
import logging
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from types import FrameType

from zoffload.runtime.errors import ExitCode


def setup_logging(level: str | None = None) -> None:
    logging.basicConfig(
        level=(level or os.environ.get("ZOFFLOAD_LOG", "INFO")).upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if os.environ.get("RUST_LOG"):  # Zenoh's own log (e.g. RUST_LOG=zenoh_transport=debug), to stderr
        import zenoh

        zenoh.try_init_log_from_env()


SHUTDOWN_LIMIT = 60.0
"""Seconds a daemon's stop may take (services stopped, maps exported, results written, session
closed; a second or two normally) before it is cut short with a stack dump: above the sum of the
waits the shutdown bounds itself (the ROS 2 mapper's 15 s, the detector's 5 s, each map worker's
5 s) so a slow but finishing stop is not cut. ``ZOFFLOAD_SHUTDOWN_LIMIT`` (seconds) sets it: the
system tests use 20, under their own 30 s kill. An edge's drain on SIGTERM comes before it and has
its own ``fleet.drain_timeout``."""
WAIT_SLICE = 0.25  # seconds a signal handled on another thread may wait to run (StopSignal.wait)


def wait_in_slices(event: threading.Event, timeout: float | None, step: float,
                   give_up: Callable[[], bool] | None = None) -> bool:
    """``event.wait(timeout)`` (None: for ever), woken every ``step`` seconds: to run a signal
    handler the main thread owes, and to return at once (the event's state) when ``give_up()``
    says there is nothing left to wait for."""
    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        left = step if deadline is None else min(step, max(0.0, deadline - time.monotonic()))
        if event.wait(left):
            return True
        if (deadline is not None and time.monotonic() >= deadline) or (give_up is not None and give_up()):
            return event.is_set()


def shutdown_limit_env() -> float:
    """``ZOFFLOAD_SHUTDOWN_LIMIT`` when set to a positive number of seconds, else ``SHUTDOWN_LIMIT``."""
    raw = os.environ.get("ZOFFLOAD_SHUTDOWN_LIMIT", "")
    try:
        value = float(raw)
    except ValueError:
        if raw:
            logging.getLogger("zoffload").warning("ZOFFLOAD_SHUTDOWN_LIMIT=%r is not a number: %g s",
                                                  raw, SHUTDOWN_LIMIT)
        return SHUTDOWN_LIMIT
    return value if math.isfinite(value) and value > 0 else SHUTDOWN_LIMIT


assert int(ExitCode.FAILURE) == 1  # faulthandler's exit code


class StopSignal:
    """An event set by the first SIGINT/SIGTERM; the second one exits immediately."""

    def __init__(self, shutdown_limit: float | None = None) -> None:
        self.event = threading.Event()
        self.shutdown_limit = shutdown_limit if shutdown_limit is not None else shutdown_limit_env()
        self._count = 0
        self._installed = False  # this process's signals are ours: its shutdown is bounded

    def install(self) -> StopSignal:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self._handle)
            signal.signal(signal.SIGTERM, self._handle)
            self._installed = True
        return self

    @contextlib.contextmanager
    def bounded_shutdown(self) -> Iterator[None]:
        """A daemon's shutdown runs inside this: past ``shutdown_limit`` s every thread's stack goes
        to stderr and the process exits with ``ExitCode.FAILURE``. Faulthandler's own watchdog
        thread does it, so a call stuck while holding the GIL cannot hold it up. A no-op unless
        ``install()`` made this the process's signal handler (in-process tests, the API)."""
        if not self._installed:
            yield
            return
        self._arm()
        try:
            yield
        finally:
            faulthandler.cancel_dump_traceback_later()

    def _arm(self) -> None:
        """Start (or restart) the watchdog; one that cannot start (no stderr file) is logged, and the
        stop goes on unbounded rather than not at all."""
        try:
            faulthandler.dump_traceback_later(self.shutdown_limit, exit=True)
        except (RuntimeError, ValueError, OSError, AttributeError) as exc:
            logging.getLogger("zoffload").warning("stop not bounded (no stack dump possible): %s", exc)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self._count += 1
        if self._count > 1:
            logging.getLogger("zoffload").warning("second signal: forcing exit")
            os._exit(int(ExitCode.INTERRUPTED))
        logging.getLogger("zoffload").info("%s received: stopping", signal.Signals(signum).name)
        if self._installed:
            self._arm()  # from the signal: a main loop that never reaches its shutdown is bounded too
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    def set(self) -> None:
        self.event.set()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the stop, ``timeout`` seconds at most (None: for ever), in slices: a signal that
        the kernel hands to one of Zenoh's threads only sets Python's flag, and a main thread
        blocked on the event for ever never returns to run the handler. ``zoffload router`` did
        that: it slept through SIGINT until a test killed it 30 s later."""
        return wait_in_slices(self.event, timeout, WAIT_SLICE)
