"""Faults in one run: the edge killed (SIGKILL) and restarted again and again while the robot's link
flaps (outage rows of the link emulator's trace), in the deployment's topology (a router; the edge
and the robot as clients, the robot behind `zoffload link`). After every restart the robot's acks
resume (nothing stuck), and at the end its counters balance: every scan produced is in exactly one
bucket.

The default run: 2 restarts and 8 flaps; ``-m slow``: the issue's 20 restarts and 100 flaps."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.helpers import KEYS, client, wait_for, wait_token
from tests.system.procs import Proc, script
from zoffload.lab.runner import StatusWatcher
from zoffload.runtime.session import free_tcp_port

pytestmark = pytest.mark.system
pytest.importorskip("kiss_icp")


def flapping_trace(path: Path, flaps: int, period: float = 1.2, outage: float = 0.3) -> float:
    """A trace of ``flaps`` outages of ``outage`` seconds, one every ``period``; returns its length."""
    rows = ["time_s, up_mbps, down_mbps, delay_ms, jitter_ms, outage"]
    for i in range(flaps):
        rows += [f"{i * period:.2f}, 200, 200, 2, 1, 0", f"{i * period + period - outage:.2f}, 0, 0, 0, 0, 1"]
    rows.append(f"{flaps * period:.2f}, 200, 200, 2, 1, 0")
    path.write_text("\n".join(rows) + "\n")
    return flaps * period


def run_faults(tmp: Path, restarts: int, flaps: int) -> None:
    router_port, link_port = free_tcp_port(), free_tcp_port()
    trace_s = flapping_trace(tmp / "flaps.csv", flaps)
    router = Proc(script("zoffload") + ["router", "--no-multicast-scouting", "-l",
                                        f"tcp/127.0.0.1:{router_port}"], tmp / "router.log")
    link = subprocess.Popen([sys.executable, "-m", "zoffload.cli", "link", "--trace", str(tmp / "flaps.csv"),
                             "--listen-port", str(link_port), "--target", f"127.0.0.1:{router_port}",
                             "--quiet", "--report", str(tmp / "link.csv")], stdout=subprocess.PIPE, text=True)
    assert link.stdout is not None and link.stdout.readline().startswith("ready")
    client_args = ["-m", "client", "--no-multicast-scouting", "--no-shm"]
    edge_cmd = script("zoffload-edge") + client_args + ["-e", f"tcp/127.0.0.1:{router_port}"]
    edges: list[Proc] = []
    robot = None
    try:
        with client(router_port) as s:
            edges.append(Proc(edge_cmd, tmp / "edge0.log"))
            wait_token(s, KEYS.edge_alive("edge1"), 60)
            status = StatusWatcher(s, KEYS, "robot1")
            # 10 Hz, long enough for every fault (a restart took 4 s here, so 6 s is room for a busy machine)
            scans = int((max(trace_s, 6.0 * restarts) + 4) * 10)
            robot = Proc(script("zoffload-robot") + client_args
                         + ["-e", f"tcp/127.0.0.1:{link_port}", "--max-scans", str(scans), "--replay", "loop",
                            "--out", str(tmp / "robot")], tmp / "robot.log")
            wait_for(lambda: status.values.get("acked", 0) >= 10, 60, "the robot's first acks")
            t0 = time.monotonic()
            for k in range(1, restarts + 1):
                assert robot.p.poll() is None, f"the robot finished before restart {k}: raise its scans"
                edges[-1].p.kill()  # no goodbye
                edges[-1].wait(10)
                wait_for(lambda: status.values.get("edges", 1) == 0, 20, "the robot noticing the edge gone")
                before = status.values.get("acked", 0)
                edges.append(Proc(edge_cmd, tmp / f"edge{k}.log"))
                wait_token(s, KEYS.edge_alive("edge1"), 60)
                try:
                    wait_for(lambda b=before: status.values.get("acked", 0) >= b + 5,  # type: ignore[misc]
                             60, f"acks resuming after restart {k}")
                except AssertionError:
                    tail = robot.text()[-3000:]
                    raise AssertionError(f"stuck after restart {k}: {status.values}\n{tail}") from None
                print(f"restart {k} resumed at {time.monotonic() - t0:.1f} s of {scans / 10:.0f}", flush=True)
            assert robot.wait(scans / 10 + 120) == 0, robot.text()[-3000:]
            status.close()
        metrics = json.loads((tmp / "robot" / "robot_metrics.json").read_text())
        b = metrics["balance"]
        assert metrics["balanced"], b
        assert b["produced"] == scans and b["in_flight"] == 0
        assert b["acked"] > 0.3 * b["published"], b  # the link flapped and the edge kept dying, yet
        assert b["local"] > 0  # while no edge answered, the robot mapped by itself
        assert "Traceback" not in robot.text()
    finally:
        if robot is not None and robot.p.poll() is None:
            robot.sigint()
        for e in edges[:-1]:
            if e.p.poll() is None:
                e.p.kill()
        last = edges[-1].sigint() if edges else 0
        link.send_signal(2)
        link.wait(20)
        assert router.sigint() == 0
    assert last == 0
    # the emulator played the outages (its report: one row per second, the outage flag last)
    outage_s = sum(int(ln.rsplit(",", 1)[1]) for ln in (tmp / "link.csv").read_text().splitlines()[1:])
    assert outage_s >= 1


def test_edge_restarts_and_link_flaps_leave_the_robot_balanced(tmp_path: Path) -> None:
    run_faults(tmp_path, restarts=2, flaps=8)


@pytest.mark.slow
def test_20_edge_restarts_and_100_link_flaps_in_one_run(tmp_path: Path) -> None:
    run_faults(tmp_path, restarts=20, flaps=100)
