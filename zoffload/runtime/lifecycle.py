"""Process lifecycle shared by the daemons: logging set-up and signal handling.

The first SIGINT/SIGTERM asks the daemon to stop gracefully (finish, flush results, close the
session); a second one forces the exit with ``ExitCode.INTERRUPTED``.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from types import FrameType

from zoffload.runtime.errors import ExitCode


def setup_logging(level: str | None = None) -> None:
    logging.basicConfig(
        level=(level or os.environ.get("ZOFFLOAD_LOG", "INFO")).upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )


class StopSignal:
    """An event set by the first SIGINT/SIGTERM; the second one exits immediately."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self._count = 0

    def install(self) -> StopSignal:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self._handle)
            signal.signal(signal.SIGTERM, self._handle)
        return self

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
