"""A Zenoh router process built on zenoh-python, for machines without ``zenohd``.

The docker deployment uses the official ``eclipse/zenoh`` router image; this is the same role for
a bare-metal set-up or tests: a session in router mode that forwards between its peers/clients.

It waits up to ``DROP_WAIT_US`` (50 ms, Zenoh's default is 1 ms) before it drops a message it
cannot queue: the router forwards every robot's scans (BLOCK_FIRST) to an edge over one link, and
with the default a busy CPU made it drop a scan that arrived while another robot's was still being
queued (``python -m benchmarks.bench_fanin``). The price: a client whose link is full holds up what
the router forwards from the same sender by up to that much per message (a BLOCK message, such as a
checkpoint, already could for longer). ``--cfg`` setting the key wins; with a config file the
file is taken as it is (``zoffload certs`` writes the key into the router's).
"""

from __future__ import annotations

import json
import logging

from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import DROP_WAIT_KEY, DROP_WAIT_US, open_session, with_defaults, zenoh_config

log = logging.getLogger("zoffload.runtime.router")


def router_zenoh(z: ZenohSettings) -> ZenohSettings:
    """The router's session settings: ``z`` with the longer wait before a drop."""
    return with_defaults(z, {DROP_WAIT_KEY: str(DROP_WAIT_US)})


def run(z: ZenohSettings, stop: StopSignal) -> None:
    conf = router_zenoh(z)
    session = open_session(conf)
    try:  # what it listens on: -l, else its config file's, else Zenoh's default
        listen = json.loads(zenoh_config(conf).get_json("listen/endpoints"))
    except Exception:  # not said in a form this reads
        listen = z.listen or None
    log.info("router up, listening on %s", listen or "Zenoh's default endpoint")
    try:
        stop.wait()
    finally:
        session.close()
