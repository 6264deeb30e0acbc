"""Camera frames in a fleet, with real processes and real models: two edges (detector only, each
hearing every frame) and one robot. Each frame is detected by the one edge it names, the other
counts it ``other_edge``; when the robot's edge is killed its frames move to the other edge."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.helpers import KEYS, wait_for
from tests.system.procs import Proc, script, session_args, start_edge
from zoffload.lab.runner import StatusWatcher
from zoffload.protocol import wire
from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.session import free_tcp_port, loopback_endpoint, open_session

pytestmark = [pytest.mark.system, pytest.mark.realdata]

EDGES = ("edge1", "edge2")


class EdgeStatus:
    """The latest status values of every edge."""

    def __init__(self, session: Any) -> None:
        self.values: dict[str, dict[str, float]] = {}
        self._sub = session.declare_subscriber(KEYS.all_edge_status(), self._on)

    def _on(self, sample: Any) -> None:
        msg = wire.decode(sample.payload.to_bytes(), expect=wire.Status)
        self.values[msg.id] = dict(msg.values)

    def get(self, edge: str, key: str) -> float:
        return self.values.get(edge, {}).get(key, 0.0)


def test_each_frame_is_detected_by_one_edge_and_frames_move_when_it_goes(tmp_path: Path, coco_dir: Path,
                                                                          models_dir: Path) -> None:
    ports = {edge: free_tcp_port() for edge in EDGES}
    cfg = {
        "scans": "none", "images": f"coco-clips:{coco_dir}", "out_dir": str(tmp_path / "robot"),
        "perception": {"local_threads": 1, "strategy": "edge", "max_frames": 250, "encoding": "jpeg"},
        "zenoh": {"connect": [f"tcp/127.0.0.1:{p}" for p in ports.values()], "multicast_scouting": False,
                  "shared_memory": False},
    }
    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(cfg))
    session = open_session(ZenohSettings(connect=[loopback_endpoint(p) for p in ports.values()],
                                         multicast_scouting=False, shared_memory=False))
    edges: dict[str, Proc] = {}
    try:
        for edge, port in ports.items():
            args = script("zoffload-edge") + session_args(listen=port) + ["--no-mapping", "--edge-id", edge]
            edges[edge] = start_edge(session, args, tmp_path / f"{edge}.log", edge_id=edge)
        status = EdgeStatus(session)
        robot_status = StatusWatcher(session, KEYS, "robot1")
        robot = Proc(script("zoffload-robot") + ["--settings", str(tmp_path / "robot.yaml")],
                     tmp_path / "robot.log")
        wait_for(lambda: robot_status.values.get("edge_done", 0) >= 40 or robot.p.poll() is not None, 90,
                 "edge results before the kill")
        assert robot.p.poll() is None, robot.text()
        # The robot's edge now: the one receiving its frames
        before = {e: status.get(e, "detector.received") for e in EDGES}
        time.sleep(1.5)
        grew = {e: status.get(e, "detector.received") - before[e] for e in EDGES}
        gone = max(grew, key=lambda e: grew[e])
        survivor = next(e for e in EDGES if e != gone)
        free_before = status.get(gone, "detector.free")
        t_kill = time.time()
        edges[gone].p.kill()  # no goodbye: its token goes when its sockets close
        edges[gone].wait()
        assert robot.wait(120) == 0, robot.text()
        time.sleep(1.5)  # the survivor's last status after the robot's last frame
        final = dict(status.values[survivor])
    finally:
        for proc in edges.values():
            if proc.p.poll() is None:
                proc.sigint()
        session.close()
    run = tmp_path / "robot"
    m = json.loads((run / "vision_metrics.json").read_text())
    assert m["balanced"] and m["balance"]["frames_in"] == 250 and m["balance"]["pending"] == 0, m["balance"]
    with open(run / "frames.csv") as f:
        rows = list(csv.DictReader(f))
    sent = [r for r in rows if r["bytes"]]  # put on the link (its byte count is booked then)
    to = {e: [r for r in sent if r["edge"] == e] for e in EDGES}
    print(f"killed {gone}; frames sent to {', '.join(f'{e}: {len(v)}' for e, v in to.items())}; "
          f"survivor {survivor}: received {final['detector.received']:.0f}, other_edge "
          f"{final.get('detector.other_edge', 0):.0f}; switches {m['edge_switches']}; "
          f"fallbacks {len(m['fallbacks'])}; per edge {m['per_edge']}; {gone} free before {free_before:.2f}")
    assert all(r["edge"] in EDGES for r in sent)  # every frame named its edge
    # Each frame detected once: the survivor received exactly the frames sent to it and counted the
    # ones sent to the other edge as not its own (before the change, both edges took every frame)
    assert final["detector.received"] == len(to[survivor])
    assert len(to[gone]) - 5 <= final.get("detector.other_edge", 0) <= len(to[gone])
    assert m["other"].get("wrong_edge_results", 0) == 0
    # The frames moved: after the kill every frame goes to the survivor and is detected there
    after = [r for r in sent if float(r["capture"]) > t_kill + 1.0]
    assert after and all(r["edge"] == survivor for r in after)
    assert sum(r["status"] == "edge_done" for r in after) >= 10  # (the rest: queue overflow, a busy machine)
    assert m["per_edge"].get(gone, 0) > 0 and m["per_edge"].get(survivor, 0) > 0
    assert m["edge_switches"] >= 1
