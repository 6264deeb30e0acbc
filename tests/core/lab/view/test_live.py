"""The live view as a whole, in-process: served over gRPC, saved to .rrd, its errors, its session
mode, and its flags (``zoffload view``, ``--view`` on the edge and the demo)."""

from __future__ import annotations

import socket
import sys
from pathlib import Path

import pytest

from tests.core.lab.view.messages import R, ack, entities, pose, preview
from tests.helpers import listen_on, wait_for
from zoffload.cli.main import build_parser
from zoffload.cli.view import view_options
from zoffload.protocol import wire
from zoffload.protocol.keys import Keys
from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.errors import ConfigError
from zoffload.runtime.session import free_tcp_port, open_session

pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install 'zoffload[view]')")

from zoffload.lab.view import ViewError, rerun  # noqa: E402
from zoffload.lab.view.live import LiveView, ViewOptions, view_zenoh  # noqa: E402


def test_a_live_view_records_what_its_session_hears_to_an_rrd_file(free_port: int, tmp_path: Path) -> None:
    rrd = tmp_path / "view.rrd"
    session = open_session(listen_on(free_port))
    view = LiveView(ViewOptions(web=False, grpc_port=free_tcp_port(), save=str(rrd), map_period=3600))
    try:
        uri = view.start(session)
        assert uri.startswith("rerun+http://127.0.0.1:") and uri.endswith("/proxy")
        with socket.create_connection(("127.0.0.1", view.options.grpc_port), timeout=5):
            pass  # the gRPC server listens
        keys = Keys()
        for seq in range(1, 4):
            session.put(keys.scan_ack(R, "e1"), wire.encode(ack(R, seq, pose(float(seq)))))
        session.put(keys.preview(R), wire.encode(preview(R, 1, "local")))
        assert view.feed is not None
        feed = view.feed
        wait_for(lambda: feed.logged >= 4, 10, "the messages logged")
    finally:
        view.close()
        session.close()
    got = entities(rrd, tmp_path)
    names = ("pose", "trajectory", "link/T_s", "camera", "camera/persons")
    assert {f"/robots/{R}/{n}" for n in names} <= set(got)


def test_a_busy_port_is_a_clear_error(tmp_path: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        session = open_session(ZenohSettings(multicast_scouting=False, shared_memory=False))
        try:
            with pytest.raises(ViewError, match=f"127.0.0.1:{port}.*--grpc-port"):
                LiveView(ViewOptions(web=False, grpc_port=port)).start(session)
        finally:
            session.close()
    assert issubclass(ViewError, ConfigError)  # the command line reports it, exit code 2


def test_without_rerun_sdk_the_error_says_how_to_install_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)  # makes `import rerun` fail
    with pytest.raises(ViewError, match=r"pip install 'zoffload\[view\]'"):
        rerun()


def test_the_viewer_is_a_client_of_the_endpoint_it_connects_to() -> None:
    assert view_zenoh(ZenohSettings(connect=["tcp/10.0.0.2:7447"])).mode == "client"
    assert view_zenoh(ZenohSettings()).mode == "peer"  # nothing to connect to: find peers
    assert view_zenoh(ZenohSettings(mode="peer", connect=["tcp/10.0.0.2:7447"])).mode == "peer"  # asked for


def test_view_flags_of_the_view_command_the_edge_and_the_demo() -> None:
    a = build_parser().parse_args(["view", "-e", "tcp/127.0.0.1:7447", "--save", "x.rrd", "--robot", "r1",
                                   "--robot", "r2", "--no-scans", "--web-port", "8000", "--namespace", "lab"])
    o = view_options(a, namespace=a.namespace)
    assert (o.save, o.robots, o.scans, o.web_port, o.namespace, o.frames) == ("x.rrd", ("r1", "r2"), False,
                                                                              8000, "lab", False)
    e = build_parser().parse_args(["edge", "--view", "--view-grpc-port", "9999", "--view-frames"])
    assert e.view and view_options(e, "view-").grpc_port == 9999 and view_options(e, "view-").frames
    d = build_parser().parse_args(["demo", "--view", "--view-bind", "0.0.0.0"])
    assert d.view and view_options(d, "view-").bind == "0.0.0.0"
    assert not build_parser().parse_args(["edge"]).view
    with pytest.raises(ConfigError, match="map-period"):
        view_options(build_parser().parse_args(["view", "--map-period", "0"]))

