"""The live view as a whole: a Rerun recording served to the browser and fed from a Zenoh session.

``LiveView(options).start(session)`` serves the recording over gRPC (``grpc_port`` on ``bind``),
the web viewer bundled with rerun-sdk (``web_port``, page at ``url``), and saves it as an .rrd
file when ``save`` is set; ``close()`` stops the feed and finishes the file. The session is the
caller's: the edge's own (``--view`` on the edge), the demo's watching session, or one opened by
``run`` (``zoffload view``). The viewer sends nothing but map queries.
"""

from __future__ import annotations

import logging
import socket
import time
import uuid
from dataclasses import dataclass
from typing import Any
from urllib.parse import quote

import zenoh

from zoffload.lab.view import ViewError, rerun
from zoffload.lab.view.feed import Feed
from zoffload.lab.view.recording import Recording
from zoffload.protocol.keys import DEFAULT_NAMESPACE, Keys
from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.session import open_session

log = logging.getLogger("zoffload.view")


@dataclass(frozen=True)
class ViewOptions:
    """What the live view serves and records (``zoffload view --help`` has each as a flag)."""

    web_port: int = 9090  # the web viewer's page (rerun's default)
    grpc_port: int = 9876  # the recording's gRPC server, which the page connects to (rerun's default)
    bind: str = "127.0.0.1"  # where the gRPC server listens: 0.0.0.0 to view from another machine
    web: bool = True  # serve the web viewer page (off: gRPC only, e.g. for a native `rerun` viewer)
    save: str | None = None  # also write the recording to this .rrd file
    memory_limit: str = "512MiB"  # the gRPC server's buffer for late-joining viewers (oldest dropped)
    namespace: str = DEFAULT_NAMESPACE
    robots: tuple[str, ...] = ()  # only these robots; empty: the first max_robots seen
    max_robots: int = 16
    map_period: float = 3.0  # seconds between map queries (only when the map grew)
    scans: bool = True  # subscribe to the scans (each one crosses to the viewer)
    frames: bool = False  # subscribe to the camera frames sent to the edge (heavy; previews are not)


def _check_port_free(host: str, port: int) -> None:
    """rerun's gRPC server reports a port in use only in its log: check first, say it clearly."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ViewError(f"cannot serve the live view on {host}:{port}: {exc} (choose another "
                            "port with --grpc-port)") from exc


class LiveView:
    def __init__(self, options: ViewOptions) -> None:
        self.options = options
        self.url: str | None = None  # the page to open, once started
        self.grpc_uri: str | None = None
        self.feed: Feed | None = None
        self.stream: Any = None

    def start(self, session: zenoh.Session) -> str:
        """Serve the recording and feed it from ``session``; returns the URL to open (or the gRPC
        URI without the web viewer)."""
        rr, o = rerun(), self.options
        self.stream = rr.RecordingStream("zoffload", recording_id=uuid.uuid4())
        _check_port_free(o.bind, o.grpc_port)
        # A page served from another host (bind 0.0.0.0) calls the gRPC server from its own origin
        origins = None if o.bind.startswith("127.") else [f"http://*:{o.web_port}"]
        grpc = rr.GrpcServerSink(bind_ip=o.bind, port=o.grpc_port, server_memory_limit=o.memory_limit,
                                 cors_allow_origin=origins)
        sinks: list[Any] = [grpc]
        if o.save:
            try:
                sinks.append(rr.FileSink(o.save))
            except Exception as exc:  # rerun raises its own error types for an unwritable path
                raise ViewError(f"cannot write the recording to {o.save}: {exc}") from exc
        self.stream.set_sinks(*sinks)
        host = socket.gethostname() if o.bind == "0.0.0.0" else o.bind
        self.grpc_uri = str(grpc.uri).replace("0.0.0.0", host)
        self.url = self.grpc_uri
        if o.web:
            try:
                rr.serve_web_viewer(web_port=o.web_port, open_browser=False, connect_to=self.grpc_uri)
            except RuntimeError as exc:
                raise ViewError(f"cannot serve the web viewer on port {o.web_port}: {exc} (choose another "
                                "port with --web-port)") from exc
            self.url = f"http://{host}:{o.web_port}/?url={quote(self.grpc_uri, safe='')}"
        self.feed = Feed(session, Keys(o.namespace), Recording(self.stream), robots=o.robots,
                         max_robots=o.max_robots, map_period=o.map_period, scans=o.scans, frames=o.frames)
        self.feed.start()
        log.info("live view: %s%s", self.url, f" (recording to {o.save})" if o.save else "")
        return self.url

    def announce(self, session: zenoh.Session) -> None:
        """``start``, then print where to open it (what the daemons and the demo show the user)."""
        url = self.start(session)
        saving = f"  (recording to {self.options.save})" if self.options.save else ""
        print(f"zoffload live view: open {url}{saving}", flush=True)

    def close(self) -> None:
        """Stop the feed (its last messages are logged) and finish the .rrd file."""
        if self.feed is not None:
            self.feed.close()
            if self.feed.drops.total():
                log.info("live view drops: %s", self.feed.drops.snapshot())
            self.feed = None
        if self.stream is not None:
            self.stream.flush()
            self.stream.disconnect()
            self.stream = None


def view_zenoh(z: ZenohSettings) -> ZenohSettings:
    """The viewer's session: a client of the router or edge it connects to (a peer would join the
    mesh, and robots would then send their scans to it directly, over their own uplink)."""
    if z.connect and z.mode == "peer" and "mode" not in z.model_fields_set:
        return z.model_copy(update={"mode": "client"})
    return z


def run(options: ViewOptions, z: ZenohSettings, stop: StopSignal, duration: float | None = None) -> None:
    """``zoffload view``: open a session, serve the live view until stopped (or ``duration`` s)."""
    session = open_session(view_zenoh(z))
    view = LiveView(options)
    try:
        view.announce(session)
        deadline = time.monotonic() + duration if duration else None
        while not stop.wait(0.5):
            if deadline is not None and time.monotonic() >= deadline:
                break
    finally:
        view.close()
        session.close()
