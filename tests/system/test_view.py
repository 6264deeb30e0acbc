"""The live view with real processes: ``zoffload-edge --view`` looked at in a real headless browser,
and ``zoffload view -e`` recording a run to an .rrd file.

A simulated robot process supplies scans, acks, status and the map; this test publishes the camera
previews itself (wire.Preview: a synthetic frame with two person boxes, alternating local/edge)."""

from __future__ import annotations

import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.core.lab.view.messages import entities
from tests.helpers import KEYS, client, wait_for, wait_token
from tests.system.browser import Browser, chromium
from tests.system.procs import Proc, edge_args, script, session_args, start_edge
from zoffload.protocol import wire
from zoffload.runtime.session import free_tcp_port

pytestmark = pytest.mark.system
pytest.importorskip("kiss_icp")
pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install 'zoffload[view]')")

from zoffload.lab.view.recording import EDGE_COLOR, LOCAL_COLOR, MAP_COLOR, SCAN_COLOR  # noqa: E402

ROBOT = "robot1"
FRAME_RGB = (30, 60, 90)
RECORDED = [f"/robots/{ROBOT}/{n}" for n in ("map", "trajectory", "pose", "scan", "camera", "camera/persons",
                                              "link/rate_hz", "link/T_s", "link/rtt_ms",
                                              "perception/on_edge")]


def _previews(session: object, stop: threading.Event, period: float = 1.5) -> None:
    """What the robot's camera pipeline publishes while a viewer listens. (Slower than the
    pipeline's few per second: the CPU-rendered headless viewer takes about a second to decode a
    JPEG, and shows a loading mark until then; each newer frame restarts it.)"""
    import cv2

    img = np.zeros((360, 640, 3), np.uint8)
    img[:] = FRAME_RGB[::-1]
    cv2.rectangle(img, (100, 80), (220, 330), (200, 200, 200), -1)
    cv2.rectangle(img, (380, 60), (520, 340), (160, 160, 220), -1)
    jpeg = np.asarray(cv2.imencode(".jpg", img)[1], np.uint8).ravel()
    boxes = np.array([[95, 75, 225, 335], [375, 55, 525, 345]], np.float32)
    seq = 0
    while not stop.wait(period):
        msg = wire.Preview(robot=ROBOT, seq=seq, stamp=time.time(), side="edge" if seq % 2 else "local",
                           width=640, height=360, jpeg=jpeg, boxes=boxes,
                           scores=np.array([0.9, 0.7], np.float32))
        session.put(KEYS.preview(ROBOT), wire.encode(msg))  # type: ignore[attr-defined]
        seq += 1


def _url(proc: Proc) -> str:
    for line in proc.text().splitlines():
        if line.startswith("zoffload live view: open "):
            return line.split("open ", 1)[1].split()[0]
    return ""


def _rendered(png: Path) -> bool:
    """The page shows data, not just the viewer's chrome: the preview's boxes, and the map's or
    the scan's points are on screen."""
    import cv2

    img = cv2.imread(str(png))
    if img is None:
        return False
    rgb = img[:, :, ::-1].astype(np.int16)

    def count(color: tuple[int, int, int]) -> int:
        return int((np.abs(rgb - np.array(color)).max(axis=2) < 25).sum())

    # (the JPEG itself is not counted: the viewer dims it while it decodes the next one)
    boxes = count(EDGE_COLOR) + count(LOCAL_COLOR)
    return boxes > 300 and count(SCAN_COLOR) + count(MAP_COLOR) > 2000


def test_the_edge_serves_a_live_view_that_renders_in_a_browser(free_port: int, tmp_path: Path) -> None:
    binary = chromium()
    if binary is None:
        pytest.skip("no chromium to look at the web viewer with (apt-get install -y chromium)")
    web, grpc = free_tcp_port(), free_tcp_port()
    rrd = tmp_path / "edge_view.rrd"
    stop = threading.Event()
    with client(free_port) as s:
        edge = start_edge(s, edge_args(free_port, "--no-detector", "--view", "--view-web-port", str(web),
                                       "--view-grpc-port", str(grpc), "--view-save", str(rrd)),
                          tmp_path / "edge.log")
        browser = None
        try:
            wait_for(lambda: bool(_url(edge)), 30, "the live view's URL in the edge's output")
            robot = Proc(script("zoffload-robot") + session_args(connect=free_port) + ["--max-scans", "400"],
                         tmp_path / "robot.log")
            wait_token(s, KEYS.robot_alive(ROBOT))
            sender = threading.Thread(target=_previews, args=(s, stop), daemon=True)
            sender.start()
            browser = Browser(binary)
            browser.open(_url(edge))
            shot = tmp_path / "live_view.png"
            ok = browser.screenshot_until(shot, _rendered, timeout=150)
            keep = shutil.copy(shot, Path(str(shot).replace(".png", "_checked.png")))
            assert ok, f"the viewer did not show the robot's data; screenshot: {keep}\n{edge.text()[-2000:]}"
        finally:
            stop.set()
            if browser is not None:
                browser.close()
            robot_code = robot.sigint(60) if "robot" in locals() else 0
            code = edge.sigint(60)
    assert code == 0, edge.text()
    assert robot_code == 0, robot.text()
    got = entities(rrd, tmp_path)
    assert set(RECORDED) <= set(got), sorted(got)


# -m slow: the browser test records a real run's entities, tests/core/lab/view the view's own session
@pytest.mark.slow
def test_zoffload_view_records_a_run_from_its_own_session(free_port: int, tmp_path: Path) -> None:
    rrd = tmp_path / "view.rrd"
    with client(free_port) as s:
        edge = start_edge(s, edge_args(free_port, "--no-detector"), tmp_path / "edge.log")
        try:
            view = Proc(script("zoffload") + ["view"] + session_args(connect=free_port)
                        + ["--web-port", str(free_tcp_port()), "--grpc-port", str(free_tcp_port()),
                           "--save", str(rrd), "--map-period", "1", "--duration", "120"],
                        tmp_path / "view.log")
            wait_for(lambda: "zoffload live view: open http://" in view.text(), 30, "the viewer started")
            stop = threading.Event()
            sender = threading.Thread(target=_previews, args=(s, stop), daemon=True)
            sender.start()
            robot = Proc(script("zoffload-robot") + session_args(connect=free_port) + ["--max-scans", "60"],
                         tmp_path / "robot.log")
            assert robot.wait(120) == 0, robot.text()
            time.sleep(2.0)  # the last map poll (every 1 s) and previews
            stop.set()
            assert view.sigint(30) == 0, view.text()
        finally:
            edge.sigint(60)
    got = entities(rrd, tmp_path)
    assert set(RECORDED) <= set(got), sorted(got)
    # the viewer saw the whole run: one trajectory vertex per registered scan in its last strip
    strips = [v for row in got[f"/robots/{ROBOT}/trajectory"] for k, v in row.items() if k.endswith("strips")]
    assert len(strips[-1][0]) == 60
