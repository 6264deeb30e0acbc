"""``zoffload-edge --view``: the edge daemon with the live view on the edge's own Zenoh session.

In-process, the viewer sees every robot the edge serves without another connection; its worker
and map poller are two more threads of the edge process (the map query is answered by the same
process). The edge's lifecycle is unchanged: the view starts after the services and the token,
and stops before them.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from zoffload.edge.server import EdgeServer
from zoffload.lab.view.live import LiveView, ViewOptions
from zoffload.runtime.config import EdgeSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.loading import write_effective


def run(settings: EdgeSettings, options: ViewOptions, stop: StopSignal | None = None) -> None:
    """The edge's ``run`` (edge/server.py) with the live view alongside."""
    if settings.map_dir:
        write_effective(settings, Path(settings.map_dir) / "edge_config.yaml")
    server = EdgeServer(settings, stop)
    view = LiveView(replace(options, namespace=settings.namespace))
    try:
        server.startup()
        assert server.session is not None, "startup() opens the session"
        view.announce(server.session)
        server.main_loop()
    finally:
        view.close()
        server.shutdown()
