"""A Zenoh router process built on zenoh-python, for machines without ``zenohd``.

The docker deployment uses the official ``eclipse/zenoh`` router image; this is the same role for
a bare-metal set-up or tests: a session in router mode that forwards between its peers/clients.
"""

from __future__ import annotations

import logging

from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import open_session

log = logging.getLogger("zoffload.runtime.router")


def run(z: ZenohSettings, stop: StopSignal) -> None:
    session = open_session(z)
    log.info("router up, listening on %s", z.listen or "the default endpoint")
    try:
        stop.wait()
    finally:
        session.close()
