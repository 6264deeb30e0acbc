"""``zoffload view``: the live view in the browser; ``--view`` flags of the edge and the demo.

    zoffload view -e tcp/EDGE:7447                 # then open the printed http://… URL
    zoffload view -e tcp/EDGE:7447 --save run.rrd  # and keep the recording
    zoffload-edge --view …                         # the edge serves it on its own session
    zoffload demo --view                           # the demo too
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from typing import Any

from zoffload.cli.daemons import add_session_arguments, session_flags
from zoffload.runtime.errors import ConfigError, ExitCode
from zoffload.runtime.lifecycle import StopSignal


def add_view_flags(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """The live view's flags; ``prefix`` ("view-") when they join another program's flags."""
    g = p.add_argument_group("live view" + (" (with --view)" if prefix else ""))
    if prefix:
        g.add_argument("--view", action="store_true",
                       help="also serve the live view (Rerun in the browser; needs zoffload[view])")
    g.add_argument(f"--{prefix}web-port", type=int, default=9090, metavar="PORT",
                   help="port of the web viewer page (default 9090)")
    g.add_argument(f"--{prefix}grpc-port", type=int, default=9876, metavar="PORT",
                   help="port of the recording's gRPC server the page reads from (default 9876)")
    g.add_argument(f"--{prefix}bind", default="127.0.0.1", metavar="ADDR",
                   help="address the gRPC server listens on (default 127.0.0.1; 0.0.0.0 to view from "
                   "another machine: it serves the robots' camera previews to anyone who connects)")
    g.add_argument(f"--{prefix}no-web", action="store_true",
                   help="serve only the gRPC stream (for a native viewer: rerun rerun+http://HOST:PORT/proxy)")
    g.add_argument(f"--{prefix}save", default=None, metavar="FILE.rrd",
                   help="also write the recording to this file (open it later with: rerun FILE.rrd)")
    g.add_argument(f"--{prefix}robot", action="append", default=None, metavar="ID",
                   help="show only this robot (repeat for several; default: the first 16 seen)")
    g.add_argument(f"--{prefix}map-period", type=float, default=3.0, metavar="S",
                   help="seconds between map downloads, made only when the map grew (default 3)")
    g.add_argument(f"--{prefix}no-scans", action="store_true",
                   help="do not subscribe to the scans (each one would cross to the viewer)")
    g.add_argument(f"--{prefix}frames", action="store_true",
                   help="also show the camera frames sent to the edge with its detections (heavy)")


def view_options(a: argparse.Namespace, prefix: str = "", namespace: str | None = None) -> Any:
    """The ``ViewOptions`` of the parsed flags (``prefix`` as in ``add_view_flags``)."""
    from zoffload.lab.view.live import ViewOptions

    def get(name: str) -> Any:
        return getattr(a, (prefix + name).replace("-", "_"))

    if get("map-period") <= 0:
        raise ConfigError("--map-period must be positive")
    options = ViewOptions(web_port=get("web-port"), grpc_port=get("grpc-port"), bind=get("bind"),
                          save=get("save"), robots=tuple(get("robot") or ()), map_period=get("map-period"),
                          scans=not get("no-scans"), frames=get("frames"), web=not get("no-web"))
    return replace(options, namespace=namespace) if namespace else options


def _run_view(a: argparse.Namespace) -> int:
    from zoffload.lab.view.live import run
    from zoffload.runtime.config import EdgeSettings
    from zoffload.runtime.loading import load_settings

    z = load_settings(EdgeSettings, None, {"zenoh": session_flags(a)}).zenoh
    run(view_options(a, namespace=a.namespace), z, StopSignal().install(), duration=a.duration)
    return ExitCode.OK


def run_edge_with_view(a: argparse.Namespace, settings: Any) -> int:
    """``zoffload-edge --view``: the edge with the live view on its session."""
    from zoffload.lab.view.edge import run

    run(settings, view_options(a, "view-"), StopSignal().install())
    return ExitCode.OK


def add_view(sub: Any) -> None:
    v = sub.add_parser("view", help="live view of robots and edges in the browser (Rerun)",
                       description="Serve a Rerun viewer in the browser with each robot's map, "
                       "trajectory, latest scan, link figures and camera (where each frame was "
                       "detected, with its boxes), from the Zenoh traffic it observes.")
    add_session_arguments(v)
    v.add_argument("--namespace", default="zoffload", help="key namespace (default zoffload)")
    add_view_flags(v)
    v.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S seconds (default: until Ctrl-C)")
    v.add_argument("--log-level", default=None)
    v.set_defaults(func=_run_view)
