"""Process lifecycle shared by the daemons: logging set-up and signal handling.

The first SIGINT/SIGTERM asks the daemon to stop gracefully (finish, flush results, close the
session); a second one forces the exit with ``ExitCode.INTERRUPTED``. A graceful stop that has not
finished ``shutdown_limit`` seconds after it began writes every thread's stack to stderr (the log)
and exits with ``ExitCode.FAILURE``: a daemon asked to stop stops, and says where it was stuck.
(Once in CI an edge hung in its shutdown after its robot had finished, at a point that left no log
line; a supervisor's SIGKILL would have ended it without saying where.)
"""

from __future__ import annotations

import contextlib
import faulthandler
import logging
import os
import signal
import threading
from collections.abc import Iterator
from types import FrameType

from zoffload.runtime.errors import ExitCode


def setup_logging(level: str | None = None) -> None:
    logging.basicConfig(
        level=(level or os.environ.get("ZOFFLOAD_LOG", "INFO")).upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )


SHUTDOWN_LIMIT = 20.0
"""Seconds a daemon's shutdown may take (services stopped, maps exported, results written, session
closed; a second or two normally) before it is cut short with a stack dump. An edge's drain on
SIGTERM comes before it and has its own ``fleet.drain_timeout``."""


assert int(ExitCode.FAILURE) == 1  # faulthandler's exit code


class StopSignal:
    """An event set by the first SIGINT/SIGTERM; the second one exits immediately."""

    def __init__(self, shutdown_limit: float = SHUTDOWN_LIMIT) -> None:
        self.event = threading.Event()
        self.shutdown_limit = shutdown_limit
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
        faulthandler.dump_traceback_later(self.shutdown_limit, exit=True)
        try:
            yield
        finally:
            faulthandler.cancel_dump_traceback_later()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self._count += 1
        if self._count > 1:
            logging.getLogger("zoffload").warning("second signal: forcing exit")
            os._exit(int(ExitCode.INTERRUPTED))
        logging.getLogger("zoffload").info("%s received: stopping", signal.Signals(signum).name)
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    def set(self) -> None:
        self.event.set()

    def wait(self, timeout: float | None = None) -> bool:
        return self.event.wait(timeout)
